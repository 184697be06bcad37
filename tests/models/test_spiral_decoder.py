"""The spiral identity decoder: pooling hierarchy, spirals, convolution, training, latent fitting, the body
decoder it plugs into, its asset checks, bad input and ONNX parity."""

from __future__ import annotations

import json
import shutil
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import torch

from bodyfit.models.assets import assets_dir, sha256
from bodyfit.models.body.model import BodyModel
from bodyfit.models.decoders import mesh_hierarchy as mh
from bodyfit.models.decoders.asset import SpiralBodyModel, asset_name, load_asset
from bodyfit.models.decoders.export import SpiralBody, bone_only_decoder
from bodyfit.models.decoders.spiral import (
    Gather,
    Hierarchy,
    SpiralConv,
    SpiralDecoder,
    build_hierarchy,
    dense,
)
from bodyfit.models.decoders.train import TrainConfig, fit_latents, train_spiral, vertex_distance
from bodyfit.models.errors import AssetError, NonFiniteError, ShapeError


@pytest.fixture(scope="module")
def sphere() -> tuple[np.ndarray, np.ndarray]:
    import trimesh

    mesh = trimesh.creation.icosphere(subdivisions=3)
    return np.asarray(mesh.vertices), np.asarray(mesh.faces)


@pytest.fixture(scope="module")
def sphere_hierarchy(sphere: tuple[np.ndarray, np.ndarray]) -> Hierarchy:
    return build_hierarchy(*sphere, factors=(2, 2), length=7)


@pytest.fixture(scope="module")
def body() -> BodyModel:
    return BodyModel.load()


@pytest.fixture(scope="module")
def shipped(body: BodyModel) -> SpiralBodyModel:
    return SpiralBodyModel(body, load_asset(8))


def _edge_counts(faces: np.ndarray) -> np.ndarray:
    e = np.sort(np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]]), axis=1)
    return np.unique(e, axis=0, return_counts=True)[1]


def test_decimation_keeps_a_closed_manifold_and_the_kept_positions(
    sphere: tuple[np.ndarray, np.ndarray],
) -> None:
    v, f = sphere
    coarse = mh.decimate(v, f, len(v) // 4)
    assert len(coarse.vertices) == len(v) // 4
    assert (_edge_counts(coarse.faces) == 2).all()  # every edge between exactly two triangles
    assert len(coarse.faces) == 2 * len(coarse.vertices) - 4  # still a sphere (Euler characteristic 2)
    np.testing.assert_array_equal(coarse.vertices, v[coarse.kept])


def test_upsampling_is_barycentric_and_copies_the_kept_vertices(
    sphere: tuple[np.ndarray, np.ndarray],
) -> None:
    v, f = sphere
    coarse = mh.decimate(v, f, len(v) // 2)
    index, weight = mh.upsampling(v, coarse)
    np.testing.assert_allclose(weight.sum(axis=1), 1.0, atol=1e-12)
    assert (weight >= -1e-12).all()
    carried = (weight[:, :, None] * coarse.vertices[index]).sum(axis=1)
    np.testing.assert_allclose(carried[coarse.kept], v[coarse.kept], atol=1e-12)
    # Removed vertices land on the coarse surface near where they were (a unit sphere, edges ~0.15).
    assert np.linalg.norm(carried - v, axis=1).max() < 0.05


def test_spirals_start_at_the_vertex_then_its_ring(sphere: tuple[np.ndarray, np.ndarray]) -> None:
    v, f = sphere
    s = mh.spirals(v, f, 9)
    assert s.shape == (len(v), 9)
    np.testing.assert_array_equal(s[:, 0], np.arange(len(v)))
    for a in (0, 17, 300):
        ring = set(f[(f == a).any(axis=1)].ravel()) - {a}
        assert set(s[a, 1 : 1 + len(ring)]) == ring
        assert len(set(s[a])) == 9  # no repeats on a closed mesh this fine


def test_spiral_conv_is_the_weighted_sum_over_each_spiral(sphere_hierarchy: Hierarchy) -> None:
    torch.manual_seed(0)
    spiral = sphere_hierarchy.spirals[1]
    conv = SpiralConv(spiral, 5, 3)
    x = torch.randn(len(spiral), 2, 5)
    direct = conv.linear(x[torch.as_tensor(spiral)].permute(2, 0, 1, 3).reshape(2, len(spiral), -1))
    np.testing.assert_allclose(conv(x).detach().numpy(), direct.permute(1, 0, 2).detach().numpy(), atol=1e-5)
    dense(conv)
    np.testing.assert_allclose(conv(x).detach().numpy(), direct.permute(1, 0, 2).detach().numpy(), atol=1e-5)


def test_gather_sparse_and_dense_paths_agree() -> None:
    rng = np.random.default_rng(0)
    g = Gather(rng.integers(0, 7, (5, 3)), rng.random((5, 3)), 7)
    x = torch.randn(7, 4)
    sparse = g(x)
    g.sparse = False
    np.testing.assert_allclose(sparse.numpy(), g(x).numpy(), atol=1e-6)


def test_untrained_decoder_is_the_linear_model(sphere_hierarchy: Hierarchy) -> None:
    rng = np.random.default_rng(1)
    V = sphere_hierarchy.sizes[0]
    basis, mean = rng.normal(size=(3, V, 3)), rng.normal(size=(V, 3))
    dec = SpiralDecoder(sphere_hierarchy, 3, basis, mean)
    z = rng.normal(size=(4, 3))
    expected = mean + np.einsum("bk,kvc->bvc", z, basis)
    np.testing.assert_allclose(
        dec(torch.as_tensor(z, dtype=torch.float32)).detach().numpy(), expected, atol=1e-4
    )


def _bent_spheres(v: np.ndarray, n: int, seed: int) -> np.ndarray:
    """Offsets (n, V, 3) nonlinear in two parameters: a bulge whose place and size vary."""
    rng = np.random.default_rng(seed)
    a, b = rng.uniform(-1, 1, n), rng.uniform(-1, 1, n)
    centre = np.stack([np.cos(a), np.sin(a), 0 * a], 1)
    w = np.exp(-4.0 * ((v[None] - centre[:, None]) ** 2).sum(-1))
    return 0.01 * (1.5 + b)[:, None, None] * w[:, :, None] * v[None]


def test_training_beats_the_pca_of_equal_size_on_a_nonlinear_family(sphere_hierarchy: Hierarchy) -> None:
    import trimesh

    from bodyfit.models.decoders.train import compare, pca_of

    v = np.asarray(trimesh.creation.icosphere(subdivisions=3).vertices)
    train, test = _bent_spheres(v, 256, 0), _bent_spheres(v, 40, 1)
    torch.manual_seed(0)
    config = TrainConfig(d=2, minutes=5.0, batch=16, epochs=10)
    trained = train_spiral(sphere_hierarchy, train, config, log=lambda _: None)
    assert trained.history[-1]["train_mm"] < trained.history[0]["train_mm"]
    result = compare(trained, pca_of(train, 2), test)
    assert result["spiral_mm"] < 0.95 * result["pca_mm"]


def test_fit_latents_recovers_the_codes_of_decoded_bodies(sphere_hierarchy: Hierarchy) -> None:
    torch.manual_seed(2)
    dec = SpiralDecoder(sphere_hierarchy, 3, np.random.default_rng(2).normal(size=(3, 642, 3)) * 0.01)
    for p in dec.out.parameters():
        torch.nn.init.normal_(p, std=0.3)
    z = np.random.default_rng(3).normal(size=(5, 3))
    with torch.no_grad():
        target = dec(torch.as_tensor(z, dtype=torch.float32)).numpy()
    found = fit_latents(dec, target, np.zeros_like(z), iterations=15)
    with torch.no_grad():
        err = vertex_distance(dec(torch.as_tensor(found, dtype=torch.float32)), torch.as_tensor(target))
    assert float(err) < 1e-5


# -- the shipped decoder and the body decoder ------------------------------------------------------------


def test_spiral_body_equals_the_linear_model_when_the_convolutions_are_off(
    body: BodyModel, shipped: SpiralBodyModel
) -> None:
    """With the identity PCA as the linear term and the convolutions zeroed, the spiral body decoder must
    give the linear body model's skin and joints (same skinning, same skeleton)."""
    d = shipped.d
    h = Hierarchy.from_arrays(load_asset_arrays())
    spiral = SpiralDecoder(h, d, body.data["identity_basis"][:d].astype(np.float64))
    module = SpiralBody(
        bone_only_decoder(body.skeleton, body.data, torch.float32), spiral, np.zeros(d), np.ones(d)
    )
    rng = np.random.default_rng(4)
    shape = rng.normal(size=(3, body.n_bone + d))
    q = np.clip(0.3 * rng.normal(size=(3, body.skeleton.n_dof)), *body.skeleton.ranges.T)
    root = rng.normal(size=(3, 3))
    full = np.concatenate([shape, np.zeros((3, body.n_identity - d))], axis=1)
    ref = body.forward(full, q, root)
    with torch.no_grad():
        v, j = module(*(torch.as_tensor(a, dtype=torch.float32) for a in (shape, q, root)))
    np.testing.assert_allclose(v.numpy(), ref.vertices.numpy(), atol=2e-5)
    np.testing.assert_allclose(j.numpy(), ref.joints.numpy(), atol=2e-5)


def load_asset_arrays() -> dict[str, np.ndarray]:
    with np.load(assets_dir() / asset_name(8)) as z:
        return {k: z[k] for k in z.files}


def test_skeleton_follows_the_bone_coefficients_alone(body: BodyModel, shipped: SpiralBodyModel) -> None:
    rng = np.random.default_rng(5)
    c_b = rng.normal(size=(2, body.n_bone))
    q = np.clip(0.3 * rng.normal(size=(2, body.skeleton.n_dof)), *body.skeleton.ranges.T)
    a = shipped.forward(np.concatenate([c_b, rng.normal(size=(2, shipped.d))], 1), q)
    b = shipped.forward(np.concatenate([c_b, rng.normal(size=(2, shipped.d))], 1), q)
    ref = body.forward(np.concatenate([c_b, np.zeros((2, body.n_identity))], 1), q)
    np.testing.assert_allclose(a.joints.numpy(), ref.joints.numpy(), atol=1e-5)
    np.testing.assert_allclose(b.joints.numpy(), ref.joints.numpy(), atol=1e-5)
    assert float((a.vertices - b.vertices).abs().max()) > 1e-3  # the identity code does move the skin


def test_the_mean_code_gives_a_body_near_the_linear_mean(body: BodyModel, shipped: SpiralBodyModel) -> None:
    out = shipped.forward(np.zeros((1, shipped.n_shape)))
    ref = body.forward(np.zeros((1, body.n_shape)))
    assert float(np.linalg.norm(out.vertices.numpy() - ref.vertices.numpy(), axis=-1).mean()) < 5e-3


@pytest.mark.parametrize(
    ("shape", "error", "words"),
    [
        (np.zeros((1, 5)), ShapeError, "spiral identity code"),
        (np.zeros((2, 16)), ShapeError, "shape coefficients must have shape (1, 16)"),
        (np.full((1, 16), np.nan), NonFiniteError, "NaN"),
        (np.concatenate([np.zeros((1, 8)), np.full((1, 8), 5.5)], 1), ShapeError, "within +-5"),
    ],
)
def test_bad_codes_are_refused_with_what_was_expected(
    shipped: SpiralBodyModel, shape: np.ndarray, error: type[Exception], words: str
) -> None:
    with pytest.raises(error, match=words.replace("(", r"\(").replace(")", r"\)").replace("+", r"\+")):
        shipped.forward(shape, np.zeros((1, shipped.body.skeleton.n_dof)))


def _copy_assets(tmp_path: Path) -> Path:
    out = tmp_path / "assets"
    shutil.copytree(assets_dir(), out, ignore=shutil.ignore_patterns("*.onnx"))
    return out


def test_a_decoder_trained_for_another_body_model_is_refused(tmp_path: Path) -> None:
    folder = _copy_assets(tmp_path)
    data: dict[str, Any] = load_asset_arrays()
    data["body_sha256"] = np.asarray("0" * 64)
    path = folder / asset_name(8)
    np.savez_compressed(path, **data)
    manifest = json.loads((folder / "manifest.json").read_text())
    manifest["files"][asset_name(8)]["sha256"] = sha256(path)
    (folder / "manifest.json").write_text(json.dumps(manifest))
    with pytest.raises(AssetError, match="trained for the body model 000000000000"):
        load_asset(8, folder)


def test_a_corrupted_decoder_asset_is_refused(tmp_path: Path) -> None:
    folder = _copy_assets(tmp_path)
    with (folder / asset_name(8)).open("ab") as f:
        f.write(b"x")
    with pytest.raises(AssetError, match="corrupted or stale"):
        load_asset(8, folder)


def test_onnx_matches_torch(shipped: SpiralBodyModel) -> None:
    import onnxruntime as ort

    from bodyfit.models.decoders.export import export_spiral_onnx

    module = SpiralBody(shipped.module.body, shipped.asset.decoder, shipped.asset.latent_mean,
                        shipped.asset.latent_std)  # fmt: skip
    session = ort.InferenceSession(export_spiral_onnx(module), providers=["CPUExecutionProvider"])
    rng = np.random.default_rng(6)
    sk = shipped.body.skeleton
    for batch in (1, 3):
        shape = rng.normal(size=(batch, shipped.n_shape)).clip(-2, 2).astype(np.float32)
        q = np.clip(0.3 * rng.normal(size=(batch, sk.n_dof)), *sk.ranges.T).astype(np.float32)
        root = rng.normal(size=(batch, 3)).astype(np.float32)
        v, j = session.run(None, {"shape": shape, "coordinates": q, "root": root})
        ref = shipped.forward(shape, q, root)
        assert np.abs(v - ref.vertices.numpy()).max() <= 1e-5
        assert np.abs(j - ref.joints.numpy()).max() <= 1e-5
