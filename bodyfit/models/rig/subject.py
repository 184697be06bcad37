"""The portable subject file: one person's shape coefficients, rest-pose template offsets, skinning weights
and joint centres (segment scale offsets) for one body model, saved as a single ``.npz`` and refused when it
was built for another model, by an older version, or has been altered."""

from __future__ import annotations

import hashlib
import io
import zipfile
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

from bodyfit.io.npz import DAMAGED
from bodyfit.models.body.model import BodyDecoder, BodyModel
from bodyfit.models.errors import BodyfitError

FORMAT = "bodyfit-subject-2"
OLD_FORMATS = ("bodyfit-subject-1",)
MAX_BYTES = 64 * 2**20
"""The most a subject file's arrays may hold together, decompressed, as their zip entries declare them (a
subject of our 13,348-vertex body holds about 3 MB; zipfile reads no member past its declared size). A
small upload that would decompress to gigabytes is refused before any array is read."""
FINGERPRINT_ARRAYS = ("faces", "vertices_mean", "weights", "scale_mean", "scale_basis", "identity_basis")


class SubjectError(BodyfitError):
    """A subject file that cannot be used: unreadable, altered, or built for another body model."""


def _read_arrays(data: bytes) -> dict[str, np.ndarray]:
    """Every array of a subject file's bytes, once their declared sizes are within :data:`MAX_BYTES`.

    Raises:
        SubjectError: not an .npz, a damaged one, or one declaring more than :data:`MAX_BYTES`.
    """
    try:
        with zipfile.ZipFile(io.BytesIO(data)) as archive:
            declared = sum(info.file_size for info in archive.infolist())
        if declared <= MAX_BYTES:
            with np.load(io.BytesIO(data), allow_pickle=False) as npz:
                return {k: npz[k] for k in npz.files}
    except DAMAGED as exc:
        raise SubjectError(f"not a subject file (an .npz written by `bodyfit rig`): {exc}") from None
    raise SubjectError(
        f"not a subject file: its arrays declare {declared / 2**20:,.0f} MiB decompressed, more than the "
        f"{MAX_BYTES / 2**20:.0f} MiB any subject holds (about 3 MiB): write it with `bodyfit rig`"
    )


def model_fingerprint(model: BodyModel) -> str:
    """sha256 (hex) of the body model's topology, template, skinning weights and shape bases: a subject's
    offsets and coefficients mean something only for the model with this fingerprint."""
    h = hashlib.sha256()
    for name in FINGERPRINT_ARRAYS:
        a = np.ascontiguousarray(model.data[name])
        h.update(name.encode() + str(a.dtype).encode() + str(a.shape).encode() + a.tobytes())
    return h.hexdigest()


@dataclass(frozen=True)
class PersonalParts:
    """What one person's decoder carries beyond the shape coefficients: skinning ``weights`` (V, n_body),
    template ``offsets`` (V, 3) metres and segment ``scale_offsets`` (n_seg, 3) (their joint centres)."""

    weights: np.ndarray
    offsets: np.ndarray
    scale_offsets: np.ndarray

    @classmethod
    def generic(cls, model: BodyModel) -> PersonalParts:
        """The body model's own weights and joints, no offsets: its decoder is ``model.decoder``'s."""
        shape = np.asarray(model.data["scale_mean"]).shape
        return cls(
            np.asarray(model.data["weights"], np.float64), np.zeros((model.n_vertices, 3)), np.zeros(shape)
        )

    def decoder(self, model: BodyModel, dtype: torch.dtype = torch.float64) -> BodyDecoder:
        """``model``'s decoder carrying these parts (:meth:`BodyModel.scaled_decoder`,
        :meth:`BodyDecoder.with_weights`, :meth:`BodyDecoder.with_offsets`)."""
        decoder = model.scaled_decoder(self.scale_offsets, dtype)
        return decoder.with_weights(self.weights).with_offsets(self.offsets)


@dataclass(frozen=True)
class Subject:
    """One person for one body model: ``shape`` (n_shape,) coefficients [bone, identity]; ``offsets`` (V, 3)
    metres added to the template before skinning; ``model`` the body model's :func:`model_fingerprint`;
    ``poses`` (K, n_dof) and ``roots`` (K, 3) of the scans it was built from, named by ``scans``;
    ``report``: how well it fits them (mm); ``weights`` (V, n_body) their skinning weights and
    ``scale_offsets`` (n_seg, 3) their joint centres as segment scale offsets (None: the body model's)."""

    shape: np.ndarray
    offsets: np.ndarray
    model: str
    poses: np.ndarray
    roots: np.ndarray
    scans: tuple[str, ...] = ()
    report: dict[str, float] = field(default_factory=dict)
    weights: np.ndarray | None = None
    scale_offsets: np.ndarray | None = None

    def parts(self, model: BodyModel) -> PersonalParts:
        """This person's weights, offsets and joints, the body model's where the subject has none."""
        generic = PersonalParts.generic(model)
        return PersonalParts(
            generic.weights if self.weights is None else np.asarray(self.weights, np.float64),
            np.asarray(self.offsets, np.float64),
            generic.scale_offsets
            if self.scale_offsets is None
            else np.asarray(self.scale_offsets, np.float64),
        )

    def decoder(self, model: BodyModel, dtype: torch.dtype = torch.float32) -> BodyDecoder:
        """``model``'s decoder carrying everything personal: this person's template offsets, skinning weights
        and joint centres (shape coefficients are still an input: pass :attr:`shape`).

        Raises:
            SubjectError: the subject was built for another body model.
        """
        self.check_model(model)
        return self.parts(model).decoder(model, dtype)

    def check_model(self, model: BodyModel) -> None:
        """Raises SubjectError unless this subject was built for ``model``."""
        if self.model != model_fingerprint(model):
            raise SubjectError(
                f"this subject was built for another body model (fingerprint {self.model[:12]}..., the "
                f"loaded model's is {model_fingerprint(model)[:12]}...); rebuild it with `bodyfit rig` "
                "against the model you serve"
            )

    def to_bytes(self) -> bytes:
        """The ``.npz`` bytes, with a sha256 of the contents that :meth:`from_bytes` checks."""
        arrays = self._arrays()
        buffer = io.BytesIO()
        np.savez_compressed(buffer, allow_pickle=False, sha256=np.array(_digest(arrays)), **arrays)
        return buffer.getvalue()

    def save(self, path: str | Path) -> Path:
        target = Path(path)
        target.write_bytes(self.to_bytes())
        return target

    @classmethod
    def from_bytes(cls, data: bytes, model: BodyModel | None = None) -> Subject:
        """Read a subject file; with ``model``, also check it was built for that model.

        Raises:
            SubjectError: not a subject file, altered contents (hash mismatch), or another body model.
        """
        arrays = _read_arrays(data)
        found = str(arrays.pop("format", ""))
        if found in OLD_FORMATS:
            raise SubjectError(
                f"this subject file was written by an older bodyfit ({found}, without the person's own "
                "skinning weights and joint centres); rebuild it with `bodyfit rig` from the same scans"
            )
        if found != FORMAT:
            raise SubjectError(
                f"not a subject file: its format is not {FORMAT!r} (write one with `bodyfit rig`)"
            )
        stored = str(arrays.pop("sha256", ""))
        if stored != _digest({"format": np.array(FORMAT), **arrays}):
            raise SubjectError(
                "the subject file's contents do not match its sha256: it was altered or damaged"
            )
        try:
            subject = cls._from_arrays(arrays)
        except KeyError as missing:
            raise SubjectError(
                f"the subject file lacks {missing.args[0]}: rebuild it with `bodyfit rig`"
            ) from None
        if model is not None:
            subject.check_model(model)
            generic = PersonalParts.generic(model)
            if (
                subject.offsets.shape != (model.n_vertices, 3)
                or subject.shape.shape != (model.n_shape,)
                or (subject.weights is not None and subject.weights.shape != generic.weights.shape)
                or (
                    subject.scale_offsets is not None
                    and subject.scale_offsets.shape != generic.scale_offsets.shape
                )
            ):
                raise SubjectError("the subject's arrays do not match the body model's sizes")
        return subject

    @classmethod
    def _from_arrays(cls, arrays: dict[str, np.ndarray]) -> Subject:
        """The subject held by a file's arrays (format and sha256 removed); KeyError for a missing one."""
        return cls(
            shape=arrays["shape"],
            offsets=arrays["offsets"],
            model=str(arrays["model"]),
            poses=arrays["poses"],
            roots=arrays["roots"],
            scans=tuple(str(s) for s in arrays["scans"]),
            report=dict(
                zip(map(str, arrays["report_keys"]), map(float, arrays["report_values"]), strict=True)
            ),
            weights=arrays["weights"] if arrays["weights"].size else None,
            scale_offsets=arrays["scale_offsets"] if arrays["scale_offsets"].size else None,
        )

    @classmethod
    def load(cls, path: str | Path, model: BodyModel | None = None) -> Subject:
        return cls.from_bytes(Path(path).read_bytes(), model)

    def _arrays(self) -> dict[str, np.ndarray]:
        return {
            "format": np.array(FORMAT),
            "shape": np.asarray(self.shape, np.float64),
            "offsets": np.asarray(self.offsets, np.float64),
            "model": np.array(self.model),
            "poses": np.asarray(self.poses, np.float64),
            "roots": np.asarray(self.roots, np.float64),
            "scans": np.array(self.scans, dtype=str),
            "report_keys": np.array(list(self.report), dtype=str),
            "report_values": np.array(list(self.report.values()), np.float64),
            "weights": np.zeros(0) if self.weights is None else np.asarray(self.weights, np.float64),
            "scale_offsets": np.zeros(0)
            if self.scale_offsets is None
            else np.asarray(self.scale_offsets, np.float64),
        }


def _digest(arrays: dict[str, np.ndarray]) -> str:
    h = hashlib.sha256()
    for name in sorted(arrays):
        a = np.ascontiguousarray(arrays[name])
        h.update(name.encode() + str(a.dtype).encode() + str(a.shape).encode() + a.tobytes())
    return h.hexdigest()
