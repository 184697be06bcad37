"""Personal rigs in the service: the scans of one person fitted each as :meth:`BodyService.fit_mesh` fits
them, then one rig built from their registrations (:func:`bodyfit.models.rig.build.build_rig`). The service
keeps no state: the caller gets the portable subject file back."""

from __future__ import annotations

from collections.abc import Sequence
from typing import TYPE_CHECKING

import numpy as np

from bodyfit.models.rig.build import RigBuild, RigConfig, build_rig
from bodyfit.service.core import REGISTERED
from bodyfit.service.errors import InvalidInputError
from bodyfit.service.jobs import Job
from bodyfit.service.validation import invalid_input

if TYPE_CHECKING:
    from bodyfit.io.scans import Scan
    from bodyfit.service.core import BodyService
    from bodyfit.service.hints import ScanHints

MAX_SCANS = 32
"""Scans one rig is built from at most (each is a whole fit)."""


def registrations(
    service: BodyService, scans: Sequence[Scan], names: Sequence[str], job: Job, hints: ScanHints | None
) -> np.ndarray:
    """(K, V, 3) metres: each scan in our topology, as given when it is one already, else its fit's
    registration (in the scan's frame). ``job`` gets one progress step per scan and each fit's own progress;
    its cancellation and deadline reach into the fits."""
    out = []
    for k, (scan, name) in enumerate(zip(scans, names, strict=True)):
        job.check()
        job.report("rig", k, len(scans) + 1, f"registering {name}")
        if service.route(scan) == REGISTERED:
            service.check_scan(scan)
            out.append(scan.points)
        else:
            out.append(service.fit_mesh(scan, job, hints).vertices)
    return np.stack(out)


def build_subject(
    service: BodyService,
    scans: Sequence[Scan],
    names: Sequence[str],
    job: Job | None = None,
    hints: ScanHints | None = None,
    config: RigConfig | None = None,
) -> RigBuild:
    """One person's rig from their scans (any topology; ``hints`` go with every raw scan's fit); the rig is
    refined against the raw scans' own points, in the frame of their registrations (the scan's).

    Raises:
        InvalidInputError: fewer than the rig's minimum or more than :data:`MAX_SCANS` scans, a scan that
            cannot be a body, scans of different people, or poses that leave joints undetermined (each
            message names the scans or joints and the fix).
    """
    job = job or Job(timeout_s=service.limits.max_seconds)
    cfg = config or RigConfig()
    if len(scans) < cfg.min_scans:
        raise InvalidInputError(
            f"a rig needs at least {cfg.min_scans} scans of the person in different poses; got {len(scans)}",
            field="files",
        )
    if len(scans) > MAX_SCANS:
        raise InvalidInputError(
            f"{len(scans)} scans sent; a rig is built from at most {MAX_SCANS}: pick the most varied poses",
            field="files",
        )
    x = registrations(service, scans, names, job, hints)
    points = [None if service.route(scan) == REGISTERED else scan.points for scan in scans]
    job.report("rig", len(scans), len(scans) + 1, "building the rig")
    with invalid_input("files"):
        built = build_rig(service.model, x, names, config=cfg, points=points)
    job.report("rig", len(scans) + 1, len(scans) + 1, "done")
    return built
