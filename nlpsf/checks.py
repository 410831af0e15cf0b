"""Argument checking shared by the library, the CLI and the service, and the two kinds of error.

``InputError``: the user asked for something invalid; it names the argument, so every layer can
report it the same way (CLI exit 2 naming the option, API 422 naming the field).
``SimulationError``: a valid request could not be computed (every moment fit failed, a data file is
missing); the user cannot fix it by changing one field (CLI exit 1, API 500/503 with the reason).

Kept free of numpy so that the command line can import it while it builds its parser.
"""

from __future__ import annotations

import math
import numbers

from . import defaults


class InputError(ValueError):
    """A user-supplied argument is out of range or malformed; the message names the argument."""

    def __init__(self, argument: str, message: str):
        super().__init__(f"{argument}: {message}")
        self.argument = argument
        self.reason = message


class SimulationError(RuntimeError):
    """A valid request failed while being computed; the message says why."""


def shown(value: object, limit: int = 40) -> str:
    """``repr(value)`` cut to a short prefix: an error message never echoes a huge input back."""
    text = repr(value)
    return text if len(text) <= limit else f"{text[: limit - 3]}... ({len(text):,} characters)"


def check_integer(value, name: str, lo: int, hi: int) -> int:
    if isinstance(value, bool) or not isinstance(value, numbers.Integral) or not lo <= int(value) <= hi:
        raise InputError(name, f"must be an integer from {lo} to {hi}, got {shown(value)}")
    return int(value)


def check_number(value, name: str, lo: float = -math.inf, hi: float = math.inf, *, open_low: bool = False) -> float:
    """A finite float in [lo, hi] (or (lo, hi] with ``open_low``)."""
    if isinstance(value, bool):
        raise InputError(name, f"must be a number, got {shown(value)}")
    try:
        number = float(value)
    except (TypeError, ValueError):
        raise InputError(name, f"must be a number, got {shown(value)}") from None
    if not math.isfinite(number):
        raise InputError(name, f"must be finite, got {shown(value)}")
    if number < lo or number > hi or (open_low and number == lo):
        low = "(" if open_low else "["
        raise InputError(name, f"must lie in {low}{lo:g}, {hi:g}], got {shown(value)}")
    return number


def check_numbers(values, name: str, lo: float = -math.inf, hi: float = math.inf) -> list[float]:
    """One number or a sequence of them, each checked by :func:`check_number`."""
    if isinstance(values, (str, bytes, numbers.Number)) or not hasattr(values, "__iter__"):
        values = [values]
    out = [check_number(v, name, lo, hi) for v in values]
    if not out:
        raise InputError(name, "give at least one value")
    return out


# --- the quantities every entry point takes, with the ranges in ``defaults`` ------------------------


def check_exptime(value, name: str = "exptime") -> float:
    return check_number(value, name, *defaults.EXPTIME_RANGE_S)


def check_full_well(value, name: str = "full_well") -> float:
    return check_number(value, name, *defaults.FULL_WELL_RANGE_E)


def check_beta0(value, name: str = "beta0") -> float:
    return check_number(value, name, *defaults.BETA0_RANGE)


def check_magnitude(value, name: str = "magnitude") -> float:
    return check_number(value, name, *defaults.MAGNITUDE_RANGE)


def check_choice(value, name: str, choices: tuple[str, ...]) -> str:
    if value not in choices:
        raise InputError(name, f"must be one of {', '.join(choices)}, got {shown(value)}")
    return value
