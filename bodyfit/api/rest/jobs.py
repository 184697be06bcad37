"""Running long work for REST: in a worker thread, as an NDJSON stream of progress and results or as one
JSON answer; a client that goes away cancels the work (at the core's next progress check)."""

from __future__ import annotations

import asyncio
from collections.abc import AsyncGenerator, Callable, Sequence
from typing import Any

from fastapi import Request
from fastapi.responses import JSONResponse, StreamingResponse

from bodyfit import wire as w
from bodyfit.api import problems
from bodyfit.api.results import progress_event
from bodyfit.service.errors import as_service_error
from bodyfit.service.formats import json_bytes, json_ready
from bodyfit.service.jobs import Job, Progress

NDJSON = "application/x-ndjson"
Work = Callable[[Job], Sequence[w.WireModel]]
"""Runs in a worker thread; may emit partial results (:meth:`Job.emit`) while it runs; returns the result
events, the ``result`` event last."""


def wants_stream(request: Request) -> bool:
    return NDJSON in request.headers.get("accept", "")


def _line(doc: w.WireModel | dict[str, Any]) -> bytes:
    """One NDJSON line; NaN as null, so that every JSON parser reads it."""
    if isinstance(doc, w.WireModel):
        doc = doc.model_dump(mode="json")
    return json_bytes(doc) + b"\n"


async def stream(work: Work, job: Job) -> AsyncGenerator[bytes, None]:
    """NDJSON lines: ``progress`` events and the events the work emits (:meth:`Job.emit`: a sequence's
    chunks) while it runs, then its result events, or one ``error`` event (a problem document) if it
    failed. Closing the stream early cancels the job."""
    loop = asyncio.get_running_loop()
    queue: asyncio.Queue[Progress | w.WireModel] = asyncio.Queue()

    def forward(item: Progress | w.WireModel) -> None:
        loop.call_soon_threadsafe(queue.put_nowait, item)

    job.on_progress = forward
    job.on_event = forward
    task = loop.run_in_executor(None, work, job)
    try:
        while not task.done() or not queue.empty():
            getter: asyncio.Future[Progress | w.WireModel] = asyncio.ensure_future(queue.get())
            pending: set[asyncio.Future[Any]] = {getter, task}
            await asyncio.wait(pending, return_when=asyncio.FIRST_COMPLETED)
            if getter.done():
                item = getter.result()
                yield _line(progress_event(item) if isinstance(item, Progress) else item)
            else:
                getter.cancel()
        try:
            events = task.result()
        except Exception as exc:
            error = as_service_error(exc)  # the model layer's input errors are the client's: 422
            if error is not None:
                yield _line(w.ErrorEvent.model_validate(problems.service_problem(error)))
                return
            problems.LOG.exception("unhandled error in a streamed job")
            bug = problems.problem("internal", "Internal error", _BUG, 500)
            yield _line(w.ErrorEvent.model_validate(bug))
            return
        for event in events:
            yield _line(event)
    finally:
        job.cancel()  # no-op when finished; stops the work when the client went away


async def answer(request: Request, work: Work, job: Job) -> StreamingResponse | JSONResponse:
    """Stream NDJSON when the client accepts it, else wait and answer with the result event as JSON, and
    the chunk events under ``chunks`` when there are any, without their ``event`` (errors then get their
    own HTTP status)."""
    if wants_stream(request):
        return StreamingResponse(stream(work, job), media_type=NDJSON)
    emitted: list[w.WireModel] = []
    job.on_event = emitted.append  # the chunks the work emits come first in the answer
    loop = asyncio.get_running_loop()
    task = loop.run_in_executor(None, work, job)
    while not task.done():
        await asyncio.wait({task}, timeout=0.5)
        if not task.done() and await request.is_disconnected():
            job.cancel()
    try:
        events = [*emitted, *task.result()]  # ServiceError -> the app's problem handler
    except Exception as exc:
        error = as_service_error(exc)
        if error is None or error is exc:
            raise
        raise error from exc
    result = events[-1].model_dump(mode="json", exclude={"event"})
    if len(events) > 1:
        result["chunks"] = [e.model_dump(mode="json", exclude={"event"}) for e in events[:-1]]
    return JSONResponse(json_ready(result))  # NaN as null: JSONResponse refuses NaN


_BUG = "the server failed unexpectedly; the error is logged on the server. Please report it."
