"""End to end: the real server (``bodyfit serve`` in a subprocess, REST and gRPC on 127.0.0.1) answered
through the SDK; bad input does not stop it; SIGTERM stops it cleanly."""

from __future__ import annotations

import io
import os
import shutil
import signal
import time
from collections.abc import Iterator
from pathlib import Path

import httpx
import numpy as np
import pytest

from benchmarks.server_process import ServerProcess, start_server
from bodyfit.clients.batch import batch_upgrade
from bodyfit.clients.errors import InvalidRequestError, RequestTooLargeError
from bodyfit.clients.grpc_client import GrpcClient
from bodyfit.clients.rest_client import Client

ROOT = Path(__file__).resolve().parents[2]


@pytest.fixture(scope="module")
def server() -> Iterator[ServerProcess]:
    smpl = ROOT / "tests" / "data" / "smpl_format" / "smpl_like_model.npz"
    env = {"BODYFIT_MAX_UPLOAD_MB": "1", "BODYFIT_THREADS": "1", "BODYFIT_SMPL_MODEL": str(smpl)}
    process = start_server(env)
    yield process
    process.stop()


def test_rest_operations_through_the_sdk(server: ServerProcess) -> None:
    url = server.url
    with Client(url) as client:
        info = client.model_info()
        assert len(info.dof_names) == 46 and all(len(h) == 64 for h in info.assets["sha256"].values())
        body = client.synthesize(coordinates={"hip_flexion_r": 0.9, "knee_angle_r": 1.1})
        buf = io.BytesIO()
        np.savez(buf, points=body.vertices[0])
        fit = client.fit_scan(buf.getvalue(), format="npz")
        assert fit.fitted_as == "registered" and fit.confident
        knee = info.dof_names.index("knee_angle_r")
        assert abs(fit.coordinates[knee] - 1.1) < 0.05
        with pytest.raises(InvalidRequestError, match="knee_angle_r"):
            client.synthesize(coordinates={"knee_angle": 1.0})
        with pytest.raises(RequestTooLargeError, match=r"at most 1\.0 MiB"):
            client.fit_scan(os.urandom(2 * 2**20), format="ply")
        assert client.synthesize().vertices.shape == (1, 13348, 3)  # still serving
        metrics = httpx.get(f"{url}/metrics").text
        assert 'outcome="413",transport="rest"} 1.0' in metrics


def test_grpc_operations_through_the_sdk(server: ServerProcess) -> None:
    url, target = server.url, server.target
    with GrpcClient(target) as grpc_client, Client(url) as rest_client:
        assert grpc_client.model_info().dof_names == rest_client.model_info().dof_names
        over_grpc = grpc_client.synthesize(coordinates={"ankle_angle_l": 0.3})
        over_rest = rest_client.synthesize(coordinates={"ankle_angle_l": 0.3})
        assert np.array_equal(over_grpc.vertices, over_rest.vertices)
        with pytest.raises(InvalidRequestError, match="ankle_angle_l"):
            grpc_client.synthesize(coordinates={"ankle_angle_l": 3.0})
    metrics = httpx.get(f"{url}/metrics").text
    assert 'operation="Synthesize",outcome="OK",transport="grpc"' in metrics


def test_batch_upgrade_against_the_server(server: ServerProcess, tmp_path: Path) -> None:
    url = server.url
    (tmp_path / "data" / "s1").mkdir(parents=True)
    shutil.copy(
        ROOT / "tests" / "data" / "smpl_format" / "cmu_131_smpl.npz", tmp_path / "data" / "s1" / "walk.npz"
    )
    (tmp_path / "data" / "s1" / "bad.npz").write_bytes(b"not an npz")
    report = batch_upgrade(tmp_path / "data", tmp_path / "out", concurrency=2, backend=url, progress=False)
    assert report.done == ["s1/walk.npz"] and "not a readable .npz" in report.failed["s1/bad.npz"]
    assert np.load(tmp_path / "out" / "s1" / "walk.npz")["coordinates"].shape == (60, 46)


def test_sigterm_stops_the_server(server: ServerProcess) -> None:
    url, proc = server.url, server.proc
    assert httpx.get(f"{url}/healthz").json() == {"status": "ok"}
    proc.send_signal(signal.SIGTERM)
    code = proc.wait(30)
    time.sleep(0.5)  # the log's last lines
    log = server.log()
    # uvicorn shuts down gracefully, then re-raises the signal so the exit status tells it was stopped.
    assert code in (0, -signal.SIGTERM) and "Finished server process" in log, log[-2000:]
