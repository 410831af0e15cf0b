"""Service settings: one object, the only reader of the environment (``NLPSF_*`` variables, see the
README's Configuration). pydantic-settings parses and range-checks them, so a bad value stops the
service at start with the variable named, instead of surfacing later as a wrong limit.

Limits bound the work one request may ask for, so a single simulation cannot take the machine:
they are checked before a job is queued and reported in ``GET /api/v1/meta``.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Annotated, Any

from pydantic import BaseModel, ConfigDict, Field, SecretStr, field_validator, model_validator
from pydantic_settings import BaseSettings, NoDecode, SettingsConfigDict

from nlpsf import defaults

#: Peak resident memory a simulation job adds per stamp pixel (realizations x stamp^2), measured by
#: benchmarks/bench_job_memory.py: 37 bytes for the linear fidelity (the worst), 18 for Monte Carlo
#: (2026-11-26, H158, 200 and 1200 realizations of 96^2 stamps); rounded up.
JOB_BYTES_PER_STAMP_PIXEL = 40

_LIMIT_FIELDS = ("max_realizations", "max_stamp", "max_grid", "max_wavelengths", "max_stamp_pixels", "max_work")


def _default_db_path() -> str:
    state = os.environ.get("XDG_STATE_HOME") or str(Path.home() / ".local" / "state")
    return str(Path(state) / "nlpsf" / "jobs.sqlite3")


# The limits' ranges, shared by ``Limits`` (code) and ``Settings`` (the flat environment fields).
# A limit can only tighten what the library accepts: its top is the library's own range (nlpsf.defaults).
_Realizations = Annotated[int, Field(ge=1, le=defaults.MAX_REALIZATIONS)]
_Stamp = Annotated[int, Field(ge=defaults.STAMP_RANGE[0], le=defaults.STAMP_RANGE[1])]
_Grid = Annotated[int, Field(ge=1, le=100_000)]
_Wavelengths = Annotated[int, Field(ge=1, le=defaults.MAX_WAVELENGTHS)]
_StampPixels = Annotated[int, Field(ge=256, le=10**11)]
_Work = Annotated[int, Field(ge=256, le=10**15)]


class Limits(BaseModel):
    """Caps on the work of one simulation request (each named in the 422 that enforces it)."""

    model_config = ConfigDict(frozen=True)

    #: centroid realizations (or beta-map draws) per request
    max_realizations: _Realizations = 2000
    #: stamp side in fine pixels
    max_stamp: _Stamp = 256
    #: cells of the request's grid: magnitudes x betas x sigma_betas
    max_grid: _Grid = 200
    #: wavelengths of a polychromatic PSF
    max_wavelengths: _Wavelengths = 16
    #: realizations x stamp^2: the stamps a job holds in memory; at JOB_BYTES_PER_STAMP_PIXEL (measured)
    #: 40 million pixels need about 1.6 GB, inside the default job_memory_mb
    max_stamp_pixels: _StampPixels = 40_000_000
    #: realizations x stamp^2 x (wavelengths + grid cells): a proxy for CPU time
    max_work: _Work = 4_000_000_000

    def to_dict(self) -> dict[str, int]:
        return self.model_dump()


class Settings(BaseSettings):
    """Everything the service reads from its environment. Constructed once per process."""

    model_config = SettingsConfigDict(
        env_prefix="NLPSF_", frozen=True, extra="forbid", case_sensitive=False, populate_by_name=True
    )

    # --- where and how it listens -------------------------------------------------------------
    host: str = Field("127.0.0.1", description="address to listen on (0.0.0.0 for all interfaces)")
    port: int = Field(8000, ge=0, le=65535)
    #: HTTP worker processes; None: one per core, up to 8
    workers: int | None = Field(None, ge=1, le=64)
    #: Host header values accepted (comma-separated; "*" accepts any). A deployment behind a name sets it.
    allowed_hosts: Annotated[list[str], NoDecode] = Field(default_factory=lambda: ["*"])
    #: API keys (comma-separated); with any set, /api/v1 (except /health) needs one, as
    #: ``Authorization: Bearer <key>`` or ``X-API-Key``, and job listings group by key
    api_keys: Annotated[list[SecretStr], NoDecode] = Field(default_factory=list)
    #: largest request body in bytes; a larger one is answered 413 before it is read
    max_body_bytes: int = Field(65_536, ge=1024, le=64 * 1024**2)
    #: an HTTP worker whose event loop is silent this long (stopped, or blocked) is killed and replaced, s
    heartbeat_timeout_s: float = Field(3.0, ge=0.5, le=600.0)
    #: a request's headers must arrive within this of its first byte, else 408 and the connection closes, s
    header_timeout_s: float = Field(10.0, ge=0.5, le=600.0)
    #: a request's body must arrive within this of its headers, else 408 and the connection closes, s
    body_timeout_s: float = Field(30.0, ge=0.5, le=3600.0)
    #: an idle kept-alive connection is closed after this, s
    keep_alive_s: float = Field(5.0, ge=0.5, le=600.0)
    #: open connections per HTTP worker; beyond it the worker answers 503
    max_connections: int = Field(1000, ge=8, le=1_000_000)
    #: all HTTP workers accept from one listening socket (a stopped worker then takes no new
    #: connections); false: one SO_REUSEPORT socket per worker (see docs/service.md for the measurement)
    shared_socket: bool = True
    #: the page's files; None: the installed package data ``nlpsf.web.static``
    static_dir: str | None = None
    #: addresses of trusted reverse proxies (comma-separated; "*" trusts any peer): uvicorn takes a
    #: request's client address from their X-Forwarded-For (and the scheme from X-Forwarded-Proto).
    #: Empty (the default): the socket's peer is the client, whatever headers it sends
    forwarded_allow_ips: Annotated[list[str], NoDecode] = Field(default_factory=list)

    # --- inline answers (the tables, the field grid, the page's curves), budgeted per client ----------
    #: CPU a client's inline answers may use, sustained, in CPU-seconds per second of each HTTP worker
    inline_cpu_share: float = Field(0.1, gt=0.0, le=1.0)
    #: CPU-seconds a client may spend at once (its bucket's size); also the most one request (a batch) may cost
    inline_cpu_burst_s: float = Field(2.0, ge=0.01, le=3600.0)
    #: CPU all clients' inline answers may use together, in CPU-seconds per second of each HTTP worker
    inline_cpu_total_share: float = Field(0.5, gt=0.0, le=1.0)
    #: answers kept for repeated requests (pure functions of the request), MB per HTTP worker
    inline_cache_mb: int = Field(32, ge=0, le=64 * 1024)
    #: the large fixed documents (/tables, .csv, .ecsv with their gzip), MB per HTTP worker
    documents_cache_mb: int = Field(64, ge=8, le=64 * 1024)

    # --- simulation jobs ----------------------------------------------------------------------
    db_path: str = Field(default_factory=_default_db_path)
    #: simulation processes running at once, across all web workers
    job_workers: int = Field(1, ge=1, le=64)
    #: simulations waiting for a worker; beyond this a POST gets 429
    max_queue: int = Field(16, ge=0, le=100_000)
    #: niceness of simulation processes, so the calculator keeps the CPU when both want it
    job_nice: int = Field(10, ge=0, le=19)
    #: memory one simulation process may add to its start-up size (RLIMIT_AS), MB: a request whose
    #: measured need (JOB_BYTES_PER_STAMP_PIXEL x stamp pixels) is larger is refused, and a job that
    #: still grows past it fails cleanly instead of taking the host
    job_memory_mb: int = Field(2048, ge=64, le=1024**2)
    #: queued simulations one client (its API key, else its address) may hold; the rest of the queue
    #: stays open to others. None: a quarter of max_queue (at least 1)
    max_queue_per_client: int | None = Field(None, ge=1, le=100_000)
    #: a running job that reports no progress for this long is ended (failed) and its place freed, s
    job_stall_s: float = Field(120.0, ge=2.0, le=86_400.0)
    #: a job's wall-time limit is this many times its estimated duration (and at least 10 x job_stall_s)
    job_time_factor: float = Field(20.0, ge=1.0, le=10_000.0)
    #: longest ``wait`` a POST /simulations may ask for, seconds
    max_wait_s: float = Field(30.0, ge=0.0, le=600.0, validation_alias="NLPSF_MAX_WAIT")
    #: how long POST /solve waits for a solve that needs a simulation before answering 202 with its job
    solve_wait_s: float = Field(10.0, ge=0.0, le=600.0)
    #: a service instance on another host not heard from for this long has its running jobs interrupted
    stale_after_s: float = Field(30.0, ge=3.0, le=86_400.0, validation_alias="NLPSF_STALE_AFTER")
    #: GET /simulations lists every job (operator option); off: only the caller's (by API key)
    list_all_jobs: bool = False

    # --- retention: the job database must not grow without bound --------------------------------
    #: finished jobs and stored results older than this are deleted, days
    retention_days: float = Field(30.0, gt=0.0, le=36_500.0)
    #: at most this many stored results (and 4x as many finished jobs) are kept; the oldest go first
    max_stored_results: int = Field(5000, ge=1, le=10**7)

    # --- limits per request (flat in the environment: NLPSF_MAX_REALIZATIONS, ...) -------------
    # (ranges and defaults: ``Limits``, their one owner)
    max_realizations: _Realizations = Limits.model_fields["max_realizations"].default
    max_stamp: _Stamp = Limits.model_fields["max_stamp"].default
    max_grid: _Grid = Limits.model_fields["max_grid"].default
    max_wavelengths: _Wavelengths = Limits.model_fields["max_wavelengths"].default
    max_stamp_pixels: _StampPixels = Limits.model_fields["max_stamp_pixels"].default
    max_work: _Work = Limits.model_fields["max_work"].default

    @model_validator(mode="before")
    @classmethod
    def _spread_limits(cls, values: Any) -> Any:
        """Accept ``limits=Limits(...)`` in code as well as the flat fields the environment sets."""
        if isinstance(values, dict) and "limits" in values:
            values = dict(values)
            limits = values.pop("limits")
            values.update(limits.to_dict() if isinstance(limits, Limits) else dict(limits))
        return values

    @field_validator("allowed_hosts", mode="before")
    @classmethod
    def _split_hosts(cls, value: Any) -> Any:
        if isinstance(value, str):
            return [h.strip() for h in value.split(",") if h.strip()] or ["*"]
        return value

    @field_validator("forwarded_allow_ips", mode="before")
    @classmethod
    def _split_proxies(cls, value: Any) -> Any:
        if isinstance(value, str):
            return [a.strip() for a in value.split(",") if a.strip()]
        return value

    @model_validator(mode="after")
    def _total_covers_one(self) -> Settings:
        if self.inline_cpu_total_share < self.inline_cpu_share:
            raise ValueError("inline_cpu_total_share must be at least inline_cpu_share")
        return self

    @field_validator("api_keys", mode="before")
    @classmethod
    def _split_keys(cls, value: Any) -> Any:
        if isinstance(value, str):
            return [k.strip() for k in value.split(",") if k.strip()]
        return value

    @field_validator("api_keys")
    @classmethod
    def _long_keys(cls, value: list[SecretStr]) -> list[SecretStr]:
        if any(len(k.get_secret_value()) < 16 for k in value):
            raise ValueError("each API key must have at least 16 characters")
        return value

    @property
    def limits(self) -> Limits:
        return Limits(**{name: getattr(self, name) for name in _LIMIT_FIELDS})

    @property
    def http_workers(self) -> int:
        # One HTTP worker per core: on 2 cores that doubles the calculator's throughput (benchmarks/bench_service.py).
        return self.workers or min(os.cpu_count() or 1, 8)

    @property
    def queue_per_client(self) -> int:
        return self.max_queue_per_client or max(1, self.max_queue // 4)

    def job_time_limit_s(self, estimate_s: float | None) -> float:
        """The wall time a job may run: job_time_factor x its estimated duration, at least 10 x job_stall_s."""
        return max(10.0 * self.job_stall_s, self.job_time_factor * (estimate_s or 0.0))

    @property
    def retention_s(self) -> float:
        return self.retention_days * 86_400.0

    @classmethod
    def from_env(cls) -> Settings:
        return cls()
