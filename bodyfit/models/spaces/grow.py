"""Growing a shape space from raw scans: BLiSS's closing of the loop (section 3.4, Algorithm 1).

Start from the registrations the space already explains (a sample of the model's own population, plus any
seed registrations). Each round registers every scan not yet accepted in the current space
(:func:`~bodyfit.models.spaces.register.register`: projection, non-rigid refinement, unposing), accepts the
registrations whose Chamfer distance to their scan is within the round's minimum plus one standard
deviation (and below an absolute ceiling, so that a round of poor registrations adds nothing), adds their
bind-pose meshes to the population and recomputes the space from it
(:func:`~bodyfit.models.spaces.population.recompute_space`). It stops when a round accepts nothing, every
scan is accepted, or after ``rounds`` rounds.

Scans that are already meshes in the model's topology (its vertex count and faces) need no registration:
their correspondence to the template is exact, and projecting them into the space would replace the body
they carry by its nearest body of the space plus what the refinement recovers along the normals. They are
unposed as they are with their first fit's pose, as seed registrations are
(:func:`~bodyfit.models.spaces.register.seed_registrations`), and enter the population in one round of their
own (reported with ``"unposed"``) before the projection rounds of the other scans.

BLiSS: S. Muralikrishnan, C.-H. P. Huang, D. Ceylan and N. J. Mitra, "BLiSS: Bootstrapped Linear Shape
Space", International Conference on 3D Vision (3DV), 2024.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from bodyfit.models.body.model import BodyModel
from bodyfit.models.fitting.common.nonrigid import NonRigidConfig, NonRigidStage
from bodyfit.models.spaces.population import Population, recompute_space, rest_meshes, sample_population
from bodyfit.models.spaces.register import (
    PosedScan,
    Registration,
    in_topology,
    initial_shape,
    register,
    seed_registrations,
)

Evaluate = Callable[[dict[str, np.ndarray]], dict[str, float]]
"""A space's arrays (``body.npz``) -> its errors on held-out bodies (``v2v_mm``, ``v2p_mm``, ``v2v_cm``)."""


# The refinement's schedule while growing: two levels like the finer ones of the scan fit's schedule. The
# projection already brings the body within a few millimetres, which the coarse levels (built to move whole
# misplaced parts) would only spend time on: a registration takes seconds instead of tens of seconds.
GROW_NONRIGID = NonRigidConfig(
    stages=(
        NonRigidStage(smoothness=4.0, max_distance=0.06, sigma=0.02, rounds=3),
        NonRigidStage(smoothness=1.0, max_distance=0.04, sigma=0.01, rounds=3),
    )
)


@dataclass(frozen=True)
class GrowConfig:
    """rounds: the most rounds; n_population: bodies sampled from the model's own space as the starting
    registrations (the population it was built from, which the grown space must keep explaining); seed:
    their draw; max_chamfer_mm: registrations further from their scan are never accepted; nonrigid: the
    refinement's schedule."""

    rounds: int = 5
    n_population: int = 200
    seed: int = 0
    max_chamfer_mm: float = 12.0
    nonrigid: NonRigidConfig = GROW_NONRIGID


@dataclass
class GrowResult:
    """The grown space's ``body.npz`` arrays, one report entry per round (round 0: the space it started
    from) and the accepted registrations by scan name."""

    data: dict[str, np.ndarray]
    rounds: list[dict[str, Any]] = field(default_factory=list)
    accepted: dict[str, Registration] = field(default_factory=dict)

    def report(self) -> dict[str, Any]:
        """The JSON report: the rounds, the accepted scans and the totals."""
        return {
            "rounds": self.rounds,
            "n_rounds": len(self.rounds) - 1,
            "accepted": sorted(self.accepted),
            "n_accepted": len(self.accepted),
        }


def accept(chamfer: np.ndarray, ceiling: float) -> np.ndarray:
    """(N,) bool: the Chamfer distances (N,) within the minimum plus one standard deviation (BLiSS 3.4) and
    at most ``ceiling``."""
    c = np.asarray(chamfer, np.float64)
    if not len(c):
        return np.zeros(0, bool)
    return np.asarray((c <= c.min() + c.std()) & (c <= ceiling))


def _round_entry(
    index: int,
    candidates: Sequence[Registration],
    taken: np.ndarray,
    total: int,
    seconds: float,
    ceiling: float,
) -> dict[str, Any]:
    """A round's report entry: candidates, accepted (new, total, names), seconds and the Chamfer distances
    (mm) with the acceptance threshold (min + one deviation, at most ``ceiling``)."""
    chamfer = np.array([r.chamfer_mm for r in candidates])
    entry: dict[str, Any] = {
        "round": index,
        "candidates": len(candidates),
        "accepted": int(taken.sum()),
        "accepted_total": total,
        "accepted_scans": [r.name for r, t in zip(candidates, taken, strict=True) if t],
        "seconds": round(seconds, 1),
    }
    if len(chamfer):
        entry["chamfer_mm"] = {
            "min": round(float(chamfer.min()), 3),
            "mean": round(float(chamfer.mean()), 3),
            "max": round(float(chamfer.max()), 3),
            "threshold": round(float(min(chamfer.min() + chamfer.std(), ceiling)), 3),
        }
    return entry


def grow_space(
    model: BodyModel,
    scans: Sequence[PosedScan],
    config: GrowConfig | None = None,
    seeds: Population | None = None,
    evaluate: Evaluate | None = None,
    log: Callable[[str], None] = print,
) -> GrowResult:
    """Grow ``model``'s shape space from ``scans`` (each with its first fit in ``model``'s space) and the seed
    registrations ``seeds`` (bind pose; added to the population before the first round). ``evaluate``
    scores each round's space for the report. Returns the grown arrays and the per-round report."""
    cfg = config or GrowConfig()
    original = model
    population = sample_population(model, cfg.n_population, cfg.seed)
    if seeds is not None and len(seeds):
        population = population + seeds
        model = BodyModel(model.skeleton, recompute_space(model, population), "lbs")
    result = GrowResult(dict(model.data))
    result.rounds.append({"round": 0, "accepted": 0, "accepted_total": 0, **_score(evaluate, model.data)})
    log(_round_line(result.rounds[0]))
    # scan name -> its last bind-pose registration, where the next projection starts; before the first, the
    # template of the scan's own fit
    last = {s.name: rest_meshes(original.data, s.shape[None])[0] for s in scans}
    current = model
    meshes = [s for s in scans if in_topology(original, s)]
    if meshes:
        population = _unpose_round(original, meshes, population, result, evaluate)
        log(_round_line(result.rounds[-1]))
        current = BodyModel(model.skeleton, result.data, "lbs")
    first = len(result.rounds)
    for index in range(first, first + cfg.rounds):
        t0 = time.perf_counter()
        pending = [s for s in scans if s.name not in result.accepted]
        if not pending:
            break
        # every round projects: from the first fit's shape in the original space (a raw scan's first fit can
        # stop short of the best shape in it), from the last registration in a grown one
        candidates = [
            register(
                current,
                s,
                s.shape if current is original else initial_shape(current.data, last[s.name]),
                cfg.nonrigid,
            )
            for s in pending
        ]
        last.update({r.name: r.bind for r in candidates})
        taken = accept(np.array([r.chamfer_mm for r in candidates]), cfg.max_chamfer_mm)
        new = [r for r, t in zip(candidates, taken, strict=True) if t]
        result.accepted.update({r.name: r for r in new})
        seconds = time.perf_counter() - t0
        entry = _round_entry(index, candidates, taken, len(result.accepted), seconds, cfg.max_chamfer_mm)
        if new:
            population = population + Population(
                np.stack([r.bind for r in new]), np.stack([r.scales for r in new])
            )
            result.data = recompute_space(model, population)
            current = BodyModel(model.skeleton, result.data, "lbs")
        entry.update(_score(evaluate, result.data))
        result.rounds.append(entry)
        log(_round_line(entry))
        if not new:
            break
    return result


def _unpose_round(
    model: BodyModel,
    meshes: Sequence[PosedScan],
    population: Population,
    result: GrowResult,
    evaluate: Evaluate | None,
) -> Population:
    """Meshes in ``model``'s topology unposed as they are and accepted in a round of their own: their
    registrations (Chamfer 0 to themselves) join ``result.accepted``, the space is recomputed from the
    ``population`` with them (``result.data``) and the round's entry lists them under ``"unposed"``. Returns
    the grown population."""
    t0 = time.perf_counter()
    bind, scales = seed_registrations(model, list(meshes))
    for m, b, s in zip(meshes, bind, scales, strict=True):
        result.accepted[m.name] = Registration(m.name, b, s, m.points, 0.0)
    population = population + Population(bind, scales)
    result.data = recompute_space(model, population)
    entry: dict[str, Any] = {
        "round": len(result.rounds),
        "candidates": len(meshes),
        "accepted": len(meshes),
        "accepted_total": len(result.accepted),
        "accepted_scans": [m.name for m in meshes],
        "unposed": len(meshes),
        "seconds": round(time.perf_counter() - t0, 1),
    }
    entry.update(_score(evaluate, result.data))
    result.rounds.append(entry)
    return population


def _score(evaluate: Evaluate | None, data: dict[str, np.ndarray]) -> dict[str, float]:
    return {} if evaluate is None else dict(evaluate(data))


def _round_line(entry: dict[str, Any]) -> str:
    line = f"round {entry['round']}: {entry['accepted']} of {entry.get('candidates', 0)} accepted"
    if "unposed" in entry:
        line += " (meshes in the model's topology, unposed as they are)"
    line += f" ({entry['accepted_total']} in all)"
    if "chamfer_mm" in entry:
        line += f", Chamfer {entry['chamfer_mm']['min']:.2f}-{entry['chamfer_mm']['max']:.2f} mm"
    line += "".join(f", held-out {k} {entry[k]:.2f}" for k in ("v2v_mm", "fit_v2v_mm") if k in entry)
    return line
