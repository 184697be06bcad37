"""Anthropometry: bodies built from real people's measurements, and today's population against NHANES.

What is measured
----------------
* Data: ANSUR II (US Army 2012: 4,082 men, 1,986 women) and NHANES 2017-2020 adults from
  ../shared/data/anthropometry when present, else the 200-per-sex and 500-per-sex extracts in
  tests/data/anthropometry. Subjects are split 80/20 per sex with seed 39; scores are on the test split.
* Prior: bodies are built under a Gaussian prior over the shape coefficients per sex, learned from the
  bodies built (under the mean ANSUR II body of the sex) for 400 training subjects (60 with ``--quick``),
  its precision scaled by :data:`REPRO_PRIOR` for bodies built from full rows and by
  :data:`PREDICT_PRIOR` for bodies built from the six inputs (chosen on training subjects held out of the
  prior, never on the test split; docs/anthropometry.md).
* ``repro_*``: a body built (``fit_measurements``) from all of a test subject's
  measurements that have an ANSUR II column; mean absolute error of its measurements against the subject's,
  over heights, lengths and breadths (``repro_mae_length_mm``), circumferences (``repro_mae_circ_mm``)
  and the weight (``repro_mae_mass_kg``); ``repro_worst_mm`` the six measurements reproduced worst.
* ``predict_mae_mm``: a body built from sex, stature, weight, chest, waist and buttock circumference;
  mean absolute error over the subject's other measurements (mm). ``baseline_mae_mm``: a least-squares
  linear regression from the same inputs (and sex) fitted on the training split, in the same run;
  ``predict_ratio`` the first over the second.
* ``mass_from_volume_mae_kg`` and ``implied_density``: a body built from every measurement but the
  weight; its volume against the subject's weight (the density that would make the median error zero).
* ``measure_ms_b1``: one body synthesized and measured (median of 20 runs, one thread).
* ``ks_{stature,mass,bmi,waist,hip}_{male,female}``: two-sample Kolmogorov-Smirnov statistic between the
  measurements of bodies drawn from the NHANES population
  (:func:`bodyfit.models.anthropometry.population.sample`, seed 0; 2,000 per sex, 4,000 in a full run) and
  NHANES adults of each sex; waist is NHANES's (at the iliac crest), hip the buttock circumference.
  ``ks_anny_*`` the same for the model's standard-normal draws (both sexes against each).

Usage::

    python benchmarks/anthropometry.py [--quick] [--json]
    python benchmarks/anthropometry.py figure docs/anthropometry_tapes.png
    python benchmarks/anthropometry.py calibrate     # print the definitions' calibration (calibration.py)
    python benchmarks/anthropometry.py priors        # the prior weights on held-out training subjects
    python benchmarks/anthropometry.py bootstrap OUT.npz [--per-sex N] [--rounds R] [--full]
    python benchmarks/anthropometry.py populations   # rebuild bodyfit/models/anthropometry/populations.npz
"""

from __future__ import annotations

import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
import torch

from bodyfit.models.anthropometry.calibration import learn_calibration
from bodyfit.models.anthropometry.definitions import MEASUREMENTS
from bodyfit.models.anthropometry.inverse import (
    NAMES,
    evaluate,
    fit_measurements,
    gaussian_prior,
    sex_prior_mean,
)
from bodyfit.models.anthropometry.measure import DENSITY, measure
from bodyfit.models.anthropometry.population import POPULATION_FILE, build_populations, sample
from bodyfit.models.anthropometry.surveys import read_ansur, read_nhanes
from bodyfit.models.body.model import BodyModel

REPO = Path(__file__).resolve().parents[1]
SHARED = REPO.parent / "shared" / "data" / "anthropometry"
EXTRACTS = REPO / "tests" / "data" / "anthropometry"
SEED = 39
SEXES = ("male", "female")
INPUTS = ("stature", "weightkg", "chestcircumference", "waistcircumference", "buttockcircumference")
# The prior's weight per use, chosen on 80 training subjects per sex held out of the prior (``priors``;
# docs/anthropometry.md): a full row is met best under a tenth of the population's precision (the rows
# ask for more than the shape space holds, and the population's covariance is that of bodies built under
# a prior already); six inputs predict the rest best under four times it (what the inputs cannot all
# meet is left to the population's correlations rather than to a distorted body).
REPRO_PRIOR = 0.1
PREDICT_PRIOR = 4.0
KS_KEYS = {
    "stature": "stature",
    "mass": "weightkg",
    "waist": "waistcircumferenceiliaccrest",
    "hip": "buttockcircumference",
}


def load_surveys() -> tuple[dict[str, dict[str, np.ndarray]], dict[str, dict[str, np.ndarray]], str]:
    """ANSUR II and NHANES tables per sex, and where they came from."""
    if (SHARED / "ANSURII_MALE_Public.csv").exists():
        ansur = {s: read_ansur(SHARED / f"ANSURII_{s.upper()}_Public.csv") for s in SEXES}
        nhanes = {s: read_nhanes(SHARED / f"nhanes_adult_{s}_bmx_2020.csv") for s in SEXES}
        return ansur, nhanes, "shared"
    ansur = {s: read_ansur(EXTRACTS / f"ansur2_{s}_200.csv") for s in SEXES}
    nhanes = {s: read_nhanes(EXTRACTS / f"nhanes_adult_{s}_bmx_2020_500.csv") for s in SEXES}
    return ansur, nhanes, "tests/data"


def split(n: int, seed: int = SEED) -> tuple[np.ndarray, np.ndarray]:
    """80/20 train / test indices of n subjects."""
    order = np.random.default_rng(seed).permutation(n)
    cut = round(0.8 * n)
    return np.sort(order[:cut]), np.sort(order[cut:])


def table(data: dict[str, np.ndarray], rows: np.ndarray) -> np.ndarray:
    """(n, M) values in :data:`NAMES` order for ``rows``; NaN where the survey lacks the measurement."""
    return np.stack([data[n][rows] if n in data else np.full(len(rows), np.nan) for n in NAMES], 1)


def _mae_by_kind(pred: np.ndarray, truth: np.ndarray) -> dict[str, float]:
    err = np.abs(pred - truth)
    kinds = np.array([MEASUREMENTS[n].kind for n in NAMES])
    lengths = np.isin(kinds, ("height", "length", "breadth"))
    return {
        "repro_mae_length_mm": float(np.nanmean(err[:, lengths]) * 1000),
        "repro_mae_circ_mm": float(np.nanmean(err[:, kinds == "circumference"]) * 1000),
        "repro_mae_mass_kg": float(np.nanmean(err[:, kinds == "mass"])),
    }


def linear_baseline(
    train: np.ndarray, test: np.ndarray, sex_train: np.ndarray, sex_test: np.ndarray
) -> np.ndarray:
    """Least-squares predictions (n_test, M) of every measurement from sex and :data:`INPUTS`."""
    cols = [NAMES.index(n) for n in INPUTS]

    def design(x: np.ndarray, male: np.ndarray) -> np.ndarray:
        return np.column_stack([np.ones(len(x)), male, x[:, cols]])

    X = design(train, sex_train)
    out = np.full((len(test), len(NAMES)), np.nan)
    for m in range(len(NAMES)):
        ok = np.isfinite(train[:, m])
        if ok.sum() > X.shape[1]:
            coef = np.linalg.lstsq(X[ok], train[ok, m], rcond=None)[0]
            out[:, m] = design(test, sex_test) @ coef
    return out


Prior = tuple[np.ndarray, np.ndarray]


def _fit(
    model: BodyModel, targets: np.ndarray, sexes: np.ndarray, priors: dict[str, Prior], weight: float = 1.0
) -> np.ndarray:
    """Measurements (n, M) of the bodies built from ``targets`` (n, M; NaN = not given) under each sex's
    prior (mean, precision), its precision times ``weight``."""
    out = np.empty_like(targets)
    for s in SEXES:
        rows = np.flatnonzero(sexes == s)
        if len(rows):
            mean, precision = priors[s]
            out[rows] = fit_measurements(model, targets[rows], mean, weight * precision)[1]
    return out


def learn_priors(model: BodyModel, train: dict[str, np.ndarray], n: int) -> dict[str, Prior]:
    """Each sex's Gaussian prior over the coefficients, from bodies built (under the mean-body prior of the
    sex) for ``n`` training subjects' full measurement rows."""
    priors = {}
    for s in SEXES:
        rows = train[s][np.random.default_rng(SEED).permutation(len(train[s]))[:n]]
        shapes, _ = fit_measurements(model, rows, sex_prior_mean(model, s))
        priors[s] = gaussian_prior(shapes)
    return priors


def scores(
    model: BodyModel, ansur: dict[str, dict[str, np.ndarray]], per_sex: int | None, n_prior: int
) -> dict[str, Any]:
    """Reproduction, prediction and mass-from-volume scores on the test split (``per_sex`` test subjects
    per sex at most), the bodies built under priors learned from ``n_prior`` training subjects per sex."""
    train_rows, test_rows = {}, {}
    for s in SEXES:
        train, test = split(len(ansur[s]["stature"]))
        train_rows[s] = table(ansur[s], train)
        test_rows[s] = table(ansur[s], test[:per_sex] if per_sex else test)
    priors = learn_priors(model, train_rows, n_prior)
    train, test = np.concatenate(list(train_rows.values())), np.concatenate(list(test_rows.values()))
    sex_train = np.concatenate([np.full(len(train_rows[s]), s) for s in SEXES])
    sex_test = np.concatenate([np.full(len(test_rows[s]), s) for s in SEXES])
    out: dict[str, Any] = {"test_subjects": len(test), "prior_subjects": 2 * n_prior}
    reproduced = _fit(model, test, sex_test, priors, REPRO_PRIOR)
    out.update(_mae_by_kind(reproduced, test))
    err = np.abs(reproduced - test)
    per = np.nansum(err, 0) / np.maximum(np.isfinite(err).sum(0), 1)  # 0 where ANSUR II has no column
    worst = [k for k in np.argsort(-per) if NAMES[k] != "weightkg"][:6]
    out["repro_worst_mm"] = {NAMES[k]: round(float(per[k]) * 1000, 1) for k in worst}
    given = np.isin(NAMES, INPUTS)
    others = ~given & np.isfinite(test).all(0)
    predicted = _fit(model, np.where(given, test, np.nan), sex_test, priors, PREDICT_PRIOR)
    baseline = linear_baseline(train, test, sex_train == "male", sex_test == "male")
    out["predict_mae_mm"] = float(np.mean(np.abs(predicted - test)[:, others]) * 1000)
    out["baseline_mae_mm"] = float(np.mean(np.abs(baseline - test)[:, others]) * 1000)
    out["predict_ratio"] = out["predict_mae_mm"] / out["baseline_mae_mm"]
    mass = NAMES.index("weightkg")
    no_weight = test.copy()
    no_weight[:, mass] = np.nan
    from_volume = _fit(model, no_weight, sex_test, priors, REPRO_PRIOR)[:, mass]
    out["mass_from_volume_mae_kg"] = float(np.mean(np.abs(from_volume - test[:, mass])))
    out["implied_density"] = float(DENSITY * np.median(test[:, mass] / from_volume))
    return out


def _ks(model: BodyModel, shapes: np.ndarray, real: dict[str, np.ndarray], prefix: str) -> dict[str, float]:
    """KS statistics of the bodies ``shapes`` (n, n_shape) against the survey columns ``real``."""
    from scipy.stats import ks_2samp

    ours = evaluate(model, shapes)
    mine = {k: ours[:, NAMES.index(name)] for k, name in KS_KEYS.items()}
    mine["bmi"] = mine["mass"] / mine["stature"] ** 2
    theirs = {k: real[name] for k, name in KS_KEYS.items()}
    theirs["bmi"] = theirs["mass"] / theirs["stature"] ** 2
    out = {}
    for key in ("stature", "mass", "bmi", "waist", "hip"):
        x = theirs[key][np.isfinite(theirs[key])]
        out[f"{prefix}{key}"] = round(float(ks_2samp(mine[key], x).statistic), 3)
    return out


def ks_scores(model: BodyModel, nhanes: dict[str, dict[str, np.ndarray]], n: int) -> dict[str, float]:
    """KS statistics of ``n`` draws per sex of the NHANES population against NHANES adults of that sex, and
    of ``n`` standard-normal draws against each sex (``ks_anny_*``)."""
    anny = sample(model, n, population="anny", seed=0)
    out: dict[str, float] = {}
    for s in SEXES:
        drawn = _ks(model, sample(model, n, sex=s, population="nhanes", seed=0), nhanes[s], "ks_")
        out |= {f"{k}_{s}": v for k, v in drawn.items()}
        out |= {f"{k}_{s}": v for k, v in _ks(model, anny, nhanes[s], "ks_anny_").items()}
    return out


def prior_weights(n_prior: int = 400, n_held: int = 80) -> None:
    """Print reproduction and prediction on ``n_held`` training subjects per sex held out of the prior
    (learned from ``n_prior`` others, as in :func:`scores`) for a range of prior weights: how
    :data:`REPRO_PRIOR` and :data:`PREDICT_PRIOR` were chosen without the test split."""
    torch.set_num_threads(1)
    model = BodyModel.load()
    ansur, _, _ = load_surveys()
    fit_rows, held_rows = {}, {}
    for s in SEXES:
        train, _ = split(len(ansur[s]["stature"]))
        rows = table(ansur[s], train)
        held = np.random.default_rng(SEED).permutation(len(rows))[:n_held]
        fit_rows[s], held_rows[s] = np.delete(rows, held, axis=0), rows[held]
    priors = learn_priors(model, fit_rows, n_prior)
    train, held = np.concatenate(list(fit_rows.values())), np.concatenate(list(held_rows.values()))
    sex_train = np.concatenate([np.full(len(fit_rows[s]), s) for s in SEXES])
    sex_held = np.concatenate([np.full(len(held_rows[s]), s) for s in SEXES])
    for weight in (1.0, 0.3, 0.1, 0.03):
        print(
            f"reproduction, prior x{weight}:", _mae_by_kind(_fit(model, held, sex_held, priors, weight), held)
        )
    given = np.isin(NAMES, INPUTS)
    others = ~given & np.isfinite(held).all(0)
    baseline = linear_baseline(train, held, sex_train == "male", sex_held == "male")
    base = np.mean(np.abs(baseline - held)[:, others])
    for weight in (1.0, 2.0, 4.0, 8.0):
        predicted = _fit(model, np.where(given, held, np.nan), sex_held, priors, weight)
        ratio = np.mean(np.abs(predicted - held)[:, others]) / base
        print(f"prediction, prior x{weight}: ratio {ratio:.4f}")


def bootstrap(args: list[str]) -> None:
    """Grow the shape space from ANSUR II training subjects (bodyfit.models.anthropometry.bootstrap) and
    score it as the benchmark does: ``bootstrap OUT.npz [--per-sex N] [--rounds R] [--full]`` writes the
    grown space's ``body.npz`` arrays to OUT.npz (never to assets/) and prints its rounds and scores (the
    quick run's test subjects, or all with ``--full``), under the shipped calibration."""
    from bodyfit.models.anthropometry.bootstrap import bootstrap_space

    torch.set_num_threads(1)
    out = Path(args[0])
    per_sex = int(args[args.index("--per-sex") + 1]) if "--per-sex" in args else 300
    rounds = int(args[args.index("--rounds") + 1]) if "--rounds" in args else 1
    model = BodyModel.load()
    ansur, _, _ = load_surveys()
    rows = {}
    for s in SEXES:
        train, _ = split(len(ansur[s]["stature"]))
        pick = np.random.default_rng(SEED + 1).permutation(len(train))[:per_sex]
        rows[s] = table(ansur[s], train[pick])
    grown = bootstrap_space(model, rows, rounds=rounds)
    np.savez(out, allow_pickle=False, **grown.data)
    print("rounds:", grown.rounds)
    full = "--full" in args
    result = scores(BodyModel(model.skeleton, grown.data), ansur, None if full else 40, 400 if full else 60)
    print({k: round(v, 3) if isinstance(v, float) else v for k, v in result.items()})


def calibrate(per_sex: int = 200) -> None:
    """Learn the definitions' scales, offsets and the density (bodyfit.models.anthropometry.calibration) on
    ``per_sex`` subjects of each sex's training split, and print them as the sources' tables."""
    torch.set_num_threads(1)
    model = BodyModel.load()
    ansur, _, _ = load_surveys()
    rows = {}
    for s in SEXES:
        train, _ = split(len(ansur[s]["stature"]))
        rows[s] = table(ansur[s], train[np.random.default_rng(SEED).permutation(len(train))[:per_sex]])
    learned = learn_calibration(model, rows, NAMES)
    print(f"DENSITY = {learned.density}")
    for title, values in (("SCALES", learned.scales), ("OFFSETS", learned.offsets)):
        print(f"{title}: dict[str, float] = {{")
        for name, value in values.items():
            print(f'    "{name}": {value},')
        print("}")


def build(args: list[str]) -> None:
    """Rebuild the stored populations from the full surveys in ../shared/data/anthropometry: 500 ANSUR II
    subjects and 2,000 NHANES adults (with all five measurements) per sex, drawn with the seed.
    ``--sex male|female --out PATH`` builds one sex into PATH (two processes; ``merge A B`` joins them)."""
    torch.set_num_threads(1)
    if args[:1] == ["merge"]:
        arrays: dict[str, np.ndarray] = {}
        for part in args[1:]:
            with np.load(part) as f:
                arrays |= {k: f[k] for k in f.files}
        np.savez_compressed(POPULATION_FILE, allow_pickle=False, **arrays)
        return
    sexes = (args[args.index("--sex") + 1],) if "--sex" in args else SEXES
    path = Path(args[args.index("--out") + 1]) if "--out" in args else POPULATION_FILE
    model = BodyModel.load()
    ansur, nhanes, source = load_surveys()
    if source != "shared":
        raise SystemExit(f"the full surveys are not in {SHARED}")
    a, n = {}, {}
    for s in sexes:
        rng = np.random.default_rng(SEED)
        rows = table(ansur[s], np.arange(len(ansur[s]["stature"])))
        a[s] = rows[np.sort(rng.permutation(len(rows))[:500])]
        rows = table(nhanes[s], np.arange(len(nhanes[s]["stature"])))
        n[s] = rows[np.sort(rng.permutation(len(rows))[:2000])]
    for key, p in build_populations(model, a, n, path).items():
        print(f"{key}: {len(p.shapes)} people")


def measure_ms(model: BodyModel) -> float:
    """Median milliseconds of :func:`measure` on one body."""
    shape = np.random.default_rng(1).standard_normal((1, model.n_shape))
    measure(model, shape)
    times = []
    for _ in range(20):
        start = time.perf_counter()
        measure(model, shape)
        times.append(time.perf_counter() - start)
    return float(np.median(times) * 1000)


def run(quick: bool) -> dict[str, Any]:
    torch.set_num_threads(1)
    model = BodyModel.load()
    ansur, nhanes, source = load_surveys()
    out: dict[str, Any] = {"data": source}
    out.update(scores(model, ansur, 40 if quick else None, 60 if quick else 400))
    out["measure_ms_b1"] = measure_ms(model)
    out.update(ks_scores(model, nhanes, 2000 if quick else 4000))
    return {k: round(v, 3) if isinstance(v, float) else v for k, v in out.items()}


# Figure colours: the skin, the tapes, the landmarks and the straight lengths.
_SKIN, _TAPE, _MARK, _LINE = (0.86, 0.72, 0.62), (0.12, 0.32, 0.85), (0.85, 0.1, 0.1), (0.1, 0.6, 0.2)
# Straight lengths drawn in the figure: (from, to) named points of the measured body.
_LINES = (
    ("acromion_r", "lateral_humeral_epicondyle_r"),
    ("joint_elbow_r", "joint_wrist_r"),
    ("acromion_r", "acromion_l"),
    ("iliac_crest_r", "iliac_crest_l"),
    ("wrist_r", "dactylion_r"),
    ("heel_r", "toe_tip_r"),
)
_MARKS = (
    "acromion_r", "acromion_l", "lateral_humeral_epicondyle_r", "radial_styloid_r", "ulnar_styloid_r",
    "dactylion_r", "C7", "suprasternale", "omphalion", "iliac_crest_r", "iliac_crest_l", "tragion_r",
    "tragion_l", "heel_r", "toe_tip_r", "first_metatarsal_head_r", "lateral_malleolus_r",
    "medial_malleolus_r", "bust_r", "bust_l", "buttock",
)  # fmt: skip


def _ribbon(path: np.ndarray, width: float) -> tuple[np.ndarray, np.ndarray]:
    """A closed band (vertices, triangles) of ``width`` metres along the closed polyline ``path`` (k, 3),
    offset across it both ways so that it shows from any side."""
    k = len(path)
    centre = path.mean(0)
    out = path + 0.002 * (path - centre) / np.linalg.norm(path - centre, axis=1, keepdims=True).clip(1e-9)
    tangent = np.roll(out, -1, 0) - np.roll(out, 1, 0)
    normal = np.cross(tangent, out - centre)
    normal /= np.linalg.norm(normal, axis=1, keepdims=True).clip(1e-12)
    verts = np.concatenate([out + width / 2 * normal, out - width / 2 * normal])
    i = np.arange(k)
    j = (i + 1) % k
    faces = np.concatenate([np.stack([i, i + k, j], 1), np.stack([i + k, j + k, j], 1)])
    return verts, faces


def _rod(a: np.ndarray, b: np.ndarray, width: float) -> tuple[np.ndarray, np.ndarray]:
    """A thin square rod (vertices, triangles) from a to b (3,)."""
    axis = (b - a) / max(float(np.linalg.norm(b - a)), 1e-9)
    side = np.cross(axis, [0.0, 0.0, 1.0] if abs(axis[2]) < 0.9 else [1.0, 0.0, 0.0])
    side /= np.linalg.norm(side)
    up = np.cross(axis, side)
    ring = np.array([side, up, -side, -up]) * width / 2
    verts = np.concatenate([a + ring, b + ring])
    faces = [[q, (q + 1) % 4, 4 + q] for q in range(4)] + [
        [(q + 1) % 4, 4 + (q + 1) % 4, 4 + q] for q in range(4)
    ]
    return verts, np.asarray(faces)


def _marker(p: np.ndarray, size: float) -> tuple[np.ndarray, np.ndarray]:
    """An octahedron (vertices, triangles) of radius ``size`` at p (3,)."""
    verts = p + size * np.array([[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1]], float)
    faces = [[a, b, c] for a in (0, 1) for b in (2, 3) for c in (4, 5)]
    return verts, np.asarray(faces)


def figure(path: Path) -> None:
    """The landmarks (red), straight lengths (green) and tapes (blue) on the mean body in the measuring
    posture, from the front and the side, written as a PNG."""
    from render import RenderMesh, label_grid, render, save_png, tile  # benchmarks/ is on sys.path

    from bodyfit.models.anthropometry.measure import _points, body_in_pose, measure_torch
    from bodyfit.models.anthropometry.regions import topology

    model = BodyModel.load()
    topo = topology(model)
    v, j = body_in_pose(model, torch.zeros(1, model.n_shape))
    paths: dict[str, torch.Tensor] = {}
    with torch.no_grad():
        measure_torch(topo, v, j, paths)
        named = {k: t[0].numpy().astype(np.float64) for k, t in _points(topo, v, j).items() if t.ndim == 2}
    named["wrist_r"] = 0.5 * (named["radial_styloid_r"] + named["ulnar_styloid_r"])
    skin = v[0].numpy().astype(np.float64)
    meshes = [RenderMesh(skin, model.faces, _SKIN, opacity=0.5)]
    for tape in paths.values():
        meshes.append(RenderMesh(*_ribbon(tape[0].numpy().astype(np.float64), 0.006), _TAPE))
    for a, b in _LINES:
        meshes.append(RenderMesh(*_rod(named[a], named[b], 0.005), _LINE))
    for name in _MARKS:
        meshes.append(RenderMesh(*_marker(named[name], 0.009), _MARK))
    images = [render(meshes, view=view, size=(520, 820)) for view in ("front", "side")]
    grid = label_grid(
        tile(images, 2),
        [["front", "side"]],
        [""],
        caption="landmarks (red), straight lengths (green) and tapes (blue): mean body, measuring posture",
    )
    save_png(grid, path)


def main(argv: list[str] | None = None) -> None:
    args = sys.argv[1:] if argv is None else argv
    if args[:1] == ["calibrate"]:
        calibrate()
        return
    if args[:1] == ["bootstrap"]:
        bootstrap(args[1:])
        return
    if args[:1] == ["priors"]:
        prior_weights()
        return
    if args[:1] == ["populations"]:
        build(args[1:])
        return
    if args[:1] == ["figure"]:
        figure(Path(args[1]) if len(args) > 1 else REPO / "docs" / "anthropometry_tapes.png")
        return
    from bench_cli import bench_main

    bench_main(run, __doc__.split("\n")[0], "40 test subjects per sex and 2,000 draws per sex", args)


if __name__ == "__main__":
    main()
