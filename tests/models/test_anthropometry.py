"""Anthropometry: tape lengths on known shapes, measurements of bodies, bodies from measurements, errors."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
import torch

from bodyfit.models.anthropometry.definitions import MEASUREMENTS, UnknownMeasurementError
from bodyfit.models.anthropometry.inverse import NAMES, TOLERANCE, gaussian_prior, shape_from_measurements
from bodyfit.models.anthropometry.measure import body_in_pose, measure, measure_torch, measure_vertices
from bodyfit.models.anthropometry.ranges import ImplausibleMeasurementError, plausible_range
from bodyfit.models.anthropometry.regions import topology
from bodyfit.models.anthropometry.sections import (
    closed_volume,
    crossings,
    mesh_edges,
    plane_basis,
    polygon_perimeter,
    support_polygon,
)
from bodyfit.models.anthropometry.surveys import read_ansur, read_nhanes
from bodyfit.models.body.model import BodyModel

DATA = Path(__file__).resolve().parents[1] / "data" / "anthropometry"


@pytest.fixture(scope="module")
def body() -> BodyModel:
    torch.set_num_threads(1)
    return BodyModel.load()


def _cylinder(radius: float, height: float, n: int = 90, rings: int = 8) -> tuple[np.ndarray, np.ndarray]:
    """A closed cylinder along y: (V, 3) vertices and outward (F, 3) triangles."""
    angles = np.arange(n) * 2 * math.pi / n
    ring = np.stack([radius * np.cos(angles), np.zeros(n), -radius * np.sin(angles)], 1)
    verts = [ring + np.array([0.0, height * k / (rings - 1), 0.0]) for k in range(rings)]
    v = np.concatenate([*verts, [[0.0, 0.0, 0.0], [0.0, height, 0.0]]])
    faces = []
    for k in range(rings - 1):
        for i in range(n):
            a, b, c, d = k * n + i, k * n + (i + 1) % n, (k + 1) * n + i, (k + 1) * n + (i + 1) % n
            faces += [[a, b, d], [a, d, c]]
    bottom, top = rings * n, rings * n + 1
    for i in range(n):
        faces += [[bottom, (i + 1) % n, i], [top, (rings - 1) * n + i, (rings - 1) * n + (i + 1) % n]]
    return v, np.asarray(faces)


def test_tape_around_a_cylinder_is_its_circumference() -> None:
    v, f = _cylinder(0.1, 0.5)
    e = torch.as_tensor(mesh_edges(f))
    vt = torch.as_tensor(v)[None]
    normal = torch.tensor([[0.0, 1.0, 0.0]], dtype=torch.float64)
    origin = torch.tensor([[0.0, 0.2, 0.0]], dtype=torch.float64)
    points, valid = crossings(vt, e, origin, normal, torch.zeros(1, 1))
    u, w = plane_basis(normal)
    length = float(polygon_perimeter(support_polygon(points, valid, u, w))[0])
    polygon = 90 * 2 * 0.1 * math.sin(math.pi / 90)  # the inscribed 90-gon the mesh is made of
    assert length == pytest.approx(polygon, rel=1e-4)
    assert float(closed_volume(vt, torch.as_tensor(f))[0]) == pytest.approx(
        0.5 * 0.5 * 90 * 0.1**2 * math.sin(2 * math.pi / 90), rel=1e-9
    )


def test_tape_bridges_a_concavity() -> None:
    """A section shaped like two touching discs: the tape is the hull (two half circles and two lines)."""
    r, gap = 0.05, 0.12
    v1, f1 = _cylinder(r, 0.4)
    v2 = v1 + np.array([0.0, 0.0, gap])
    v, f = np.concatenate([v1, v2]), np.concatenate([f1, f1 + len(v1)])
    e = torch.as_tensor(mesh_edges(f))
    vt = torch.as_tensor(v)[None]
    normal = torch.tensor([[0.0, 1.0, 0.0]], dtype=torch.float64)
    origin = torch.tensor([[0.0, 0.1, 0.0]], dtype=torch.float64)
    points, valid = crossings(vt, e, origin, normal, torch.zeros(1, 1))
    u, w = plane_basis(normal)
    length = float(polygon_perimeter(support_polygon(points, valid, u, w))[0])
    assert length == pytest.approx(2 * math.pi * r + 2 * gap, rel=2e-3)


def test_measurements_of_the_mean_body(body: BodyModel) -> None:
    out = measure(body, np.zeros(body.n_shape))
    assert list(out) == list(MEASUREMENTS) and len(out) >= 25
    assert all(v.shape == (1,) and np.isfinite(v).all() for v in out.values())
    v, _ = body_in_pose(body, torch.zeros(1, body.n_shape))
    extent = float(v[0, :, 1].max() - v[0, :, 1].min())
    assert out["stature"][0] == pytest.approx(extent, abs=1e-6)
    # The mean body is an adult: every measurement within its plausible range.
    for name, value in out.items():
        lo, hi = plausible_range(name)
        assert lo <= value[0] <= hi, name
    assert out["crotchheight"][0] < out["buttockheight"][0] < out["waistheightomphalion"][0]
    assert out["waistheightomphalion"][0] < out["chestheight"][0] < out["acromialheight"][0]


def test_scaled_body_scales_lengths_and_mass(body: BodyModel) -> None:
    shape = np.random.default_rng(3).normal(size=(2, body.n_shape))
    v, j = body_in_pose(body, torch.as_tensor(shape, dtype=torch.float64))
    topo = topology(body)
    with torch.no_grad():
        base = measure_torch(topo, v, j)
        scaled = measure_torch(topo, 1.1 * v, 1.1 * j)
    for name, m in MEASUREMENTS.items():
        power = 3 if m.kind == "mass" else 1
        assert np.allclose(scaled[name].numpy(), 1.1**power * base[name].numpy(), rtol=1e-6), name


def test_measure_vertices_matches_measure_and_batches(body: BodyModel) -> None:
    shape = np.random.default_rng(4).normal(size=(3, body.n_shape))
    out = measure(body, shape)
    one = measure(body, shape[1])
    v, j = body_in_pose(body, torch.as_tensor(shape, dtype=torch.float32))
    mesh = measure_vertices(body, v.numpy(), j.numpy())
    for name in MEASUREMENTS:
        assert out[name].shape == (3,)
        assert out[name][1] == pytest.approx(one[name][0], rel=1e-5, abs=1e-6)
        assert mesh[name] == pytest.approx(out[name], rel=1e-5, abs=1e-6)


def test_section_bands_hold_across_the_shape_space(body: BodyModel) -> None:
    """The template's edge bands contain every edge the planes cross on bodies 3 SD away."""
    topo = topology(body)
    wide = topo.__class__(**{**topo.__dict__, "edges": _all_region_edges(body, topo), "_local": {}})
    shape = 3.0 * np.random.default_rng(5).standard_normal((4, body.n_shape))
    v, j = body_in_pose(body, torch.as_tensor(shape, dtype=torch.float64))
    with torch.no_grad():
        banded, full = measure_torch(topo, v, j), measure_torch(wide, v, j)
    for name in MEASUREMENTS:
        assert np.allclose(banded[name].numpy(), full[name].numpy(), atol=1e-9), name


def _all_region_edges(body: BodyModel, topo: object) -> dict[str, np.ndarray]:
    from bodyfit.models.anthropometry.regions import _REGION_BODIES  # the unbanded regions

    regions = topo.regions  # type: ignore[attr-defined]
    edges = mesh_edges(body.faces)
    region_of = {
        "chest": "torso", "waist": "torso", "hips": "hips", "thigh": "leg_r", "shank": "leg_r",
        "head": "head", "neck": "neck", "upperarm": "arm_r", "forearm": "arm_r",
    }  # fmt: skip
    assert set(region_of.values()) <= set(_REGION_BODIES)
    out = {}
    for name, region in region_of.items():
        inside = np.zeros(body.n_vertices, bool)
        inside[regions[region]] = True
        out[name] = edges[inside[edges].any(1)]
    return out


def test_body_from_stature_and_mass(body: BodyModel) -> None:
    result = shape_from_measurements(body, {"stature": 1.82, "mass": 84.0}, sex="male")
    assert abs(result.residuals["stature"]) < TOLERANCE["height"]
    assert abs(result.residuals["weightkg"]) < TOLERANCE["mass"]
    assert not result.flagged
    assert result.shape.shape == (body.n_shape,)
    assert measure(body, result.shape)["stature"][0] == pytest.approx(1.82, abs=0.005)
    # The rest stays plausible: the prior keeps the unrequested coefficients near the mean.
    assert np.abs(result.shape).max() < 4.0


def test_unmeetable_set_is_flagged(body: BodyModel) -> None:
    result = shape_from_measurements(
        body, {"stature": 1.60, "crotchheight": 0.86, "waistcircumference": 1.2, "mass": 50.0}
    )
    assert result.flagged and result.unmet
    assert set(result.residuals) == {"stature", "crotchheight", "waistcircumference", "weightkg"}


def test_bad_measurements_are_named(body: BodyModel) -> None:
    with pytest.raises(ImplausibleMeasurementError, match=r"waistcircumference = 3 m .*expected"):
        shape_from_measurements(body, {"stature": 1.7, "waist": 3.0})
    with pytest.raises(ImplausibleMeasurementError, match=r"stature = 0\.5 m"):
        shape_from_measurements(body, {"stature": 0.5})
    with pytest.raises(
        ImplausibleMeasurementError, match=r"crotchheight = 1 m contradicts the stature 1\.4 m"
    ):
        shape_from_measurements(body, {"stature": 1.4, "inseam": 1.0})
    with pytest.raises(UnknownMeasurementError, match="did you mean 'stature'"):
        shape_from_measurements(body, {"statur": 1.7})
    with pytest.raises(ImplausibleMeasurementError, match="sex must be"):
        shape_from_measurements(body, {"stature": 1.7}, sex="other")


def test_survey_extracts_read_in_our_units() -> None:
    ansur = read_ansur(DATA / "ansur2_female_200.csv")
    assert len(ansur["stature"]) == 200 and set(ansur["sex"]) == {"female"}
    assert 1.5 < float(np.mean(ansur["stature"])) < 1.75
    assert 55 < float(np.mean(ansur["weightkg"])) < 80
    nhanes = read_nhanes(DATA / "nhanes_adult_male_bmx_2020_500.csv")
    assert 1.65 < float(np.nanmean(nhanes["stature"])) < 1.85
    assert 0.8 < float(np.nanmean(nhanes["waistcircumferenceiliaccrest"])) < 1.2


def test_gaussian_prior_recovers_a_population() -> None:
    rng = np.random.default_rng(6)
    scale = np.linspace(0.5, 2.0, 4)
    shapes = rng.standard_normal((20000, 4)) * scale + [1.0, -1.0, 0.0, 2.0]
    mean, precision = gaussian_prior(shapes, shrink=0.0)
    assert np.allclose(mean, [1.0, -1.0, 0.0, 2.0], atol=0.05)
    assert np.allclose(np.linalg.inv(precision), np.diag(scale**2), atol=0.08)


def test_benchmark_split_and_linear_baseline() -> None:
    from benchmarks.anthropometry import INPUTS, linear_baseline, split, table

    train, test = split(100)
    assert len(train) == 80 and len(test) == 20 and not set(train) & set(test)
    assert np.array_equal(split(100)[1], test)
    ansur = read_ansur(DATA / "ansur2_male_200.csv")
    rows = table(ansur, np.arange(200))
    assert (
        rows.shape == (200, len(MEASUREMENTS))
        and np.isnan(rows[:, NAMES.index("forearmcircumference")]).all()
    )
    # A measurement that is exactly linear in the inputs is predicted exactly.
    x = rows.copy()
    x[:, NAMES.index("sittingheight")] = (
        0.5 * x[:, NAMES.index(INPUTS[0])] + 0.01 * x[:, NAMES.index(INPUTS[1])]
    )
    male = np.ones(200, bool)
    pred = linear_baseline(x[:150], x[150:], male[:150], male[150:])
    column = NAMES.index("sittingheight")
    assert np.allclose(pred[:, column], x[150:, column], atol=1e-9)


def test_population_draws_follow_the_survey_and_the_seed(body: BodyModel) -> None:
    from bodyfit.models.anthropometry.inverse import evaluate
    from bodyfit.models.anthropometry.population import sample

    men = sample(body, 48, sex="male", population="nhanes", seed=3)
    assert men.shape == (48, body.n_shape) and np.array_equal(men, sample(body, 48, "male", "nhanes", 3))
    assert not np.array_equal(men, sample(body, 48, "male", "nhanes", 4))
    assert np.array_equal(men, body.sample(48, sex="male", seed=3))  # BodyModel.sample: the same draw
    values = evaluate(body, men)
    nhanes = read_nhanes(DATA / "nhanes_adult_male_bmx_2020_500.csv")
    for name, tol in (("stature", 0.03), ("weightkg", 8.0), ("waistcircumferenceiliaccrest", 0.05)):
        assert np.mean(values[:, NAMES.index(name)]) == pytest.approx(np.nanmean(nhanes[name]), abs=tol), name
    # The model's own population is lighter than US men: the point of drawing from the survey.
    anny = evaluate(body, sample(body, 48, population="anny", seed=3))[:, NAMES.index("weightkg")]
    assert np.mean(values[:, NAMES.index("weightkg")]) > np.mean(anny) + 8.0
    both = sample(body, 10, population="ansur")
    assert both.shape == (10, body.n_shape) and np.isfinite(both).all()


def test_population_errors_name_the_choices(body: BodyModel, tmp_path: Path) -> None:
    from bodyfit.models.anthropometry.population import (
        PopulationError,
        build_population,
        load_populations,
        sample,
        shape_space_probe,
    )

    with pytest.raises(PopulationError, match="nhanes, ansur, anny"):
        sample(body, 2, population="us")
    with pytest.raises(PopulationError, match="sex must be"):
        sample(body, 2, sex="other")
    with pytest.raises(PopulationError, match="no population file"):
        load_populations(body, tmp_path / "none.npz")
    rows = np.full((3, len(NAMES)), np.nan)
    rows[:, NAMES.index("stature")] = [1.6, 1.7, 1.8]
    people = build_population(body, rows, "male")
    assert measure(body, people.shapes)["stature"] == pytest.approx([1.6, 1.7, 1.8], abs=0.005)
    assert people.weights == pytest.approx([1 / 3] * 3) and people.spread.shape == (body.n_shape,) * 2
    path = tmp_path / "other.npz"
    np.savez(path, probe=shape_space_probe(body) + 0.01, x_male_shapes=people.shapes,
             x_male_weights=people.weights, x_male_spread=people.spread)  # fmt: skip
    with pytest.raises(PopulationError, match="another shape space"):
        load_populations(body, path)
    rows[1, NAMES.index("weightkg")] = 70.0
    with pytest.raises(PopulationError, match="the same measurements"):
        build_population(body, rows, "male")


def test_calibration_offsets_recover_a_known_shift(body: BodyModel) -> None:
    from bodyfit.models.anthropometry.calibration import OFFSETS, SCALES, learn_calibration
    from bodyfit.models.anthropometry.inverse import evaluate
    from bodyfit.models.anthropometry.measure import DENSITY

    shapes = np.random.default_rng(8).normal(size=(6, body.n_shape)) * 0.7
    ours = evaluate(body, shapes)
    size = ours[:, 0] / 1.7  # offsets in proportion to the stature
    truth = ours.copy()
    shift = {"cervicaleheight": -0.02, "neckcircumference": 0.03}
    for name, value in shift.items():
        truth[:, NAMES.index(name)] += value * size
    keep = ["stature", "cervicaleheight", "acromialheight", "neckcircumference", "chestcircumference"]
    rows = np.where(np.isin(NAMES, keep), truth, np.nan)
    learned = learn_calibration(body, {"male": rows}, NAMES, rounds=3, shrink=np.inf)
    assert set(learned.offsets) == set(learned.scales) == set(keep) - {"stature"}
    assert set(learned.scales.values()) == {1.0}  # offsets alone
    assert learned.density == DENSITY  # no weights given: the density stays
    moved = {}  # how much the learned calibration moves each measurement of these bodies, per unit size
    for name in keep[1:]:
        old = ours[:, NAMES.index(name)]
        raw = (old - OFFSETS.get(name, 0.0) * size) / SCALES.get(name, 1.0)
        moved[name] = float(np.mean((learned.scales[name] * raw + learned.offsets[name] * size - old) / size))
    # The bodies absorb part of a shift their shape can make; the offsets take what is left, and the
    # measurements not shifted keep theirs.
    for name in keep[1:]:
        if name in shift:
            assert 0.3 * abs(shift[name]) < moved[name] * np.sign(shift[name]) < 1.1 * abs(shift[name]), name
        else:
            assert abs(moved[name]) < 0.008, name


def test_calibration_scale_is_shrunk_towards_one() -> None:
    from bodyfit.models.anthropometry.calibration import _slope

    x = np.random.default_rng(3).uniform(0.8, 1.2, 200)
    y = 1.2 * x + 0.05 + np.random.default_rng(4).normal(0.0, 0.002, 200)
    assert np.allclose(_slope(x, y, 0.0), (1.2, 0.05), atol=0.01)  # least squares
    assert np.allclose(_slope(x, y, 1.0), (1.1, 0.15), atol=0.01)  # halfway to one
    scale, offset = _slope(x, y, np.inf)  # an offset alone: the mean difference
    assert scale == 1.0 and offset == pytest.approx(np.mean(y - x))


def test_bootstrap_fields_widen_the_space_symmetrically(body: BodyModel) -> None:
    from bodyfit.models.anthropometry.bootstrap import FIELD_SIZE, smooth_fields, widened
    from bodyfit.models.spaces.population import rest_meshes

    fields = smooth_fields(body, 2)
    assert 2 <= len(fields) <= 6 and fields.shape[1:] == (body.n_vertices, 3)
    assert np.allclose(np.linalg.norm(fields, axis=2).max(1), FIELD_SIZE)
    mirror = np.asarray(body.data["mirror"])
    assert np.allclose(fields[:, mirror] * np.array([1.0, 1.0, -1.0]), fields, atol=1e-9)  # symmetric
    flat = fields.reshape(len(fields), -1)
    gram = flat @ flat.T
    assert np.allclose(gram - np.diag(np.diag(gram)), 0.0, atol=1e-9)  # independent directions
    wide = widened(body, fields)
    assert wide.n_shape == body.n_shape + len(fields)
    c = np.zeros((2, wide.n_shape))
    c[1, body.n_shape + 1] = 1.5
    moved = rest_meshes(wide.data, c)
    assert np.allclose(moved[1] - moved[0], 1.5 * fields[1], atol=1e-5)


def test_bootstrap_accepts_within_one_deviation_of_the_best() -> None:
    from bodyfit.models.anthropometry.bootstrap import accepted

    misfit = np.array([1.0, 1.2, 1.5, 5.0, 9.0])
    threshold = 1.0 + misfit.std()  # 3.97
    assert accepted(misfit).tolist() == (misfit <= threshold).tolist() == [True, True, True, False, False]
