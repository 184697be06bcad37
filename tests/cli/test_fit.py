"""``bodyfit fit``: each input kind through its subcommand and through ``auto`` (no kind given, as every
command written before the subcommands), real fits and the errors a user meets."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from bodyfit.cli import app
from bodyfit.models.body.model import BodyModel
from bodyfit.models.skeleton.opensim_export import read_mot

runner = CliRunner()
DATA = Path(__file__).resolve().parents[1] / "data"
TRIAL = DATA / "opensim_gait" / "hamner_subject02_running.trc"


def test_fit_registered_meshes(tmp_path: Path) -> None:
    """`bodyfit fit scan` on two meshes of the model written as PLY in millimetres: reports and outputs."""
    import trimesh

    from bodyfit.models.body.model import BodyModel

    model = BodyModel.load()
    q = model.skeleton.coordinates({"knee_angle_r": 0.9, "hip_flexion_r": 0.6, "elbow_flex_l": 1.2}, batch=2)
    shape = np.random.default_rng(0).normal(size=(2, model.n_shape)) * 0.5
    verts = model.forward(shape, q, np.array([[0.1, 0.9, 0.0], [2.0, 1.0, -1.0]])).vertices.numpy()
    paths = []
    for k, v in enumerate(verts):
        paths.append(tmp_path / f"m{k}.ply")
        trimesh.Trimesh(v * 1000.0, model.faces, process=False).export(paths[-1])
    out = tmp_path / "fit"
    result = runner.invoke(app, ["fit", "scan", *map(str, paths), "--out", str(out)])
    assert result.exit_code == 0, result.output
    reports = json.loads((out / "fit.json").read_text())
    assert [r["confident"] for r in reports] == [True, True]
    assert max(r["distances"]["mean"] for r in reports) < 3.0
    data = np.load(out / "fit.npz")
    knee = model.dof_names.index("knee_angle_r")
    assert abs(data["coordinates"][0, knee] - 0.9) < 0.1
    np.testing.assert_array_equal(data["to_model"], np.tile(np.eye(4), (2, 1, 1)))  # placed by their vertices
    assert np.linalg.norm(data["vertices"] - verts, axis=2).mean() < 0.003  # in the files' own frame
    assert (out / "registration_001.ply").exists() and (out / "fit.mot").exists()


@pytest.mark.parametrize(
    ("raw", "registered", "option", "expected"),
    [
        (3, 0, [], 2),
        (2, 0, [], 1),
        (2, 1, [], 1),
        (3, 0, ["--processes", "1"], 1),
        (1, 0, ["--processes", "2"], 2),
    ],
)
def test_fit_starts_a_helper_process_for_three_or_more_raw_scans(
    tmp_path: Path,
    monkeypatch: pytest.MonkeyPatch,
    raw: int,
    registered: int,
    option: list[str],
    expected: int,
) -> None:
    """`bodyfit fit` fits raw scans with a helper process (``scan_processes=2``) when three or more of its
    inputs are raw scans, or when told to; meshes in our topology do not count. The service's first fit is
    stopped here, before any fitter (or helper) starts."""
    from bodyfit.models.body.model import BodyModel
    from bodyfit.service.core import BodyService

    seen: list[int] = []

    def first_fit(
        self: BodyService, scan: object, job: object = None, hints: object = None, body: object = None
    ) -> None:
        seen.append(self.scan_processes)
        raise OSError("stopped by the test")

    monkeypatch.setattr(BodyService, "fit_mesh", first_fit)
    rng = np.random.default_rng(0)
    paths = []
    for k in range(raw):
        paths.append(tmp_path / f"scan{k}.npz")
        np.savez(paths[-1], points=rng.normal(size=(600, 3)) * 0.3)
    for k in range(registered):
        paths.append(tmp_path / f"mesh{k}.npz")
        np.savez(paths[-1], points=BodyModel.load().data["vertices_mean"])
    result = runner.invoke(app, ["fit", *map(str, paths), "--out", str(tmp_path / "o"), *option])
    assert result.exit_code == 2 and "stopped by the test" in result.output
    assert seen == [expected]


def test_fit_reads_a_depth_camera_cloud_as_the_server_does(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The repository's Kinect PCD marks missing pixels with NaN: `bodyfit fit` drops them, as the server
    does, and says how many (the fit itself is stopped here: reading is what is tested)."""
    from bodyfit.service.core import BodyService

    def first_fit(
        self: BodyService, scan: object, job: object = None, hints: object = None, body: object = None
    ) -> None:
        raise OSError("stopped by the test")

    monkeypatch.setattr(BodyService, "fit_mesh", first_fit)
    path = DATA / "scans" / "pcl_template_alignment_person.pcd"
    result = runner.invoke(app, ["fit", "scan", str(path), "--out", str(tmp_path / "o")])
    assert "drop_nonfinite" not in result.output, result.output
    assert "dropped 64,451 of 307,200 points that were NaN or infinite" in result.output
    assert result.exit_code == 2 and "stopped by the test" in result.output


def _stub_fit(monkeypatch: pytest.MonkeyPatch) -> list[object]:
    """Stops the service's first fit, keeping the hints it was given."""
    from bodyfit.service.core import BodyService

    given: list[object] = []

    def first_fit(
        self: BodyService, scan: object, job: object = None, hints: object = None, body: object = None
    ) -> None:
        given.append(hints)
        raise OSError("stopped by the test")

    monkeypatch.setattr(BodyService, "fit_mesh", first_fit)
    return given


@pytest.mark.parametrize("kind", [["scan"], []])
def test_fit_scan_passes_its_hints_to_every_fit(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, kind: list[str]
) -> None:
    """`bodyfit fit scan --up -z --facing +x --pose sitting --sex female --height-m 1.68` (and the same
    without the kind): the hints, in their canonical spelling, go with the fit."""
    from bodyfit.service.hints import ScanHints

    given = _stub_fit(monkeypatch)
    path = tmp_path / "scan.npz"
    np.savez(path, points=np.random.default_rng(0).normal(size=(600, 3)) * 0.3)
    hints = ["--up", "-z", "--facing", "+x", "--pose", "sitting", "--sex", "female", "--height-m", "1.68"]
    result = runner.invoke(app, ["fit", *kind, str(path), "--out", str(tmp_path / "o"), *hints])
    assert result.exit_code == 2 and "stopped by the test" in result.output, result.output
    assert given == [ScanHints("-z", "+x", "sitting", "female", 1.68)]


@pytest.mark.parametrize(
    ("option", "words"),
    [
        (["--up", "q"], "up must be one of +x, -x, +y, -y, +z, -z"),
        (["--up", "+y", "--facing", "-y"], "facing must be perpendicular to up"),
        (["--height-m", "175"], "height_m must be an adult's, between 1.2 and 2.3"),
        (["--pose", "kneeling"], "'standing', 'sitting', 'a-pose', 't-pose'"),
        (["--sex", "x"], "'male', 'female', 'neutral'"),
    ],
)
def test_fit_scan_refuses_a_bad_hint_before_any_fit(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, option: list[str], words: str
) -> None:
    given = _stub_fit(monkeypatch)
    path = tmp_path / "scan.npz"
    np.savez(path, points=np.random.default_rng(0).normal(size=(600, 3)) * 0.3)
    result = runner.invoke(app, ["fit", "scan", str(path), "--out", str(tmp_path / "o"), *option])
    assert result.exit_code == 2 and words in " ".join(result.output.split()), result.output
    assert given == [] and "Traceback" not in result.output


def test_fit_scan_help_states_each_hints_values() -> None:
    result = runner.invoke(app, ["fit", "scan", "--help"], terminal_width=200)
    text = " ".join(result.output.split())
    assert result.exit_code == 0
    for words in ("+x, -x, +y, -y, +z or -z", "standing", "t-pose", "standing height in metres", "neutral"):
        assert words in text, words


def test_a_scan_hint_is_refused_for_a_marker_trial(tmp_path: Path) -> None:
    result = runner.invoke(app, ["fit", str(TRIAL), "--facing", "+x", "--out", str(tmp_path / "o")])
    assert result.exit_code == 2 and "--facing is an option of `bodyfit fit scan`" in result.output


def test_fit_a_sphere_is_refused_as_no_person(tmp_path: Path) -> None:
    """A mesh of another topology goes to the raw-scan fit; a sphere holds no person and is refused before
    any fit, saying what it found, and nothing is written."""
    import trimesh

    path = tmp_path / "sphere.ply"
    trimesh.creation.icosphere(subdivisions=4, radius=0.8).export(path)
    out = tmp_path / "o"
    result = runner.invoke(app, ["fit", str(path), "--out", str(out)])
    assert result.exit_code == 2, result.output
    assert "fitting as a raw scan" in result.output and "no person found in the scan" in result.output
    assert "sphere" in result.output and not (out / "fit.json").exists()


def test_fit_a_real_head_and_shoulders_scan(tmp_path: Path) -> None:
    """The real Kinect capture cropped to the person (tests/data/scans) is fitted as a head and shoulders,
    and the command's summary and fit.json say so."""
    from bodyfit.io.scans import load_scan

    scan = load_scan(
        DATA / "scans" / "pcl_template_alignment_person.pcd",
        drop_nonfinite=True,
    )
    path = tmp_path / "person.npz"
    np.savez(path, points=scan.points[scan.points[:, 2] < 1.0])
    out = tmp_path / "o"
    result = runner.invoke(app, ["fit", str(path), "--out", str(out)])
    assert result.exit_code == 0, result.output
    assert "fitted as a head and shoulders" in result.output
    report = json.loads((out / "fit.json").read_text())[0]
    assert report["extra"]["fitted_part"] == "head and shoulders" and report["confident"] is False
    assert report["distances"]["mean"] < 3.0


def test_fit_an_smpl_topology_mesh(tmp_path: Path) -> None:
    """A 6,890-vertex mesh goes through the stored SMPL correspondence, then is refined on its surface (the
    CC BY woman, in millimetres)."""
    import trimesh

    from bodyfit.models.fitting.registered.smpl_topology import SOURCE_DIR, read_obj

    verts, faces = read_obj(SOURCE_DIR / "human_woman.obj")
    path = tmp_path / "woman.ply"
    trimesh.Trimesh(verts * 1000.0, faces, process=False).export(path)
    out = tmp_path / "o"
    result = runner.invoke(app, ["fit", "scan", str(path), "--out", str(out), "--units", "mm"])
    assert result.exit_code == 0, result.output
    report = json.loads((out / "fit.json").read_text())[0]
    assert report["fitted_as"] == "SMPL topology" and report["limit_violations"] == 0
    assert report["distances"]["mean"] < 3.0  # the mesh's surface to the registration (10 mm before)
    assert np.load(out / "fit.npz")["vertices"].shape == (1, 13348, 3)


def test_fit_reports_an_unreadable_file(tmp_path: Path) -> None:
    path = tmp_path / "broken.ply"
    path.write_bytes(b"ply\nformat nonsense\n")
    result = runner.invoke(app, ["fit", str(path), "--out", str(tmp_path / "o")])
    assert result.exit_code == 2
    assert "error:" in result.output and "Traceback" not in result.output


def test_fit_a_marker_trial_with_its_static_trial(tmp_path: Path) -> None:
    """A real running trial (TRC), its feet's markers placed from the static trial with the ankles held:
    the .mot's flexion angles lie within 5 degrees of OpenSim's reference IK, and the .osim carries the
    calibrated markers."""
    gait = DATA / "opensim_gait"
    args = [
        "fit", "markers", str(gait / "hamner_subject02_running.trc"),
        "--static", str(gait / "hamner_subject02_static.trc"), "--calibration", "motion",
        "--static-pose", "ankle_angle_r=0.5", "--static-pose", "ankle_angle_l=0.5", "--out", str(tmp_path),
    ]  # fmt: skip
    result = runner.invoke(app, args)
    assert result.exit_code == 0, result.output
    assert "hamner_subject02_running.trc (gait2392, 181 frames" in result.output
    (record,) = json.loads((tmp_path / "fit.json").read_text())
    assert record["confident"] and record["limit_violations"] == 0 and record["distances"]["mean"] < 15.0
    assert "ankle_angle_r, ankle_angle_l held" in record["extra"]["calibration"]
    cols, ours, _ = read_mot(tmp_path / "hamner_subject02_running.mot")
    ref_cols, ref, _ = read_mot(gait / "hamner_subject02_running_ik.mot")
    for name in ("hip_flexion_r", "knee_angle_l", "ankle_angle_r", "ankle_angle_l"):
        sign = -1.0 if name.startswith("knee") else 1.0  # the reference's model flexes its knee negative
        mine = np.interp(ref[:, 0], ours[:, 0], ours[:, cols.index(name)])
        assert np.sqrt(np.mean((mine - sign * ref[:, ref_cols.index(name)]) ** 2)) < 5.0, name
    osim = (tmp_path / "hamner_subject02_running.osim").read_text()
    assert osim.count("<Marker ") == 41 and 'name="R.Toe.Tip"' in osim


@pytest.mark.parametrize("command", [["fit"], ["fit", "markers"]], ids=["auto", "markers"])
@pytest.mark.parametrize(
    ("extra", "message"),
    [
        (["--static-pose", "ankle_angle_r"], "NAME=DEGREES"),
        (["--static-pose", "ankle_angle_r=0"], "pass the static trial"),
        (["--calibration", "static"], "needs the static trial"),
        (["--up", "q"], "axis must be one of x, y, z"),
        (["--marker-set", "vicon"], "unknown marker set 'vicon'"),
    ],
)
def test_fit_a_marker_trial_reports_bad_options(
    tmp_path: Path, command: list[str], extra: list[str], message: str
) -> None:
    result = runner.invoke(app, [*command, str(TRIAL), "--out", str(tmp_path), *extra])
    assert result.exit_code == 2 and message in result.output and "Traceback" not in result.output
    assert not (tmp_path / "fit.json").exists()


def test_fit_refuses_inputs_of_different_kinds(tmp_path: Path) -> None:
    """One run fits one kind: the message lists which file is which and the commands that fit them."""
    np.savez(tmp_path / "seq.npz", frames=np.zeros((2, 13348, 3), np.float32))
    (tmp_path / "scan.ply").write_bytes(b"ply\n")
    for inputs, kinds in (
        ([TRIAL, tmp_path / "scan.ply"], ["markers", "scan"]),
        ([tmp_path / "seq.npz", TRIAL], ["sequence", "markers"]),
    ):
        result = runner.invoke(app, ["fit", *map(str, inputs), "--out", str(tmp_path / "o")])
        assert result.exit_code == 2 and "separate run" in result.output, result.output
        for path in inputs:
            assert path.name in result.output
        for kind in kinds:
            assert f"`bodyfit fit {kind} FILE...`" in result.output
        assert not (tmp_path / "o").exists()


def test_fit_a_registered_sequence(tmp_path: Path) -> None:
    """An .npz of frames (T, 13348, 3) is one person over time: one shape, a pose per frame, written as
    .npz, .mot (at --fps) and fit.json; the knee's motion comes back."""
    model = BodyModel.load()
    T = 12
    q = np.tile(model.skeleton.inside(model.bind_coordinates, 0.1), (T, 1))
    knee = model.skeleton.dof_index("knee_angle_r")
    q[:, knee] = np.linspace(0.2, 1.2, T)
    frames = model.forward(np.zeros((T, model.n_shape)), q, np.zeros((T, 3))).vertices.numpy()
    np.savez(tmp_path / "walk.npz", frames=frames)
    out = tmp_path / "o"
    result = runner.invoke(
        app, ["fit", "sequence", str(tmp_path / "walk.npz"), "--out", str(out), "--fps", "50"]
    )
    assert result.exit_code == 0, result.output
    assert "walk.npz (sequence, 12 frames)" in result.output
    fit = np.load(out / "walk.npz")
    assert fit["coordinates"].shape == (T, model.skeleton.n_dof) and fit["vertices"].shape == (T, 13348, 3)
    assert np.abs(fit["coordinates"][:, knee] - q[:, knee]).max() < 0.05 and fit["error_mm"].max() < 2.0
    (record,) = json.loads((out / "fit.json").read_text())
    assert record["frames"] == T and record["limit_violations"] == 0 and record["confident_frames"] == T
    cols, mot, _ = read_mot(out / "walk.mot")
    np.testing.assert_allclose(mot[:, 0], np.arange(T) / 50.0, atol=1e-6)
    knee_mot = np.radians(mot[:, cols.index("knee_angle_r")])
    np.testing.assert_allclose(knee_mot, fit["coordinates"][:, knee], atol=1e-6)


def test_fit_reports_a_malformed_sequence(tmp_path: Path) -> None:
    np.savez(tmp_path / "seq.npz", frames=np.zeros((3, 100, 3), np.float32))
    result = runner.invoke(app, ["fit", str(tmp_path / "seq.npz"), "--out", str(tmp_path / "o")])
    assert result.exit_code == 2 and "(T, 13348, 3)" in result.output and "Traceback" not in result.output


def kinds_of_files(tmp_path: Path) -> dict[str, Path]:
    """One small file of each kind: a raw scan (.npz of points), a marker trial and a sequence."""
    np.savez(tmp_path / "scan.npz", points=np.zeros((10, 3)))
    np.savez(tmp_path / "seq.npz", frames=np.zeros((2, 13348, 3), np.float32))
    return {"scan": tmp_path / "scan.npz", "markers": TRIAL, "sequence": tmp_path / "seq.npz"}


@pytest.mark.parametrize(
    ("given", "expected"),
    [
        ("scan", "markers"),
        ("scan", "sequence"),
        ("markers", "scan"),
        ("markers", "sequence"),
        ("sequence", "scan"),
        ("sequence", "markers"),
    ],
)
def test_a_file_given_to_the_wrong_kind_says_which_command_fits_it(
    tmp_path: Path, given: str, expected: str
) -> None:
    """`bodyfit fit markers scan.npz` and the like stop before any fit: the message says what the file is,
    what the subcommand takes, and the command that fits it."""
    path = kinds_of_files(tmp_path)[given]
    result = runner.invoke(app, ["fit", expected, str(path), "--out", str(tmp_path / "o")])
    assert result.exit_code == 2, result.output
    assert f"error: {path} is a" in result.output
    assert (
        f"fit it with `bodyfit fit {given} {path}`" in result.output and "detects the kind" in result.output
    )
    assert "Traceback" not in result.output and not (tmp_path / "o").exists()


@pytest.mark.parametrize("option_first", [False, True])
@pytest.mark.parametrize("kind", ["scan", "markers", "sequence"])
def test_no_kind_detects_it_and_runs_that_subcommands_fit(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, kind: str, option_first: bool
) -> None:
    """`bodyfit fit FILE --out DIR` (or with the options first) runs the fit of the file's kind with that
    kind's defaults (the fits are stubbed: the routing is tested)."""
    import bodyfit.cli.fit.commands as commands

    seen: list[tuple[str, tuple[object, ...]]] = []
    for name in ("scan", "markers", "sequence"):
        runner_name = {"scan": "run_scans", "markers": "run_markers", "sequence": "run_sequences"}[name]
        monkeypatch.setattr(commands, runner_name, lambda *args, k=name: seen.append((k, args)))
    path, out = kinds_of_files(tmp_path)[kind], tmp_path / "o"
    args = ["--out", str(out), str(path)] if option_first else [str(path), "--out", str(out)]
    result = runner.invoke(app, ["fit", *args])
    assert result.exit_code == 0, result.output
    ((ran, called),) = seen
    assert ran == kind and called[:2] == ([path], out)
    defaults = {"scan": (commands.ScanOptions(),), "sequence": (30.0, None)}
    if kind == "markers":
        options = called[2]
        assert isinstance(options, commands.MarkerOptions)
        assert (options.calibration, options.marker_set, options.up, options.forward) == (
            "auto",
            "auto",
            "y",
            "x",
        )
    else:
        assert called[2:] == defaults[kind]


def test_no_kind_refuses_an_option_of_another_kind(tmp_path: Path) -> None:
    result = runner.invoke(app, ["fit", str(TRIAL), "--fps", "30", "--out", str(tmp_path / "o")])
    assert result.exit_code == 2
    assert "--fps is an option of `bodyfit fit sequence`" in result.output
    assert "is a motion-capture marker trial" in result.output and "leave --fps out" in result.output
    import trimesh

    path = tmp_path / "sphere.ply"
    trimesh.creation.icosphere(subdivisions=2).export(path)
    scan = runner.invoke(app, ["fit", str(path), "--no-skin", "--out", str(tmp_path / "s")])
    assert scan.exit_code == 2 and "--skin is an option of `bodyfit fit markers`" in scan.output


def test_fit_help_lists_the_kinds(tmp_path: Path) -> None:
    for args in (["fit"], ["fit", "--help"]):
        result = runner.invoke(app, args)
        assert "Commands:" in result.output
        for kind in ("scan", "markers", "sequence", "auto"):
            assert f"\n  {kind} " in result.output, kind
    missing = runner.invoke(app, ["fit", str(tmp_path / "none.ply")])
    assert missing.exit_code == 2 and "does not exist" in missing.output


def test_fit_a_marker_trial_writes_the_skin(tmp_path: Path) -> None:
    """`bodyfit fit` on a real walking trial writes the skin estimated from the markers: the mesh sequence
    (every frame, the model's faces) and a glTF binary of one frame; ``skin=False``
    writes neither."""
    from bodyfit.cli.fit.markers import MarkerOptions, fit_marker_trials

    trial = DATA / "opensim_gait" / "gait2392_subject01_walk1.trc"
    result = runner.invoke(app, ["fit", str(trial), "--out", str(tmp_path)])
    assert result.exit_code == 0, result.output
    assert "estimating the skin from the markers" in result.output
    (record,) = json.loads((tmp_path / "fit.json").read_text())
    with np.load(record["files"]["skin"]) as npz:
        vertices, faces = npz["vertices"], npz["faces"]
    model = BodyModel.load()
    assert vertices.shape == (record["frames"], model.n_vertices, 3) and np.isfinite(vertices).all()
    np.testing.assert_array_equal(faces, model.faces)
    assert Path(record["files"]["skin_glb"]).read_bytes()[:4] == b"glTF"
    off = tmp_path / "off"
    (bare,) = fit_marker_trials([trial], off, MarkerOptions(skin=False), lambda _: None)
    assert set(bare["files"]) == {"osim", "mot"} and not list(off.glob("*_skin*"))
    cli_off = tmp_path / "cli_off"  # the command line's --no-skin
    result = runner.invoke(app, ["fit", str(trial), "--no-skin", "--out", str(cli_off)])
    assert result.exit_code == 0, result.output
    assert "estimating the skin" not in result.output and not list(cli_off.glob("*_skin*"))
