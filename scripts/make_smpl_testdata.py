"""Regenerate tests/data/smpl_format (an SMPL-format model file and sequence made from open data only).

Usage: python scripts/make_smpl_testdata.py [--frames 60]
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # benchmarks/ is not installed
from benchmarks.smpl_testdata import write_test_data

ROOT = Path(__file__).resolve().parents[1]

if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--frames", type=int, default=60)
    args = parser.parse_args()
    bvh = ROOT / "tests" / "data" / "cmu_bvh" / "cmu_131_01_clip.bvh"
    for kind, path in write_test_data(ROOT / "tests" / "data" / "smpl_format", bvh, args.frames).items():
        print(f"{kind}: {path} ({path.stat().st_size:,} bytes)")
