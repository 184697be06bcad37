"""Growing a shape space from scans of a population it does not cover (BLiSS, issue 40 deliverable 3).

What is measured
----------------
* Population: our own bodies (shape coefficients from N(0, 1)) carrying a population's soft tissue the
  shipped space has never seen: ``N_FIELDS`` smooth offset fields along the skin's normal (each a sum of
  Gaussian bumps of 6-14 cm radius and 1.5-3 cm height on the torso, hips and limbs, fixed for the
  population, seed 1) with per-person amplitudes drawn from N(1, 0.35), plus a smaller per-person smooth
  field of its own. Training scans and held-out bodies are drawn apart (seeds 2 and 3).
* Scans: each body posed in the zero pose (standing, arms down) with its offsets skinned along. Quick: the
  posed meshes themselves in our topology (registration-quality inputs, which the batch fit fits as
  registrations: seconds each, and which the rounds unpose as they are instead of projecting them); full:
  raw scans made from them as in ``benchmarks/fit_scans.py`` (surface points with 2 mm noise, 8 % holes,
  40,000 points; ``bodyfit batch-fit`` fits them as raw scans: 4-62 s each on 2 shared cores, and each
  round registers the pending scans in seconds each; the full run takes about 6 minutes there unloaded,
  more when the cores are shared: run it in the background).
  Quick: 16 scans, 12 held-out bodies, 4 rounds; full: 32 scans, 16 held-out bodies, 6 rounds.
* First round: ``bodyfit batch-fit`` (the SDK's batch engine, local back-end) fits every scan in the
  shipped space; ``bodyfit grow-space``'s rounds then reuse each scan's pose and re-project its shape,
  refine non-rigidly and accept (:mod:`bodyfit.models.spaces.grow`).
* ``grow_v2v_mm_original`` / ``grow_v2v_mm_grown``: the held-out bodies' bind-pose meshes replaced by their
  least-squares template in the shipped / grown space with the same coefficient count (the best any fit in
  that space can do; BLiSS Table 2's "PCA only"), mean vertex distance; ``grow_ratio``: grown over
  original (target <= 0.6). ``grow_v2p_mm_*``: the same, point to the reconstruction's tangent plane.
  ``grow_v2v_mm_population``: the shipped space's own population (bodies drawn from it), in the grown
  space: what growing costs the bodies the space already covered (0 for the shipped space).
* ``grow_rounds``, ``grow_accepted``: rounds run and registrations accepted; ``grow_curve``: per round,
  accepted (new, total), Chamfer distances and the held-out v2v / v2p (mm and BLiSS's cm).
* ``grow_anny_*`` (quick run): the same keys for a second space grown from anny bodies outside the adult
  population the shipped space was learned from: children (ages 5-18) and adults at the corners of anny's
  phenotype sliders (extreme BMI, height and proportions), half each, as meshes in our topology (16 to
  grow from, 12 held out; :func:`outside_population`), unposed as they are.

Usage::

    python benchmarks/grow_space.py [--quick] [--json]
    python benchmarks/grow_space.py --render build/grow/full/grown docs/grow_space_components.png

The grown space is written to ``build/grow/{quick,full}/grown`` (a complete asset folder); ``--render``
draws a space's first identity components.
"""

from __future__ import annotations

import shutil
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[1]
N_FIELDS = 3


def offset_fields(rest: np.ndarray, normals: np.ndarray, k: int, rng: np.random.Generator) -> np.ndarray:
    """``k`` smooth offset fields (k, V, 3) along the mean body's normals (V, 3): each a sum of 3 Gaussian
    bumps (radius 6-14 cm, height 1.5-3 cm, either sign) centred on random vertices of the body (V, 3) below
    the neck."""
    below_neck = np.flatnonzero(rest[:, 1] < np.quantile(rest[:, 1], 0.82))
    fields = np.zeros((k, *rest.shape))
    for f in range(k):
        for _ in range(3):
            centre = rest[rng.choice(below_neck)]
            radius, height = rng.uniform(0.06, 0.14), rng.uniform(0.015, 0.03) * rng.choice([-1.0, 1.0])
            bump = height * np.exp(-np.sum((rest - centre) ** 2, axis=1) / (2 * radius**2))
            fields[f] += bump[:, None] * normals
    return fields


def population(
    model: Any, fields: np.ndarray, n: int, seed: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``n`` bodies of the offset population: shape coefficients (n, n_shape), rest-pose offsets (n, V, 3)
    (the population's fields with N(1, 0.35) amplitudes plus a personal field at a third of the height) and
    bind-pose meshes (n, V, 3)."""
    from bodyfit.models.fitting.common.surface import vertex_normals
    from bodyfit.models.spaces.population import rest_meshes

    rng = np.random.default_rng(seed)
    shape = rng.normal(size=(n, model.n_shape)) * 0.8
    bind = rest_meshes(model.data, shape)
    normals = vertex_normals(bind, model.faces)
    offsets = np.empty_like(bind)
    for i in range(n):
        amplitude = rng.normal(1.0, 0.35, len(fields))
        personal = offset_fields(bind[i], normals[i], 1, rng)[0] / 3.0
        offsets[i] = np.einsum("k,kvc->vc", amplitude, fields) + personal
    return shape, offsets, bind + offsets


def posed_meshes(model: Any, shape: np.ndarray, offsets: np.ndarray) -> np.ndarray:
    """The bodies (n, V, 3) of shapes (n, n_shape) with rest-pose offsets (n, V, 3), in the zero pose."""
    decoder = model.decoder(torch.float64, "lbs")
    q = torch.zeros(1, model.skeleton.n_dof, dtype=torch.float64)
    out = []
    for i in range(len(shape)):
        with torch.no_grad():
            v = decoder.with_offsets(offsets[i])(torch.as_tensor(shape[i : i + 1]), q, torch.zeros(1, 3))[0]
        out.append(v[0].double().numpy())
    return np.stack(out)


def fitted_errors(model: Any, data: dict[str, np.ndarray], posed: np.ndarray) -> dict[str, float]:
    """The held-out bodies (n, V, 3) fitted in the space ``data`` (pose and shape, the registered fitter):
    mean vertex-to-vertex and vertex-to-plane distance of the fitted body to each (mm, and v2v in cm)."""
    from bodyfit.models.body.model import BodyModel
    from bodyfit.models.fitting.common.surface import vertex_normals
    from bodyfit.models.fitting.registered.fitter import RegisteredFitter

    fit = RegisteredFitter(BodyModel(model.skeleton, data)).fit(posed)
    diff = posed - fit.vertices
    v2v = float(np.linalg.norm(diff, axis=-1).mean()) * 1e3
    v2p = float(np.abs((diff * vertex_normals(fit.vertices, model.faces)).sum(-1)).mean()) * 1e3
    return {"fit_v2v_mm": round(v2v, 3), "fit_v2p_mm": round(v2p, 3), "fit_v2v_cm": round(v2v / 10, 4)}


def write_scans(model: Any, shape: np.ndarray, offsets: np.ndarray, out: Path, raw: bool) -> None:
    """One scan per body in the zero pose: the posed mesh in our topology (``raw`` False) or, as a raw scan,
    its surface points with 2 mm noise and 8 % holes (binary PLY point cloud)."""
    from benchmarks.corrupt import add_noise, remove_patches
    from bodyfit.clients.batch_fit import ply_bytes

    out.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(4)
    for i, v in enumerate(posed_meshes(model, shape, offsets)):
        if raw:
            points, _ = remove_patches(add_noise(surface_points(v, model.faces, rng), 0.002, rng), 0.08, rng)
            (out / f"body_{i:03d}.ply").write_bytes(ply_bytes(points, np.zeros((0, 3), np.int64)))
        else:
            (out / f"body_{i:03d}.ply").write_bytes(ply_bytes(v, model.faces))


def surface_points(v: np.ndarray, faces: np.ndarray, rng: np.random.Generator, n: int = 40000) -> np.ndarray:
    """``n`` points (n, 3) uniform on the mesh (V, 3), (F, 3) by area."""
    tri = v[faces]
    area = np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    pick = rng.choice(len(faces), n, p=area / area.sum())
    a, b = rng.random((2, n, 1))
    flip = (a + b) > 1
    a, b = np.where(flip, 1 - a, a), np.where(flip, 1 - b, b)
    t = tri[pick]
    return np.asarray(t[:, 0] + a * (t[:, 1] - t[:, 0]) + b * (t[:, 2] - t[:, 0]))


def outside_population(model: Any, n_train: int, n_held: int) -> tuple[tuple[np.ndarray, ...], ...]:
    """anny children (ages 5-18) and adults at the corners of anny's phenotype sliders, half each, as bodies
    of our model: shapes (n, n_shape) whose bone part is the fitted skeleton's and identity part zero, and
    rest-pose offsets (n, V, 3) that carry the rest of each body (its identity offsets from the bone-corrected
    mean, :mod:`bodyfit.models.decoders.population`). Returns (shape, offsets) of ``n_train`` training
    bodies and (shape, offsets, bind meshes) of ``n_held`` held-out ones, each half children."""
    from bodyfit.models.decoders.pipeline import default_work_dir, identity_sets
    from bodyfit.models.spaces.population import rest_meshes

    sets = identity_sets(model, default_work_dir())
    half_train, half_held = n_train // 2, n_held // 2
    parts: list[list[np.ndarray]] = [[], [], [], []]
    for name in ("children", "extreme"):
        s = sets[name]
        for k, rows in enumerate((slice(0, half_train), slice(half_train, half_train + half_held))):
            c = np.zeros((len(s.c_bone[rows]), model.n_shape))
            c[:, : model.n_bone] = s.c_bone[rows]
            parts[2 * k].append(c)
            parts[2 * k + 1].append(np.asarray(s.offsets[rows], np.float64))
    shape, offsets, held_shape, held_offsets = (np.concatenate(p) for p in parts)
    return (shape, offsets), (held_shape, held_offsets, rest_meshes(model.data, held_shape) + held_offsets)


def grow_and_measure(
    model: Any,
    train: tuple[np.ndarray, ...],
    held: tuple[np.ndarray, ...],
    work: Path,
    raw: bool,
    rounds: int,
) -> dict[str, Any]:
    """Scans of the ``train`` bodies (shapes, rest-pose offsets) written under ``work``, fitted through the
    batch engine, the space grown from them and the ``held`` bodies (shapes, offsets, bind meshes) measured
    in it after every round: the keys of :func:`run` without the population's."""
    from bodyfit.cli.backends import fitter
    from bodyfit.clients.batch_fit import batch_fit
    from bodyfit.models.assets import assets_dir
    from bodyfit.models.spaces.grow import GrowConfig, grow_space
    from bodyfit.models.spaces.population import parametric_errors
    from bodyfit.models.spaces.register import read_fit
    from bodyfit.models.spaces.writer import write_space

    t0 = time.perf_counter()
    held_posed = posed_meshes(model, held[0], held[1])
    write_scans(model, train[0], train[1], work / "scans", raw=raw)
    batch = batch_fit(work / "scans", work / "fits", backend=fitter("local"), progress=False)
    names = sorted(Path(p).stem for p in batch.done + batch.skipped)
    scans = [read_fit(work / "scans" / f"{p}.ply", work / "fits" / f"{p}.npz") for p in names]
    fit_s = time.perf_counter() - t0

    def evaluate(data: dict[str, np.ndarray]) -> dict[str, float]:
        return {**parametric_errors(data, held[2], model.faces), **fitted_errors(model, data, held_posed)}

    result = grow_space(model, scans, GrowConfig(rounds=rounds), evaluate=evaluate, log=_err)
    grown = work / "grown"
    shutil.rmtree(grown, ignore_errors=True)
    write_space(assets_dir(), grown, model, result.data, result.report())
    first, last = result.rounds[0], result.rounds[-1]
    keys = (
        "round",
        "accepted",
        "accepted_total",
        "fit_v2v_mm",
        "fit_v2p_mm",
        "fit_v2v_cm",
        "v2v_mm",
        "v2p_mm",
    )
    return {
        "grow_ratio": round(last["fit_v2v_mm"] / first["fit_v2v_mm"], 3),
        "grow_v2v_mm_original": first["fit_v2v_mm"],
        "grow_v2v_mm_grown": last["fit_v2v_mm"],
        "grow_v2p_mm_original": first["fit_v2p_mm"],
        "grow_v2p_mm_grown": last["fit_v2p_mm"],
        "grow_span_ratio": round(last["v2v_mm"] / first["v2v_mm"], 3),
        "grow_rounds": len(result.rounds) - 1,
        "grow_accepted": len(result.accepted),
        "grow_scans": len(scans),
        "grow_span_v2v_mm_original": first["v2v_mm"],
        "grow_span_v2v_mm_grown": last["v2v_mm"],
        "grow_fit_s": round(fit_s, 1),
        "grow_curve": [{k: r[k] for k in keys if k in r} for r in result.rounds],
        "_data": result.data,
    }


def run(quick: bool, work: Path | None = None) -> dict[str, Any]:
    """Build the offset population, fit it through the batch engine, grow the space and measure it; on the
    quick run also grow a space from anny children and extreme adults (keys ``grow_anny_*``)."""
    from bodyfit.models.body.model import BodyModel
    from bodyfit.models.fitting.common.surface import vertex_normals
    from bodyfit.models.spaces.population import parametric_errors, rest_meshes, sample_population

    torch.set_num_threads(1)
    t0 = time.perf_counter()
    model = BodyModel.load()
    mean = rest_meshes(model.data, np.zeros((1, model.n_shape)))[0]
    fields = offset_fields(mean, vertex_normals(mean, model.faces), N_FIELDS, np.random.default_rng(1))
    n_scans, n_held = (16, 12) if quick else (32, 16)
    shape, offsets, _ = population(model, fields, n_scans, seed=2)
    held = population(model, fields, n_held, seed=3)
    work = work or ROOT / "build" / "grow" / ("quick" if quick else "full")
    out = grow_and_measure(model, (shape, offsets), held, work, not quick, 4 if quick else 6)
    covered = sample_population(model, 24, seed=5).meshes
    data = out.pop("_data")
    out["grow_v2v_mm_population"] = parametric_errors(data, covered, model.faces)["v2v_mm"]
    out["grow_coefficients"] = model.n_shape
    if quick:
        train, held_anny = outside_population(model, 16, 12)
        anny = grow_and_measure(model, train, held_anny, work.parent / f"{work.name}_anny", False, 4)
        anny.pop("_data")
        out.update({k.replace("grow_", "grow_anny_", 1): v for k, v in anny.items()})
    out["grow_s"] = round(time.perf_counter() - t0, 1)
    return out


def render_components(folder: Path, out: Path, k: int = 4) -> None:
    """The first ``k`` identity components of the space in asset folder ``folder``: the mean body in the bind
    pose with the component at -3 and +3 standard deviations, from the front and the side, one row per
    component (PNG ``out``)."""
    from benchmarks.render import RenderMesh, label_grid, render, save_png, tile
    from bodyfit.models.body.model import BodyModel
    from bodyfit.models.spaces.population import rest_meshes

    model = BodyModel.load(folder)
    images, rows = [], []
    skin = (0.85, 0.65, 0.55)
    for i in range(k):
        c = np.zeros((2, model.n_shape))
        c[:, model.n_bone + i] = (-3.0, 3.0)
        meshes = rest_meshes(model.data, c)
        lo, hi = meshes.reshape(-1, 3).min(0) - 0.02, meshes.reshape(-1, 3).max(0) + 0.02
        for view in ("front", "side"):
            for v in meshes:
                images.append(render([RenderMesh(v, model.faces, skin)], view, (240, 360), bounds=(lo, hi)))
        rows.append(f"identity {i + 1}")
    columns = [["front -3 sd", "front +3 sd", "side -3 sd", "side +3 sd"]]
    save_png(label_grid(tile(images, 4), columns, rows), out)


def _err(line: str) -> None:
    print(line, file=sys.stderr)


def main(argv: list[str] | None = None) -> None:
    from benchmarks.bench_cli import bench_main

    args = sys.argv[1:] if argv is None else argv
    if args[:1] == ["--render"]:
        render_components(Path(args[1]), Path(args[2]))
        return

    bench_main(
        run,
        "Growing a shape space from scans of a population it does not cover (BLiSS).",
        "16 registration-quality scans, 12 held-out bodies",
        argv,
    )


if __name__ == "__main__":
    sys.path.insert(0, str(ROOT))
    main()
