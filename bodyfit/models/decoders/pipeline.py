"""From the asset build's population to a shipped spiral decoder: cached data, training, held-out
comparison with the identity PCA, asset (``bodyfit decoders train``; build time, needs anny)."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

from bodyfit.models.assets import assets_dir, read_manifest
from bodyfit.models.body.model import BODY_ASSET, BodyModel
from bodyfit.models.decoders.population import IdentitySet
from bodyfit.models.decoders.spiral import Hierarchy, build_hierarchy
from bodyfit.models.decoders.train import TrainConfig, Trained, compare, pca_of, train_spiral

# Bodies outside the training population: (name, builder's seed, count).
OUTSIDE = (("children", 7, 100), ("extreme", 8, 100))


def default_work_dir() -> Path:
    """Where the bodies, hierarchy and checkpoints are cached: build/decoders of the checkout."""
    return Path(__file__).resolve().parents[3] / "build" / "decoders"


def _tag(folder: Path | None) -> str:
    return str(read_manifest(folder or assets_dir())["files"][BODY_ASSET]["sha256"])[:12]


def identity_sets(model: BodyModel, work: Path, folder: Path | None = None) -> dict[str, IdentitySet]:
    """The population (``population``, its held-out tenth marked) and the bodies outside it, from the
    cache in ``work`` (keyed by the body model's hash) or generated with anny (about 5 minutes)."""
    from bodyfit.models.build_assets import default_cache_dir
    from bodyfit.models.decoders import population as pop

    out = {}
    makers: dict[str, Callable[[], IdentitySet]] = {
        "population": lambda: pop.build_population(model, default_cache_dir()),
        "children": lambda: pop.children(model, default_cache_dir(), OUTSIDE[0][2], OUTSIDE[0][1]),
        "extreme": lambda: pop.extreme_adults(model, default_cache_dir(), OUTSIDE[1][2], OUTSIDE[1][1]),
    }
    for name, make in makers.items():
        path = work / f"{name}_{_tag(folder)}.npz"
        if not path.is_file():
            make().save(path)
        out[name] = IdentitySet.load(path)
    return out


def hierarchy(model: BodyModel, work: Path, folder: Path | None = None) -> Hierarchy:
    """The template's decimation hierarchy and spirals, cached in ``work`` (about a minute to compute)."""
    path = work / f"hierarchy_{_tag(folder)}.npz"
    if not path.is_file():
        path.parent.mkdir(parents=True, exist_ok=True)
        h = build_hierarchy(model.data["vertices_mean"], model.data["faces"])
        arrays: dict[str, Any] = h.arrays()
        np.savez(path, **arrays)
    with np.load(path) as z:
        return Hierarchy.from_arrays({k: z[k] for k in z.files})


def evaluate(
    trained: Trained,
    sets: dict[str, IdentitySet],
    d: int,
    limit: int | None = None,
    outside_limit: int | None = None,
) -> dict[str, dict[str, float]]:
    """Spiral against a d-component identity PCA fitted on the same training bodies, on the held-out tenth
    (at most ``limit`` bodies) and on each set outside the population (at most ``outside_limit``)."""
    train = sets["population"]
    pca = pca_of(train.offsets[~train.held], d)
    out = {"heldout": compare(trained, pca, train.offsets[train.held][:limit])}
    for name, s in sets.items():
        if name != "population":
            out[name] = compare(trained, pca, s.offsets[:outside_limit])
    return out


def train_decoder(
    d: int,
    minutes: float,
    work: Path | None = None,
    folder: Path | None = None,
    log: Callable[[str], None] = print,
    device: str = "cpu",
) -> tuple[Trained, Hierarchy, dict[str, Any]]:
    """Train the spiral decoder of latent size d on the population's training bodies and compare it with
    the PCA. Returns the decoder, its hierarchy and the metrics for the manifest."""
    work = work or default_work_dir()
    model = BodyModel.load(folder)
    sets = identity_sets(model, work, folder)
    h = hierarchy(model, work, folder)
    pop = sets["population"]
    config = replace(TrainConfig(), d=d, minutes=minutes)
    trained = train_spiral(h, pop.offsets[~pop.held], config, work / f"spiral_d{d}.pt", log, device)
    metrics: dict[str, Any] = {
        "train_bodies": int((~pop.held).sum()),
        "epochs": len(trained.history),
        "train_mm": round(trained.history[-1]["train_mm"], 3),
        "compare_mm": {
            k: {m: round(x, 3) for m, x in v.items()} for k, v in evaluate(trained, sets, d).items()
        },
    }
    return trained, h, metrics
