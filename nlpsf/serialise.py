"""JSON-safe values: the one owner of turning results into what JSON can carry.

JSON has no NaN or infinity (a silent ``Infinity`` token breaks clients), and numpy scalars are not
JSON numbers; the library's ``to_dict`` methods, the CLI's ``--json`` and the service all use these.
"""

from __future__ import annotations

import math
from typing import Any


def json_number(value: float | None) -> float | None:
    """A float for JSON: None for None, NaN and infinities."""
    return None if value is None or not math.isfinite(value) else float(value)


def json_safe(value: Any) -> Any:
    """``value`` with non-finite floats as None, numpy scalars as Python numbers, tuples as lists
    and dict keys as strings, recursively."""
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, dict):
        return {str(k): json_safe(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [json_safe(v) for v in value]
    if hasattr(value, "item") and callable(value.item):  # numpy scalar
        return json_safe(value.item())
    return value
