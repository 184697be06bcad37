"""POST /v1/subjects: one person's rig from several scans of them, streamed as NDJSON (Accept:
application/x-ndjson) or answered as one JSON document; the subject file comes back in the answer."""

from __future__ import annotations

from pathlib import PurePath
from typing import Annotated, Literal

from fastapi import APIRouter, File, Form, Request, UploadFile
from fastapi.concurrency import run_in_threadpool
from fastapi.responses import JSONResponse, StreamingResponse

from bodyfit.api import results
from bodyfit.api.rest.jobs import answer
from bodyfit.api.rest.openapi import streamed
from bodyfit.api.rest.state import Service
from bodyfit.io.scans import Scan
from bodyfit.models.fitting.registered.fitter import FixedBody
from bodyfit.models.rig.build import RigConfig
from bodyfit.service.core import BodyService
from bodyfit.service.errors import InvalidInputError
from bodyfit.service.hints import ScanHints
from bodyfit.service.jobs import Job
from bodyfit.service.subjects import build_subject
from bodyfit.wire.hints import FACING_HELP, POSE_HELP, UP_HELP
from bodyfit.wire.subjects import SubjectResult, SubjectResultEvent

router = APIRouter(prefix="/v1", tags=["subjects"])

SUBJECT_HELP = (
    "Optional: a subject file (the .npz of POST /v1/subjects or `bodyfit rig`): the body is that person's, "
    "their shape and template held fixed; only the pose is fitted"
)


async def subject_body(service: BodyService, upload: UploadFile | None) -> FixedBody | None:
    """The person's body of a route's optional ``subject`` upload, read and checked before any work starts
    (a subject that cannot be used: 422 naming the field ``subject``)."""
    if upload is None:
        return None
    return await run_in_threadpool(service.subject_body, await upload.read())


@router.post(
    "/subjects",
    summary="Build one person's rig from several scans of them in different poses",
    responses=streamed(SubjectResult, "SubjectEvent", "The rig: errors per scan and the subject file"),
    response_model=None,
)
async def build_subject_route(
    request: Request,
    service: Service,
    files: Annotated[
        list[UploadFile],
        File(description="Three or more scans of one person (PLY, OBJ, STL, PCD or NPZ), one part each."),
    ],
    units: Annotated[Literal["auto", "m", "mm"], Form()] = "auto",
    up: Annotated[str | None, Form(description=f"Hint for every raw scan: {UP_HELP}.")] = None,
    facing: Annotated[str | None, Form(description=f"Hint for every raw scan: {FACING_HELP}.")] = None,
    pose: Annotated[str | None, Form(description=f"Hint for every raw scan: {POSE_HELP}.")] = None,
    allow_undetermined: Annotated[
        bool, Form(description="Build even when the poses leave limb joints undetermined.")
    ] = False,
) -> StreamingResponse | JSONResponse:
    hints = ScanHints.given(up, facing, pose)  # a bad hint: 422 before the uploads are read
    names: list[str] = []
    scans: list[Scan] = []
    for upload in files:
        name = upload.filename or f"scan{len(names)}"
        fmt = PurePath(name).suffix.lstrip(".")
        if not fmt:
            raise InvalidInputError(f"{name!r} has no suffix: name each file with its format", "files")
        scans.append(await run_in_threadpool(service.read_scan, await upload.read(), fmt, units))
        names.append(name)
    config = RigConfig(allow_undetermined=allow_undetermined)

    def work(job: Job) -> list[SubjectResultEvent]:
        return [results.subject_result(build_subject(service, scans, names, job, hints, config))]

    return await answer(request, work, Job(timeout_s=service.limits.max_seconds))
