"""Inline work budgeted per client, as simulation jobs are: what one client's answers may cost an HTTP worker.

The service answers what the tables and the Roman default's field grid hold inline, inside the HTTP
worker (a default solve, a batch, the page's curves). Each such answer has a cost *estimate* before
it runs -- a count of units of work times what one unit has cost in this process (:class:`CostModel`,
measured as it serves: the CPU time the work's own thread used) -- and a *charge* after, what it
measured. Every client (its API key, else its socket's address; ``deps.client_key``) has a token
bucket of CPU seconds (:class:`Buckets`): it refills at ``inline_cpu_share`` CPU-seconds per second
up to ``inline_cpu_burst_s``; an answer whose estimate the client's balance does not cover is
refused with 429 and ``Retry-After`` (the time the bucket takes to hold it), and the measured cost
replaces the reservation when the answer is done. All clients together draw on a second bucket of
``inline_cpu_total_share``, so many clients cannot take a worker either. An answer that costs
(almost) nothing (a paper-table solve, a cached answer) is charged but never refused, so a client
that shares an address with an abuser keeps its cheap answers.

The units, so the budget follows the code's speed (a faster solver costs less without a setting
changed): a field-grid node read and answered (a Roman-default solve at a position reads one, the
SCA range without one reads every node of the SCA; a batch counts its rows' nodes), a table solve
(the paper's tables, the field-point tables), and one answer of a page or curve route.

Answers that are a pure function of the request -- the default without a position, the page's
curves -- are kept (:class:`AnswerCache`, bounded): a repeated request costs a dictionary look-up.
"""

from __future__ import annotations

import contextvars
import math
import threading
import time
from collections import OrderedDict
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from typing import Any

from nlpsf.checks import InputError

from .errors import Throttled

#: Units of inline work: a field-grid node read and answered; a table solve; a page or curve answer.
NODE = "node"
TABLE = "table"
#: What a unit costs before this process has measured one (CPU s): deliberately high, so the first
#: requests are admitted on a cautious estimate; every measurement moves it toward the truth.
PRIOR_S = {NODE: 0.005, TABLE: 0.001}
PRIOR_ROUTE_S = 0.05
#: Weight of each new measurement in a unit's running cost (an exponential average).
LEARNING_RATE = 0.2
#: An estimate under this many CPU seconds is never refused (only charged).
FREE_S = 0.002
#: Clients remembered at once per HTTP worker; the longest idle (whose buckets are full again) go first.
MAX_CLIENTS = 100_000


class WorkLimit(InputError):
    """One request that costs more than a client's whole budget: it can never be admitted (a 422
    naming the setting; a batch is split, a costlier answer sent to POST /solve as a job)."""

    def __init__(self, argument: str, limit: str, message: str):
        super().__init__(argument, message)
        self.limit = limit


class Buckets:
    """Token buckets of CPU seconds by key: each refills at ``rate`` per second up to ``burst``."""

    def __init__(self, rate: float, burst: float, max_keys: int = MAX_CLIENTS):
        self.rate = rate
        self.burst = burst
        self.max_keys = max_keys
        self._balance: OrderedDict[str, tuple[float, float]] = OrderedDict()  # key -> (balance, as of)

    def balance(self, key: str, now: float) -> float:
        balance, then = self._balance.get(key, (self.burst, now))
        return min(self.burst, balance + (now - then) * self.rate)

    def set(self, key: str, balance: float, now: float) -> None:
        self._balance[key] = (balance, now)
        self._balance.move_to_end(key)
        while len(self._balance) > self.max_keys:
            self._balance.popitem(last=False)

    def wait_s(self, key: str, amount: float, now: float) -> float:
        """Seconds until the bucket holds ``amount`` (0: it does now)."""
        return max(0.0, (amount - self.balance(key, now)) / self.rate)


class CostModel:
    """What one unit of each kind of inline work costs in this process (CPU s), as measured."""

    def __init__(self) -> None:
        self._per_unit: dict[str, float] = {}

    def per_unit(self, kind: str) -> float:
        return self._per_unit.get(kind, PRIOR_S.get(kind, PRIOR_ROUTE_S))

    def estimate(self, kind: str, units: float) -> float:
        return units * self.per_unit(kind)

    def observe(self, kind: str, units: float, used_s: float) -> None:
        if units > 0 and used_s >= 0:
            measured = used_s / units
            known = self._per_unit.get(kind)
            self._per_unit[kind] = measured if known is None else known + LEARNING_RATE * (measured - known)


class AnswerCache:
    """Answers that are pure functions of their request, by a canonical key, up to ``max_bytes`` in
    all (each entry's size given when it is put); the least recently used go first."""

    def __init__(self, max_bytes: int):
        self.max_bytes = max_bytes
        self.size = 0
        self._entries: OrderedDict[Any, tuple[Any, int]] = OrderedDict()
        self._lock = threading.Lock()

    def get(self, key: Any) -> Any:
        with self._lock:
            entry = self._entries.get(key)
            if entry is None:
                return None
            self._entries.move_to_end(key)
            return entry[0]

    def put(self, key: Any, value: Any, size: int) -> None:
        if size > self.max_bytes // 16:
            return  # one answer may not crowd out the rest
        with self._lock:
            if (old := self._entries.pop(key, None)) is not None:
                self.size -= old[1]
            self._entries[key] = (value, size)
            self.size += size
            while self.size > self.max_bytes and self._entries:
                _, (_, dropped) = self._entries.popitem(last=False)
                self.size -= dropped


@dataclass
class Meter:
    """One request's inline work: whose it is, what was reserved for it and what it used (CPU s)."""

    client: str
    reserved_s: float = 0.0
    used_s: float = 0.0


class InlineBudget:
    """The per-client and total buckets, the cost model and the answer cache of one HTTP worker."""

    def __init__(self, share: float, burst_s: float, total_share: float, cache_bytes: int = 32 * 1024**2):
        self.clients = Buckets(share, burst_s)
        self.total = Buckets(total_share, 2 * burst_s)
        self.costs = CostModel()
        self.answers = AnswerCache(cache_bytes)
        self._lock = threading.Lock()

    @property
    def burst_s(self) -> float:
        return self.clients.burst

    def check_size(self, estimate_s: float, argument: str, what: str) -> None:
        """Refuse (422) a request that alone costs more than a client's whole budget."""
        if estimate_s > self.clients.burst:
            raise WorkLimit(
                argument,
                "inline_cpu_burst_s",
                f"{what} would cost about {estimate_s:.3g} CPU-s inline, more than one client's budget of "
                f"{self.clients.burst:g} CPU-s (the setting inline_cpu_burst_s); split it into smaller requests",
            )

    def admit(self, meter: Meter, estimate_s: float) -> None:
        """Reserve ``estimate_s`` for ``meter``'s client, or raise :class:`Throttled` (an estimate
        under :data:`FREE_S` is reserved without a check)."""
        now = time.monotonic()
        with self._lock:
            mine = self.clients.balance(meter.client, now)
            everyone = self.total.balance("", now)
            if estimate_s >= FREE_S:
                need = min(estimate_s, self.clients.burst)
                if mine < need:
                    wait = self.clients.wait_s(meter.client, need, now)
                    raise Throttled(
                        f"your share of the service's inline CPU is used (the setting inline_cpu_share, "
                        f"{self.clients.rate:g} CPU-s per s per HTTP worker); retry after {math.ceil(wait)} s",
                        "inline_cpu_share",
                        wait,
                    )
                if everyone < min(estimate_s, self.total.burst):
                    wait = self.total.wait_s("", min(estimate_s, self.total.burst), now)
                    raise Throttled(
                        f"the service's inline CPU is fully used by its clients (the setting inline_cpu_total_share, "
                        f"{self.total.rate:g} CPU-s per s per HTTP worker); retry after {math.ceil(wait)} s",
                        "inline_cpu_total_share",
                        wait,
                    )
            self.clients.set(meter.client, mine - estimate_s, now)
            self.total.set("", everyone - estimate_s, now)
        meter.reserved_s += estimate_s

    def settle(self, meter: Meter) -> None:
        """Charge what ``meter`` used in place of what was reserved for it."""
        difference = meter.used_s - meter.reserved_s
        if difference == 0.0:
            return
        now = time.monotonic()
        with self._lock:
            self.clients.set(meter.client, self.clients.balance(meter.client, now) - difference, now)
            self.total.set("", self.total.balance("", now) - difference, now)
        meter.reserved_s = meter.used_s


@dataclass
class Work:
    budget: InlineBudget
    meter: Meter


#: The request in progress: its budget and meter (set by ``InlineWork``; copied into the threads the
#: request's work runs in, so ``metered`` charges the right client).
ACTIVE: contextvars.ContextVar[Work | None] = contextvars.ContextVar("nlpsf_inline_work", default=None)


def active() -> Work | None:
    return ACTIVE.get()


def admit(kind: str, units: float) -> None:
    """Reserve the estimated cost of ``units`` of ``kind`` for the request in progress (a no-op outside one)."""
    work = ACTIVE.get()
    if work is not None:
        work.budget.admit(work.meter, work.budget.costs.estimate(kind, units))


def estimate(kind: str, units: float) -> float:
    work = ACTIVE.get()
    return work.budget.costs.estimate(kind, units) if work is not None else 0.0


@contextmanager
def metered(kind: str, units: float) -> Iterator[None]:
    """Measure the CPU time of the work inside (this thread's), charge it to the request in progress
    and teach the cost model what a unit of ``kind`` costs."""
    start = time.thread_time()
    try:
        yield
    finally:
        used = time.thread_time() - start
        work = ACTIVE.get()
        if work is not None:
            work.meter.used_s += used
            work.budget.costs.observe(kind, units, used)


def metered_call(function: Callable[..., Any], kind: str, units: float = 1.0) -> Callable[..., Any]:
    """``function`` run inside :func:`metered` (for a route's endpoint)."""
    import functools
    import inspect

    if inspect.iscoroutinefunction(function):

        @functools.wraps(function)
        async def run_async(*args: Any, **kwargs: Any) -> Any:
            with metered(kind, units):
                return await function(*args, **kwargs)

        return run_async

    @functools.wraps(function)
    def run(*args: Any, **kwargs: Any) -> Any:
        with metered(kind, units):
            return function(*args, **kwargs)

    return run


# --- the middleware: whose request it is, and the page's pure GET answers -------------------------


def client_key(scope: Any) -> str:
    """Whose share a request counts against: its API key (``security.ApiKey`` puts the key's hash in
    the scope's state), else the socket's address -- the peer's, unless ``forwarded_allow_ips`` names
    the peer as a trusted proxy (then uvicorn has put the forwarded client there)."""
    key = (scope.get("state") or {}).get("client")
    if key is not None:
        return key
    client = scope.get("client")
    return f"address:{client[0] if client else 'unknown'}"


def canonical_query(query_string: bytes) -> tuple[tuple[str, str], ...]:
    """A query as a cache key: its parameters by name (a name's repeated values keep their order)."""
    from urllib.parse import parse_qsl

    pairs = parse_qsl(query_string.decode("latin-1"), keep_blank_values=True)
    return tuple(sorted(pairs, key=lambda pair: pair[0]))


class InlineWork:
    """ASGI middleware around the API's routes: every request gets its :class:`Meter` (whose it is,
    what its inline work reserved and used; settled when it is answered), and the GET routes in
    ``routes`` -- pure functions of their query (the page's curves, /fits, /meta) -- are answered
    from :class:`AnswerCache` when asked again and admitted against the client's share when not."""

    def __init__(self, app: Any, budget: InlineBudget, routes: frozenset[str]):
        self.app = app
        self.budget = budget
        self.routes = routes

    async def __call__(self, scope: Any, receive: Any, send: Any) -> None:
        if scope["type"] != "http" or not scope.get("path", "").startswith("/api/"):
            await self.app(scope, receive, send)
            return
        work = Work(self.budget, Meter(client_key(scope)))
        token = ACTIVE.set(work)
        try:
            if scope["method"] == "GET" and scope["path"] in self.routes:
                await self._cached(scope, receive, send, work)
            else:
                await self.app(scope, receive, send)
        finally:
            self.budget.settle(work.meter)
            ACTIVE.reset(token)

    async def _cached(self, scope: Any, receive: Any, send: Any, work: Work) -> None:
        from .errors import send_problem

        path = scope["path"]
        key = ("GET", path, canonical_query(scope.get("query_string", b"")))
        if (hit := self.budget.answers.get(key)) is not None:
            headers, body = hit
            # A fresh list: the middleware outside (gzip, the security headers) edits it in place.
            await send({"type": "http.response.start", "status": 200, "headers": list(headers)})
            await send({"type": "http.response.body", "body": body})
            return
        try:
            self.budget.admit(work.meter, self.budget.costs.estimate(path, 1.0))
        except Throttled as refused:
            await send_problem(send, 429, refused.message, refused.limit, [(b"retry-after", refused.retry_after().encode())],
                               refused.body())  # fmt: skip
            return
        start: dict[str, Any] = {}
        chunks: list[bytes] = []

        async def keep(message: Any) -> None:
            if message["type"] == "http.response.start":
                start.update(message, headers=list(message.get("headers", [])))  # as this route sent them
            elif message["type"] == "http.response.body":
                chunks.append(message.get("body", b""))
                if not message.get("more_body", False) and start.get("status") == 200:
                    body = b"".join(chunks)
                    self.budget.answers.put(key, (start["headers"], body), len(body) + 512)
            await send(message)

        await self.app(scope, receive, keep)


def meter_routes(app: Any, paths: frozenset[str]) -> None:
    """Run the (synchronous) endpoints of ``paths`` inside :func:`metered`, each answer one unit of
    its own kind (its path), so that their cost is measured in the thread that computes it."""
    import inspect

    from fastapi.routing import APIRoute

    for route in app.router.routes:
        if isinstance(route, APIRoute) and route.path in paths and not inspect.iscoroutinefunction(route.endpoint):
            route.dependant.call = metered_call(route.dependant.call, route.path)
