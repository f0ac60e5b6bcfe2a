"""highway-env's IDM class constants as found at import, kept from process-wide changes.

Building a highway-env ``IntersectionEnv`` (ours, or a user's ``gym.make("intersection-v1")``)
overwrites IDM class constants for the whole process, so a scene recorded after it would
differ from the same seed recorded before it. Recordings (``scene/highway.py``) run inside
:func:`pristine_idm_constants`, and the closed loop's IDM cars (``sim/traffic.py``) carry
:func:`idm_defaults` on the instance.
"""

from __future__ import annotations

import contextlib
from collections.abc import Iterator

from highway_env.vehicle.behavior import IDMVehicle

from counterscene_env.scene.gap_acceptance import GapAcceptingVehicle
from counterscene_env.scene.highway_vehicle import ForwardIDMVehicle

__all__ = ["idm_defaults", "pristine_idm_constants"]


@contextlib.contextmanager
def pristine_idm_constants() -> Iterator[None]:
    """Record with highway-env's own IDM constants, whatever ran before, and leave the
    caller's as they were.

    Building an ``IntersectionEnv`` (ours, or a user's ``gym.make("intersection-v1")``) sets
    IDM class constants process-wide; a scene recorded after it would differ from the same
    seed recorded before it. So the constants are set to :data:`_IDM_DEFAULTS` on entry and
    the caller's values restored on exit.
    """
    saved = {(c, n): c.__dict__.get(n, _MISSING) for c in _IDM_CLASSES for n in _IDM_NAMES}
    try:
        _set_idm_constants(_IDM_DEFAULTS)
        yield
    finally:
        _set_idm_constants(saved)


def _set_idm_constants(values: dict) -> None:
    for (c, n), v in values.items():
        if v is not _MISSING:
            setattr(c, n, v)
        elif n in c.__dict__:
            delattr(c, n)


_MISSING = object()
_IDM_NAMES = ("DISTANCE_WANTED", "COMFORT_ACC_MAX", "COMFORT_ACC_MIN", "TIME_WANTED", "DELTA")
_IDM_CLASSES = (IDMVehicle, ForwardIDMVehicle, GapAcceptingVehicle)
#: highway-env's IDM constants as this module found them at import, before any of our envs
#: existed (``counterscene_env`` is imported before a user builds highway-env envs with it).
_IDM_DEFAULTS = {(c, n): c.__dict__.get(n, _MISSING) for c in _IDM_CLASSES for n in _IDM_NAMES}


def idm_defaults() -> dict[str, float]:
    """highway-env's ``IDMVehicle`` constants (``DISTANCE_WANTED`` [m], ``COMFORT_ACC_MAX`` and
    ``COMFORT_ACC_MIN`` [m/s^2], ``TIME_WANTED`` [s], ``DELTA``) as found at import: set on an
    IDM vehicle instance, they shield it from the process-wide changes highway-env's
    intersection env makes (``sim/traffic.py``)."""
    return {n: _IDM_DEFAULTS[(IDMVehicle, n)] for n in _IDM_NAMES}
