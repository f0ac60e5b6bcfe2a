"""Shared helper of the frozen, documented config dataclasses (Waymax style)."""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from typing import TypeVar

T = TypeVar("T")


def from_mapping(cls: type[T], values: Mapping, what: str) -> T:
    """``cls(**values)``; an unknown key raises a ValueError naming it and the valid keys.

    ``what`` names the settings in the message ("simulation", "guidance", ...).
    """
    names = {f.name for f in dataclasses.fields(cls)}
    unknown = sorted(set(values) - names)
    if unknown:
        raise ValueError(f"unknown {what} keys {unknown}; valid keys: {sorted(names)}")
    return cls(**values)
