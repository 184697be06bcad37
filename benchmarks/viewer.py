"""Viewer benchmark: how fast the browser viewer loads and follows a slider, how large it is, and whether
its console stays clean, in real headless Chromium against a real server on the loopback.

What is measured
----------------
* A real server (``bodyfit serve`` in a subprocess on 127.0.0.1, ``--threads 1``) is started and waited
  for (``/readyz``); headless Chromium (Debian's ``chromium``) is driven over the DevTools protocol.
* ``page_load_ms``: median over N loads of ``/`` with the browser's cache disabled (every script and the
  three.js build fetched again), from the navigation's start to the first body drawn: the page, its
  scripts, ``GET /v1/model`` and the first synthesize answer (skin with its triangles) parsed and
  rendered. Target <= 1000 ms.
* ``slider_roundtrip_ms``: median over N slider moves of the page's synthesize round trip at B = 1 (the
  request the page sends while a slider is dragged: npz, skin only), from the request to its arrays
  parsed; ``slider_roundtrip_p95_ms`` its 95th percentile; ``slider_frame_ms`` the same move until the new
  body is drawn (round trip, upload to the GPU and render). Target (median round trip) <= 50 ms.
* ``static_kb``: every file the viewer serves (page, scripts, styles, vendored three.js and its licence),
  KiB. Target <= 2048.
* ``console_errors``: error-level console messages and uncaught exceptions over all of it. Target 0.
* The browser, the server and this script share the machine's cores.

Usage::

    python benchmarks/viewer.py [--quick] [--json]
"""

from __future__ import annotations

import statistics
import sys
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
TARGETS = {"page_load_ms": 1000.0, "slider_roundtrip_ms": 50.0, "static_kb": 2048.0, "console_errors": 0}

# One slider move from the page, timed: a new knee angle, the page's own request (skin only, as while
# dragging), then the frame drawn. Resolves to [round trip ms, until drawn ms].
MOVE = """(async (value) => {
  const synth = window.bodyfitViewer.modes.synth;
  const slider = document.getElementById('dof-knee_angle_r');
  slider.value = value;
  const began = performance.now();
  const frames = window.bodyfitViewer.view.frames;
  await synth.request(false);
  await new Promise(requestAnimationFrame);
  if (window.bodyfitViewer.view.frames === frames) throw new Error('the move drew no frame');
  return [synth.timings[synth.timings.length - 1].ms, performance.now() - began];
})"""


def static_kb() -> float:
    """The viewer's files (everything under its static folder), KiB."""
    from bodyfit.api.rest.routes_viewer import STATIC

    return sum(p.stat().st_size for p in STATIC.rglob("*") if p.is_file()) / 1024


def page_loads(page: Any, url: str, n: int) -> tuple[list[float], dict[str, float]]:
    """``n`` loads of the page without the browser's cache: ms from navigation start to the first body,
    and the median ms at which each stage ended (the page's marks: scripts run, WebGL set up, model info,
    sliders built, first body parsed, drawn)."""
    page.call("Network.enable")
    page.call("Network.setCacheDisabled", cacheDisabled=True)
    times, marks = [], []
    for _ in range(n):
        page.navigate("about:blank")
        page.navigate(f"{url}/")
        times.append(float(page.wait_for("window.bodyfitViewer && window.bodyfitViewer.readyMs", 30)))
        marks.append(page.evaluate("window.bodyfitViewer.marks"))
        page.wait_for("!window.bodyfitViewer.modes.synth.inFlight")  # the bones that follow the skin
    page.call("Network.setCacheDisabled", cacheDisabled=False)
    stages = {k: round(statistics.median(float(m[k]) for m in marks), 1) for k in marks[0]}
    return times, stages


def slider_moves(page: Any, n: int) -> tuple[list[float], list[float]]:
    """``n`` knee-slider moves timed in the page: (round trips ms, until drawn ms)."""
    trips, frames = [], []
    for i in range(n + 3):
        trip, frame = page.evaluate(f"{MOVE}({0.1 + 1.8 * (i % 10) / 9})")
        if i >= 3:  # the first requests warm the connection and the page's code paths
            trips.append(float(trip))
            frames.append(float(frame))
    return trips, frames


def run(quick: bool) -> dict[str, Any]:
    from benchmarks.chromium import browser, find_chromium
    from benchmarks.server_process import start_server

    loads, moves = (3, 30) if quick else (10, 200)
    server = start_server({"BODYFIT_THREADS": "1"})
    try:
        with browser(install=True) as page:
            version = page.call("Browser.getVersion")["product"]
            load_ms, stages = page_loads(page, server.url, loads)
            trips, frames = slider_moves(page, moves)
            errors = page.errors()
    finally:
        server.stop()
    trips_sorted = sorted(trips)
    result: dict[str, Any] = {
        "browser": f"{version} ({find_chromium()})",
        "loads": loads,
        "moves": moves,
        "page_load_ms": round(statistics.median(load_ms), 1),
        "page_load_max_ms": round(max(load_ms), 1),
        "page_load_stages_ms": stages,
        "slider_roundtrip_ms": round(statistics.median(trips), 1),
        "slider_roundtrip_p95_ms": round(trips_sorted[int(0.95 * (len(trips_sorted) - 1))], 1),
        "slider_frame_ms": round(statistics.median(frames), 1),
        "static_kb": round(static_kb(), 1),
        "console_errors": len(errors),
        "console_error_messages": errors[:5],
        "targets": TARGETS,
    }
    result["met"] = bool(
        result["page_load_ms"] <= TARGETS["page_load_ms"]
        and result["slider_roundtrip_ms"] <= TARGETS["slider_roundtrip_ms"]
        and result["static_kb"] <= TARGETS["static_kb"]
        and result["console_errors"] == TARGETS["console_errors"]
    )
    return result


def main(argv: list[str] | None = None) -> None:
    from benchmarks.bench_cli import bench_main

    bench_main(
        run, "Viewer page load, slider round trip, size and console errors (Chromium).", "fewer loads", argv
    )


if __name__ == "__main__":
    sys.path.insert(0, str(ROOT))
    main()
