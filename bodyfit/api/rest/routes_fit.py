"""POST /v1/fit/scan and /v1/fit/sequence: long work, streamed as NDJSON (Accept: application/x-ndjson)
or answered as one JSON document."""

from __future__ import annotations

from pathlib import PurePath
from typing import Annotated, Literal

from fastapi import APIRouter, File, Form, Query, Request, UploadFile
from fastapi.concurrency import run_in_threadpool
from fastapi.responses import JSONResponse, StreamingResponse

from bodyfit import wire as w
from bodyfit.api import results
from bodyfit.api.rest.jobs import answer
from bodyfit.api.rest.openapi import streamed
from bodyfit.api.rest.routes_subjects import SUBJECT_HELP, subject_body
from bodyfit.api.rest.state import Service
from bodyfit.service.errors import InvalidInputError
from bodyfit.service.hints import ScanHints
from bodyfit.service.jobs import Job
from bodyfit.wire.hints import FACING_HELP, HEIGHT_HELP, POSE_HELP, SEX_HELP, UP_HELP

router = APIRouter(prefix="/v1/fit", tags=["fitting"])


@router.post(
    "/scan",
    summary="Fit a mesh or point cloud (any topology and placement)",
    responses=streamed(w.MeshFit, "ScanFitEvent", "The fit: parameters, registration and report"),
    response_model=None,
)
async def fit_scan(
    request: Request,
    service: Service,
    file: Annotated[UploadFile, File(description="PLY, OBJ, STL, PCD or NPZ (points / vertices, faces).")],
    units: Annotated[Literal["auto", "m", "mm"], Form()] = "auto",
    format: Annotated[str | None, Form(description="Overrides the file name's suffix.")] = None,
    up: Annotated[str | None, Form(description=f"Hint: {UP_HELP}.")] = None,
    facing: Annotated[str | None, Form(description=f"Hint: {FACING_HELP}.")] = None,
    pose: Annotated[str | None, Form(description=f"Hint: {POSE_HELP}.")] = None,
    sex: Annotated[str | None, Form(description=f"Hint: {SEX_HELP}.")] = None,
    height_m: Annotated[float | None, Form(description=f"Hint: {HEIGHT_HELP}.")] = None,
    subject: Annotated[UploadFile | None, File(description=f"{SUBJECT_HELP}.")] = None,
) -> StreamingResponse | JSONResponse:
    hints = ScanHints.given(up, facing, pose, sex, height_m)  # a bad hint: 422 before the upload is read
    body = await subject_body(service, subject)
    data = await file.read()
    fmt = format or PurePath(file.filename or "").suffix.lstrip(".")
    if not fmt:
        raise InvalidInputError(
            "the file name has no suffix; give format= (ply, obj, stl, pcd or npz)", "format"
        )
    scan = await run_in_threadpool(service.read_scan, data, fmt, units)
    # a scan that cannot be a body: 422 before streaming; the fit reuses the check's cleaning
    ready = await run_in_threadpool(service.check_scan, scan)
    info = service.info()

    def work(job: Job) -> list[w.MeshFitEvent]:
        fit = service.fit_mesh(ready, job, hints, body)
        return [results.mesh_fit_result(fit, list(info.dof_names), list(info.joint_names))]

    return await answer(request, work, Job(timeout_s=service.limits.max_seconds))


@router.post(
    "/sequence",
    summary="Fit a registered mesh sequence (one person, our topology): one shape, per-frame pose",
    responses=streamed(w.SequenceAnswer, "SequenceFitEvent", "The fit: the summary and every chunk"),
    response_model=None,
)
async def fit_sequence(
    request: Request,
    service: Service,
    file: Annotated[
        UploadFile, File(description=".npz with frames (T, 13348, 3) metres, optional weights (T, V)")
    ],
    chunk: Annotated[int, Query(ge=1, le=1024, description="Frames per chunk event.")] = 64,
    subject: Annotated[
        UploadFile | None, File(description=f"{SUBJECT_HELP} (no shape fit: every frame is that body).")
    ] = None,
) -> StreamingResponse | JSONResponse:
    body = await subject_body(service, subject)
    data = await file.read()
    frames, weights = await run_in_threadpool(service.read_sequence, data)
    await run_in_threadpool(service.check_sequence, frames, weights)  # 422 before streaming or fitting
    joint_names = list(service.info().joint_names)

    def work(job: Job) -> list[w.SequenceResultEvent]:
        chunks = results.SequenceChunker(chunk, job.emit)  # streamed while the later frames are fitted
        fit = service.fit_sequence(frames, weights, job, checked=True, on_frames=chunks, body=body)
        chunks.flush()
        return [results.sequence_summary(fit, joint_names)]

    return await answer(request, work, Job(timeout_s=service.limits.max_seconds))
