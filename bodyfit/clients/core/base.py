"""The clients' shared body: the public methods (declared once, from :mod:`.operations`) and the call
loop (send, fold the events into a result, retry by the :class:`~.retry.RetryPolicy`). A transport only
implements ``_send``: an operation in, its events out, or a typed error raised."""

from __future__ import annotations

import functools
import inspect
import typing
from collections.abc import AsyncGenerator, Callable, Coroutine, Generator
from contextlib import aclosing, closing
from dataclasses import replace
from typing import Any, Concatenate, ParamSpec, Self, TypeVar

from bodyfit.clients.core import operations as ops
from bodyfit.clients.core.operations import Event, Operation
from bodyfit.clients.core.retry import RetryPolicy
from bodyfit.clients.errors import BodyfitClientError
from bodyfit.clients.results import EventCollector

P = ParamSpec("P")
R = TypeVar("R")
F = TypeVar("F", bound=Callable[..., Any])


def retry_policy(retries: int, retry: RetryPolicy | None) -> RetryPolicy:
    """``retry`` (or the default policy) with at most ``retries`` retries (the fewer of the two counts)."""
    policy = retry or RetryPolicy()
    return replace(policy, retries=min(retries, policy.retries))


def sync_method(build: Callable[P, Operation[R]]) -> Callable[Concatenate[SyncClientCore, P], R]:
    """A client method with ``build``'s parameters and documentation that runs its operation."""

    @functools.wraps(build)
    def method(self: SyncClientCore, /, *args: P.args, **kwargs: P.kwargs) -> R:
        return self._call(build(*args, **kwargs))

    return _signed(method, build)


def async_method(
    build: Callable[P, Operation[R]],
) -> Callable[Concatenate[AsyncClientCore, P], Coroutine[Any, Any, R]]:
    """:func:`sync_method`, awaited."""

    @functools.wraps(build)
    async def method(self: AsyncClientCore, /, *args: P.args, **kwargs: P.kwargs) -> R:
        return await self._call(build(*args, **kwargs))

    return _signed(method, build)


def _signed(method: F, build: Callable[..., Operation[Any]]) -> F:
    """``method`` introspected as ``build``'s parameters after ``self``, returning its operation's result
    (for help(), IDEs and documentation tools)."""
    signature = inspect.signature(build)
    (result,) = typing.get_args(typing.get_type_hints(build)["return"])
    self = inspect.Parameter("self", inspect.Parameter.POSITIONAL_OR_KEYWORD)
    method.__signature__ = signature.replace(  # type: ignore[attr-defined]
        parameters=[self, *signature.parameters.values()], return_annotation=result
    )
    return method


class SyncClientCore:
    """The synchronous clients' methods and call loop over ``_send``."""

    retry: RetryPolicy
    # unary calls: idempotent, retried when the server is busy or unreachable
    model_info = sync_method(ops.model_info)
    synthesize = sync_method(ops.synthesize)
    synthesize_file = sync_method(ops.synthesize_file)
    measure = sync_method(ops.measure)

    def _send(self, op: Operation[Any]) -> Generator[Event, None, None]:
        raise NotImplementedError

    def close(self) -> None:
        raise NotImplementedError

    def __enter__(self) -> Self:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def _call(self, op: Operation[R]) -> R:
        retrying = self.retry.start(op.idempotent)
        while True:
            events = EventCollector(op.progress, op.parse)
            try:
                with closing(self._send(op)) as stream:
                    for event in stream:
                        if events.feed(event):
                            break
            except BodyfitClientError as error:
                self.retry.sleep(retrying.after(error, answered=events.events > 0))
                continue
            return op.finish(*events.finish())

    # streamed calls: progress, then the result; sent again only when the request never left
    fit_scan = sync_method(ops.fit_scan)
    fit_sequence = sync_method(ops.fit_sequence)
    upgrade = sync_method(ops.upgrade)


class AsyncClientCore:
    """The asynchronous clients' methods (awaited) and call loop over ``_send``."""

    # unary calls: idempotent, retried when the server is busy or unreachable
    model_info = async_method(ops.model_info)
    synthesize = async_method(ops.synthesize)
    synthesize_file = async_method(ops.synthesize_file)
    measure = async_method(ops.measure)
    retry: RetryPolicy

    def _send(self, op: Operation[Any]) -> AsyncGenerator[Event, None]:
        raise NotImplementedError

    async def _close(self) -> None:
        raise NotImplementedError

    async def __aenter__(self) -> Self:
        return self

    async def __aexit__(self, *exc: object) -> None:
        await self._close()

    async def _call(self, op: Operation[R]) -> R:
        retrying = self.retry.start(op.idempotent)
        while True:
            events = EventCollector(op.progress, op.parse)
            try:
                async with aclosing(self._send(op)) as stream:
                    async for event in stream:
                        if events.feed(event):
                            break
            except BodyfitClientError as error:
                await self.retry.async_sleep(retrying.after(error, answered=events.events > 0))
                continue
            return op.finish(*events.finish())

    # streamed calls: progress, then the result; sent again only when the request never left
    fit_scan = async_method(ops.fit_scan)
    fit_sequence = async_method(ops.fit_sequence)
    upgrade = async_method(ops.upgrade)
