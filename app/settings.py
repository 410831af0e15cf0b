"""Service settings, read from ``NLPSF_*`` environment variables (see the README's Configuration).

Limits bound the work one request may ask for, so a single simulation cannot take the machine:
they are checked before a job is queued and reported in ``GET /api/v1/meta``.
"""

from __future__ import annotations

import os
from dataclasses import asdict, dataclass, field
from pathlib import Path


def _default_db_path() -> str:
    state = os.environ.get("XDG_STATE_HOME") or str(Path.home() / ".local" / "state")
    return str(Path(state) / "nlpsf" / "jobs.sqlite3")


def _env_int(name: str, default: int, low: int, high: int) -> int:
    raw = os.environ.get(name)
    if raw is None or raw.strip() == "":
        return default
    try:
        value = int(raw)
    except ValueError:
        raise ValueError(f"{name} must be an integer, got {raw!r}") from None
    if not low <= value <= high:
        raise ValueError(f"{name} must lie in [{low}, {high}], got {value}")
    return value


def _env_float(name: str, default: float, low: float, high: float) -> float:
    raw = os.environ.get(name)
    if raw is None or raw.strip() == "":
        return default
    try:
        value = float(raw)
    except ValueError:
        raise ValueError(f"{name} must be a number, got {raw!r}") from None
    if not low <= value <= high:
        raise ValueError(f"{name} must lie in [{low:g}, {high:g}], got {value:g}")
    return value


@dataclass(frozen=True)
class Limits:
    """Caps on the work of one simulation request (each named in the 422 that enforces it)."""

    #: centroid realizations (or beta-map draws) per request
    max_realizations: int = 2000
    #: stamp side in fine pixels
    max_stamp: int = 256
    #: cells of the request's grid: magnitudes x betas x sigma_betas
    max_grid: int = 200
    #: wavelengths of a polychromatic PSF
    max_wavelengths: int = 16
    #: realizations x stamp^2: the rendered stamps held in memory (8 bytes each)
    max_stamp_pixels: int = 40_000_000
    #: realizations x stamp^2 x (wavelengths + grid cells): a proxy for CPU time
    max_work: int = 4_000_000_000

    def to_dict(self) -> dict:
        return asdict(self)


@dataclass(frozen=True)
class Settings:
    db_path: str = field(default_factory=_default_db_path)
    #: simulation processes running at once, across all web workers
    job_workers: int = 1
    #: simulations waiting for a worker; beyond this a POST gets 429
    max_queue: int = 16
    #: niceness of simulation processes, so the calculator keeps the CPU when both want it
    job_nice: int = 10
    #: longest ``wait`` a POST /simulations may ask for, seconds
    max_wait_s: float = 30.0
    #: a running job whose owning service has not been heard from for this long is interrupted
    stale_after_s: float = 30.0
    limits: Limits = field(default_factory=Limits)

    @classmethod
    def from_env(cls) -> Settings:
        limits = Limits(
            max_realizations=_env_int("NLPSF_MAX_REALIZATIONS", Limits.max_realizations, 1, 100_000),
            max_stamp=_env_int("NLPSF_MAX_STAMP", Limits.max_stamp, 16, 512),
            max_grid=_env_int("NLPSF_MAX_GRID", Limits.max_grid, 1, 100_000),
            max_wavelengths=_env_int("NLPSF_MAX_WAVELENGTHS", Limits.max_wavelengths, 1, 64),
            max_stamp_pixels=_env_int("NLPSF_MAX_STAMP_PIXELS", Limits.max_stamp_pixels, 256, 10**11),
            max_work=_env_int("NLPSF_MAX_WORK", Limits.max_work, 256, 10**15),
        )
        return cls(
            db_path=os.environ.get("NLPSF_DB_PATH") or _default_db_path(),
            job_workers=_env_int("NLPSF_JOB_WORKERS", 1, 1, 64),
            max_queue=_env_int("NLPSF_MAX_QUEUE", 16, 0, 100_000),
            job_nice=_env_int("NLPSF_JOB_NICE", 10, 0, 19),
            max_wait_s=_env_float("NLPSF_MAX_WAIT", 30.0, 0.0, 600.0),
            stale_after_s=_env_float("NLPSF_STALE_AFTER", 30.0, 3.0, 86_400.0),
            limits=limits,
        )
