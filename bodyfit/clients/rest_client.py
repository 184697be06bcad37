"""REST clients of the bodyfit service (httpx): :class:`Client` (sync) and :class:`AsyncClient`.

Numpy in, numpy out; errors raise the typed exceptions of :mod:`bodyfit.clients.errors` built from the
server's problem+json; default timeouts; retries by :class:`~bodyfit.clients.core.RetryPolicy` (busy or
loading server, ``Retry-After`` honoured; connections never made). Pass ``http_client`` to inject a
transport (e.g. an in-process app in tests). The methods, checks and results are those of
:mod:`bodyfit.clients.core`; this module only turns an operation into an HTTP request and the answer into
documents (JSON text, one per NDJSON line), which the core reads with the models of :mod:`bodyfit.wire`.
"""

from __future__ import annotations

import base64
import os
from collections.abc import AsyncGenerator, Generator
from typing import Any, Generic, TypeVar

import httpx
import numpy as np

from bodyfit.clients.core import AsyncClientCore, Event, Operation, SyncClientCore, parse_retry_after
from bodyfit.clients.core import operations as ops
from bodyfit.clients.core.base import async_method, retry_policy, sync_method
from bodyfit.clients.core.operations import Coordinates, frames_npz, synthesis_args, upgrade_upload
from bodyfit.clients.core.retry import DEFAULT_RETRIES, RetryPolicy
from bodyfit.clients.errors import (
    BodyfitClientError,
    ConnectionFailedError,
    RequestTimeoutError,
    ServerError,
    error_from_http,
)
from bodyfit.clients.results import synthesis_event

DEFAULT_URL = "http://127.0.0.1:8000"
DEFAULT_TIMEOUT = httpx.Timeout(30.0, read=600.0)
NDJSON = "application/x-ndjson"
BUILT_HEADER = "bodyfit-measurements"
"""The synthesis answer's header with the measurements document of a body built from measurements."""
H = TypeVar("H", httpx.Client, httpx.AsyncClient)


def synth_body(
    shape: np.ndarray | None,
    coordinates: Coordinates,
    root: np.ndarray | None,
    skeleton: bool,
    format: str,
    faces: bool,
    batch: int | None,
) -> dict[str, Any]:
    """The JSON body of POST /v1/synthesize (arrays as nested lists)."""
    return _json_body(synthesis_args(shape, coordinates, root, skeleton, faces, batch, format))


def _json_body(args: dict[str, Any]) -> dict[str, Any]:
    body: dict[str, Any] = {k: args[k] for k in ("skeleton", "format", "faces")}
    body.update(_arrays(args, ("shape", "coordinates", "root")))
    for key in ("batch", "measurements", "sex"):
        if args.get(key) is not None:
            body[key] = args[key]
    if args.get("subject") is not None:
        body["subject"] = base64.b64encode(args["subject"]).decode()
    return body


def _with_subject(files: dict[str, Any], a: dict[str, Any]) -> dict[str, Any]:
    """The multipart files of an upload plus the operation's subject file, when it has one."""
    return files if a.get("subject") is None else {**files, "subject": ("subject.npz", a["subject"])}


def _arrays(args: dict[str, Any], keys: tuple[str, ...]) -> dict[str, Any]:
    """The arrays of ``args`` that are set, as nested lists (named coordinates as {name: list})."""
    body: dict[str, Any] = {}
    for key in keys:
        value = args[key]
        if isinstance(value, dict):
            body[key] = {name: v.tolist() for name, v in value.items()}
        elif value is not None:
            body[key] = value.tolist()
    return body


def measure_request(a: dict[str, Any]) -> dict[str, Any]:
    """The httpx keyword arguments of POST /v1/measure: a multipart mesh upload or a JSON body."""
    if a["mesh"] is not None:
        name, data = a["mesh"]
        return {"files": {"file": (name, data)}, "data": {"units": a["units"]}}
    if a["measurements"] is not None:
        sex = {"sex": a["sex"]} if a["sex"] is not None else {}
        return {"json": {"measurements": a["measurements"], **sex}}
    return {"json": _arrays(a, ("shape", "coordinates"))}


def hint_fields(sex: str | None, height_m: float | None, mass_kg: float | None) -> dict[str, str] | None:
    """The upgrade's shape-hint form fields (None when no hint is given)."""
    fields = {
        k: str(v) for k, v in (("sex", sex), ("height_m", height_m), ("mass_kg", mass_kg)) if v is not None
    }
    return fields or None


def request_of(op: Operation[Any]) -> tuple[str, str, dict[str, Any]]:
    """(method, path, httpx keyword arguments) of an operation."""
    a = op.args
    if op.name == "model_info":
        return "GET", "/v1/model", {}
    if op.name in ("synthesize", "synthesize_file"):
        return "POST", "/v1/synthesize", {"json": _json_body(a)}
    if op.name == "measure":
        return "POST", "/v1/measure", measure_request(a)
    stream: dict[str, Any] = {"headers": {"accept": NDJSON}}
    if op.name == "fit_scan":
        files = _with_subject({"file": (a["name"], a["data"])}, a)
        fields = {"units": a["units"], **{k: str(v) for k, v in a["hints"].items()}}
        return "POST", "/v1/fit/scan", {"files": files, "data": fields, **stream}
    if op.name == "fit_sequence":
        files = _with_subject({"file": ("frames.npz", frames_npz(a["frames"], a["weights"]))}, a)
        return "POST", f"/v1/fit/sequence?chunk={a['chunk']}", {"files": files, **stream}
    if op.name == "build_subject":
        parts = [("files", item) for item in a["files"]]
        return "POST", "/v1/subjects", {"files": parts, "data": a["fields"], **stream}
    hints = {k: str(v) for k, v in a["hints"].items()} or None
    files = _with_subject({"file": (a["name"], a["data"])}, a)
    return "POST", f"/v1/upgrade?chunk={a['chunk']}", {"files": files, "data": hints, **stream}


def answer_event(op: Operation[Any], response: httpx.Response) -> Event:
    """The document of a unary answer: the synthesis's npz arrays, a file's bytes, or the JSON body; a
    synthesis from measurements adds the build's measurements document (its response header) as
    ``built``."""
    content = response.content
    built = response.headers.get(BUILT_HEADER)
    extra = {} if built is None else {"built": built}
    if op.name == "synthesize":
        return synthesis_event(content) | extra
    if op.name == "synthesize_file":
        return {"data": content, **extra}
    return content


def raise_for_problem(response: httpx.Response) -> None:
    """Raise the typed error of a non-2xx response (problem+json, or plain text from a proxy)."""
    if not response.is_success:
        raise http_error(response)


def http_error(response: httpx.Response) -> BodyfitClientError:
    retry_after = parse_retry_after(response.headers.get("retry-after"))
    return error_from_http(response.status_code, response.content, retry_after)


def transport_error(exc: httpx.HTTPError, url: str) -> BodyfitClientError:
    """A failure below HTTP; a connection that was never made is marked not sent."""
    sent = not isinstance(exc, httpx.ConnectError | httpx.ConnectTimeout)
    if isinstance(exc, httpx.TimeoutException):
        message = f"no answer from {url} in time ({type(exc).__name__}); raise timeout="
        return RequestTimeoutError(message, sent=sent)
    return ConnectionFailedError(f"cannot reach the bodyfit server at {url}: {exc}", sent=sent)


class _Rest(Generic[H]):
    def __init__(
        self,
        base_url: str | None = None,
        timeout: float | httpx.Timeout = DEFAULT_TIMEOUT,
        retries: int = DEFAULT_RETRIES,
        http_client: H | None = None,
        *,
        retry: RetryPolicy | None = None,
    ) -> None:
        self.base_url = base_url or os.environ.get("BODYFIT_URL", DEFAULT_URL)
        self.retries = retries
        self.retry = retry_policy(retries, retry)
        self._http: H = http_client or self._new_http(base_url=self.base_url, timeout=timeout)

    def _new_http(self, **kwargs: Any) -> H:
        raise NotImplementedError


class Client(_Rest[httpx.Client], SyncClientCore):
    """Synchronous REST client.

    Args:
        base_url: the server (default http://127.0.0.1:8000, or $BODYFIT_URL).
        timeout: seconds (connect / write) or an httpx.Timeout; reads of long fits may take minutes.
        retries: attempts after the first, at most, when safe (see :class:`RetryPolicy`).
        http_client: an httpx.Client to use instead of a new one (its base_url wins).
        retry: the retry policy (default :class:`RetryPolicy`: a 20 s budget); ``retries`` caps its count.
    """

    # a rig from several scans (``POST /v1/subjects``)
    build_subject = sync_method(ops.build_subject)

    def _new_http(self, **kwargs: Any) -> httpx.Client:
        return httpx.Client(**kwargs)

    def close(self) -> None:
        self._http.close()

    def _send(self, op: Operation[Any]) -> Generator[Event, None, None]:
        method, path, kwargs = request_of(op)
        try:
            with self._http.stream(method, path, **kwargs) as response:
                if not response.is_success or not op.stream:
                    response.read()
                    raise_for_problem(response)
                    yield answer_event(op, response)
                    return
                for line in response.iter_lines():
                    if line.strip():
                        yield line
        except httpx.HTTPError as exc:
            raise transport_error(exc, self.base_url) from exc


class AsyncClient(_Rest[httpx.AsyncClient], AsyncClientCore):
    """Asynchronous REST client; the same methods as :class:`Client`, awaited."""

    build_subject = async_method(ops.build_subject)

    def _new_http(self, **kwargs: Any) -> httpx.AsyncClient:
        return httpx.AsyncClient(**kwargs)

    async def aclose(self) -> None:
        await self._http.aclose()

    async def _close(self) -> None:
        await self.aclose()

    async def _send(self, op: Operation[Any]) -> AsyncGenerator[Event, None]:
        method, path, kwargs = request_of(op)
        try:
            async with self._http.stream(method, path, **kwargs) as response:
                if not response.is_success or not op.stream:
                    await response.aread()
                    raise_for_problem(response)
                    yield answer_event(op, response)
                    return
                async for line in response.aiter_lines():
                    if line.strip():
                        yield line
        except httpx.HTTPError as exc:
            raise transport_error(exc, self.base_url) from exc


__all__ = ["AsyncClient", "Client", "RetryPolicy", "ServerError", "frames_npz", "upgrade_upload"]
