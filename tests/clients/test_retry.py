"""The SDK's retry policy with an injected clock, randomness and sleeper (nothing sleeps, nothing is
timed): full-jitter bounds, Retry-After, what is never retried, the time budget; then through a real
client over a fake transport."""

from __future__ import annotations

import asyncio
import random
from collections.abc import Callable
from datetime import UTC, datetime
from email.utils import format_datetime

import grpc
import httpx
import numpy as np
import pytest

from bodyfit.clients.core import RetryPolicy, parse_retry_after, safe_to_retry
from bodyfit.clients.errors import (
    BodyfitClientError,
    ConnectionFailedError,
    InvalidRequestError,
    NotFoundError,
    RequestTimeoutError,
    RequestTooLargeError,
    ServerBusyError,
    ServerError,
)
from bodyfit.clients.grpc_client import GrpcClient
from bodyfit.clients.rest_client import AsyncClient, Client


class FakeTime:
    """A clock that only moves when the code under test sleeps; the sleeps are recorded."""

    def __init__(self) -> None:
        self.now = 0.0
        self.sleeps: list[float] = []

    def clock(self) -> float:
        return self.now

    def sleep(self, seconds: float) -> None:
        self.sleeps.append(seconds)
        self.now += seconds

    async def async_sleep(self, seconds: float) -> None:
        self.sleep(seconds)

    def policy(self, rand: Callable[[], float] = lambda: 0.5, **kwargs: float) -> RetryPolicy:
        return RetryPolicy(
            clock=self.clock,
            random=rand,
            sleep=self.sleep,
            async_sleep=self.async_sleep,
            **kwargs,  # type: ignore[arg-type]
        )


def busy(retry_after: float | None = None) -> ServerBusyError:
    return ServerBusyError("the model is still loading", 503, retry_after=retry_after)


def test_full_jitter_stays_within_the_exponential_ceiling() -> None:
    rng = random.Random(7)
    policy = RetryPolicy(base_s=0.5, cap_s=5.0, random=rng.random)
    for retry in range(12):
        ceiling = min(5.0, 0.5 * 2**retry)
        waits = [policy.backoff(retry) for _ in range(200)]
        assert all(0.0 <= w < ceiling for w in waits)
        assert max(waits) > 0.8 * ceiling and min(waits) < 0.2 * ceiling  # spread over the whole range
    assert RetryPolicy(random=lambda: 0.0).backoff(3) == 0.0
    assert RetryPolicy(base_s=0.5, cap_s=5.0, random=lambda: 1.0).backoff(1000) == 5.0  # no overflow


def test_retry_after_is_a_floor_on_the_wait() -> None:
    t = FakeTime()
    retrying = t.policy(rand=lambda: 0.0).start(idempotent=True)
    assert retrying.wait(busy(retry_after=5.0)) == 5.0
    assert retrying.wait(busy(retry_after=None)) == 0.0
    high = t.policy(rand=lambda: 0.99, base_s=4.0, cap_s=8.0).start(idempotent=True)
    assert high.wait(busy(retry_after=1.0)) == pytest.approx(0.99 * 4.0)  # the backoff is longer


@pytest.mark.parametrize(
    "error",
    [
        InvalidRequestError("knee_angle_r: out of range", 422, "coordinates"),
        RequestTooLargeError("at most 1 MiB", 413),
        NotFoundError("no such operation", 404),
        ServerError("bug", 500),
        RequestTimeoutError("no answer in time"),  # the work may be running: never sent again
    ],
)
def test_client_errors_timeouts_and_bugs_are_never_retried(error: BodyfitClientError) -> None:
    t = FakeTime()
    assert not safe_to_retry(error, idempotent=True, answered=False)
    assert t.policy().start(idempotent=True).wait(error) is None
    with pytest.raises(type(error)):
        t.policy().start(idempotent=True).after(error)


def test_only_requests_that_never_left_are_sent_again_for_non_idempotent_calls() -> None:
    never_sent = ConnectionFailedError("connection refused", sent=False)
    cut = ConnectionFailedError("the connection was reset", sent=True)
    connect_timeout = RequestTimeoutError("connect timeout", sent=False)
    assert safe_to_retry(never_sent, idempotent=False, answered=False)
    assert safe_to_retry(connect_timeout, idempotent=False, answered=False)
    assert not safe_to_retry(cut, idempotent=False, answered=False)  # the fit may be running
    assert not safe_to_retry(busy(), idempotent=False, answered=False)
    assert safe_to_retry(cut, idempotent=True, answered=False)
    assert safe_to_retry(busy(), idempotent=True, answered=False)
    for error in (never_sent, cut, busy()):  # events came: the work ran, whatever the call
        assert not safe_to_retry(error, idempotent=True, answered=True)


def test_the_budget_ends_the_retries_and_covers_the_start_up() -> None:
    """With the server's Retry-After of 5 s the default 20 s budget tries at 0, 5, 10 and 15 s: a model
    that loads in up to 15 s is seen ready."""
    t = FakeTime()
    retrying = t.policy().start(idempotent=True)
    while (wait := retrying.wait(busy(retry_after=5.0))) is not None:
        t.sleep(wait)
    assert t.sleeps == [5.0, 5.0, 5.0] and t.now == 15.0
    assert RetryPolicy().budget_s >= 15.0
    # without a hint: jittered waits until the next attempt would start past the budget
    t = FakeTime()
    retrying = t.policy(rand=lambda: 0.999, budget_s=10.0).start(idempotent=True)
    while (wait := retrying.wait(ConnectionFailedError("refused", sent=False))) is not None:
        t.sleep(wait)
    assert t.now <= 10.0 and len(t.sleeps) >= 4 and t.sleeps[:3] == pytest.approx([0.4995, 0.999, 1.998])
    assert t.now + min(5.0, 0.5 * 2 ** len(t.sleeps)) * 0.999 > 10.0


def test_the_retry_count_is_a_limit_too() -> None:
    t = FakeTime()
    retrying = t.policy(rand=lambda: 0.0, retries=2).start(idempotent=True)
    assert [retrying.wait(busy()) for _ in range(3)] == [0.0, 0.0, None]


def test_parse_retry_after() -> None:
    now = datetime(2026, 1, 2, 3, 4, 5, tzinfo=UTC).timestamp()
    later = format_datetime(datetime(2026, 1, 2, 3, 4, 12, tzinfo=UTC), usegmt=True)
    assert parse_retry_after("5") == 5.0 and parse_retry_after(" 2.5 ") == 2.5
    assert parse_retry_after(later, now=now) == pytest.approx(7.0)
    assert parse_retry_after("Thu, 01 Jan 2026 00:00:00 GMT", now=now) == 0.0  # a date in the past
    assert parse_retry_after("-3") == 0.0
    for unreadable in (None, "", "soon", "Mon, 99 Foo 2026"):
        assert parse_retry_after(unreadable) is None


# -- through the REST clients over a fake transport ---------------------------------------------------

MODEL = {
    "dofs": [{"name": "knee_angle_r", "min": -0.1, "max": 2.0, "unit": "rad"}],
    "shape": {"n_bone": 2, "n_identity": 3},
    "mesh": {"n_vertices": 4, "n_faces": 2},
    "joint_names": ["pelvis"],
    "assets": {"format": "test", "sources": {}, "sha256": {}},
    "version": "1",
}
PROBLEM = {"content-type": "application/problem+json"}


def loading(retry_after: str | None) -> httpx.Response:
    headers = dict(PROBLEM, **({"retry-after": retry_after} if retry_after else {}))
    doc = {"kind": "unavailable", "detail": "the model is still loading", "status": 503}
    return httpx.Response(503, json=doc, headers=headers)


def scripted(answers: list[httpx.Response | Exception]) -> tuple[httpx.MockTransport, list[str]]:
    """A transport that answers (or fails) in order, recording the paths it was sent."""
    paths: list[str] = []

    def handler(request: httpx.Request) -> httpx.Response:
        paths.append(request.url.path)
        answer = answers.pop(0)
        if isinstance(answer, Exception):
            raise answer
        return answer

    return httpx.MockTransport(handler), paths


def test_a_loading_server_is_waited_for_as_it_asks() -> None:
    t = FakeTime()
    transport, paths = scripted([loading("5"), loading("5"), httpx.Response(200, json=MODEL)])
    client = Client(http_client=httpx.Client(transport=transport, base_url="http://t"), retry=t.policy())
    assert client.model_info().dof_names == ("knee_angle_r",)
    assert paths == ["/v1/model"] * 3 and t.sleeps == [5.0, 5.0]


def test_the_async_client_retries_the_same_way() -> None:
    t = FakeTime()
    transport, paths = scripted([loading("5"), loading(None), httpx.Response(200, json=MODEL)])

    async def run() -> tuple[str, ...]:
        http = httpx.AsyncClient(transport=transport, base_url="http://t")
        async with AsyncClient(http_client=http, retry=t.policy(rand=lambda: 0.5)) as client:
            return (await client.model_info()).dof_names

    assert asyncio.run(run()) == ("knee_angle_r",)
    assert paths == ["/v1/model"] * 3 and t.sleeps == [5.0, 0.5]  # Retry-After, then 0.5 * 2**1 * 0.5


def test_a_server_still_loading_after_the_budget_raises_busy_with_its_hint() -> None:
    t = FakeTime()
    transport, paths = scripted([loading("5") for _ in range(10)])
    client = Client(http_client=httpx.Client(transport=transport, base_url="http://t"), retry=t.policy())
    with pytest.raises(ServerBusyError, match="still loading") as err:
        client.model_info()
    assert err.value.retry_after == 5.0 and err.value.status == 503
    assert len(paths) == 4 and t.sleeps == [5.0, 5.0, 5.0]


def test_a_fit_is_sent_again_only_when_it_never_left() -> None:
    t = FakeTime()
    request = httpx.Request("POST", "http://t/v1/fit/scan")
    refused = httpx.ConnectError("connection refused", request=request)
    transport, paths = scripted([refused, refused, loading("1")])
    client = Client(http_client=httpx.Client(transport=transport, base_url="http://t"), retry=t.policy())
    with pytest.raises(ServerBusyError):  # busy: the upload reached the server, the fit is not resent
        client.fit_scan(np.zeros((5, 3)))
    assert paths == ["/v1/fit/scan"] * 3 and len(t.sleeps) == 2

    t = FakeTime()
    transport, paths = scripted([httpx.ReadError("connection reset", request=request)])
    client = Client(http_client=httpx.Client(transport=transport, base_url="http://t"), retry=t.policy())
    with pytest.raises(ConnectionFailedError, match="cannot reach") as cut:
        client.fit_scan(np.zeros((5, 3)))
    assert cut.value.sent and paths == ["/v1/fit/scan"] and t.sleeps == []


def test_client_errors_are_raised_at_once() -> None:
    t = FakeTime()
    doc = {"kind": "invalid_argument", "detail": "out of range", "field": "coordinates", "status": 422}
    transport, paths = scripted([httpx.Response(422, json=doc, headers=PROBLEM)])
    client = Client(http_client=httpx.Client(transport=transport, base_url="http://t"), retry=t.policy())
    with pytest.raises(InvalidRequestError, match="coordinates: out of range"):
        client.synthesize(coordinates={"knee_angle_r": 7.0})
    assert paths == ["/v1/synthesize"] and t.sleeps == []


def test_retries_argument_and_policy() -> None:
    """``retries`` caps the policy's count; the default policy covers the server's start-up."""
    assert Client(retries=0).retry.retries == 0
    policy = RetryPolicy(budget_s=3.0)
    assert Client(retry=policy, retries=5).retry == RetryPolicy(budget_s=3.0, retries=5)
    assert Client().retry == RetryPolicy() and RetryPolicy().budget_s == 20.0


def test_grpc_sends_a_fit_again_only_when_no_connection_was_made() -> None:
    from tests.clients.test_parity import FakeStub, RpcFailure, grpc_answers

    refused = RpcFailure(
        grpc.StatusCode.UNAVAILABLE, "failed to connect to all addresses; Connection refused"
    )
    cut = RpcFailure(grpc.StatusCode.UNAVAILABLE, "Socket closed")
    for failures, outcome in (([refused, refused], "registered"), ([cut], ConnectionFailedError)):
        t, sent = FakeTime(), list[object]()

        def fit_scan(
            request: object, failures: list[RpcFailure] = failures, sent: list[object] = sent
        ) -> list[object]:
            sent.append(request)
            return [failures.pop(0)] if failures else grpc_answers()["FitScan"](request)

        with GrpcClient("127.0.0.1:1", retry=t.policy()) as client:
            client._stub = FakeStub({"FitScan": fit_scan}, aio=False)  # type: ignore[assignment]
            if outcome == "registered":
                assert client.fit_scan(np.zeros((5, 3))).fitted_as == "registered"
                assert len(sent) == 3 and len(t.sleeps) == 2
            else:
                with pytest.raises(ConnectionFailedError, match="Socket closed"):
                    client.fit_scan(np.zeros((5, 3)))
                assert len(sent) == 1 and t.sleeps == []
