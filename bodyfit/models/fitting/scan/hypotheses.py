"""The scan fit's hypotheses between their L-BFGS runs (:class:`HypothesisSteps`): where they start, the
twins a phase adds (a straight spine, the scapulae at mid-range), the head's, hands' and toes' grid search,
which vertices face a single view's sensor and which hypotheses go on after a phase."""

from __future__ import annotations

from itertools import pairwise

import numpy as np
import torch

from bodyfit.models.body.model import BodyModel
from bodyfit.models.fitting.common.nearest import PointTree
from bodyfit.models.fitting.common.surface import NormalOperators, vertex_normals
from bodyfit.models.fitting.registered.fitter import RegisteredFitter, State
from bodyfit.models.fitting.scan.config import ScanPhase
from bodyfit.models.fitting.scan.limb_search import Hypotheses, grid_vertices, search_grids
from bodyfit.models.fitting.scan.view import Silhouette, view_direction
from bodyfit.models.rotations import zxy_angles
from bodyfit.models.skeleton.model import PELVIS_ROTATIONS

VISIBLE_COS = -0.1  # a vertex faces a single view's sensor when its normal is this close to towards it

# The small, vertex-dense ends of the body, searched the same way once the limbs are placed: their bodies and
# DOFs. Their surfaces are small but carry most of the template's vertices (head 32%, hands 24%, toes 11%).
DISTAL_SEARCH = (
    (("head", "cervical_link"), {"neck_extension": 5, "neck_bending": 3, "neck_rotation": 7}),
    *(
        (bodies, grid)
        for s in ("r", "l")
        for bodies, grid in (
            ((f"hand_{s}",), {f"pro_sup_{s}": 5, f"wrist_flex_{s}": 5, f"wrist_dev_{s}": 3}),
            ((f"toes_{s}",), {f"mtp_angle_{s}": 7}),
        )
    ),
)
DISTAL_VERTICES = 400  # of each distal chain's vertices, at most, that score its candidates
DISTAL_TRUNCATION_M = 0.02
EXPLAINED_M = 0.02  # a scan point this close to the rest of the body is not a distal chain's to explain
UNSUPPORTED = 0.8  # a distal chain whose best candidate's cost is this share of the truncation's has no data
STRAIGHTENED = 1  # of the hypotheses (best first), those that get a straight-spine twin
# The arms' start poses a whole body's every orientation candidate is fitted from (coordinates in degrees over
# the start pose, both sides): as given, raised overhead and held forward at shoulder height (the shoulder
# girdle raised with them). The orientation phase fits the trunk and legs only: from arms hanging down, a
# scan with the arms raised bends the spine 20-25 degrees sideways to bring a shoulder under them, and one
# with the arms held forward twists it 25-35 degrees to bring an arm raised sideways under one of them; the
# limbs searched from such a trunk no longer reach the arms (the true arm pose, on that trunk, lies farther
# from the scan than an arm folded onto the body). The orientation phase keeps the better start of each
# orientation (:attr:`.config.ScanPhase.one_per_frame`).
ARM_STARTS: tuple[dict[str, float], ...] = (
    {},
    {
        "arm_flex": 0.0,
        "arm_add": -110.0,
        "elbow_flex": 10.0,
        "scapula_upward_rot": 50.0,
        "scapula_elevation": 20.0,
    },
    {
        "arm_flex": 90.0,
        "arm_add": 0.0,
        "elbow_flex": 10.0,
        "scapula_upward_rot": 30.0,
        "scapula_elevation": 10.0,
    },
)
# The orientation phase keeps 3 hypotheses and the best gets a twin: the pose phase runs 4, in halves of 2.
# The final fit rarely comes from the orientation phase's third best and not from a fourth, and more
# hypotheses (or twins) make the pose phase longer without making the fits better.


def orientation_candidates(points: np.ndarray, up: np.ndarray | None = None) -> np.ndarray:
    """(24, 3, 3) rotations from scan axes to body axes (+X forward, +Y up, +Z right): every signed
    principal axis as up, and four headings (the other principal axes, both signs) about it. The principal
    axes are those of principal component analysis (H. Hotelling, "Analysis of a complex of statistical
    variables into principal components", Journal of Educational Psychology 24(6), 1933), from the SVD.

    With the scan's ``up`` (3,) known, (8, 3, 3): that up axis only, and eight headings about it, the
    principal axes of the points projected on the horizontal plane and their diagonals, both signs (a
    body's heading lies near one of them, and the fit's phases turn it the rest of the way)."""
    if up is not None:
        return _headings_about(points, np.asarray(up, np.float64) / np.linalg.norm(up))
    _, _, axes = np.linalg.svd(points - points.mean(0), full_matrices=False)
    out = []
    for i in range(3):
        others = [axes[k] for k in range(3) if k != i]
        for up in (axes[i], -axes[i]):
            for forward in (others[0], -others[0], others[1], -others[1]):
                out.append(np.stack([forward, up, np.cross(forward, up)]))
    return np.array(out)


def _headings_about(points: np.ndarray, up: np.ndarray) -> np.ndarray:
    """(8, 3, 3) body frames with the unit ``up`` (3,) and eight horizontal headings
    (:func:`orientation_candidates`)."""
    flat = points - points.mean(0)
    flat = flat - np.outer(flat @ up, up)
    _, _, axes = np.linalg.svd(flat, full_matrices=False)
    a = axes[0] - (axes[0] @ up) * up
    a /= np.linalg.norm(a)
    b = np.cross(up, a)
    headings = [a, (a + b) / np.sqrt(2.0), b, (b - a) / np.sqrt(2.0)]
    return np.array([np.stack([s * f, up, np.cross(s * f, up)]) for f in headings for s in (1.0, -1.0)])


def detect_view(hyp: Hypotheses, cleaned: np.ndarray) -> None:
    """Set the hypotheses' single view (the direction (3,) towards the sensor, or None for a full scan) and
    its silhouette, as the cleaned points (M, 3) show them."""
    hyp.view = view_direction(cleaned)
    if hyp.view is not None:
        hyp.silhouette = Silhouette.of(cleaned, hyp.view)


class HypothesisSteps:
    """The steps of :class:`~bodyfit.models.fitting.scan.fitter.ScanFitter`'s phases that change its
    hypotheses other than by L-BFGS, for ``model`` and its registered ``fitter``; ``normals``: the normal
    operators of the model's faces in the fit loop's float type."""

    def __init__(self, model: BodyModel, fitter: RegisteredFitter, normals: NormalOperators) -> None:
        self.model, self.fitter, self.normals = model, fitter, normals
        self.faces = np.asarray(model.data["faces"], np.int64)
        self.pelvis = [model.skeleton.dof_index(n) for n in PELVIS_ROTATIONS]
        owner = model.vertex_bodies
        names = model.skeleton.body_names
        distal = []
        self.distal_parts = []  # each distal chain's vertices, then those of no chain
        for bodies, _ in DISTAL_SEARCH:
            own = np.flatnonzero(np.isin(owner, [names.index(b) for b in bodies]))
            distal.append(own[:: max(1, len(own) // DISTAL_VERTICES)])
            self.distal_parts.append(own)
        chained = np.concatenate(self.distal_parts)
        self.distal_parts.append(np.setdiff1d(np.arange(model.n_vertices), chained))
        self.neutral = model.skeleton.inside(model.bind_coordinates, 0.1)
        self.distal_decoder = fitter.decoder.restricted(np.concatenate(distal))
        # each distal chain's columns in the distal decoder's output
        bounds = np.cumsum([0] + [len(v) for v in distal])
        self.distal_columns = [slice(a, b) for a, b in pairwise(bounds)]
        self.spine = np.setdiff1d(np.flatnonzero(fitter.dof_mask["trunk"].numpy()), self.pelvis)
        self.thorax = names.index("thorax")
        self.scapula = [i for i, n in enumerate(model.skeleton.dof_names) if n.startswith("scapula_")]
        self.distal_grid = search_grids(model.skeleton, DISTAL_SEARCH)

    def prepare(self, hyp: Hypotheses, phase: ScanPhase, points: np.ndarray) -> None:
        """Give the hypotheses the phase's fit points (``points`` (N, 3) of the scan, into each body frame)
        and the twins it adds (a straight spine on a full scan, the scapulae at mid-range)."""
        hyp.points = np.einsum("hij,nj->hni", hyp.rotation, points - hyp.centre)
        if phase.straighten and hyp.view is None:
            self.straighten_spine(hyp)
        if phase.scapula_twin:
            self.scapula_twin(hyp)

    def candidates(
        self,
        points: np.ndarray,
        orientation: np.ndarray | None,
        start: np.ndarray | None,
        part: str = "all",
        up: np.ndarray | None = None,
    ) -> Hypotheses:
        """The start hypotheses: each orientation (given, or :func:`orientation_candidates`, about ``up``
        when that alone is known) with the start pose, a whole body's (``part`` "all") also with each other
        arm start of :data:`ARM_STARTS` (orientation-major: the candidates of one frame are adjacent), and
        the surface of the vertex set ``part`` ("all" or "upper") centred on the points' centroid."""
        given = None if orientation is None else np.asarray(orientation)[None]
        rotation = orientation_candidates(points, up) if given is None else given
        model = self.model
        q_start = model.skeleton.inside(model.bind_coordinates if start is None else np.asarray(start), 0.1)
        poses = self.arm_starts(q_start) if part == "all" else q_start[None]
        rotation = np.repeat(rotation, len(poses), axis=0)
        H = len(rotation)
        q0 = np.tile(poses, (H // len(poses), 1))
        inside = np.zeros(model.n_vertices, bool)
        inside[self.fitter.index[part]] = True
        tri = model.data["vertices_mean"][self.faces[inside[self.faces].all(1)]]
        area = np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
        centre_offset = (tri.mean(1) * area[:, None]).sum(0) / area.sum()  # the surface's centroid
        r0 = np.repeat(-centre_offset[None], H, axis=0)
        state = self.fitter.start_state(q0, r0, self.fitter.start_shape(H))
        return Hypotheses(rotation, points.mean(0), np.zeros((H, 0, 3)), state, orientation is None)

    def arm_starts(self, q: np.ndarray) -> np.ndarray:
        """(len(ARM_STARTS), n_dof) the coordinates q (n_dof,) with each arm start of :data:`ARM_STARTS`
        (moved inside the ranges)."""
        skeleton = self.model.skeleton
        out = np.repeat(q[None], len(ARM_STARTS), axis=0)
        for row, arms in zip(out, ARM_STARTS, strict=True):
            for name, degrees in arms.items():
                for side in ("r", "l"):
                    row[skeleton.dof_index(f"{name}_{side}")] = np.radians(degrees)
        return skeleton.inside(out, 0.01)

    def vertices(self, state: State) -> np.ndarray:
        """(H, V, 3) model vertices (body frames, metres) of the current state."""
        c, q, root = self.fitter.parameters(state)
        dtype = self.fitter.config.dtype
        with torch.no_grad():
            v = self.fitter.decoder(c.to(dtype), q.to(dtype), root.to(dtype))[0]
        return v.double().numpy()

    def frames(self, c: np.ndarray, q: np.ndarray, root: np.ndarray) -> np.ndarray:
        """(H, n_body, 4, 4) every body's frame for shapes c, coordinates q and roots (H, 3)."""
        dtype = self.fitter.config.dtype
        rows = (torch.as_tensor(x, dtype=dtype) for x in (c, q, root))
        with torch.no_grad():
            return self.fitter.decoders["coarse"](*rows)[2].double().numpy()

    def visible(
        self, hyp: Hypotheses, index: np.ndarray, verts: np.ndarray | None = None
    ) -> np.ndarray | None:
        """(H, len(index)) which of the vertices ``index`` face a single-view scan's sensor in each
        hypothesis's current state (normal towards it, with a little slack at the silhouette); None for a
        full scan. ``verts``: the state's (H, V, 3) vertices (:meth:`vertices`) when the caller has them."""
        if hyp.view is None:
            return None
        verts = self.vertices(hyp.state) if verts is None else verts
        towards = hyp.rotation @ hyp.view  # (H, 3) in each body frame
        normals = vertex_normals(verts, self.faces, self.normals)[:, index]
        return np.einsum("hvi,hi->hv", normals, towards) > VISIBLE_COS

    def kept(self, hyp: Hypotheses, phase: ScanPhase, score: np.ndarray) -> np.ndarray:
        """Rows of the hypotheses that go on after ``phase``: the best ``phase.keep`` by ``score`` (H,)
        (with ``phase.one_per_frame``, of the best of each body frame), and the best one facing the other way
        from the best (see :class:`ScanPhase`'s ``flipped_margin``) when it scores within the margin and none
        of those faces that way."""
        order = np.argsort(score)
        if phase.one_per_frame:
            # the first (best) row of each frame, in the order of the scores
            _, first = np.unique(hyp.rotation[order].reshape(len(order), -1), axis=0, return_index=True)
            order = order[np.sort(first)]
        rows = order[: phase.keep]
        if phase.flipped_margin <= 0.0:
            return rows
        c, q, root = (t.numpy() for t in self.fitter.parameters(hyp.state))
        pelvis_forward = self.frames(c, q, root)[:, 0, :3, 0]  # (H, 3) body frames
        forward = np.einsum("hji,hj->hi", hyp.rotation, pelvis_forward)  # in the scan's frame
        facing = forward @ forward[order[0]]
        near = score <= (1.0 + phase.flipped_margin) * score[order[0]]
        if (facing[rows] < 0.0).any():
            return rows
        flipped = [h for h in order[phase.keep :] if facing[h] < 0.0 and near[h]]
        return np.array([*rows, *flipped[:1]])

    def straighten_spine(self, hyp: Hypotheses) -> None:
        """Add, for each of the best :data:`STRAIGHTENED` hypotheses, a twin with its trunk's bend moved into
        the pelvis: the lumbar and thoracic coordinates go to zero and the pelvis turns (and the root moves)
        so that the thorax keeps its place. The orientation phase fits the trunk and the legs' flexion
        coarsely; on a seated or crouching body it still tends to tilt the pelvis back and bend the spine
        to keep the chest upright (30-50 degrees when the legs are held straight), a minimum the later phases
        do not leave. The chest's fit is the reliable part of it."""
        c, q, root = (t.numpy()[:STRAIGHTENED] for t in self.fitter.parameters(hyp.state))
        thorax = self.thorax
        frames = self.frames(c, q, root)
        straight = q.copy()
        straight[:, self.spine] = 0.0
        bent = self.frames(c, straight, root)
        # pelvis -> thorax rotation with a straight spine; the new pelvis carries the thorax where it was
        relative = np.swapaxes(bent[:, 0, :3, :3], 1, 2) @ bent[:, thorax, :3, :3]
        straight[:, self.pelvis] = zxy_angles(frames[:, thorax, :3, :3] @ np.swapaxes(relative, 1, 2))
        moved = self.frames(c, straight, root)
        root_straight = root + frames[:, thorax, :3, 3] - moved[:, thorax, :3, 3]
        hyp.add_twins(np.arange(len(q)), self.fitter.start_state(straight, root_straight, c))

    def scapula_twin(self, hyp: Hypotheses) -> None:
        """Add, for every hypothesis, a twin with the scapulae at the middle of their ranges (the limb search
        that follows places the arms from them). Fits started from the bind pose bring the shoulders onto
        the scan by elevating the scapulae to their limit and rotating them down, with the arms flexed
        30-45 degrees more to match: a minimum that scores within a fraction of a percent of the right one,
        which the twin starts outside of."""
        c, q, root = (t.numpy() for t in self.fitter.parameters(hyp.state))
        twin = q.copy()
        twin[:, self.scapula] = self.model.skeleton.ranges[self.scapula].mean(1)
        hyp.add_twins(np.arange(len(q)), self.fitter.start_state(twin, root, c))

    def search_distal(self, hyp: Hypotheses) -> None:
        """Set the head's, hands' and toes' searched DOFs (:data:`DISTAL_SEARCH`) of every hypothesis to the
        candidate (or the current pose, if better) whose vertices lie closest to the scan points the rest of
        the body does not explain (further than :data:`EXPLAINED_M` from its vertices; mean squared distance
        truncated at :data:`DISTAL_TRUNCATION_M`). A chain that no candidate brings near such points (a hand
        or head the scan lost to a hole) goes to the bind pose's values: searched against all points, it
        would fold onto whatever surface lies near (a wrist flexed onto the thigh). The chains are independent
        of each other."""
        c, q, root = (t.numpy() for t in self.fitter.parameters(hyp.state))
        grids = self.distal_grid
        K = max(len(g) for _, g in grids)
        whole = self.vertices(hyp.state)
        for h in range(len(q)):
            v = grid_vertices(self.distal_decoder, grids, c[h], q[h], root[h], self.fitter.config.dtype)
            points = hyp.points[h]
            # each point's distance to each part (the chains, the rest), inf beyond EXPLAINED_M
            parts = self.distal_parts
            near = np.stack([PointTree(whole[h, p]).query(points, EXPLAINED_M)[0] for p in parts])
            for chain, ((dofs, values), cols) in enumerate(zip(grids, self.distal_columns, strict=True)):
                loose = points[np.delete(near, chain, axis=0).min(0) > EXPLAINED_M]
                if not len(loose):
                    q[h, dofs] = self.neutral[dofs]
                    continue
                n = len(values)
                mine = np.append(np.arange(n), K)  # this chain's candidates, then the current pose
                d = PointTree(loose).query(v[mine][:, cols].reshape(-1, 3), DISTAL_TRUNCATION_M)[0]
                cost = (np.minimum(d, DISTAL_TRUNCATION_M) ** 2).reshape(n + 1, -1).mean(1)
                best = int(np.argmin(cost))
                if cost[best] > UNSUPPORTED * DISTAL_TRUNCATION_M**2:
                    q[h, dofs] = self.neutral[dofs]
                elif best < n:
                    q[h, dofs] = values[best]
        hyp.state = self.fitter.start_state(q, root, c)
