"""The commands besides ``fit``: demo, synth, upgrade and serve; every option's help and unit; the command
line starts without torch or the service."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import typer
from typer.testing import CliRunner

from bodyfit.cli import app
from bodyfit.models.skeleton import Skeleton
from bodyfit.models.skeleton.opensim_export import mot_columns, read_mot

runner = CliRunner()
DATA = Path(__file__).resolve().parents[1] / "data"


def test_demo_writes_posed_skeleton(tmp_path: Path) -> None:
    result = runner.invoke(app, ["demo", "--out", str(tmp_path), "--frames", "30"])
    assert result.exit_code == 0, result.output
    skel = Skeleton.load()
    data = np.load(tmp_path / "pose.npz")
    assert data["frames"].shape == (30, len(skel.body_names), 4, 4)
    assert list(data["dof_names"]) == skel.dof_names
    # The pose in the file is the forward kinematics of the coordinates in the file.
    again = skel.forward(data["coordinates"], data["root"]).frames.numpy()
    assert np.allclose(again, data["frames"], atol=1e-6)
    cols, values, in_degrees = read_mot(tmp_path / "demo.mot")
    assert cols == ["time", *mot_columns(skel.spec)] and in_degrees and values.shape == (30, len(cols))
    knee = cols.index("knee_angle_r")
    assert np.allclose(
        np.radians(values[:, knee]), data["coordinates"][:, skel.dof_index("knee_angle_r")], atol=1e-8
    )
    assert (tmp_path / "skeleton.osim").read_text().startswith("<?xml")
    ply = (tmp_path / "bones_frame0.ply").read_bytes()
    assert ply.startswith(b"ply") and f"element vertex {len(skel.bone_mesh().vertices)}".encode() in ply


def test_demo_reports_a_broken_asset_folder_cleanly(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("BODYFIT_ASSETS", str(tmp_path / "nowhere"))
    result = runner.invoke(app, ["demo", "--out", str(tmp_path / "out")])
    assert result.exit_code == 2
    assert "manifest" in result.output and "bodyfit build-assets" in result.output
    assert "Traceback" not in result.output


def test_synth_writes_the_requested_format(tmp_path: Path) -> None:
    out = tmp_path / "body.npz"
    result = runner.invoke(app, ["synth", str(out), "-c", "knee_angle_r=1.2", "--root", "0,1,0"])
    assert result.exit_code == 0, result.output
    data = np.load(out)
    assert data["vertices"].shape == (1, 13348, 3) and data["faces"].shape == (26692, 3)
    assert abs(np.median(data["vertices"][0, :, 1]) - 1.0) < 0.3  # lifted by the root translation
    bad = runner.invoke(app, ["synth", str(tmp_path / "b.ply"), "-c", "knee_angle_r=4"])
    assert bad.exit_code == 2 and "joint limits" in bad.output
    bad = runner.invoke(app, ["synth", str(tmp_path / "b.ply"), "-c", "knee"])
    assert bad.exit_code == 2 and "NAME=RADIANS" in bad.output


def test_upgrade_writes_opensim_files(tmp_path: Path) -> None:
    data = DATA / "smpl_format"
    args = ["upgrade", str(data / "cmu_131_smpl.npz"), "--smpl-model", str(data / "smpl_like_model.npz")]
    result = runner.invoke(app, [*args, "--out", str(tmp_path)])
    assert result.exit_code == 0, result.output
    summary = json.loads((tmp_path / "cmu_131_smpl.json").read_text())
    assert summary["path"] == "a" and summary["frames"] == 60 and summary["limit_violations"] == 0
    assert (tmp_path / "cmu_131_smpl.osim").exists() and (tmp_path / "cmu_131_smpl.mot").exists()
    rotations = runner.invoke(
        app,
        ["upgrade", str(data / "cmu_131_smpl.npz"), "--out", str(tmp_path / "b")],
        env={"BODYFIT_SMPL_MODEL": ""},
    )
    assert rotations.exit_code == 0 and "path (b)" in rotations.output
    assert json.loads((tmp_path / "b" / "cmu_131_smpl.json").read_text())["path"] == "b"


def test_serve_takes_its_settings_from_options_then_the_environment(monkeypatch: pytest.MonkeyPatch) -> None:
    """`bodyfit serve` options win over BODYFIT_* variables, which win over the defaults (the container
    moves its ports with BODYFIT_REST_PORT / BODYFIT_GRPC_PORT)."""
    import bodyfit.api.server
    from bodyfit.api.settings import ServiceSettings

    seen: list[ServiceSettings] = []
    monkeypatch.setattr(bodyfit.api.server, "run_server", seen.append)
    monkeypatch.setenv("BODYFIT_REST_PORT", "18000")
    monkeypatch.setenv("BODYFIT_GRPC_PORT", "0")
    monkeypatch.setenv("BODYFIT_HOST", "0.0.0.0")
    assert runner.invoke(app, ["serve", "--port", "9100"]).exit_code == 0
    assert (seen[0].host, seen[0].rest_port, seen[0].grpc_port) == ("0.0.0.0", 9100, 0)
    for name in ("BODYFIT_REST_PORT", "BODYFIT_GRPC_PORT", "BODYFIT_HOST"):
        monkeypatch.delenv(name)
    assert runner.invoke(app, ["serve", "--threads", "3"]).exit_code == 0
    assert (seen[1].host, seen[1].rest_port, seen[1].grpc_port, seen[1].threads) == (
        "127.0.0.1",
        8000,
        50051,
        3,
    )


def options() -> list[tuple[str, str, str]]:
    """(command path, option name, help) of every option and argument of every command."""
    found = []

    def walk(command: object, path: str) -> None:
        for name, sub in getattr(command, "commands", {}).items():
            walk(sub, f"{path} {name}".strip())
        for param in getattr(command, "params", []):
            if param.name != "help":
                found.append((path, param.name, getattr(param, "help", None) or ""))

    walk(typer.main.get_command(app), "")
    return found


def test_every_option_and_argument_is_explained() -> None:
    every = options()
    assert {path for path, _, _ in every} >= {
        "fit scan", "fit markers", "fit sequence", "fit auto", "synth", "upgrade", "batch-upgrade", "serve",
        "demo", "build-assets", "build-proxy", "export-onnx",
    }  # fmt: skip
    assert [(path, name) for path, name, text in every if len(text) < 10] == []


@pytest.mark.parametrize(
    ("command", "option", "units"),
    [
        ("synth", "coordinate", ["RADIANS"]),
        ("synth", "root", ["metres"]),
        ("synth", "shape", ["standard deviations"]),
        ("synth", "out", ["metres"]),
        ("fit scan", "units", ["metres", "millimetres"]),
        ("fit auto", "units", ["metres", "millimetres"]),
        ("fit markers", "static_pose", ["DEGREES", "radians"]),
        ("fit auto", "static_pose", ["DEGREES"]),
        ("fit sequence", "fps", ["Frames per second", "Hz"]),
        ("fit sequence", "files", ["metres"]),
        ("upgrade", "height", ["metres"]),
        ("upgrade", "mass", ["kilograms"]),
        ("upgrade", "sequence", ["radians", "metres"]),
        ("demo", "frames", ["frames per second"]),
        ("build-assets", "bodies", ["bodies"]),
    ],
)
def test_an_option_with_a_unit_states_it(command: str, option: str, units: list[str]) -> None:
    (text,) = [text for path, name, text in options() if (path, name) == (command, option)]
    for unit in units:
        assert unit in text, (command, option, text)


def test_help_shows_the_units_where_a_user_reads_them() -> None:
    """`--help` itself prints the units (not only the code): degrees for --static-pose, radians for -c."""
    markers = " ".join(runner.invoke(app, ["fit", "markers", "--help"]).output.split())
    synth = " ".join(runner.invoke(app, ["synth", "--help"]).output.split())
    assert "NAME=DEGREES" in markers and "in DEGREES" in markers
    assert "NAME=RADIANS" in synth and "in RADIANS" in synth and "x,y,z in metres" in synth


def test_the_command_line_starts_without_torch_or_the_service() -> None:
    """`bodyfit --help` and the server-backed commands load neither torch nor the service (only the commands
    that compute locally import them, inside the command)."""
    code = (
        "import sys\n"
        "from typer.testing import CliRunner\n"
        "from bodyfit.cli import app\n"
        "for args in (['--help'], ['fit', '--help'], ['fit', 'markers', '--help'], ['synth', '--help']):\n"
        "    assert CliRunner().invoke(app, args).exit_code == 0, args\n"
        "print(sorted(m for m in sys.modules if m.split('.')[0] in ('torch', 'fastapi', 'trimesh')\n"
        "             or m.startswith(('bodyfit.service', 'bodyfit.models.body', 'bodyfit.api.rest'))))\n"
    )
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr[-2000:]
    assert done.stdout.strip() == "[]"


def test_upgrade_takes_the_input_up_axis(tmp_path: Path) -> None:
    """`--up` names the input's up axis (the summary says it was given); `auto`, the default, detects
    AMASS's Z-up; a value naming no axis is refused with the allowed ones."""
    from bodyfit.io.smpl import read_smpl_sequence
    from bodyfit.models.upgrade.axes import turned
    from bodyfit.models.upgrade.smpl_model import load_smpl_model, rodrigues

    data = DATA / "smpl_format"
    seq = read_smpl_sequence(data / "cmu_131_smpl.npz")
    z_up = turned(seq, load_smpl_model(data / "smpl_like_model.npz"), rodrigues(np.array([np.pi / 2, 0, 0])))
    clip = tmp_path / "zup.npz"
    np.savez(clip, poses=z_up.poses[:8].reshape(8, 72), trans=z_up.trans[:8], mocap_framerate=30.0)
    args = ["upgrade", str(clip), "--smpl-model", str(data / "smpl_like_model.npz")]
    for up, given in (("auto", False), ("+z", True)):
        result = runner.invoke(app, [*args, "--out", str(tmp_path / up), "--up", up])
        assert result.exit_code == 0, result.output
        summary = json.loads((tmp_path / up / "zup.json").read_text())
        assert summary["up_axis"] == "+z" and summary["up_given"] is given
        assert "the input's up axis: +z" in result.output
    bad = runner.invoke(app, [*args, "--out", str(tmp_path / "bad"), "--up", "north"])
    assert bad.exit_code != 0 and "up must be auto or one of" in bad.output
