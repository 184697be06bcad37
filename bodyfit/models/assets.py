"""Locating model assets and checking them against their manifest."""

from __future__ import annotations

import hashlib
import json
import os
from pathlib import Path
from typing import Any

from bodyfit.models.errors import AssetError

MANIFEST = "manifest.json"
REBUILD_HINT = "rebuild the assets with `bodyfit build-assets` (or restore them with `git checkout assets/`)"


def assets_dir() -> Path:
    """The asset folder: $BODYFIT_ASSETS, else ``assets/`` next to the package (source checkout)."""
    env = os.environ.get("BODYFIT_ASSETS")
    return Path(env) if env else Path(__file__).resolve().parents[2] / "assets"


def sha256(path: Path) -> str:
    h = hashlib.sha256()
    with path.open("rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


def read_manifest(folder: Path | None = None) -> dict[str, Any]:
    folder = folder or assets_dir()
    path = folder / MANIFEST
    if not path.is_file():
        raise AssetError(f"asset manifest {path} is missing; {REBUILD_HINT}")
    try:
        manifest: dict[str, Any] = json.loads(path.read_text())
    except json.JSONDecodeError as exc:
        raise AssetError(f"asset manifest {path} is not valid JSON ({exc}); {REBUILD_HINT}") from exc
    return manifest


def verified_asset(name: str, folder: Path | None = None) -> Path:
    """Path of asset ``name`` after checking its sha256 against the manifest.

    Raises:
        AssetError: the manifest or the file is missing, or the hash does not match.
    """
    folder = folder or assets_dir()
    files = read_manifest(folder).get("files", {})
    if name not in files:
        raise AssetError(f"asset {name!r} is not listed in {folder / MANIFEST}; {REBUILD_HINT}")
    path = folder / name
    if not path.is_file():
        raise AssetError(f"asset file {path} is missing; {REBUILD_HINT}")
    digest = sha256(path)
    if digest != files[name]["sha256"]:
        raise AssetError(
            f"asset file {path} is corrupted or stale (sha256 {digest[:12]}..., manifest says "
            f"{files[name]['sha256'][:12]}...); {REBUILD_HINT}"
        )
    return path


def write_manifest(folder: Path, entries: dict[str, dict[str, Any]], info: dict[str, Any]) -> Path:
    """Write ``manifest.json`` listing every file with its sha256 and size, plus build ``info``.

    ``entries`` maps file name -> extra fields (metrics, seeds...). Existing entries for other files are kept.
    """
    path = folder / MANIFEST
    old: dict[str, Any] = json.loads(path.read_text()) if path.is_file() else {}
    files = old.get("files", {})
    for name, extra in entries.items():
        f = folder / name
        files[name] = {"sha256": sha256(f), "bytes": f.stat().st_size, **extra}
    manifest = {**old, **info, "files": dict(sorted(files.items()))}
    path.write_text(json.dumps(manifest, indent=1, sort_keys=True) + "\n")
    return path
