"""Copies of frozen dataclasses whose values are already checked."""

from __future__ import annotations

from typing import TypeVar

T = TypeVar("T")


def replaced(instance: T, **changes) -> T:
    """``dataclasses.replace(instance, **changes)`` of a frozen dataclass whose values are already
    checked (no ``__post_init__``): its fields copied as they are rather than passed through
    ``__init__`` again (a Solution has 30; an SCA range's answer is the most demanding node's with
    its range added, and moves its request and scene to the nodes). The caller checks what it changes."""
    copy = object.__new__(type(instance))
    copy.__dict__.update(instance.__dict__)
    copy.__dict__.update(changes)
    return copy
