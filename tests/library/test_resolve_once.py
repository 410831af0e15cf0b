"""A request is read and checked once: its band is validated once per solve, whatever the
solve reads (every field-grid node of the SCA, the tables, the model parts)."""

from __future__ import annotations

import pytest

from nlpsf import roman, solve
from nlpsf.roman import check_band


@pytest.mark.parametrize(
    "request_",
    [
        {"band": "W146", "magnitude": 19.3, "tolerance": 1e-4},  # the Roman default over the SCA (25 nodes)
        {"band": "W146", "precision": 0.011, "tolerance": 1e-4},  # a magnitude solve over the SCA
        {"band": "H158", "precision": 0.01, "magnitude": 20.0, "scene": "paper"},
    ],
)
def test_a_solve_checks_its_band_once(monkeypatch, request_):
    band = request_.pop("band")
    solve(band, **request_)  # tables, grid and caches read: what a running service has
    calls = []

    def counted(value, *args, **kwargs):
        calls.append(value)
        return check_band(value, *args, **kwargs)

    monkeypatch.setattr(roman, "check_band", counted)
    solve(band, **request_)
    assert calls == [band]
