"""What a handler needs from the running service, as FastAPI dependencies (``Annotated`` types), so
that no handler reaches into ``request.app.state``.

- :data:`SettingsDep`: the service settings;
- :data:`ServicesDep`: the job store, dispatcher and notifier the lifespan started;
- :data:`CallerDep`: who is asking: the API key's hash (listings) and whose share of the queue a
  submission counts against (the key, else the address).

Each is ``async``, though none awaits: FastAPI runs a plain function dependency in a worker thread,
and that hop (a queue, a wake-up, the answer passed back to the loop) cost about 0.25 ms of CPU per
request, a third of a paper-table solve's; these only read the request and the app's state.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Annotated, Any

from fastapi import Depends, Request

from .settings import Settings


async def _settings(request: Request) -> Settings:
    return request.app.state.settings


SettingsDep = Annotated[Settings, Depends(_settings)]


@dataclass(frozen=True)
class Services:
    settings: Settings
    store: Any  # store.Store (None before the lifespan has run)
    dispatcher: Any  # jobs.Dispatcher
    notifier: Any  # jobs.Notifier


async def _services(request: Request) -> Services:
    state = request.app.state
    get = state._state.get  # before the lifespan has run, the job parts are None
    return Services(state.settings, get("store"), get("dispatcher"), get("notifier"))


ServicesDep = Annotated[Services, Depends(_services)]


@dataclass(frozen=True)
class Caller:
    #: the API key's hash (security.client_of), None without keys: listings group by it
    key: str | None
    #: whose share of the queue a submission counts against: the key, else the address
    share: str


async def caller_of(request: Request) -> Caller:
    key = getattr(request.state, "client", None)
    address = request.client.host if request.client else "unknown"
    return Caller(key, key if key is not None else f"address:{address}")


CallerDep = Annotated[Caller, Depends(caller_of)]
