"""Streamed REST work: progress lines while it runs, and a client that goes away cancels it."""

from __future__ import annotations

import asyncio
import json
import threading
import time
from typing import Any

from bodyfit.api.rest.jobs import stream
from bodyfit.service.errors import JobCancelledError
from bodyfit.service.jobs import Job
from bodyfit.wire import WireModel


def test_closing_the_stream_cancels_the_work() -> None:
    stopped = threading.Event()

    def work(job: Job) -> list[WireModel]:
        try:
            for k in range(10_000):
                job.report("fit", k, 10_000)
                time.sleep(0.005)
        except JobCancelledError:
            stopped.set()
            raise
        return []

    async def client_reads_one_line_and_leaves() -> dict[str, Any]:
        job = Job()
        lines = stream(work, job)
        first = json.loads(await lines.__anext__())
        await lines.aclose()  # what the server does when the connection drops
        assert job.cancelled
        return first

    first = asyncio.run(client_reads_one_line_and_leaves())
    assert first["event"] == "progress" and first["total"] == 10_000
    assert stopped.wait(60.0), "the work kept running after the client left"


def test_a_failure_midway_is_an_error_event() -> None:
    def work(job: Job) -> list[WireModel]:
        job.report("fit", 0, 2)
        raise JobCancelledError("stopped on purpose")

    async def read_all() -> list[dict[str, Any]]:
        return [json.loads(line) async for line in stream(work, Job())]

    events = asyncio.run(read_all())
    assert events[0]["event"] == "progress"
    assert (
        events[-1]["event"] == "error"
        and events[-1]["status"] == 499
        and "on purpose" in events[-1]["detail"]
    )
