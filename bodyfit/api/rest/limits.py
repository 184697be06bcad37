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
        guard = _BodyGuard(self, receive, send)
        try:
            await self.app(scope, guard.receive, guard.send)
        except BodyTooLargeError:
            await guard.refuse_once()

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


class _BodyGuard:
    """One request's body counted against the limit as the app reads it; once it ran over, whatever the
    app answers (its body parser turns the error into a 400) is replaced by one 413."""

    def __init__(self, limit: BodyLimit, receive: Receive, send: Send) -> None:
        self.limit = limit
        self._receive = receive
        self._send = send
        self.received = 0
        self.exceeded = False
        self.refused = False

    async def receive(self) -> Message:
        """Returns the next message; raises BodyTooLargeError once the bodies so far exceed the limit."""
        message = await self._receive()
        if message["type"] == "http.request":
            self.received += len(message.get("body", b""))
            if self.received > self.limit.max_bytes:
                self.exceeded = True
                raise BodyTooLargeError
        return message

    async def send(self, message: Message) -> None:
        """Returns None; passes the app's message on, or the 413 instead once the body ran over."""
        if not self.exceeded:
            await self._send(message)
        else:
            await self.refuse_once()

    async def refuse_once(self) -> None:
        """Returns None; sends the 413 unless it was sent already."""
        if not self.refused:
            self.refused = True
            await self.limit._refuse(self._send, None)
