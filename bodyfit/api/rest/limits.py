"""ASGI middleware refusing request bodies above the upload limit before they are read into memory."""

from __future__ import annotations

import json

from starlette.types import ASGIApp, Message, Receive, Scope, Send

from bodyfit.api.problems import MEDIA_TYPE, problem


class BodyTooLargeError(Exception):
    pass


class BodyLimit:
    """413 problem+json when Content-Length (or the streamed body) exceeds ``max_bytes``."""

    def __init__(self, app: ASGIApp, max_bytes: int) -> None:
        self.app = app
        self.max_bytes = max_bytes

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        headers = dict(scope.get("headers") or [])
        length = headers.get(b"content-length")
        if length is not None and (not length.isdigit() or int(length) > self.max_bytes):
            await self._refuse(send, int(length) if length.isdigit() else None)
            return
        received = 0
        exceeded = refused = False

        async def counted() -> Message:
            nonlocal received, exceeded
            message = await receive()
            if message["type"] == "http.request":
                received += len(message.get("body", b""))
                if received > self.max_bytes:
                    exceeded = True
                    raise BodyTooLargeError
            return message

        async def replaced(message: Message) -> None:
            # Once the body ran over, whatever the app answers (its body parser turns the error into a
            # 400) is replaced by the 413.
            nonlocal refused
            if not exceeded:
                await send(message)
            elif not refused:
                refused = True
                await self._refuse(send, None)

        try:
            await self.app(scope, counted, replaced)
        except BodyTooLargeError:
            if not refused:
                await self._refuse(send, None)

    async def _refuse(self, send: Send, size: int | None) -> None:
        got = f"{size / 2**20:.1f} MiB" if size is not None else "more"
        detail = (
            f"the request body is {got}; the server accepts at most {self.max_bytes / 2**20:.1f} MiB "
            "(BODYFIT_MAX_UPLOAD_MB): thin or split the upload"
        )
        body = json.dumps(problem("resource_exhausted", "Request too large", detail, 413)).encode()
        await send(
            {
                "type": "http.response.start",
                "status": 413,
                "headers": [
                    (b"content-type", MEDIA_TYPE.encode()),
                    (b"content-length", str(len(body)).encode()),
                ],
            }
        )
        await send({"type": "http.response.body", "body": body})
