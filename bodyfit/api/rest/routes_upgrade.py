"""POST /v1/upgrade: an SMPL-format sequence -> biomechanical coordinates, in chunks, then the files."""

from __future__ import annotations

from pathlib import PurePath
from typing import Annotated

from fastapi import APIRouter, File, Form, Query, Request, UploadFile
from fastapi.concurrency import run_in_threadpool
from fastapi.responses import JSONResponse, StreamingResponse

from bodyfit import wire as w
from bodyfit.api import results
from bodyfit.api.rest.jobs import answer
from bodyfit.api.rest.openapi import streamed
from bodyfit.api.rest.routes_subjects import SUBJECT_HELP, subject_body
from bodyfit.api.rest.state import Service
from bodyfit.service.core import shape_hints, upgrade_up
from bodyfit.service.jobs import Job
from bodyfit.service.personal import check_alone

router = APIRouter(prefix="/v1", tags=["upgrade"])


@router.post(
    "/upgrade",
    summary="Upgrade an AMASS-style SMPL sequence (.npz) to biomechanical coordinates and OpenSim files",
    responses=streamed(w.UpgradeAnswer, "UpgradeEvent", "The upgrade: the summary, files and every chunk"),
    response_model=None,
)
async def upgrade(
    request: Request,
    service: Service,
    file: Annotated[
        UploadFile, File(description="AMASS-style .npz: poses, trans, betas, gender, mocap_framerate")
    ],
    chunk: Annotated[int, Query(ge=1, le=4096, description="Frames per chunk event.")] = 256,
    sex: Annotated[
        str | None,
        Form(description="Path (b) shape hint: male, female or neutral (default: the file's gender)."),
    ] = None,
    height_m: Annotated[float | None, Form(description="Path (b) shape hint: stature in metres.")] = None,
    mass_kg: Annotated[float | None, Form(description="Path (b) shape hint: body mass in kilograms.")] = None,
    up: Annotated[
        str | None,
        Form(
            description="The input's up axis: +x, -x, +y, -y, +z or -z (a bare axis is +); unset or auto: "
            "detected from the motion (AMASS's Z-up needs nothing). The output is Y-up."
        ),
    ] = None,
    subject: Annotated[
        UploadFile | None,
        File(description=f"{SUBJECT_HELP}; the .osim carries their bone scales. Not with the shape hints."),
    ] = None,
) -> StreamingResponse | JSONResponse:
    hints = shape_hints(sex, height_m, mass_kg)
    up_axis = upgrade_up(up)
    body = await subject_body(service, subject)
    check_alone(body, [("shape hints (sex, height_m, mass_kg)", hints)])
    data = await file.read()
    name = file.filename or "upload.npz"
    sequence = await run_in_threadpool(service.read_upgrade, data, name)

    def work(job: Job) -> list[w.UpgradeChunkEvent | w.UpgradeResultEvent]:
        result = service.upgrade(sequence, job, hints, up_axis, body)
        files = service.upgrade_files(result, PurePath(name).stem or "upgrade")
        return [*results.upgrade_chunks(result, chunk), results.upgrade_summary(result, files)]

    return await answer(request, work, Job(timeout_s=service.limits.max_seconds))
