"""MultiAccum (MA) tables: which reads each resultant averages, the shipped tables and their loader."""

from __future__ import annotations

import json
from collections.abc import Sequence
from dataclasses import dataclass
from functools import lru_cache
from importlib import resources
from pathlib import Path

import numpy as np

from nlpsf import defaults
from nlpsf.checks import InputError, check_integer, check_number

ROMAN_FRAME_TIME_S = defaults.ROMAN_FRAME_TIME_S
MAX_READS = defaults.MAX_RAMP_READS
#: Relative slack when comparing a table's last read time with the exposure time (rounding of
#: frame_time * n).
_TIME_SLACK = 1e-9


def shipped_table_dir() -> Path:
    return Path(str(resources.files("nlpsf") / "data" / "ma_tables"))


def shipped_table_names() -> list[str]:
    return sorted(p.stem for p in shipped_table_dir().glob("*.json"))


# --- the MA table -----------------------------------------------------------------------------


@dataclass(frozen=True)
class MATable:
    """Resultants as tuples of read indices (read i ends at i * frame_time after the reset)."""

    resultants: tuple[tuple[int, ...], ...]
    frame_time_s: float
    name: str = "custom"
    source: str = ""

    def __post_init__(self) -> None:
        field = "ma_table"
        try:
            resultants = tuple(tuple(r) for r in self.resultants)
        except TypeError:
            raise InputError(f"{field}.resultants", "must be a list of lists of read indices") from None
        if not resultants:
            raise InputError(f"{field}.resultants", "give at least one resultant")
        previous = 0
        for j, reads in enumerate(resultants, start=1):
            if not reads:
                raise InputError(f"{field}.resultants", f"resultant {j} has no reads")
            for index in reads:
                if isinstance(index, bool) or not isinstance(index, (int, np.integer)) or index < 1:
                    raise InputError(f"{field}.resultants", f"resultant {j}: read indices are integers >= 1, got {index!r}")
                if index <= previous:
                    raise InputError(
                        f"{field}.resultants",
                        f"resultant {j}: read {index} is not after read {previous}; reads must increase "
                        "within and across resultants (no reordering, no read in two resultants)",
                    )
                previous = int(index)
        if previous > MAX_READS:
            raise InputError(f"{field}.resultants", f"at most {MAX_READS} reads, got read {previous}")
        object.__setattr__(self, "resultants", tuple(tuple(int(i) for i in r) for r in resultants))
        check_number(self.frame_time_s, f"{field}.frame_time_s", *defaults.FRAME_TIME_RANGE_S, open_low=True)
        object.__setattr__(self, "frame_time_s", float(self.frame_time_s))

    @classmethod
    def uniform(cls, n: int, exptime_s: float) -> MATable:
        """``--ramp N``: N reads evenly spaced over the exposure, the last at its end, one per resultant."""
        n = check_integer(n, "ramp", 1, MAX_READS)
        exptime_s = check_number(exptime_s, "exptime", *defaults.EXPTIME_RANGE_S)
        return cls(tuple((i,) for i in range(1, n + 1)), exptime_s / n, name=f"uniform-{n}", source="uniform reads")

    @classmethod
    def from_dict(cls, data: dict, name: str = "custom") -> MATable:
        if not isinstance(data, dict):
            raise InputError("ma_table", "must be an object with 'resultants' (or 'read_pattern') and 'frame_time_s'")
        resultants = data.get("resultants", data.get("read_pattern"))
        if resultants is None:
            raise InputError("ma_table.resultants", "missing (a list of lists of read indices)")
        frame = data.get("frame_time_s", ROMAN_FRAME_TIME_S)
        return cls(resultants, frame, name=str(data.get("name", name)), source=str(data.get("source", "")))

    @property
    def n_resultants(self) -> int:
        return len(self.resultants)

    @property
    def n_reads(self) -> int:
        return sum(len(r) for r in self.resultants)

    @property
    def duration_s(self) -> float:
        """Time of the last read after the reset."""
        return self.resultants[-1][-1] * self.frame_time_s

    def check_exposure(self, exptime_s: float, field: str = "ma_table") -> None:
        if self.duration_s > exptime_s * (1 + _TIME_SLACK):
            raise InputError(
                field,
                f"the table's last read is at {self.duration_s:.6g} s, after the end of the {exptime_s:.6g} s exposure; "
                "give a longer exposure or a shorter table",
            )

    def read_fractions(self, exptime_s: float) -> np.ndarray:
        """tau of every read (time / exposure), in order."""
        return np.array([i for r in self.resultants for i in r], dtype=np.float64) * self.frame_time_s / exptime_s

    def resultant_means(self, reads: np.ndarray) -> np.ndarray:
        """(..., reads) -> (..., resultants): each resultant the mean of its reads (O(reads))."""
        sizes = np.array([len(r) for r in self.resultants])
        starts = np.concatenate([[0], np.cumsum(sizes)[:-1]])
        return np.add.reduceat(reads, starts, axis=-1) / sizes

    def mean_powers(self, exptime_s: float, orders: Sequence[int]) -> np.ndarray:
        """<tau^n>_j: (orders, resultants)."""
        tau = self.read_fractions(exptime_s)
        return self.resultant_means(np.stack([tau**n for n in orders]))

    def last_read_fractions(self, exptime_s: float) -> np.ndarray:
        return np.array([r[-1] for r in self.resultants], dtype=np.float64) * self.frame_time_s / exptime_s

    def to_dict(self) -> dict:
        return {
            "name": self.name,
            "frame_time_s": self.frame_time_s,
            "resultants": [list(r) for r in self.resultants],
            "source": self.source,
        }


def load_ma_table(spec: str | Path) -> MATable:
    """An MA table from a JSON file, or a shipped one by name (``nlpsf/data/ma_tables``)."""
    path = Path(spec)
    if path.suffix.lower() == ".json" or path.exists():
        if not path.is_file():
            raise InputError("ma_table", f"no MA table file at {path}")
        try:
            data = json.loads(path.read_text())
        except (OSError, ValueError) as error:
            raise InputError("ma_table", f"cannot read {path} as JSON: {error}") from None
        return MATable.from_dict(data, name=path.stem)
    table = _shipped_tables().get(str(spec).strip().lower())
    if table is None:
        shipped = ", ".join(shipped_table_names())
        raise InputError("ma_table", f"no file and no shipped MA table named {spec!r}; shipped: {shipped}")
    return table


@lru_cache(maxsize=1)
def _shipped_tables() -> dict[str, MATable]:
    """Every shipped table under its file name and the names its source gives it (C2A_IMG_HLWAS),
    lower case. Read once per process: a solve asks for its readout dozens of times."""
    tables: dict[str, MATable] = {}
    for name in shipped_table_names():
        data = json.loads((shipped_table_dir() / f"{name}.json").read_text())
        table = MATable.from_dict(data, name=name)
        for key in (name, *data.get("aliases", ())):
            tables[key.lower()] = table
    return tables


def _resultant_fractions(table: MATable, exptime_s: float) -> np.ndarray:
    return table.mean_powers(exptime_s, (1,))[0]


def _ols_factors(table: MATable, exptime_s: float, orders: Sequence[int]) -> np.ndarray:
    """(K, orders): c_n = w_k . <tau^n> for every number k of usable resultants, in O(K) from running
    sums (sum_j (tau_j - mean) m_j / sum_j (tau_j - mean)^2), so long tables cost no K x K matrix."""
    tau = _resultant_fractions(table, exptime_s)
    powers = table.mean_powers(exptime_s, orders)  # (orders, K)
    k = np.arange(1, tau.size + 1, dtype=np.float64)
    # Centre on the full table's mean first: the running sums then carry no large common offset.
    shift = tau - tau.mean()
    s_shift = np.cumsum(shift)
    variance = np.cumsum(shift**2) - s_shift**2 / k
    covariance = np.cumsum(shift * powers, axis=1) - s_shift * np.cumsum(powers, axis=1) / k
    out = np.empty((tau.size, len(orders)))
    out[0] = powers[:, 0] / tau[0]
    if tau.size > 1:
        out[1:] = (covariance[:, 1:] / variance[1:]).T
    return out
