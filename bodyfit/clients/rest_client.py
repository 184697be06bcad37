"""REST clients of the bodyfit service (httpx): :class:`Client` (sync) and :class:`AsyncClient`.

Numpy in, numpy out; errors raise the typed exceptions of :mod:`bodyfit.clients.errors` built from the
server's problem+json; default timeouts; idempotent calls (model info, synthesize) are retried with
exponential backoff when the server is busy, not ready or unreachable. Pass ``http_client`` to inject a
transport (e.g. an in-process app in tests).
"""

from __future__ import annotations

import asyncio
import json
import os
import time
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import httpx
import numpy as np

from bodyfit.clients.errors import (
    BodyfitClientError,
    ConnectionFailedError,
    RequestTimeoutError,
    ServerError,
    error_from_problem,
)
from bodyfit.clients.results import (
    EventCollector,
    MeshFitResult,
    ModelInfo,
    ProgressCallback,
    SequenceResult,
    Synthesis,
    UpgradeOutput,
)
from bodyfit.clients.uploads import ScanInput, scan_upload

DEFAULT_URL = "http://127.0.0.1:8000"
DEFAULT_TIMEOUT = httpx.Timeout(30.0, read=600.0)
NDJSON = "application/x-ndjson"
Coordinates = np.ndarray | Mapping[str, float | Sequence[float] | np.ndarray] | None


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
    body: dict[str, Any] = {"skeleton": skeleton, "format": format, "faces": faces}
    if shape is not None:
        body["shape"] = np.atleast_2d(np.asarray(shape, np.float64)).tolist()
    if isinstance(coordinates, Mapping):
        body["coordinates"] = {k: np.asarray(v, np.float64).tolist() for k, v in coordinates.items()}
    elif coordinates is not None:
        body["coordinates"] = np.atleast_2d(np.asarray(coordinates, np.float64)).tolist()
    if root is not None:
        body["root"] = np.atleast_2d(np.asarray(root, np.float64)).tolist()
    if batch is not None:
        body["batch"] = batch
    return body


def upgrade_upload(sequence: str | os.PathLike[str] | bytes) -> tuple[str, bytes]:
    """(file name, bytes) of an AMASS-style .npz given as a path or bytes."""
    if isinstance(sequence, bytes | bytearray):
        return "sequence.npz", bytes(sequence)
    path = Path(sequence)
    return path.name, path.read_bytes()


def hint_fields(sex: str | None, height_m: float | None, mass_kg: float | None) -> dict[str, str] | None:
    """The upgrade's shape-hint form fields (None when no hint is given)."""
    fields = {
        k: str(v) for k, v in (("sex", sex), ("height_m", height_m), ("mass_kg", mass_kg)) if v is not None
    }
    return fields or None


def frames_upload(frames: np.ndarray, weights: np.ndarray | None) -> bytes:
    import io

    buf = io.BytesIO()
    arrays = {"frames": np.asarray(frames, np.float32)}
    if weights is not None:
        arrays["weights"] = np.asarray(weights, np.float32)
    np.savez(buf, allow_pickle=False, **arrays)
    return buf.getvalue()


def raise_for_problem(response: httpx.Response) -> None:
    """Raise the typed error of a non-2xx response (problem+json, or plain text from a proxy)."""
    if response.is_success:
        return
    try:
        doc = response.json()
    except (json.JSONDecodeError, UnicodeDecodeError):
        doc = {}
    if not isinstance(doc, dict) or "kind" not in doc:
        kind = {
            413: "resource_exhausted",
            404: "not_found",
            503: "unavailable",
            504: "deadline_exceeded",
        }.get(response.status_code, "invalid_argument" if response.status_code < 500 else "internal")
        doc = {"kind": kind, "detail": f"HTTP {response.status_code}: {response.text[:300]}"}
    raise error_from_problem(doc, response.status_code)


def _transport_error(exc: httpx.HTTPError, url: str) -> BodyfitClientError:
    if isinstance(exc, httpx.TimeoutException):
        return RequestTimeoutError(f"no answer from {url} in time ({type(exc).__name__}); raise timeout=")
    return ConnectionFailedError(f"cannot reach the bodyfit server at {url}: {exc}")


class Client:
    """Synchronous REST client.

    Args:
        base_url: the server (default http://127.0.0.1:8000, or $BODYFIT_URL).
        timeout: seconds (connect / write) or an httpx.Timeout; reads of long fits may take minutes.
        retries: attempts after the first for idempotent calls when the server is busy or unreachable.
        http_client: an httpx.Client to use instead of a new one (its base_url wins).
    """

    def __init__(
        self,
        base_url: str | None = None,
        timeout: float | httpx.Timeout = DEFAULT_TIMEOUT,
        retries: int = 3,
        http_client: httpx.Client | None = None,
    ) -> None:
        self.base_url = base_url or os.environ.get("BODYFIT_URL", DEFAULT_URL)
        self.retries = retries
        self._http = http_client or httpx.Client(base_url=self.base_url, timeout=timeout)

    def __enter__(self) -> Client:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def close(self) -> None:
        self._http.close()

    def _request(self, method: str, path: str, idempotent: bool, **kwargs: Any) -> httpx.Response:
        for attempt in range(self.retries + 1 if idempotent else 1):
            try:
                response = self._http.request(method, path, **kwargs)
                raise_for_problem(response)
                return response
            except httpx.HTTPError as exc:
                error = _transport_error(exc, self.base_url)
            except BodyfitClientError as exc:
                error = exc
            if not error.retryable or attempt == self.retries or not idempotent:
                raise error
            time.sleep(min(0.25 * 2**attempt, 4.0))
        raise AssertionError("unreachable")

    def model_info(self) -> ModelInfo:
        """DOF names, ranges and units, shape sizes, joint names, asset hashes."""
        return ModelInfo.from_dict(self._request("GET", "/v1/model", True).json())

    def synthesize(
        self,
        shape: np.ndarray | None = None,
        coordinates: Coordinates = None,
        root: np.ndarray | None = None,
        skeleton: bool = False,
        faces: bool = False,
        batch: int | None = None,
    ) -> Synthesis:
        """Posed bodies as arrays. shape (B, n_shape); coordinates (B, n_dof) or {name: value(s)}; root
        (B, 3); see :meth:`synthesize_file` for ply / obj / glb / json bytes."""
        body = synth_body(shape, coordinates, root, skeleton, "npz", faces, batch)
        return Synthesis.from_npz(self._request("POST", "/v1/synthesize", True, json=body).content)

    def synthesize_file(
        self,
        format: str,
        shape: np.ndarray | None = None,
        coordinates: Coordinates = None,
        root: np.ndarray | None = None,
        skeleton: bool = False,
    ) -> bytes:
        """Posed bodies encoded as ``format`` (npz, ply, obj, glb or json)."""
        body = synth_body(shape, coordinates, root, skeleton, format, True, None)
        return self._request("POST", "/v1/synthesize", True, json=body).content

    def fit_scan(
        self,
        scan: ScanInput,
        format: str | None = None,
        units: str = "auto",
        progress: ProgressCallback | None = None,
    ) -> MeshFitResult:
        """Fit a mesh or point cloud: a file (path, or bytes with ``format``) or (N, 3) points."""
        name, data = scan_upload(scan, format)
        files = {"file": (name, data)}
        return MeshFitResult.from_event(self._stream("/v1/fit/scan", files, {"units": units}, progress)[1])

    def fit_sequence(
        self,
        frames: np.ndarray,
        weights: np.ndarray | None = None,
        progress: ProgressCallback | None = None,
        chunk: int = 64,
    ) -> SequenceResult:
        """Fit a registered sequence (T, V, 3) in the model's topology (one shape, per-frame pose)."""
        files = {"file": ("frames.npz", frames_upload(frames, weights))}
        return SequenceResult.from_events(
            *self._stream(f"/v1/fit/sequence?chunk={chunk}", files, None, progress)
        )

    def upgrade(
        self,
        sequence: str | os.PathLike[str] | bytes,
        progress: ProgressCallback | None = None,
        chunk: int = 256,
        sex: str | None = None,
        height_m: float | None = None,
        mass_kg: float | None = None,
    ) -> UpgradeOutput:
        """Upgrade an AMASS-style .npz (path or bytes) to biomechanical coordinates and OpenSim files.
        ``sex``, ``height_m`` and ``mass_kg`` shape the body when the server has no SMPL-family model file
        (path b)."""
        files = {"file": upgrade_upload(sequence)}
        hints = hint_fields(sex, height_m, mass_kg)
        return UpgradeOutput.from_events(*self._stream(f"/v1/upgrade?chunk={chunk}", files, hints, progress))

    def _stream(
        self, path: str, files: dict[str, Any], data: dict[str, str] | None, progress: ProgressCallback | None
    ) -> tuple[list[dict[str, Any]], dict[str, Any]]:
        collector = EventCollector(progress)
        try:
            with self._http.stream("POST", path, files=files, data=data, headers={"accept": NDJSON}) as r:
                if not r.is_success:
                    r.read()
                    raise_for_problem(r)
                for line in r.iter_lines():
                    if line.strip() and collector.feed(json.loads(line)):
                        break
        except httpx.HTTPError as exc:
            raise _transport_error(exc, self.base_url) from exc
        return collector.finish()


class AsyncClient:
    """Asynchronous REST client; the same methods as :class:`Client`, awaited."""

    def __init__(
        self,
        base_url: str | None = None,
        timeout: float | httpx.Timeout = DEFAULT_TIMEOUT,
        retries: int = 3,
        http_client: httpx.AsyncClient | None = None,
    ) -> None:
        self.base_url = base_url or os.environ.get("BODYFIT_URL", DEFAULT_URL)
        self.retries = retries
        self._http = http_client or httpx.AsyncClient(base_url=self.base_url, timeout=timeout)

    async def __aenter__(self) -> AsyncClient:
        return self

    async def __aexit__(self, *exc: object) -> None:
        await self.aclose()

    async def aclose(self) -> None:
        await self._http.aclose()

    async def _request(self, method: str, path: str, idempotent: bool, **kwargs: Any) -> httpx.Response:
        for attempt in range(self.retries + 1 if idempotent else 1):
            try:
                response = await self._http.request(method, path, **kwargs)
                raise_for_problem(response)
                return response
            except httpx.HTTPError as exc:
                error = _transport_error(exc, self.base_url)
            except BodyfitClientError as exc:
                error = exc
            if not error.retryable or attempt == self.retries or not idempotent:
                raise error
            await asyncio.sleep(min(0.25 * 2**attempt, 4.0))
        raise AssertionError("unreachable")

    async def model_info(self) -> ModelInfo:
        return ModelInfo.from_dict((await self._request("GET", "/v1/model", True)).json())

    async def synthesize(
        self,
        shape: np.ndarray | None = None,
        coordinates: Coordinates = None,
        root: np.ndarray | None = None,
        skeleton: bool = False,
        faces: bool = False,
        batch: int | None = None,
    ) -> Synthesis:
        body = synth_body(shape, coordinates, root, skeleton, "npz", faces, batch)
        return Synthesis.from_npz((await self._request("POST", "/v1/synthesize", True, json=body)).content)

    async def synthesize_file(
        self,
        format: str,
        shape: np.ndarray | None = None,
        coordinates: Coordinates = None,
        root: np.ndarray | None = None,
        skeleton: bool = False,
    ) -> bytes:
        body = synth_body(shape, coordinates, root, skeleton, format, True, None)
        return (await self._request("POST", "/v1/synthesize", True, json=body)).content

    async def fit_scan(
        self,
        scan: ScanInput,
        format: str | None = None,
        units: str = "auto",
        progress: ProgressCallback | None = None,
    ) -> MeshFitResult:
        name, data = scan_upload(scan, format)
        files = {"file": (name, data)}
        return MeshFitResult.from_event(
            (await self._stream("/v1/fit/scan", files, {"units": units}, progress))[1]
        )

    async def fit_sequence(
        self,
        frames: np.ndarray,
        weights: np.ndarray | None = None,
        progress: ProgressCallback | None = None,
        chunk: int = 64,
    ) -> SequenceResult:
        files = {"file": ("frames.npz", frames_upload(frames, weights))}
        path = f"/v1/fit/sequence?chunk={chunk}"
        return SequenceResult.from_events(*(await self._stream(path, files, None, progress)))

    async def upgrade(
        self,
        sequence: str | os.PathLike[str] | bytes,
        progress: ProgressCallback | None = None,
        chunk: int = 256,
        sex: str | None = None,
        height_m: float | None = None,
        mass_kg: float | None = None,
    ) -> UpgradeOutput:
        files = {"file": upgrade_upload(sequence)}
        hints = hint_fields(sex, height_m, mass_kg)
        return UpgradeOutput.from_events(
            *(await self._stream(f"/v1/upgrade?chunk={chunk}", files, hints, progress))
        )

    async def _stream(
        self, path: str, files: dict[str, Any], data: dict[str, str] | None, progress: ProgressCallback | None
    ) -> tuple[list[dict[str, Any]], dict[str, Any]]:
        collector = EventCollector(progress)
        try:
            async with self._http.stream(
                "POST", path, files=files, data=data, headers={"accept": NDJSON}
            ) as r:
                if not r.is_success:
                    await r.aread()
                    raise_for_problem(r)
                async for line in r.aiter_lines():
                    if line.strip() and collector.feed(json.loads(line)):
                        break
        except httpx.HTTPError as exc:
            raise _transport_error(exc, self.base_url) from exc
        return collector.finish()


__all__ = ["AsyncClient", "Client", "ServerError"]
