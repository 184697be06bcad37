"""The scan fit's limb search: every limb's pose from a grid of candidates, its best few refined
continuously, scored by how its vertices lie on the scan and reach the scan points the rest of the body
leaves unexplained (:class:`LimbSearch`); and the optimisation state the scan fit's phases share
(:class:`Hypotheses`)."""

from __future__ import annotations

from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass, replace
from itertools import pairwise
from typing import Any

import numpy as np
import torch

from bodyfit.models.body.model import BodyDecoder
from bodyfit.models.fitting.common.lbfgs import batched_lbfgs
from bodyfit.models.fitting.common.nearest import PointTree
from bodyfit.models.fitting.registered.fitter import RegisteredFitter, State
from bodyfit.models.fitting.scan.view import Silhouette
from bodyfit.models.skeleton.model import Skeleton

Grids = list[tuple[list[int], np.ndarray]]  # per chain: the DOFs searched, their candidates (K_chain, n)


class AsIsOrRaised(tuple[str, ...]):
    """A grid key: DOFs that move in step between two values, each its hypothesis's own (NaN in the grid:
    the candidate keeps the coordinate as it is) and 10% in from the top of its range."""


# per chain: its bodies and its grid (per DOF name, or a tuple of DOF names moved in step: how many values)
SearchTable = Sequence[tuple[Sequence[str], Mapping[Any, int]]]
# how a function of a hypothesis's row is mapped over the rows: ``map``, or a thread pool's
Mapper = Callable[[Callable[[int], list[np.ndarray]], Iterable[int]], Iterable[list[np.ndarray]]]

# Limb chains searched on a grid before the continuous fit: the chain's bodies and the DOFs sampled (values
# per DOF, spread over the range; a tuple of DOFs moves in step, each the same share along its range). A
# limb's candidates are scored by how close its vertices lie to the scan. The arm's grid holds the shoulder
# girdle (the scapula's upward rotation with its elevation) where the hypothesis has it and raised
# (:class:`AsIsOrRaised`). The glenohumeral joint alone lifts the arm to about the horizontal, and an arm
# raised overhead or flexed forward and up takes the girdle's range on top (at arm_add -99 degrees the hand
# lies 0.37 m below the top of the head with the girdle low, 0.28 m above it with the girdle raised); a grid
# without it has no candidate near such an arm, and the search folds the arm onto the chest or the head.
LIMB_SEARCH = tuple(
    (bodies, grid)
    for s in ("r", "l")
    for bodies, grid in (
        (
            (f"femur_{s}", f"tibia_{s}", f"patella_{s}", f"talus_{s}", f"calcn_{s}", f"toes_{s}"),
            {f"hip_flexion_{s}": 7, f"hip_adduction_{s}": 4, f"knee_angle_{s}": 4},
        ),
        (
            (f"humerus_{s}", f"ulna_{s}", f"radius_{s}", f"hand_{s}"),
            {
                f"arm_flex_{s}": 7,
                f"arm_add_{s}": 7,
                f"elbow_flex_{s}": 4,
                AsIsOrRaised((f"scapula_upward_rot_{s}", f"scapula_elevation_{s}")): 2,
            },
        ),
    )
)
LIMB_TRUNCATION_M = 0.05
LIMB_SWEEPS = 2  # turns of every limb in the search
REACH_WEIGHT = 3.0  # of the unexplained points a limb must reach, against lying on the scan
ON_SCAN_FRACTION = 0.7  # of a limb's vertices, the closest to the scan, that count for lying on it
LOOSE_POINTS = 200  # scan points, at most, that a limb candidate is asked to reach
EMPTY_WEIGHT = 1.0  # of a single view's empty space (outside its silhouette) entered by a limb candidate
# Each limb's coordinates refined continuously from its best grid candidates (the grid's DOFs and those it
# leaves at their current values: the shoulder girdle, the arm's and hip's rotation, the forearm's twist).
LIMB_REFINED = tuple(
    names
    for s in ("r", "l")
    for names in (
        (f"hip_flexion_{s}", f"hip_adduction_{s}", f"hip_rotation_{s}", f"knee_angle_{s}"),
        (
            *(f"scapula_{n}_{s}" for n in ("abduction", "elevation", "upward_rot")),
            *(f"{n}_{s}" for n in ("arm_flex", "arm_add", "arm_rot", "elbow_flex", "pro_sup")),
        ),
    )
)
LIMB_STARTS = 4  # of each limb's grid candidates (best first), those refined
LIMB_REFINE_ITERATIONS = 10
LIMB_APART_M = 0.1  # the refined starts of a limb lie this far apart (mean vertex distance), where they can


def distinct(shapes: np.ndarray, cost: np.ndarray, n: int, apart: float) -> np.ndarray:
    """Indices (n,) of the lowest-cost ``shapes`` (K, V, 3) that lie at least ``apart`` from each other (mean
    vertex distance), best first; topped up with the next best when fewer are that far apart."""
    order = np.argsort(cost)
    chosen = [order[0]]
    for k in order[1:]:
        if len(chosen) == n:
            break
        if np.linalg.norm(shapes[chosen] - shapes[k], axis=-1).mean(-1).min() >= apart:
            chosen.append(k)
    rest = [k for k in order if k not in chosen]
    return np.array(chosen + rest[: n - len(chosen)])


@dataclass
class Hypotheses:
    """Candidate body frames and their optimisation state: rotation (H, 3, 3), the scan's centre (3,), the fit
    points in each body frame (H, N, 3) metres, state (see :meth:`RegisteredFitter.start_state`); searched:
    the candidates came from the scan's axes (no orientation given); view: (3,) towards the sensor, in the
    scan's frame, for a single-view scan (:func:`view_direction`), else None; visible: (H, V_stage) the
    current phase's vertices that face the sensor, or None (all count); silhouette: a single view's
    :class:`Silhouette` (scan frame), else None."""

    rotation: np.ndarray
    centre: np.ndarray
    points: np.ndarray
    state: State
    searched: bool
    view: np.ndarray | None = None
    visible: np.ndarray | None = None
    silhouette: Silhouette | None = None

    def keep(self, rows: np.ndarray) -> None:
        self.rotation, self.points = self.rotation[rows], self.points[rows]
        if self.visible is not None:
            self.visible = self.visible[rows]
        r = torch.as_tensor(rows)
        self.state = (self.state[0][r], self.state[1][r], self.state[2][r])

    def copy(self) -> Hypotheses:
        """An independent copy: its arrays and optimisation state are its own."""
        z_u, z_r, z_c = self.state
        visible = None if self.visible is None else self.visible.copy()
        return replace(
            self, rotation=self.rotation.copy(), points=self.points.copy(), visible=visible,
            state=(z_u.clone(), z_r.clone(), z_c.clone()),
        )  # fmt: skip

    def take(self, rows: np.ndarray) -> Hypotheses:
        """An independent copy of the hypotheses ``rows`` (K,)."""
        part = self.copy()
        part.keep(rows)
        return part

    def join(self, parts: list[Hypotheses]) -> None:
        """Become ``parts`` (from :meth:`take`) one after the other: their frames, points, visible vertices
        and optimisation states."""
        self.rotation = np.concatenate([p.rotation for p in parts])
        self.points = np.concatenate([p.points for p in parts])
        visible = [p.visible for p in parts if p.visible is not None]
        self.visible = np.concatenate(visible) if visible else None
        z_u, z_r, z_c = (torch.cat(z) for z in zip(*(p.state for p in parts), strict=True))
        self.state = (z_u, z_r, z_c)

    def add_twins(self, rows: np.ndarray, state: State) -> None:
        """Append a twin of each hypothesis ``rows`` (K,): same frame and points, optimisation state from
        ``state`` (K rows)."""
        H = len(self.rotation)
        self.keep(np.concatenate([np.arange(H), rows]))
        for mine, twins in zip(self.state, state, strict=True):
            mine[H:] = twins


def search_grids(skeleton: Skeleton, table: SearchTable) -> Grids:
    """Per chain of ``table`` (:data:`LIMB_SEARCH`, or the scan fit's ``DISTAL_SEARCH``): the DOFs searched
    and their candidate values (K_chain, n), spread over each range (10% in from the limits); the DOFs of a
    tuple key move in step (one axis of the grid, each DOF the same share along its range); an
    :class:`AsIsOrRaised` key's axis holds NaN (as it is) and the top of each range."""
    lo, hi = skeleton.ranges[:, 0], skeleton.ranges[:, 1]
    pad = 0.1 * (hi - lo)
    grids = []
    for _, grid in table:
        dofs, axes = [], []
        for key, n in grid.items():
            step = [skeleton.dof_index(name) for name in ((key,) if isinstance(key, str) else key)]
            dofs += step
            if isinstance(key, AsIsOrRaised):
                axes.append(np.stack([[np.nan] * len(step), hi[step] - pad[step]]))
                continue
            axes.append(np.stack([np.linspace(lo[d] + pad[d], hi[d] - pad[d], n) for d in step], 1))
        # every combination of the axes' values: (K_chain, n) with each axis's DOFs side by side
        mesh = np.meshgrid(*(np.arange(len(a)) for a in axes), indexing="ij")
        index = np.stack(mesh, -1).reshape(-1, len(axes))
        grids.append((dofs, np.concatenate([a[index[:, k]] for k, a in enumerate(axes)], axis=1)))
    return grids


def as_is(values: np.ndarray, current: np.ndarray) -> np.ndarray:
    """Grid ``values`` (any shape) with each NaN (a coordinate kept as it is, :class:`AsIsOrRaised`) replaced
    by the ``current`` coordinate (broadcast to it)."""
    return np.where(np.isnan(values), current, values)


def grid_vertices(
    decoder: BodyDecoder, grids: Grids, c: np.ndarray, q: np.ndarray, root: np.ndarray, dtype: torch.dtype
) -> np.ndarray:
    """(K + 1, V', 3) ``decoder``'s vertices for one hypothesis (shape c, coordinates q, root; decoded in
    ``dtype``): row k < K sets every chain of ``grids`` to its candidate k (cycling through shorter grids),
    with K the longest grid; the last row is the current pose."""
    K = max(len(g) for _, g in grids)
    Q = np.repeat(q[None], K + 1, axis=0)
    for dofs, values in grids:
        Q[:K, dofs] = as_is(values[np.arange(K) % len(values)], Q[:K, dofs])
    rows = (np.repeat(c[None], K + 1, 0), Q, np.repeat(root[None], K + 1, 0))
    with torch.no_grad():
        return decoder(*(torch.as_tensor(x, dtype=dtype) for x in rows))[0].double().numpy()


class LimbSearch:
    """The limbs' search for :class:`ScanFitter`'s phases (call it on a :class:`Hypotheses`): the chains of
    :data:`LIMB_SEARCH` on the fitter's "subset" vertices."""

    def __init__(self, fitter: RegisteredFitter) -> None:
        self.fitter = fitter
        model = fitter.model
        names = model.skeleton.body_names
        owner = model.vertex_bodies[fitter.index["subset"]]  # each subset vertex's body
        self.vertices = [
            np.flatnonzero(np.isin(owner, [names.index(b) for b in bodies])) for bodies, _ in LIMB_SEARCH
        ]
        self.non_limb = np.setdiff1d(np.arange(len(owner)), np.concatenate(self.vertices))
        self.free = [np.array([model.skeleton.dof_index(n) for n in dofs]) for dofs in LIMB_REFINED]
        # the limbs' "subset" vertices alone, each limb's columns in its output
        self.decoder = fitter.decoder.restricted(fitter.index["subset"][np.concatenate(self.vertices)])
        ends = np.cumsum([0] + [len(v) for v in self.vertices])
        self.columns = [slice(a, b) for a, b in pairwise(ends)]
        self.grids = search_grids(model.skeleton, LIMB_SEARCH)

    def __call__(self, hyp: Hypotheses, over: Mapper = map) -> None:
        """Set every limb's searched DOFs (:func:`search_grids`) of every hypothesis to the candidate whose
        limb lies on the scan (its "subset" vertices close to scan points) and reaches the scan points that
        neither the rest of the body nor the other limbs explain (an arm folded onto the chest lies on the
        scan too, but reaches nothing). Limbs take turns, :data:`LIMB_SWEEPS` times, each against the
        others' latest choice, so an arm crossing the body is not left to the other arm. The cost is
        :meth:`on_scan` plus :meth:`reach`. Each limb's best :data:`LIMB_STARTS` candidates are then
        refined continuously (:meth:`refine`): the grid is coarse and holds the shoulder girdle and
        the limbs' rotation where they are, so its best candidate can lie far from a pose that fits the
        limb closely. ``over`` maps the hypotheses' grid searches, which are independent (a thread pool's
        ``map`` runs them at once)."""
        c, q, root = (t.numpy() for t in self.fitter.parameters(hyp.state))
        scans = [PointTree(p) for p in hyp.points]
        starts = np.repeat(q[:, None], LIMB_STARTS, axis=1)  # (H, M, n_dof): each limb's best candidates
        # per hypothesis and limb: the loose points it must reach
        targets = list(over(lambda h: self._grid(hyp, h, scans[h], c, q, root, starts), range(len(q))))
        q = self.refine(hyp, scans, c, starts, root, targets)
        hyp.state = self.fitter.start_state(q, root, c)

    def _grid(
        self,
        hyp: Hypotheses,
        h: int,
        scan: PointTree,
        c: np.ndarray,
        q: np.ndarray,
        root: np.ndarray,
        starts: np.ndarray,
    ) -> list[np.ndarray]:
        """The grid search of hypothesis h (its fit points ``scan``; shapes c, coordinates q, roots (H, ...)):
        sets its row of q to every limb's best candidate and its row of ``starts`` (H, M, n_dof) to every
        limb's best distinct candidates; returns, per limb, the loose points (T, 3) it must reach."""
        decoder = self.fitter.decoders["subset"]
        grids = self.grids
        K = max(len(g) for _, g in grids)
        far, trunc2 = LIMB_TRUNCATION_M, LIMB_TRUNCATION_M**2  # distances beyond are all alike
        own = q[h].copy()  # the coordinates the grid's candidates keep as they are (AsIsOrRaised)
        v = grid_vertices(decoder, grids, c[h], own, root[h], self.fitter.config.dtype)
        # Scan points the rest of the body does not explain: limbs must reach them, not just touch the
        # scan (an arm folded onto the chest touches it everywhere).
        rest = PointTree(v[0, self.non_limb]).query(hyp.points[h], LIMB_TRUNCATION_M)[0]
        loose = hyp.points[h][rest > LIMB_TRUNCATION_M]
        loose = loose[:: max(1, len(loose) // LOOSE_POINTS)]
        on_scan, reach = [], []
        for (_, values), limb in zip(grids, self.vertices, strict=True):
            on_scan.append(self.on_scan(hyp, h, scan, v[: len(values), limb]))
            reach.append(self.distances(v[: len(values), limb], loose))
        placed = [v[K, limb] for limb in self.vertices]  # the current pose's row
        mine = [np.zeros(len(loose), bool) for _ in grids]
        cost = list(on_scan)
        for _ in range(LIMB_SWEEPS):
            for L, ((dofs, values), limb) in enumerate(zip(grids, self.vertices, strict=True)):
                cost[L] = on_scan[L].copy()
                if len(loose):
                    others = np.concatenate([placed[M] for M in range(len(grids)) if M != L])
                    mine[L] = PointTree(others).query(loose, far)[0] > far
                    if mine[L].any():
                        cost[L] += REACH_WEIGHT * np.minimum(reach[L][:, mine[L]] ** 2, trunc2).mean(1)
                best = int(np.argmin(cost[L]))
                placed[L] = v[best, limb]
                q[h, dofs] = as_is(values[best], own[dofs])
        for L, ((dofs, values), limb) in enumerate(zip(grids, self.vertices, strict=True)):
            tops = distinct(v[: len(values), limb], cost[L], LIMB_STARTS, LIMB_APART_M)
            starts[h][:, dofs] = as_is(values[tops], own[dofs])
        return [loose[m] for m in mine]

    def on_scan(self, hyp: Hypotheses, h: int, scan: PointTree, verts: np.ndarray) -> np.ndarray:
        """(n,) how far limb candidates (n, V_limb, 3) of hypothesis h (body frame) lie from its scan points
        ``scan``: the mean truncated squared distance of the :data:`ON_SCAN_FRACTION` of vertices closest to
        the scan (a limb partly over a hole or on a single view's unseen side still lies on the scan). On a
        single view it also counts, by :data:`EMPTY_WEIGHT`, how far the vertices lie outside the view's
        :class:`Silhouette`, in space the sensor saw empty: otherwise an arm the view shows in front of the
        body may be searched into the air beside it, where nothing contradicts it."""
        n = len(verts)
        d = scan.query(verts.reshape(-1, 3), LIMB_TRUNCATION_M)[0].reshape(n, -1)
        d = np.sort(np.minimum(d, LIMB_TRUNCATION_M) ** 2, axis=1)
        cost = d[:, : max(1, round(ON_SCAN_FRACTION * d.shape[1]))].mean(1)
        if hyp.silhouette is not None:
            out = hyp.silhouette.distance(verts @ hyp.rotation[h] + hyp.centre)
            cost += EMPTY_WEIGHT * (np.minimum(out, LIMB_TRUNCATION_M) ** 2).mean(1)
        return cost

    @staticmethod
    def reach(verts: np.ndarray, targets: np.ndarray) -> np.ndarray:
        """(n,) how far the scan points ``targets`` (T, 3) that a limb must reach lie from each candidate's
        vertices (n, V_limb, 3): :data:`REACH_WEIGHT` times their mean truncated squared distance."""
        if not len(targets):
            return np.zeros(len(verts))
        d = LimbSearch.distances(verts, targets)
        return REACH_WEIGHT * (np.minimum(d, LIMB_TRUNCATION_M) ** 2).mean(1)

    @staticmethod
    def distances(verts: np.ndarray, targets: np.ndarray) -> np.ndarray:
        """(n, T) each candidate's (n, V_limb, 3) distance to each point ``targets`` (T, 3): to its nearest
        vertex, inf beyond :data:`LIMB_TRUNCATION_M`."""
        return np.stack([PointTree(x).query(targets, LIMB_TRUNCATION_M)[0] for x in verts])

    def refine(
        self,
        hyp: Hypotheses,
        scans: list[PointTree],
        c: np.ndarray,
        starts: np.ndarray,
        root: np.ndarray,
        targets: list[list[np.ndarray]],
    ) -> np.ndarray:
        """Coordinates (H, n_dof): each limb's :data:`LIMB_REFINED` DOFs from the best of its start poses
        ``starts`` (H, M, n_dof), each refined by :data:`LIMB_REFINE_ITERATIONS` of L-BFGS on a smooth form
        of the search's cost (vertices pulled onto their nearest scan points, loose points ``targets``
        (per hypothesis and limb, (T, 3)) pulled onto their nearest limb vertex; the limbs' DOFs are
        disjoint, so all limbs refine together). Every limb keeps whichever start or refined pose has the
        lowest search cost (:meth:`on_scan` + :meth:`reach`). c (H, n_shape), root (H, 3): the
        hypotheses' shape and root; ``scans``: each hypothesis's fit points (body frame) as a tree.

        L-BFGS: :func:`~bodyfit.models.fitting.common.lbfgs.batched_lbfgs` (D. C. Liu and J. Nocedal, "On the
        limited memory BFGS method for large scale optimization", Mathematical Programming 45, 1989)."""
        H, M, n_dof = starts.shape
        dtype = self.fitter.config.dtype
        rows = np.arange(H * M) // M  # each row's hypothesis
        z_u = self.fitter.start_state(starts.reshape(-1, n_dof), root[rows], c[rows])[0]
        c_t, root_t = (torch.as_tensor(x[rows], dtype=dtype) for x in (c, root))
        free = torch.as_tensor(np.concatenate(self.free))
        cols = self.columns
        trunc2 = (LIMB_TRUNCATION_M * 1000.0) ** 2
        # loose points per limb, padded to a common count: (H * M, T_L, 3) mm and their weights (H * M, T_L)
        pads = []
        for L in range(len(cols)):
            T = max(1, max(len(t[L]) for t in targets))
            pad = np.zeros((H, T, 3))
            weight = np.zeros((H, T))
            for h, t in enumerate(targets):
                pad[h, : len(t[L])] = t[L] * 1000.0
                weight[h, : len(t[L])] = REACH_WEIGHT / max(1, len(t[L]))
            pads.append((pad[rows], torch.as_tensor(weight[rows], dtype=dtype)))

        def vertices(u: torch.Tensor) -> torch.Tensor:
            return self.decoder(c_t, self.fitter.coordinates(u), root_t)[0] * 1000.0

        def losses(Z: torch.Tensor) -> torch.Tensor:
            v = vertices(z_u.index_copy(1, free, Z))  # (H * M, V_limbs, 3) mm
            v_np = v.detach().double().numpy()
            pairs = zip(rows, v_np, strict=True)
            near = np.stack([hyp.points[h][scans[h].query(x / 1000.0)[1]] for h, x in pairs])
            d2 = ((v - torch.as_tensor(near * 1000.0, dtype=dtype)) ** 2).sum(-1).clamp(max=trunc2)
            total = torch.zeros(len(rows), dtype=dtype)
            for col, (pad, weight) in zip(cols, pads, strict=True):
                k = max(1, round(ON_SCAN_FRACTION * (col.stop - col.start)))
                total = total + torch.topk(d2[:, col], k, dim=1, largest=False).values.mean(1)
                # each loose point's nearest vertex of the limb
                j = np.stack([PointTree(x[col]).query(p)[1] for x, p in zip(v_np, pad, strict=True)])
                limb = v[:, col]
                reached = torch.gather(limb, 1, torch.as_tensor(j)[..., None].expand(-1, -1, 3))
                r2 = ((reached - torch.as_tensor(pad, dtype=dtype)) ** 2).sum(-1).clamp(max=trunc2)
                total = total + (r2 * weight).sum(1)
            return total

        result = batched_lbfgs(losses, z_u[:, free], LIMB_REFINE_ITERATIONS)
        with torch.no_grad():
            refined = z_u.index_copy(1, free, result.z)
            both = torch.cat([z_u, refined])  # the starts, then the refined poses
            q_all = self.fitter.coordinates(both.double()).numpy()
            v_all = torch.cat([vertices(z_u), vertices(refined)]).double().numpy() / 1000.0
        q = starts[:, 0].copy()
        for h in range(H):
            mine = np.concatenate([np.flatnonzero(rows == h), len(rows) + np.flatnonzero(rows == h)])
            for L, (col, dofs) in enumerate(zip(cols, self.free, strict=True)):
                limb = v_all[mine][:, col]
                cost = self.on_scan(hyp, h, scans[h], limb) + self.reach(limb, targets[h][L])
                q[h, dofs] = q_all[mine[int(np.argmin(cost))], dofs]
        return q
