"""The SDK talks to the wire only: no module under bodyfit/clients imports the models, the service, the
server, the command line, torch or fastapi, checked on the source (every import statement, at any depth,
and every ``importlib.import_module`` / ``__import__`` of a constant name) and at run time."""

from __future__ import annotations

import ast
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
CLIENTS = ROOT / "bodyfit" / "clients"
FORBIDDEN = ("bodyfit.models", "bodyfit.service", "bodyfit.api", "bodyfit.cli", "torch", "fastapi")
WIRE = ("bodyfit.api.bodyfit_pb2", "bodyfit.api.bodyfit_pb2_grpc", "bodyfit.api.grpc_wire")
"""The gRPC half of the wire contract, generated from the .proto (plus its numpy array codec): shared by the
server and the SDK, and itself free of every forbidden import (checked below)."""
DEPRECATED = {
    "bodyfit/clients/cli.py": ("bodyfit.cli",),
    "bodyfit/clients/marker_cli.py": ("bodyfit.cli",),
    "bodyfit/clients/mesh_cli.py": ("bodyfit.cli",),
    "bodyfit/clients/sequence_cli.py": ("bodyfit.cli",),
    "bodyfit/clients/batch.py": ("bodyfit.cli.backends",),
}
"""Modules that keep an old path working for one release by reaching into :mod:`bodyfit.cli`, and the only
names each may reach; each says so in its docstring. Removed with the deprecated paths."""


def module_name(path: Path) -> str:
    parts = path.relative_to(ROOT).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def imports(source: str, module: str, is_package: bool = False) -> Iterator[tuple[int, str]]:
    """(line, dotted name) of everything ``source`` imports: ``from a import b`` gives ``a.b`` (so that a
    submodule counts as itself), relative imports are resolved against ``module``."""
    package = module if is_package else module.rpartition(".")[0]
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.Import):
            for alias in node.names:
                yield node.lineno, alias.name
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                anchor = package.split(".")[: len(package.split(".")) - node.level + 1]
                base = ".".join([*anchor, *([base] if base else [])])
            for alias in node.names:
                yield node.lineno, f"{base}.{alias.name}"
        elif (
            isinstance(node, ast.Call)
            and getattr(node.func, "attr", getattr(node.func, "id", None)) in ("import_module", "__import__")
            and node.args
            and isinstance(node.args[0], ast.Constant)
            and isinstance(node.args[0].value, str)
        ):
            yield node.lineno, node.args[0].value


def under(name: str, prefixes: tuple[str, ...]) -> bool:
    return any(name == p or name.startswith(p + ".") for p in prefixes)


def violations(
    source: str, module: str, is_package: bool = False, allowed: tuple[str, ...] = ()
) -> list[str]:
    return [
        f"{module}:{line} imports {name}"
        for line, name in imports(source, module, is_package)
        if under(name, FORBIDDEN) and not under(name, WIRE + allowed)
    ]


def sdk_modules() -> list[Path]:
    return sorted(CLIENTS.rglob("*.py"))


def test_the_sdk_imports_nothing_above_the_wire() -> None:
    found = []
    for path in sdk_modules():
        rel = str(path.relative_to(ROOT))
        found += violations(
            path.read_text(), module_name(path), path.name == "__init__.py", DEPRECATED.get(rel, ())
        )
    assert not found, "\n".join(found)


def test_the_wire_modules_the_sdk_imports_are_clean() -> None:
    """The gRPC wire modules, and the wire models the server and the SDK share (bodyfit/wire), import
    nothing the SDK may not."""
    paths = [ROOT / (name.replace(".", "/") + ".py") for name in WIRE]
    paths += sorted((ROOT / "bodyfit" / "wire").rglob("*.py"))
    for path in paths:
        name = module_name(path)
        assert not violations(path.read_text(), name, path.name == "__init__.py"), name


@pytest.mark.parametrize("rel", sorted(DEPRECATED))
def test_each_exception_is_a_deprecated_path(rel: str) -> None:
    doc = " ".join((ast.get_docstring(ast.parse((ROOT / rel).read_text())) or "").split())
    assert "Deprecated" in doc and "will be removed in the next release" in doc, rel


@pytest.mark.parametrize(
    ("source", "module", "bad"),
    [
        ("from bodyfit.service.core import BodyService", "bodyfit.clients.x", True),
        ("import torch.nn", "bodyfit.clients.x", True),
        ("def f():\n    from fastapi import FastAPI", "bodyfit.clients.x", True),
        ("from ..models import errors", "bodyfit.clients.x", True),
        ("from ...cli import app", "bodyfit.clients.core.x", True),
        ("import importlib\nimportlib.import_module('bodyfit.models.body')", "bodyfit.clients.x", True),
        ("from bodyfit.api import schemas", "bodyfit.clients.x", True),
        ("from bodyfit.api import bodyfit_pb2 as pb", "bodyfit.clients.x", False),
        ("from bodyfit.api.grpc_wire import to_proto", "bodyfit.clients.x", False),
        ("from . import errors\nfrom .core import base", "bodyfit.clients.x", False),
        ("import numpy, httpx\nfrom bodyfit.io.npz import read_npz", "bodyfit.clients.x", False),
    ],
)
def test_the_check_sees_every_way_of_importing(source: str, module: str, bad: bool) -> None:
    assert bool(violations(source, module)) is bad


def test_importing_the_sdk_loads_no_server_code() -> None:
    """Every SDK module, the deprecated paths included, imports without the models, the service, the server
    or torch (the deprecated paths reach the command line, which imports those only inside commands). The
    one model module loaded is ``bodyfit.models.errors``: :mod:`bodyfit.io`'s errors derive from its
    ``BodyfitError``, and the SDK reads npz results with :mod:`bodyfit.io.npz`."""
    names = [module_name(p) for p in sdk_modules() if p.name != "__init__.py" or p.parent != CLIENTS]
    code = (
        "import importlib, sys\n"
        "for m in sys.argv[1:]: importlib.import_module(m)\n"
        "print(sorted(m for m in sys.modules if m.split('.')[0] in ('torch', 'fastapi', 'uvicorn')\n"
        "             or m.startswith(('bodyfit.models.', 'bodyfit.service', 'bodyfit.api.rest'))\n"
        "             and m != 'bodyfit.models.errors'))\n"
    )
    done = subprocess.run(
        [sys.executable, "-c", code, "bodyfit.clients", *names], capture_output=True, text=True, timeout=120
    )
    assert done.returncode == 0, done.stderr[-2000:]
    assert done.stdout.strip() == "[]"
