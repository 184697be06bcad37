"""The command line the benchmark scripts share: ``--quick``, ``--json``, one result dictionary."""

from __future__ import annotations

import argparse
import json
from collections.abc import Callable
from typing import Any


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
    result = run(args.quick)
    if args.json:
        print(json.dumps(result))
        return
    if show is not None:
        show(result)
        return
    for key, value in result.items():
        print(f"{key:>30}: {value}")
