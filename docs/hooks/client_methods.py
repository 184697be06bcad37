"""A griffe extension for the API pages: the SDK clients declare their methods once, as attributes built
from the request functions (``fit_scan = sync_method(ops.fit_scan)``), which static analysis sees as plain
attributes. This turns each such attribute into a method with the function's signature and docstring, so
`Client`, `AsyncClient` and `GrpcClient` show their methods. It changes nothing when no attribute matches."""

from __future__ import annotations

import re
from typing import Any

import griffe

METHOD = re.compile(r"^(sync|async)_method\((?:\w+\.)*(\w+)\)$")


def _classes(obj: griffe.Object) -> list[griffe.Class]:
    found: list[griffe.Class] = []
    for member in obj.members.values():
        if member.is_alias:
            continue
        if isinstance(member, griffe.Class):
            found.append(member)
        if isinstance(member, griffe.Module | griffe.Class):
            found.extend(_classes(member))
    return found


def _functions(pkg: griffe.Module) -> dict[str, griffe.Function]:
    """The request functions the methods are built from, by name (any module of the package)."""
    functions: dict[str, griffe.Function] = {}

    def walk(mod: griffe.Module) -> None:
        for member in mod.members.values():
            if member.is_alias:
                continue
            if isinstance(member, griffe.Module):
                walk(member)
            elif isinstance(member, griffe.Function) and mod.path.endswith(".operations"):
                functions[member.name] = member

    walk(pkg)
    return functions


class ClientMethods(griffe.Extension):
    def on_package(self, *, pkg: griffe.Module, loader: griffe.GriffeLoader, **kwargs: Any) -> None:
        functions = _functions(pkg)
        for cls in _classes(pkg):
            for name, member in list(cls.members.items()):
                if member.is_alias or not isinstance(member, griffe.Attribute) or member.value is None:
                    continue
                match = METHOD.match(str(member.value))
                source = functions.get(match.group(2)) if match else None
                if match is None or source is None:
                    continue
                returns = source.returns
                # the function builds the request (Operation[R]); the method returns its result, R
                if isinstance(returns, griffe.ExprSubscript) and str(returns.left).endswith("Operation"):
                    returns = returns.slice
                params = [griffe.Parameter("self", kind=griffe.ParameterKind.positional_only)]
                params += list(source.parameters)
                method = griffe.Function(
                    name,
                    lineno=member.lineno,
                    endlineno=member.endlineno,
                    parameters=griffe.Parameters(*params),
                    returns=returns,
                    docstring=None,
                )
                if source.docstring is not None:
                    method.docstring = griffe.Docstring(
                        source.docstring.value, lineno=source.docstring.lineno, parent=method
                    )
                if match.group(1) == "async":
                    method.labels.add("async")
                cls.set_member(name, method)
