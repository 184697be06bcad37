"""Server settings, read from the environment (prefix ``BODYFIT_``) or given explicitly."""

from __future__ import annotations

from pathlib import Path

from pydantic import Field
from pydantic_settings import BaseSettings, SettingsConfigDict

from bodyfit.service.limits import Limits


class ServiceSettings(BaseSettings):
    """host / rest_port / grpc_port: where the service listens (gRPC off when grpc_port is 0); assets: the
    asset folder (default the checkout's assets/); smpl_model: an SMPL-family model file for upgrades
    (BODYFIT_SMPL_MODEL; the operator's own, none ships); threads: ONNX Runtime and torch threads;
    scan_processes: 2 runs part of each raw-scan fit in a helper process (faster on two or more cores,
    0.5 GB more memory), 1 keeps it in the server's process; max_decompressed_mb
    (BODYFIT_MAX_DECOMPRESSED_MB): the most an uploaded .npz's arrays or a compressed PCD may decompress to;
    max_request_mb (BODYFIT_MAX_REQUEST_MB): the working memory one request may need (estimated from its
    headers; sequences and upgrades over it get 413 with how many frames fit);
    the rest are request limits (see :class:`bodyfit.service.limits.Limits`)."""

    model_config = SettingsConfigDict(env_prefix="BODYFIT_", extra="ignore")

    host: str = "127.0.0.1"
    rest_port: int = Field(default=8000, ge=0, le=65535)
    grpc_port: int = Field(default=50051, ge=0, le=65535)
    assets: Path | None = None
    smpl_model: Path | None = None
    threads: int | None = Field(default=None, ge=1)
    scan_processes: int = Field(default=2, ge=1, le=2)
    max_upload_mb: float = Field(default=200.0, gt=0)
    max_decompressed_mb: float = Field(default=1024.0, gt=0)
    max_request_mb: float = Field(default=4096.0, gt=0)
    max_points: int = Field(default=2_000_000, ge=300)
    max_frames: int = Field(default=20_000, ge=1)
    max_batch: int = Field(default=256, ge=1)
    max_seconds: float = Field(default=600.0, gt=0)
    max_concurrent: int = Field(default=1, ge=1)
    queue_seconds: float = Field(default=30.0, ge=0)

    def limits(self) -> Limits:
        return Limits(
            max_upload_bytes=int(self.max_upload_mb * 2**20),
            max_decompressed_bytes=int(self.max_decompressed_mb * 2**20),
            max_request_bytes=int(self.max_request_mb * 2**20),
            max_points=self.max_points,
            max_frames=self.max_frames,
            max_batch=self.max_batch,
            max_seconds=self.max_seconds,
            max_concurrent=self.max_concurrent,
            queue_seconds=self.queue_seconds,
        )
