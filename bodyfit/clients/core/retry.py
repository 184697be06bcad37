"""When to send a request again, and after how long: the SDK's one retry policy.

Exponential backoff with full jitter (a wait drawn uniformly from ``[0, min(cap, base * 2**n))``), never
shorter than the server's ``Retry-After``; only what is safe is retried (:func:`safe_to_retry`), and only
while the next attempt would start less than ``budget_s`` after the first. Clock, randomness and sleeps are
injectable, so tests run the policy without waiting.
"""

from __future__ import annotations

import asyncio
import random
import time
from collections.abc import Awaitable, Callable
from dataclasses import dataclass, field
from email.utils import parsedate_to_datetime

from bodyfit.clients.errors import BodyfitClientError

DEFAULT_RETRIES = 20
"""Retries at most; with the defaults below, the budget ends the retries first."""
DEFAULT_BUDGET_S = 20.0
"""Every retry starts less than this after the first attempt. The server takes about 3-12 s to load and
asks for ``Retry-After: 5`` while it does, so attempts at 0, 5, 10 and 15 s see it ready."""


@dataclass(frozen=True)
class RetryPolicy:
    """How the clients retry. ``retries``: attempts after the first, at most; ``budget_s``: a retry
    starts less than this after the first attempt, or not at all; ``base_s`` / ``cap_s``: the backoff's
    first and largest ceiling. ``clock``, ``random``, ``sleep`` and ``async_sleep`` are injectable for
    tests."""

    retries: int = DEFAULT_RETRIES
    budget_s: float = DEFAULT_BUDGET_S
    base_s: float = 0.5
    cap_s: float = 5.0
    clock: Callable[[], float] = field(default=time.monotonic, compare=False)
    random: Callable[[], float] = field(default=random.random, compare=False)
    sleep: Callable[[float], None] = field(default=time.sleep, compare=False)
    async_sleep: Callable[[float], Awaitable[None]] = field(default=asyncio.sleep, compare=False)

    def backoff(self, retry: int) -> float:
        """The jittered wait before retry number ``retry`` (0 for the first): uniform in
        ``[0, min(cap_s, base_s * 2**retry))``."""
        return self.random() * min(self.cap_s, self.base_s * 2.0 ** min(retry, 64))

    def start(self, idempotent: bool) -> Retrying:
        """The state of one call's retries, its clock started now."""
        return Retrying(self, idempotent, self.clock())


def safe_to_retry(error: BodyfitClientError, idempotent: bool, answered: bool) -> bool:
    """Whether sending again cannot do the work twice or hide a real error: never once the server has
    streamed events (``answered``); a request that surely never left (a connection never made), always;
    a busy or unreachable server (:attr:`BodyfitClientError.retryable`), for idempotent calls only. Never
    a 4xx, a timeout after sending or a bug."""
    if answered:
        return False
    if not error.sent:
        return True
    return idempotent and error.retryable


@dataclass
class Retrying:
    """One call's retries: :meth:`wait` says how long to wait before the next attempt, or None to give
    up; :meth:`after` the same, raising the error when giving up."""

    policy: RetryPolicy
    idempotent: bool
    began: float
    done: int = 0

    def wait(self, error: BodyfitClientError, answered: bool = False) -> float | None:
        p = self.policy
        if self.done >= p.retries or not safe_to_retry(error, self.idempotent, answered):
            return None
        wait = max(error.retry_after or 0.0, p.backoff(self.done))
        if p.clock() - self.began + wait >= p.budget_s:
            return None
        self.done += 1
        return wait

    def after(self, error: BodyfitClientError, answered: bool = False) -> float:
        """The wait before sending again after ``error``.

        Raises:
            BodyfitClientError: ``error`` itself, when it is not retried."""
        wait = self.wait(error, answered)
        if wait is None:
            raise error
        return wait


def parse_retry_after(value: str | None, now: float | None = None) -> float | None:
    """Seconds to wait from a ``Retry-After`` header: delay-seconds or an HTTP date (``now``: the current
    Unix time, for tests); None when absent or unreadable, never negative."""
    if value is None or not value.strip():
        return None
    text = value.strip()
    try:
        return max(0.0, float(text))
    except ValueError:
        pass
    try:
        when = parsedate_to_datetime(text)
    except (TypeError, ValueError, IndexError):
        return None
    if when.tzinfo is None:  # an HTTP date is GMT
        return None
    return max(0.0, when.timestamp() - (time.time() if now is None else now))
