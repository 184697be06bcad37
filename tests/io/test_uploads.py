"""Hostile uploads through the readers the service uses: each gets a typed 413 (over a limit) or 422
(malformed) before anything is decompressed, in little memory; AMASS files read as before."""

from __future__ import annotations

import io
import zipfile
from functools import partial
from pathlib import Path

import numpy as np
import pytest

from bodyfit.api.settings import ServiceSettings
from bodyfit.clients.errors import ServerError
from bodyfit.clients.results import Synthesis
from bodyfit.io.errors import FileLimitError
from bodyfit.io.smpl import SmplSequenceError, read_smpl_npz, read_smpl_sequence
from bodyfit.service.core import BodyService
from bodyfit.service.errors import InvalidInputError, LimitExceededError
from tests.io.checks import MB, archive, npy, patch_members, peak_memory, refused, savez, savez_compressed

SEQUENCE = Path(__file__).resolve().parents[1] / "data" / "smpl_format" / "cmu_131_smpl.npz"


def amass(**arrays: np.ndarray) -> bytes:
    base = {"poses": np.zeros((4, 72)), "trans": np.zeros((4, 3)), "mocap_framerate": np.array(60.0)}
    return savez(**{**base, **arrays})


# -- sequences of meshes -------------------------------------------------------------------------------------
def test_a_sequence_zip_bomb_is_refused_from_its_header(body_service: BodyService) -> None:
    buf = io.BytesIO()  # 20,000 zero frames (3.2 GB decompressed) claimed, 64 MiB of zeros behind it
    with zipfile.ZipFile(buf, "w", zipfile.ZIP_DEFLATED) as zf, zf.open("frames.npy", "w") as f:
        f.write(npy((20_000, 13_348, 3), "<f4"))
        for _ in range(64):
            f.write(bytes(MB))
    with peak_memory(2):
        refused(
            LimitExceededError,
            "frames declares 20,000 frames; the limit is",
            lambda: body_service.read_sequence(buf.getvalue()),
        )
    billion = archive({"frames": npy((10**9, 13_348, 3), data=bytes(100))})
    with peak_memory(2):
        refused(
            LimitExceededError,
            "frames declares 1,000,000,000 frames; the limit is",
            lambda: body_service.read_sequence(billion),
        )


@pytest.mark.parametrize(
    ("arrays", "field", "words"),
    [
        (
            {"frames": np.zeros((2, 13_348, 3), np.float32), "weights": np.zeros((3, 13_348))},
            "weights",
            "(T=2, 13348)",
        ),
        ({"frames": np.zeros((2, 13_348, 3)), "weights": np.full((2, 13_348), "a")}, "weights", "must hold"),
        ({"frames": np.zeros((2, 13_348, 3), [("x", "f4")])}, "frames", "structured"),
        ({"frames": np.float32(0.0)}, "frames", "(a scalar)"),
    ],
)
def test_sequence_arrays_are_checked_before_they_are_read(
    body_service: BodyService, arrays: dict[str, np.ndarray], field: str, words: str
) -> None:
    with pytest.raises(InvalidInputError) as err:
        body_service.read_sequence(savez(**arrays))
    assert words in err.value.detail and err.value.field == field


def test_weights_come_back_with_the_frames(body_service: BodyService) -> None:
    frames, weights = body_service.read_sequence(
        savez_compressed(frames=np.zeros((2, 13_348, 3), np.float32), weights=np.ones((2, 13_348)))
    )
    assert frames.shape == (2, 13_348, 3) and weights is not None and weights.shape == (2, 13_348)


# -- SMPL-format sequences -----------------------------------------------------------------------------------
def test_amass_files_read_as_before() -> None:
    seq = read_smpl_sequence(SEQUENCE)
    assert seq.n_frames == 60 and seq.gender == "neutral" and seq.surface_model_type == "smplh"
    assert read_smpl_npz(SEQUENCE.read_bytes(), "cmu.npz", max_frames=60).n_frames == 60
    split = amass(
        poses=np.zeros((0, 72)),
        trans=np.zeros((0, 3)),
        global_orient=np.zeros((4, 3)),
        body_pose=np.zeros((4, 69)),
    )
    refused(SmplSequenceError, "zero frames", lambda: read_smpl_npz(split))  # poses, when given, is used


def test_long_amass_headers_are_refused_before_decompressing(body_service: BodyService) -> None:
    for rows in (5_000_000, 10**9):
        data = archive({"poses": npy((rows, 72), data=bytes(576)), "mocap_framerate": npy((), data=bytes(8))})
        with peak_memory(2):
            refused(
                LimitExceededError,
                f"poses declares {rows:,} frames; the limit is",
                partial(body_service.read_upgrade, data, "long.npz"),
            )
        refused(FileLimitError, "decompress to", partial(read_smpl_npz, data))  # no frame limit


@pytest.mark.parametrize("gender", [np.array(""), np.array(b""), np.zeros(0, "S1"), np.array(" Neutral ")])
def test_an_empty_gender_is_neutral(gender: np.ndarray) -> None:
    assert read_smpl_npz(amass(gender=gender)).gender == "neutral"


@pytest.mark.parametrize(
    ("arrays", "words"),
    [
        ({"gender": np.array("robot")}, "unknown gender 'robot'"),
        ({"gender": np.array(["male", "female"])}, "gender must have shape (), (1,) or (0,)"),
        ({"gender": np.array(1)}, "gender must hold text"),
        ({"poses": np.full((4, 72), "0")}, "poses must hold floats or integers"),
        ({"poses": np.zeros((4, 72), [("a", "f8")])}, "structured"),
        ({"trans": np.zeros((5, 3))}, "trans must have shape (T=4, 3)"),
        ({"mocap_framerate": np.zeros(3)}, "mocap_framerate must have shape () or (1,)"),
        ({"betas": np.zeros((2, 10))}, "betas must have shape (K,), (1, K) or (T=4, K)"),
    ],
)
def test_malformed_amass_arrays_are_named(
    body_service: BodyService, arrays: dict[str, np.ndarray], words: str
) -> None:
    with pytest.raises(InvalidInputError) as err:
        body_service.read_upgrade(amass(**arrays), "a.npz")
    assert words in err.value.detail and err.value.field == "file"


def test_pickled_encrypted_and_truncated_amass_uploads(body_service: BodyService) -> None:
    gender = archive({"poses": npy((4, 72), data=bytes(2304)), "gender": npy((), "|O", b"\x80\x04N.")})
    refused(
        InvalidInputError,
        "gender is an array of Python objects",
        lambda: body_service.read_upgrade(gender, "a.npz"),
    )
    encrypted = patch_members(amass(), flag=1)
    refused(InvalidInputError, "is encrypted", lambda: body_service.read_upgrade(encrypted, "a.npz"))
    refused(
        InvalidInputError, "not a readable .npz", lambda: body_service.read_upgrade(amass()[:-40], "a.npz")
    )
    lzma = patch_members(amass(), method=14)
    refused(InvalidInputError, "compressed with lzma", lambda: body_service.read_upgrade(lzma, "a.npz"))


# -- scans ---------------------------------------------------------------------------------------------------
def test_scan_uploads_map_to_413_and_422(body_service: BodyService) -> None:
    over = archive({"points": npy((3_000_000, 3), data=bytes(72))})
    with peak_memory(2):
        refused(
            LimitExceededError,
            "points declares 3,000,000 points; the limit is 2,000,000",
            lambda: body_service.read_scan(over, "npz"),
        )
    structured = savez(points=np.zeros((500, 3), [("x", "f4")]))
    refused(
        InvalidInputError,
        "points is a structured (record) array",
        lambda: body_service.read_scan(structured, "npz"),
    )
    faces = savez(points=np.zeros((500, 3)), faces=np.zeros((10, 3)))
    refused(InvalidInputError, "faces must hold integers", lambda: body_service.read_scan(faces, "npz"))
    pcd = b"FIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\nWIDTH 3000000\nPOINTS 3000000\nDATA binary\n"
    body = bytes(3_000_000 * 12)
    refused(
        LimitExceededError,
        "the PCD declares 3,000,000 points",
        lambda: body_service.read_scan(pcd + body, "pcd"),
    )
    refused(
        InvalidInputError,
        "PCD binary data has 12 bytes",
        lambda: body_service.read_scan(pcd + bytes(12), "pcd"),
    )


# -- settings and the SDK ------------------------------------------------------------------------------------
def test_the_decompressed_cap_is_a_setting(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("BODYFIT_MAX_DECOMPRESSED_MB", "64")
    assert ServiceSettings().limits().max_decompressed_bytes == 64 * MB
    assert ServiceSettings(max_decompressed_mb=1024).limits().max_decompressed_bytes == 2**30


def test_the_sdk_refuses_a_broken_synthesis_answer() -> None:
    good = savez(
        vertices=np.zeros((1, 5, 3), np.float32),
        joints=np.zeros((1, 2, 3), np.float32),
        joint_names=np.array(["a", "b"]),
    )
    assert Synthesis.from_npz(good).joint_names == ("a", "b")
    refused(ServerError, "unreadable synthesis answer", lambda: Synthesis.from_npz(good[:-20]))
    lying = archive(
        {
            "vertices": npy((10**9, 5, 3), "<f4"),
            "joints": npy((10**9, 2, 3), "<f4"),
            "joint_names": npy((2,), "<U1"),
        }
    )
    refused(ServerError, "decompress to", lambda: Synthesis.from_npz(lying))
