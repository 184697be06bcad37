"""The command line the benchmark scripts share: ``--quick``, ``--json``, one result dictionary."""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import sys
from collections.abc import Callable, Iterator
from typing import Any


@contextlib.contextmanager
def stdout_to_stderr() -> Iterator[None]:
    """Send everything written to standard output, by Python or by native libraries (warp's and OpenSim's
    banners), to standard error for the duration, so that ``--json`` prints the result alone."""
    sys.stdout.flush()
    saved = os.dup(1)
    os.dup2(2, 1)
    try:
        with contextlib.redirect_stdout(sys.stderr):
            yield
    finally:
        sys.stdout.flush()
        os.dup2(saved, 1)
        os.close(saved)


def bench_main(
    run: Callable[[bool], dict[str, Any]],
    description: str,
    quick_help: str,
    argv: list[str] | None = None,
    show: Callable[[dict[str, Any]], None] | None = None,
) -> None:
    """Parse ``--quick`` / ``--json``, call ``run(quick)`` and print its result as one JSON object, or with
    ``show`` (default: aligned ``key: value`` lines)."""
    parser = argparse.ArgumentParser(description=description)
    parser.add_argument("--quick", action="store_true", help=quick_help)
    parser.add_argument("--json", action="store_true", help="print one JSON object")
    args = parser.parse_args(argv)
    if args.json:
        with stdout_to_stderr():
            result = run(args.quick)
        print(json.dumps(result))
        return
    result = run(args.quick)
    if show is not None:
        show(result)
        return
    for key, value in result.items():
        print(f"{key:>30}: {value}")
