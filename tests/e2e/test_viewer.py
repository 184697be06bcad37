"""End to end in a real browser: the server (``bodyfit serve`` on 127.0.0.1) and its viewer page in headless
Chromium. A DOF slider moved with the keyboard, a scan dropped on the page and fitted, an upgrade played:
each changes the canvas's pixels, the numbers the page shows are the API's, and the console stays free of
errors. Screenshots go to build/screenshots/ (docs/viewer_*.png are copies of them).

Chromium is installed from Debian's packages when missing (as root, where apt-get runs); the test skips,
saying why, only where no browser can be found or installed."""

from __future__ import annotations

import base64
import io
import json
import math
import re
from collections.abc import Iterator
from pathlib import Path

import httpx
import numpy as np
import pytest
from fastapi.testclient import TestClient
from PIL import Image

from benchmarks.chromium import BrowserUnavailableError, Page, browser
from benchmarks.server_process import ServerProcess, start_server
from bodyfit.api.rest import routes_viewer
from bodyfit.api.rest.app import create_app
from bodyfit.api.settings import ServiceSettings

ROOT = Path(__file__).resolve().parents[2]
SHOTS = ROOT / "build" / "screenshots"
UPGRADE = ROOT / "tests" / "data" / "smpl_format" / "cmu_131_smpl.npz"
SYNTH = "window.bodyfitViewer.modes.synth"
# the knee_r joint centre on the screen: its sphere projected by the view's camera
KNEE_ON_SCREEN = """(() => {
  const v = window.bodyfitViewer.view;
  const sphere = v.joints.children[v.jointInfo.findIndex(j => j.name === 'knee_r')];
  const p = sphere.getWorldPosition(v.camera.position.clone()).project(v.camera);
  const r = v.canvas.getBoundingClientRect();
  return [r.x + (p.x + 1) / 2 * r.width, r.y + (1 - p.y) / 2 * r.height];
})()"""
TIMELINE = "document.getElementById('up-frame')"
POSE = {"hip_flexion_r": 0.6, "knee_angle_r": 0.9, "elbow_flex_l": 1.2, "arm_add_r": -0.4}


@pytest.fixture(scope="module")
def server() -> Iterator[ServerProcess]:
    process = start_server({"BODYFIT_THREADS": "1"})
    yield process
    process.stop()


@pytest.fixture(scope="module")
def page() -> Iterator[Page]:
    try:
        with browser(install=True) as opened:
            yield opened
    except BrowserUnavailableError as exc:
        pytest.skip(f"no browser for the viewer test: {exc}")


def canvas_pixels(page: Page, png: bytes) -> np.ndarray:
    """The 3D view's pixels (H, W, 3) uint8 cut from a screenshot of the page."""
    box = page.evaluate(
        "(() => { const r = document.getElementById('view').getBoundingClientRect();"
        " return [r.x, r.y, r.width, r.height].map(Math.round); })()"
    )
    x, y, w, h = box
    image = np.asarray(Image.open(io.BytesIO(png)).convert("RGB"))
    return image[y : y + h, x : x + w]


def changed(a: np.ndarray, b: np.ndarray) -> float:
    """The fraction of pixels that differ by more than 8 levels in some channel."""
    return float((np.abs(a.astype(np.int16) - b.astype(np.int16)).max(axis=2) > 8).mean())


def shot(page: Page, name: str) -> np.ndarray:
    return canvas_pixels(page, page.screenshot(SHOTS / f"viewer_{name}.png"))


def text(page: Page, selector: str) -> str:
    return str(page.evaluate(f"document.querySelector({json.dumps(selector)}).textContent"))


def check_synthesize(page: Page, url: str) -> np.ndarray:
    """Load the page, move knee_angle_r to its upper limit with the keyboard; the body, its stature and
    its knee centre follow the API's answer for the same parameters."""
    page.navigate(f"{url}/")
    page.wait_for(f"window.bodyfitViewer && window.bodyfitViewer.ready && !{SYNTH}.inFlight")
    before = shot(page, "loaded")
    background = np.array([247, 248, 250])
    assert (np.abs(before.astype(int) - background).max(axis=2) > 8).mean() > 0.05, "the canvas is blank"
    page.evaluate("document.querySelector('#dof-sliders details').open = true")
    sent = page.evaluate("window.bodyfitViewer.modes.synth.timings.length")
    page.evaluate("document.getElementById('dof-knee_angle_r').focus()")
    page.press("End", 35)
    page.wait_for(f"(s => s.timings.length > {sent} && !s.inFlight && s.pending === null)({SYNTH})")
    knee = float(page.evaluate("document.getElementById('dof-knee_angle_r').value"))
    assert knee > 2.0
    after = shot(page, "synthesize")
    assert changed(before, after) > 0.003, "moving the knee slider did not change the view"

    answer = httpx.post(f"{url}/v1/synthesize", json={"coordinates": {"knee_angle_r": knee}}, timeout=30)
    arrays = np.load(io.BytesIO(answer.content))
    vertices, joints = arrays["vertices"][0], arrays["joints"][0]
    stature = (vertices[:, 1].max() - vertices[:, 1].min()) * 1000
    assert abs(float(text(page, "#synth-stature")) - stature) < 0.06
    names = [str(n) for n in arrays["joint_names"]]
    shown = page.evaluate(
        "Array.from(document.querySelectorAll('#synth-joints tr'), r => r.cells[1].textContent)"
    )
    knee_centre = [float(v) for v in shown[names.index("knee_r")].split(",")]
    np.testing.assert_allclose(knee_centre, joints[names.index("knee_r")], atol=6e-4)
    page.hover(*page.evaluate(KNEE_ON_SCREEN))
    tip = page.wait_for("(t => !t.hidden && t.textContent)(document.getElementById('tooltip'))")
    assert tip.split("\n") == ["knee_r", "knee_angle_r"]  # the joint's and its coordinate's OpenSim names
    return after


def scan_file(url: str, folder: Path) -> Path:
    """A posed body as a PLY mesh, the file a scanner would write (the service's own output format)."""
    body = {"coordinates": POSE, "shape": [[0.8, -0.5] + [0.3] * 30], "format": "ply"}
    path = folder / "posed_scan.ply"
    path.write_bytes(httpx.post(f"{url}/v1/synthesize", json=body, timeout=30).content)
    return path


def check_fit(page: Page, url: str, scan: Path, synth_view: np.ndarray) -> None:
    """Drop the scan on the page: the fit's report shows the API's numbers and the view changes."""
    page.evaluate("document.querySelector('[data-tab=fit]').click()")
    page.drop_files("#fit-drop", [scan])
    page.wait_for("window.bodyfitViewer.fit || window.bodyfitViewer.errors.length", 60)
    assert page.evaluate("window.bodyfitViewer.errors") == []
    view = shot(page, "fit")
    assert changed(synth_view, view) > 0.01, "the fit did not change the view"

    with scan.open("rb") as f:
        api = httpx.post(f"{url}/v1/fit/scan", files={"file": (scan.name, f)}, timeout=120).json()
    assert text(page, "#fit-fitted-as") == api["fitted_as"]
    assert text(page, "#fit-confident") == ("yes" if api["report"]["confident"] else "no")
    shown_mean = float(text(page, "[data-key=distances-mean]").split()[0])
    assert abs(shown_mean - api["report"]["distances"]["mean"]) < 0.02
    coloured = page.evaluate("window.bodyfitViewer.fit.meanErrorMm")
    assert coloured is not None and coloured < 1.0  # a registered mesh: every vertex on the scan


def upgrade_file(folder: Path, frames: int = 24) -> Path:
    """The first ``frames`` frames of the AMASS-style test sequence (a short upload: a quick test)."""
    with np.load(UPGRADE) as z:
        arrays = {k: z[k][:frames] if z[k].ndim and len(z[k]) > frames else z[k] for k in z.files}
    path = folder / "cmu_131_short.npz"
    np.savez(path, **arrays)
    return path


def check_upgrade(page: Page, url: str, upload: Path, fit_view: np.ndarray) -> None:
    """Upload the AMASS-style sequence, play it (frames advance, the view moves), then seek to a frame:
    the coordinates shown are the API's for that frame."""
    page.evaluate("document.querySelector('[data-tab=upgrade]').click()")
    page.set_files("#up-file", [upload])
    page.wait_for("window.bodyfitViewer.upgrade || window.bodyfitViewer.errors.length", 60)
    assert page.evaluate("window.bodyfitViewer.errors") == []
    first = shot(page, "upgrade_start")
    assert changed(fit_view, first) > 0.01
    page.evaluate("document.getElementById('up-play').click()")
    page.wait_for("window.bodyfitViewer.modes.upgrade.current > 10", 20)
    page.evaluate("document.getElementById('up-play').click()")
    assert changed(first, shot(page, "upgrade_playing")) > 0.003, "playing did not move the body"

    frame = 16
    page.evaluate(f"(s => {{ s.value = {frame}; s.dispatchEvent(new Event('input')); }})({TIMELINE})")
    page.wait_for(f"window.bodyfitViewer.modes.upgrade.current === {frame}")
    shot(page, "upgrade")
    with upload.open("rb") as f:
        api = httpx.post(f"{url}/v1/upgrade", files={"file": (upload.name, f)}, timeout=120).json()
    assert text(page, "#up-frames") == str(api["summary"]["frames"])
    chunk = next(c for c in api["chunks"] if c["start"] <= frame < c["stop"])
    a = chunk["arrays"]["coordinates"]
    coords = np.frombuffer(base64.b64decode(a["data"]), "<f8").reshape(a["shape"])
    row = coords[frame - chunk["start"]]
    for name in ("hip_flexion_r", "knee_angle_l", "ankle_angle_r"):
        shown = float(text(page, f"[data-dof={name}]").rstrip("°"))
        assert abs(shown - math.degrees(row[api["dof_names"].index(name)])) < 0.06, name
    hrefs = page.evaluate("Array.from(document.querySelectorAll('#up-files a'), a => a.download)")
    assert sorted(h.rsplit(".", 1)[1] for h in hrefs) == sorted(api["files"])


def check_problem(page: Page, url: str, folder: Path) -> None:
    """A file that is no scan: the page shows the API's problem+json detail, not a blank page."""
    bad = folder / "not_a_scan.ply"
    bad.write_bytes(b"ply\nformat ascii 1.0\nelement vertex 2\nend_header\nnot numbers\n")
    page.evaluate("document.querySelector('[data-tab=fit]').click()")
    page.drop_files("#fit-drop", [bad])
    page.wait_for("window.bodyfitViewer.errors.length > 0")
    with bad.open("rb") as f:
        problem = httpx.post(f"{url}/v1/fit/scan", files={"file": (bad.name, f)}, timeout=30).json()
    assert text(page, "#error-detail") == problem["detail"]
    assert not page.evaluate("document.getElementById('error').hidden")
    shot(page, "error")


def test_viewer_in_chromium(server: ServerProcess, page: Page, tmp_path: Path) -> None:
    synth_view = check_synthesize(page, server.url)
    check_fit(page, server.url, scan_file(server.url, tmp_path), synth_view)
    check_upgrade(page, server.url, upgrade_file(tmp_path), shot(page, "fit"))
    assert page.errors() == [], "the browser console has errors"
    check_problem(page, server.url, tmp_path)
    # the refused upload is the one error: the browser logs every 4xx answer it receives
    assert all("status of 422" in e for e in page.errors()), page.errors()


def test_viewer_files_are_ours_and_small() -> None:
    """Every file the page loads is served by us (no CDN), three.js is the version the npm lock pins, and
    the whole viewer stays under 2 MiB. No browser and no model needed."""
    client = TestClient(create_app(ServiceSettings()))
    html = client.get("/").text
    assert client.get("/viewer").text == html and client.head("/").status_code == 200
    assert not re.search(r"""(src|href|import)[=\s(]*["']https?://""", html)
    urls = re.findall(r"""["'](/viewer/static/[^"']+)["']""", html)
    for name in ("three.module.min.js", "three.core.min.js", "app.js", "style.css"):
        assert any(u.endswith(name) for u in urls), name
    for url in urls:
        answer = client.get(url)
        assert answer.status_code == 200, url
        assert answer.headers["content-type"].startswith(("text/javascript", "text/css")), url
    static = routes_viewer.STATIC
    for script in static.glob("*.js"):
        assert not re.search(r"""from\s+["']https?://""", script.read_text()), script
    assert sum(p.stat().st_size for p in static.rglob("*") if p.is_file()) <= 2048 * 1024
    lock = json.loads((ROOT / "viewer" / "package-lock.json").read_text())
    pinned = lock["packages"]["node_modules/three"]["version"]
    assert (static / "vendor" / "VERSION").read_text().split() == ["three", pinned]
    installed = ROOT / "viewer" / "node_modules" / "three"
    if installed.is_dir():  # after `npm ci` in viewer/: the vendored build is the installed one
        for name in ("three.module.min.js", "three.core.min.js"):
            assert (static / "vendor" / name).read_bytes() == (installed / "build" / name).read_bytes()


def test_missing_viewer_files_leave_the_api_serving(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    """An installation without the viewer's files answers / with a problem+json 404 that says so."""
    monkeypatch.setattr(routes_viewer, "STATIC", tmp_path)
    answer = TestClient(create_app(ServiceSettings())).get("/")
    assert answer.status_code == 404
    assert answer.headers["content-type"] == "application/problem+json"
    assert "no viewer files" in answer.json()["detail"]
