"""The fitting benchmarks in one run: registered meshes against anny's AnnyInverter, mocap markers against
OpenSim's inverse kinematics, sequences, raw scans. Each part is its own script (see their docstrings for
what is measured):

* ``fit_registered.py``: ``registered_mm``, ``registered_ms``, ``anny_mm``, ``anny_ms``, ratio.
* ``fit_markers.py``: ``ik_rmse_deg``, ``ik_seconds``, ``opensim_ik_seconds``, ``ik_speed_ratio``.
* ``fit_sequences.py``: ``seq_fps``, ``seq_mm``, ``seq_jitter_ratio`` (CMU motion on held-out bodies) and
  the independent per-frame peer (``seq_peer_fps``, ``seq_peer_mm``).
* ``fit_scans.py``: ``scan_clean_mm``, ``scan_corrupt_mm`` (scan-to-model), ``scan_registration_mm``
  (against the ground-truth body), ``scan_s`` (seconds per 100k points), per corruption; ``scan_clutter_mm``.
* ``fit_ccby.py``: ``ccby_fit_to_scan_mm``, ``ccby_fit_to_scan_max_mm`` (the CC BY bodies outside our
  population, as raw points and as SMPL-topology meshes).
* ``bones.py``: ``bones_outside_frac`` (bone-mesh vertices outside the posed skin).
* ``fit_confidence.py``: ``conf_auroc``, ``conf_recall_good``, ``confident_over_25mm``,
  ``gross_failure_rate`` (the worse of ``gross_failure_rate_searched`` and ``gross_failure_rate_hinted``) on
  a held-out matrix of 11 poses x 12 corruptions.

Usage::

    python benchmarks/fit.py [--quick] [--json]
"""

from __future__ import annotations

import os
import platform
import time
from typing import Any

import bones  # benchmarks/ is on sys.path when this script runs
import fit_ccby
import fit_confidence
import fit_markers
import fit_registered
import fit_scans
import fit_sequences
from bench_cli import bench_main


def run(quick: bool) -> dict[str, Any]:
    start = time.perf_counter()
    out: dict[str, Any] = {
        "machine": {"cpu_count": os.cpu_count(), "python": platform.python_version(), "quick": quick},
    }
    out.update(fit_registered.run(quick))
    out.update(fit_markers.run(quick))
    out.update(fit_sequences.run(quick))
    out.update(fit_scans.run(quick))
    ccby = fit_ccby.run(quick)
    out.update({k: ccby[k] for k in ("ccby_fit_to_scan_mm", "ccby_fit_to_scan_max_mm")})
    out.update({k: v for k, v in fit_confidence.run(quick).items() if k != "gross_cells"})
    out.update(bones.run(quick))
    out["seconds"] = round(time.perf_counter() - start, 1)
    return out


def main(argv: list[str] | None = None) -> None:
    bench_main(
        run, "fitting benchmarks: ours against anny and OpenSim", "small samples (a minute or two)", argv
    )


if __name__ == "__main__":
    main()
