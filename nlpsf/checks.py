"""Argument checking shared by the library, the CLI and the service: one error type that names
the argument, so every layer can report bad input the same way."""

from __future__ import annotations

import math

import numpy as np


class InputError(ValueError):
    """A user-supplied argument is out of range or malformed; the message names the argument."""

    def __init__(self, argument: str, message: str):
        super().__init__(f"{argument}: {message}")
        self.argument = argument
        self.reason = message


def check_integer(value, name: str, lo: int, hi: int) -> int:
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or not lo <= int(value) <= hi:
        raise InputError(name, f"must be an integer from {lo} to {hi}, got {value!r}")
    return int(value)


def check_number(value, name: str, lo: float = -math.inf, hi: float = math.inf, *, open_low: bool = False) -> float:
    """A finite float in [lo, hi] (or (lo, hi] with ``open_low``)."""
    if isinstance(value, bool):
        raise InputError(name, f"must be a number, got {value!r}")
    try:
        number = float(value)
    except (TypeError, ValueError):
        raise InputError(name, f"must be a number, got {value!r}") from None
    if not math.isfinite(number):
        raise InputError(name, f"must be finite, got {value!r}")
    if number < lo or number > hi or (open_low and number == lo):
        low = "(" if open_low else "["
        raise InputError(name, f"must lie in {low}{lo:g}, {hi:g}], got {value!r}")
    return number


def check_numbers(values, name: str, lo: float = -math.inf, hi: float = math.inf) -> list[float]:
    """One number or a sequence of them, each checked by :func:`check_number`."""
    if np.isscalar(values) or isinstance(values, (int, float)):
        values = [values]
    out = [check_number(v, name, lo, hi) for v in values]
    if not out:
        raise InputError(name, "give at least one value")
    return out
