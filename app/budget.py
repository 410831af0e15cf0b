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
curves (``documents.CachedAnswers``) -- are kept (:class:`AnswerCache`, bounded): a repeated request
costs a dictionary look-up.
"""

from __future__ import annotations

import asyncio
import contextlib
import contextvars
import math
import threading
import time
from collections import OrderedDict
from collections.abc import AsyncIterator, Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from typing import Any

from nlpsf.checks import InputError

from .errors import Throttled

#: Units of inline work: a field-grid node read and answered; a table solve; a KiB of a request body
#: parsed and checked against its schema; (a route's path) one answer of a page or curve route.
NODE = "node"
TABLE = "table"
BODY_KIB = "body_kib"
#: A batch row read into its typed request.
ROW = "row"
#: What one request costs the event loop (receiving it, routing, answering), whatever it asks.
REQUEST = "request"
#: Requests over which the loop's cost per request is measured.
LOOP_WINDOW = 200
#: What a unit costs before this process has measured one (CPU s): deliberately high, so the first
#: requests are admitted on a cautious estimate; every measurement moves it toward the truth.
PRIOR_S = {NODE: 0.005, TABLE: 0.001, BODY_KIB: 0.0005, REQUEST: 0.002, ROW: 0.0005}
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
        self._lock = threading.Lock()

    def per_unit(self, kind: str) -> float:
        return self._per_unit.get(kind, PRIOR_S.get(kind, PRIOR_ROUTE_S))

    def estimate(self, kind: str, units: float) -> float:
        return units * self.per_unit(kind)

    def observe(self, kind: str, units: float, used_s: float) -> None:
        if units > 0 and used_s >= 0:
            measured = used_s / units
            with self._lock:
                known = self._per_unit.get(kind)
                self._per_unit[kind] = measured if known is None else known + LEARNING_RATE * (measured - known)


#: The process's cost model (one per process: what a unit costs depends on the code and the machine,
#: not on which application object serves it).
COSTS = CostModel()


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
        self.costs = COSTS
        self.answers = AnswerCache(cache_bytes)
        self.turns = Turns()
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

    def admit(self, meter: Meter, estimate_s: float, always: bool = False) -> None:
        """Reserve ``estimate_s`` for ``meter``'s client, or raise :class:`Throttled` (an estimate
        under :data:`FREE_S` is reserved without a check, unless ``always``)."""
        now = time.monotonic()
        with self._lock:
            mine = self.clients.balance(meter.client, now)
            everyone = self.total.balance("", now)
            if always or estimate_s >= FREE_S:
                if mine < min(estimate_s, self.clients.burst):
                    raise self._refusal(meter.client, estimate_s, now)
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

    def in_debt(self, client: str) -> bool:
        """Whether ``client`` has used more than its share has refilled (its balance is below zero)."""
        with self._lock:
            return self.clients.balance(client, time.monotonic()) < 0.0

    def refusal(self, client: str, estimate_s: float) -> Throttled:
        with self._lock:
            return self._refusal(client, estimate_s, time.monotonic())

    def _refusal(self, client: str, estimate_s: float, now: float) -> Throttled:
        wait = self.clients.wait_s(client, min(estimate_s, self.clients.burst), now)
        return Throttled(
            f"your share of the service's inline CPU is used (the setting inline_cpu_share, "
            f"{self.clients.rate:g} CPU-s per s per HTTP worker); retry after {math.ceil(wait)} s",
            "inline_cpu_share",
            wait,
        )

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


def admit(kind: str, units: float, always: bool = False) -> None:
    """Reserve the estimated cost of ``units`` of ``kind`` for the request in progress (a no-op outside
    one); ``always``: check the client's balance however small the estimate."""
    work = ACTIVE.get()
    if work is not None:
        work.budget.admit(work.meter, work.budget.costs.estimate(kind, units), always)


def estimate(kind: str, units: float) -> float:
    work = ACTIVE.get()
    return work.budget.costs.estimate(kind, units) if work is not None else 0.0


_thread = threading.local()


@contextmanager
def metered(kind: str, units: float) -> Iterator[None]:
    """Measure the CPU time of the work inside (this thread's), teach the cost model what a unit of
    ``kind`` costs and charge it to the request in progress (unless an enclosing measurement in this
    thread, the endpoint's own, charges it already)."""
    outer = getattr(_thread, "metering", False)
    _thread.metering = True
    start = time.thread_time()
    try:
        yield
    finally:
        used = time.thread_time() - start
        _thread.metering = outer
        work = ACTIVE.get()
        if work is not None:
            if not outer:
                work.meter.used_s += used
            if kind:
                work.budget.costs.observe(kind, units, used)


@contextmanager
def uncharged() -> Iterator[None]:
    """Work inside is charged to no client (done once for everyone: the whole tables' documents)."""
    start = time.thread_time()
    try:
        yield
    finally:
        work = ACTIVE.get()
        if work is not None and getattr(_thread, "metering", False):
            work.meter.used_s -= time.thread_time() - start


def _metered_sync(function: Callable[..., Any]) -> Callable[..., Any]:
    def run(*args: Any, **kwargs: Any) -> Any:
        with metered("", 0.0):
            return function(*args, **kwargs)

    return run


def install_metering() -> None:
    """Measure every synchronous endpoint where it runs: FastAPI runs one in a worker thread through
    ``fastapi.routing.run_in_threadpool`` (every version this service supports); wrapped here, that
    thread's CPU time is charged to the request in progress. Idempotent; outside a request it only
    measures."""
    import fastapi.routing

    original = fastapi.routing.run_in_threadpool
    if getattr(original, "nlpsf_metered", False):
        return

    async def run_in_threadpool(function: Callable[..., Any], /, *args: Any, **kwargs: Any) -> Any:
        return await original(_metered_sync(function), *args, **kwargs)

    run_in_threadpool.nlpsf_metered = True  # type: ignore[attr-defined]
    fastapi.routing.run_in_threadpool = run_in_threadpool  # type: ignore[assignment]


# --- turns: one costly computation at a time per worker, one waiting per client -------------------


#: How long a request waits for its turn to compute before it is refused (429), s.
TURN_WAIT_S = 30.0


#: Whether the request in progress holds its turn (turns are not taken twice by one request).
_HOLDING: contextvars.ContextVar[bool] = contextvars.ContextVar("nlpsf_holding_turn", default=False)


class Turns:
    """Costly inline work (an answer from the field grid, a page curve, a batch, a large body's
    parsing, a document's build) runs one at a time per HTTP worker, in a worker thread: the event
    loop then shares the interpreter lock with one thread, not with as many as there are requests.
    Each client waits in its own line first, so the shared line holds at most one request per
    client and turns go round the clients, not to whoever sent the most. For the event loop only."""

    def __init__(self) -> None:
        self._shared: asyncio.Semaphore | None = None
        self._lines: dict[str, tuple[asyncio.Semaphore, list[int]]] = {}

    async def acquire(self, client: str) -> None:
        """Wait for ``client``'s turn (its line, then the shared one); :class:`Throttled` after
        :data:`TURN_WAIT_S`."""
        if self._shared is None:
            self._shared = asyncio.Semaphore(1)
        if client not in self._lines and not self._shared.locked():
            # Nobody to wait for (the common case): both taken at once, without arming the timeout
            # (a timer scheduled and cancelled per inline answer); the line is born held by this request.
            self._lines[client] = (asyncio.Semaphore(0), [1])
            await self._shared.acquire()  # free: returns without suspending
            return
        line, users = self._lines.setdefault(client, (asyncio.Semaphore(1), [0]))
        users[0] += 1
        try:
            async with asyncio.timeout(TURN_WAIT_S):
                await line.acquire()
                try:
                    await self._shared.acquire()
                except BaseException:
                    line.release()
                    raise
        except BaseException as error:
            self._leave(client)
            if isinstance(error, TimeoutError):
                raise Throttled(
                    f"this worker's inline work has been busy for {TURN_WAIT_S:g} s; retry shortly", "inline_turn_wait_s", 1.0
                ) from None
            raise

    def release(self, client: str) -> None:
        assert self._shared is not None
        self._shared.release()
        self._lines[client][0].release()
        self._leave(client)

    def _leave(self, client: str) -> None:
        users = self._lines[client][1]
        users[0] -= 1
        if users[0] == 0:
            self._lines.pop(client, None)

    @contextlib.asynccontextmanager
    async def turn(self, client: str) -> AsyncIterator[None]:
        if _HOLDING.get():
            yield  # this request has its turn already (a cached route's miss parsing its large body)
            return
        await self.acquire(client)
        holding = _HOLDING.set(True)
        try:
            yield
        finally:
            _HOLDING.reset(holding)
            self.release(client)


def turn() -> contextlib.AbstractAsyncContextManager[None]:
    """The request in progress's turn to compute (no wait outside a request)."""
    work = ACTIVE.get()
    if work is None:
        return contextlib.nullcontext()
    return work.budget.turns.turn(work.meter.client)


@contextmanager
def turn_in_thread() -> Iterator[None]:
    """:func:`turn` from a worker thread that anyio started (a synchronous endpoint): waits on the
    event loop for the turn; elsewhere (a direct call, a test) no wait."""
    import anyio.from_thread

    work = ACTIVE.get()
    if work is None or _HOLDING.get():
        yield
        return
    turns, client = work.budget.turns, work.meter.client
    try:
        anyio.from_thread.run(turns.acquire, client)
    except RuntimeError:  # not in a thread of the event loop's
        yield
        return
    holding = _HOLDING.set(True)
    try:
        yield
    finally:
        _HOLDING.reset(holding)
        anyio.from_thread.run_sync(turns.release, client)


# --- the middleware: whose request it is --------------------------------------------------------


def client_key(scope: Any) -> str:
    """Whose share a request counts against: its API key (``security.ApiKey`` puts the key's hash in
    the scope's state), else the socket's address -- the peer's, unless ``forwarded_allow_ips`` names
    the peer as a trusted proxy (then uvicorn has put the forwarded client there)."""
    key = (scope.get("state") or {}).get("client")
    if key is not None:
        return key
    client = scope.get("client")
    return f"address:{client[0] if client else 'unknown'}"


class ClientMeter:
    """ASGI middleware around every API request, outside the body's reading: the request gets its
    :class:`Meter` (whose it is, what its inline work reserved and used; settled when it is
    answered), is charged what a request costs this worker's event loop (:data:`REQUEST`, measured:
    the loop thread's CPU over the requests it served), and -- when its client is in debt and it
    brings a body larger than ``small_body`` bytes -- is refused (429, the connection closed) before
    a byte of that body is read. A client in debt keeps its small requests (a table solve) and
    everything its share covers."""

    def __init__(self, app: Any, budget: InlineBudget, small_body: int = 1024):
        self.app = app
        self.budget = budget
        self.small_body = small_body
        self._window = (time.thread_time(), 0)  # the loop thread's CPU, requests since then

    async def __call__(self, scope: Any, receive: Any, send: Any) -> None:
        if scope["type"] != "http" or not scope.get("path", "").startswith("/api/"):
            await self.app(scope, receive, send)
            return
        work = Work(self.budget, Meter(client_key(scope)))
        token = ACTIVE.set(work)
        try:
            if _declared_length(scope) > self.small_body and self.budget.in_debt(work.meter.client):
                refused = self.budget.refusal(work.meter.client, self.budget.costs.per_unit(REQUEST))
                await refuse(send, refused, [(b"connection", b"close")])
                return
            await self.app(scope, receive, send)
        finally:
            work.meter.used_s += self.budget.costs.per_unit(REQUEST)
            self.budget.settle(work.meter)
            ACTIVE.reset(token)
            self._learn()

    def _learn(self) -> None:
        """Every :data:`LOOP_WINDOW` requests, what one cost the loop thread on average (its CPU
        time, this request's included, minus nothing: the loop does little else)."""
        cpu, served = self._window
        served += 1
        if served >= LOOP_WINDOW:
            now = time.thread_time()
            self.budget.costs.observe(REQUEST, served, now - cpu)
            self._window = (now, 0)
        else:
            self._window = (cpu, served)


def _declared_length(scope: Any) -> int:
    """The body size a request declares (a chunked body: as large as the limit allows)."""
    for name, value in scope.get("headers", []):
        if name == b"content-length":
            try:
                return int(value)
            except ValueError:
                return 0
        if name == b"transfer-encoding":
            return 1 << 30
    return 0


async def refuse(send: Any, refused: Throttled, headers: list | None = None) -> None:
    """A 429 for a client past its share, after a pause (``Throttled.pause_s``): a client that
    retries at once, as an abusive one does, then sends a few requests a second, not hundreds."""
    import asyncio

    from .errors import send_problem

    await asyncio.sleep(refused.pause_s())
    headers = [(b"retry-after", refused.retry_after().encode()), *(headers or [])]
    await send_problem(send, 429, refused.message, refused.limit, headers, refused.body())
