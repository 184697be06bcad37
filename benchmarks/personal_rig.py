"""Personal rigs (issue: personal rigs and growing shape spaces): a person outside the shape space, six
scans of them to build the rig from, six other poses held out.

What is measured
----------------
* Subjects outside the population the shape space was learned from:
  ``offsets``: our body (coefficients 0.8 SD, seeded) with smooth random soft tissue added to the
  template, as thick as tissue is where it is (:data:`TISSUE_MM`: 12 mm on the trunk and thighs, 2-3 mm
  over the skull, hands and feet; 8 mm over the surface), posed by our skin; ``anny_*``: anny bodies at
  extreme phenotypes (old and heavy, young and lean and short) posed by anny's own rig through our skeleton
  (:mod:`bodyfit.models.body.anny_posed`), in our topology.
* Poses: uniform within half of every coordinate's range about its middle, pelvis upright; 12 per subject
  (seeded), the first 6 build the rig (:func:`bodyfit.models.rig.build.build_rig`), the last 6 are held
  out. The inputs are registered meshes (our topology, exact correspondence), so the registration of each
  route is its parametric fit.
* ``generic_mm``: mean vertex error on the held-out poses of the generic model fitted to each alone (its
  own shape and pose, :class:`RegisteredFitter`); ``personal_mm``: the rig fitted to them (pose only,
  :func:`bodyfit.models.rig.fit.fit_registered`); ``ratio`` the second over the first.
* ``raw_offsets_0`` (full run only): the rig of the first offsets subject built from raw scans instead,
  20,000 points sampled on each of the six build meshes, each registered as the service registers a raw
  scan (:func:`bodyfit.service.subjects.registrations`), the rig then built from the registrations and
  refined by closest points against all six scans' points (``build_rig(..., points=...)``); held-out poses
  scored as above; ``build_s`` there includes the six scan fits. Beside it, raw against raw:
  ``raw_generic_mm``, the held-out poses given as raw scans too (20,000 points each) and fitted by the
  service generically, and ``raw_personal_mm``, fitted by the service with the subject (pose only,
  ``fit/scan`` with ``subject=``), each the registration's mean vertex error against the mesh, and
  ``raw_ratio`` the second over the first. The headline ``ratio`` stays the stricter one: its peer is the
  generic model fitted to registered meshes, which no raw scan's correspondence error inflates.
* Keys: ``rig_ratio`` and ``rig_param_mm`` the worst subject's; ``rig_build_s`` the slowest build from
  registered meshes (wall clock, one torch thread).

Usage::

    python benchmarks/personal_rig.py [--quick] [--json]
    python benchmarks/personal_rig.py --render docs/rig_anny.png     # the figure of docs/rigs.md
"""

from __future__ import annotations

import time
from typing import Any

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spl
import torch

from bodyfit.models.body.model import BodyModel
from bodyfit.models.fitting.common.surface import laplacian, vertex_normals
from bodyfit.models.fitting.registered.fitter import RegisteredFitter
from bodyfit.models.rig.build import RigBuild, build_rig
from bodyfit.models.rig.fit import fit_registered

N_BUILD, N_HELD = 6, 6
RAW_POINTS = 20_000
SPREAD = 0.5
EXTREMES = {
    "anny_old_heavy": (dict(gender=0.0, age=1.0, muscle=0.1, weight=1.0, height=0.8, proportions=0.9), 85.0),
    "anny_lean_short": (
        dict(gender=1.0, age=0.55, muscle=0.9, weight=0.0, height=0.1, proportions=0.1),
        25.0,
    ),
}
"""anny phenotype sliders (0..1) and age in years of each extreme subject."""


TISSUE_MM = {
    "pelvis": 12.0, "torso": 12.0, "thoracic_link": 12.0, "thorax": 12.0, "femur": 12.0,
    "scapula": 8.0, "scapulothoracic_link": 8.0, "humerus": 8.0,
    "cervical_link": 5.0, "tibia": 5.0, "patella": 5.0, "ulna": 5.0, "radius": 5.0,
    "head": 3.0, "talus": 2.0, "calcn": 2.0, "toes": 2.0, "hand": 2.0,
}  # fmt: skip
"""Mean thickness (mm, in or out) of the random soft tissue on each body's skin, both sides alike: full on
the trunk, pelvis and thighs, where subcutaneous fat and muscle differ most between people (abdominal,
gluteal and thigh fat ranges over centimetres); two thirds of it on the upper arms and shoulders; under half
on the neck, forearms and shanks (muscle over a bone close to the skin: the shin's front, the ulna); a few
millimetres over bone: the skull and face, the feet and toes, the hands and fingers. Over the body's surface
(area-weighted) the mean is about 8 mm (:func:`soft_tissue`)."""


def tissue_profile(model: BodyModel) -> np.ndarray:
    """(V,) mean thickness (mm) of the soft tissue at each template vertex: :data:`TISSUE_MM` of its bodies
    blended by the model's skinning weights, so it changes smoothly across the joints."""
    amplitude = np.array(
        [TISSUE_MM[name.removesuffix("_r").removesuffix("_l")] for name in model.skeleton.spec.body_names]
    )
    return np.asarray(model.data["weights"], np.float64) @ amplitude


def soft_tissue(model: BodyModel, seed: int) -> np.ndarray:
    """(V, 3) smooth random soft tissue (in or out) along the mean body's normals: white noise diffused by
    the mesh Laplacian, scaled to a mean magnitude of one and then by each vertex's
    :func:`tissue_profile` (mm): 12 mm on the trunk, pelvis and thighs, 8 mm on the upper arms and
    shoulders, 5 mm on the neck, forearms and shanks, 3 mm on the head, 2 mm on the hands, feet and toes;
    8 mm over the body's surface (area-weighted; 7.6-8.4 mm for seeds 0-2) and 4.4 mm over its vertices,
    two thirds of which lie on the head, hands and feet. Along the normal only, as tissue is: an offset
    along the surface would move no point of the skin, and no scan could see it."""
    V = model.n_vertices
    L = laplacian(model.faces, V)
    solve = spl.factorized((sp.identity(V) + 30.0 * (L.T @ L)).tocsc())
    noise = solve(np.random.default_rng(seed).normal(size=V))
    thickness = noise / np.abs(noise).mean() * tissue_profile(model) / 1000.0
    return vertex_normals(model.data["vertices_mean"], model.faces) * thickness[:, None]


def poses(model: BodyModel, n: int, seed: int) -> np.ndarray:
    from bodyfit.models.body.anny_posed import random_poses

    return random_poses(model.skeleton, n, np.random.default_rng(seed), SPREAD)


def offsets_subject(model: BodyModel, seed: int) -> np.ndarray:
    """(12, V, 3) our body with smooth soft tissue, posed by our skin."""
    shape = np.random.default_rng(seed).normal(size=(1, model.n_shape)) * 0.8
    decoder = model.decoder(torch.float64).with_offsets(soft_tissue(model, seed))
    q = poses(model, N_BUILD + N_HELD, 100 + seed)
    with torch.no_grad():
        c = torch.as_tensor(np.repeat(shape, len(q), 0))
        return decoder(c, torch.as_tensor(q), torch.zeros(len(q), 3, dtype=torch.float64))[0].numpy()


def anny_subject(model: BodyModel, name: str, seed: int) -> np.ndarray:
    """(12, V, 3) one anny body at an extreme phenotype (:data:`EXTREMES`), posed by anny's rig."""
    from bodyfit.models.body.anny_posed import pose_anny, template_landmarks
    from bodyfit.models.body.anny_source import AnnySource, Population
    from bodyfit.models.body.skeleton_fit import place_skeletons
    from bodyfit.models.build_assets import default_cache_dir

    phenotypes, age = EXTREMES[name]
    src = AnnySource(default_cache_dir())
    pop = Population({k: np.array([v]) for k, v in phenotypes.items()}, np.array([age]))
    landmarks, _ = template_landmarks(src)
    fit = place_skeletons(model.skeleton, src.rest(pop)["vertices"][:, landmarks], 150)
    fk = model.skeleton.kinematics(torch.float64)
    frames_a = fk(torch.as_tensor(fit.q), torch.as_tensor(fit.root), torch.as_tensor(fit.scales)).frames
    q = poses(model, N_BUILD + N_HELD, 200 + seed)
    ids = np.zeros(len(q), dtype=np.int64)
    vertices, _ = pose_anny(src, pop, model.skeleton, fit, ids, q, frames_a)
    return vertices


def raw_scans(model: BodyModel, meshes: np.ndarray, first_seed: int) -> list[Any]:
    """Raw scans of meshes (K, V, 3): :data:`RAW_POINTS` points sampled on each (seeded), no faces."""
    from bodyfit.io.scans import Scan, sample_surface

    return [
        Scan(sample_surface(v, model.faces, RAW_POINTS, seed=first_seed + k)[0], None, None, "m", RAW_POINTS)
        for k, v in enumerate(meshes)
    ]


def raw_build(service: Any, model: BodyModel, build: np.ndarray) -> RigBuild:
    """The rig of meshes (K, V, 3) given as raw scans: points sampled on each, registered by the service,
    the rig refined against the points."""
    from bodyfit.service.jobs import Job
    from bodyfit.service.subjects import registrations

    scans = raw_scans(model, build, 0)
    names = [f"raw{k}" for k in range(len(build))]
    x = registrations(service, scans, names, Job(), None)
    return build_rig(model, x, names, points=[scan.points for scan in scans])


def mean_mm(a: np.ndarray, b: np.ndarray) -> float:
    """Mean vertex distance (mm) between meshes a and b (..., V, 3) metres."""
    return float(np.linalg.norm(a - b, axis=-1).mean() * 1000.0)


def raw_peer(service: Any, model: BodyModel, built: RigBuild, held: np.ndarray) -> dict[str, float]:
    """Held-out meshes (B, V, 3) given as raw scans too, fitted by the service generically and with the
    subject (pose only): each registration's mean vertex error (mm) against the mesh, and their ratio."""
    scans = raw_scans(model, held, N_BUILD)
    body = service.subject_body(built.subject)
    generic = np.stack([service.fit_mesh(scan).vertices for scan in scans])
    personal = np.stack([service.fit_mesh(scan, body=body).vertices for scan in scans])
    g, p = mean_mm(generic, held), mean_mm(personal, held)
    return {"raw_generic_mm": round(g, 3), "raw_personal_mm": round(p, 3), "raw_ratio": round(p / g, 4)}


def rig_case(model: BodyModel, bodies: np.ndarray, raw: bool = False) -> dict[str, float]:
    """Build on the first :data:`N_BUILD` bodies (from raw scans of them with ``raw``), score on the rest
    (module docstring)."""
    build, held = bodies[:N_BUILD], bodies[N_BUILD:]
    service = None
    began = time.perf_counter()
    if raw:
        from bodyfit.service.core import BodyService

        service = BodyService.load(fitters=False)
        built = raw_build(service, model, build)
    else:
        built = build_rig(model, build, [f"pose{k}" for k in range(N_BUILD)])
    build_s = time.perf_counter() - began
    generic = RegisteredFitter(model).fit(held)
    personal = fit_registered(model, built.subject, held)
    g, p = mean_mm(generic.vertices, held), mean_mm(personal.vertices, held)
    out = {
        "generic_mm": round(g, 3),
        "personal_mm": round(p, 3),
        "ratio": round(p / g, 4),
        "build_fit_mm": round(float(built.personal_mm.mean()), 3),
        "build_s": round(build_s, 2),
    }
    if service is not None:
        out.update(raw_peer(service, model, built, held))
    return out


def run(quick: bool) -> dict[str, Any]:
    """The keys of the module docstring, and the per-subject table ``rig_cases``."""
    torch.set_num_threads(1)
    model = BodyModel.load()
    cases: dict[str, np.ndarray] = {}
    for seed in range(1 if quick else 3):
        cases[f"offsets_{seed}"] = offsets_subject(model, seed)
    for k, name in enumerate(list(EXTREMES)[: 1 if quick else None]):
        cases[name] = anny_subject(model, name, k)
    table = {name: rig_case(model, bodies) for name, bodies in cases.items()}
    build_s = max(r["build_s"] for r in table.values())
    if not quick:
        table["raw_offsets_0"] = rig_case(model, cases["offsets_0"], raw=True)
    return {
        "rig_ratio": max(r["ratio"] for r in table.values()),
        "rig_param_mm": max(r["personal_mm"] for r in table.values()),
        "rig_build_s": build_s,
        "rig_cases": table,
    }


def render_rig(out: str) -> None:
    """The old, heavy anny subject in two held-out poses: the scan, the generic model's fit and the rig's,
    each skin see-through over its skeleton (the rig's with the person's joints), and the error (mm) in
    the column title (PNG ``out``)."""
    from render import RenderMesh, label_grid, render, save_png, tile  # benchmarks/ is on sys.path

    torch.set_num_threads(1)
    model = BodyModel.load()
    bodies = anny_subject(model, "anny_old_heavy", 0)
    held = bodies[N_BUILD : N_BUILD + 2]
    subject = build_rig(model, bodies[:N_BUILD]).subject
    generic = RegisteredFitter(model).fit(held)
    personal = fit_registered(model, subject, held)
    skin, bone = (0.85, 0.65, 0.55), (0.93, 0.89, 0.80)
    images: list[np.ndarray] = []
    titles = ["scan (anny's own rig)"]
    for name, fit in (("generic", generic), ("rig", personal)):
        mm = np.linalg.norm(fit.vertices - held, axis=-1).mean() * 1000.0
        titles.append(f"{name} fit, {mm:.2f} mm")
    lo, hi = held.reshape(-1, 3).min(0) - 0.03, held.reshape(-1, 3).max(0) + 0.03
    for k in range(len(held)):
        images.append(render([RenderMesh(held[k], model.faces, skin)], "front", (300, 440), bounds=(lo, hi)))
        for fit, decoder in (
            (generic, model.decoder(torch.float64)),
            (personal, subject.decoder(model, torch.float64)),
        ):
            with torch.no_grad():
                c, q, r = (torch.as_tensor(a[k : k + 1]) for a in (fit.shape, fit.coordinates, fit.root))
                _, _, frames, scales = decoder(c, q, r)
                bones = model.pose_bones(frames, scales)[0].numpy()
            meshes = [
                RenderMesh(bones, model.skeleton.bone_mesh().faces, bone),
                RenderMesh(fit.vertices[k], model.faces, skin, opacity=0.35),
            ]
            images.append(render(meshes, "front", (300, 440), bounds=(lo, hi)))
    rows = [f"held-out pose {k + 1}" for k in range(len(held))]
    save_png(
        label_grid(tile(images, 3), [titles], rows, "anny, old and heavy: a rig from six other poses"), out
    )


if __name__ == "__main__":
    import sys

    from bench_cli import bench_main  # benchmarks/ is on sys.path

    if sys.argv[1:2] == ["--render"]:
        render_rig(sys.argv[2])
    else:
        bench_main(
            run,
            "Personal rigs: subjects outside the shape space, six scans each.",
            "one offsets subject, one anny",
        )
