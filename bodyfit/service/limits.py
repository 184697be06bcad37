"""Request limits the core enforces (configured by the transport's settings)."""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class Limits:
    """max_upload_bytes: largest accepted upload; max_decompressed_bytes: the most an uploaded file's arrays
    may decompress to (checked from their headers before decompressing); max_points: points in one scan
    (and twice as many faces); max_request_bytes: the working memory one request may need, estimated from
    its validated headers before any work (sequences and upgrades: frames times their measured cost, so
    fewer frames than ``max_frames`` may fit); max_frames: frames in one sequence; max_batch: bodies in one
    synthesize call; max_seconds: wall time of one request; max_concurrent: fits / upgrades run at once
    (others wait up to ``queue_seconds``, then get "busy")."""

    max_upload_bytes: int = 200 * 1024 * 1024
    max_request_bytes: int = 4096 * 1024 * 1024
    max_decompressed_bytes: int = 1024 * 1024 * 1024
    max_points: int = 2_000_000
    max_frames: int = 20_000
    max_batch: int = 256
    max_seconds: float = 600.0
    max_concurrent: int = 1
    queue_seconds: float = 30.0
