"""Action checks and observation bounds of the envs, on top of highway-env's types."""

from __future__ import annotations

from typing import Any

import numpy as np
from gymnasium import spaces
from highway_env.envs.common.observation import GrayscaleObservation, KinematicObservation

from counterscene_env.envs.kinematics import observe_kinematics


def check_action(space: spaces.Space, action: Any, who: str = "action") -> None:
    """Refuse an action that does not fit ``space``, before anything is applied: not numbers
    (strings, None, an int too large for a float), a wrong shape, NaN or inf (ValueError), a
    value outside a discrete space (ValueError). Out-of-range Box values are clipped by
    highway-env.

    Raises:
        TypeError: not numbers; ValueError: the rest. The message names ``who``.
    """
    if isinstance(space, spaces.Tuple):
        if not isinstance(action, tuple | list) or len(action) != len(space.spaces):
            raise ValueError(f"{who} must be a tuple of {len(space.spaces)} actions")
        for k, (sub, a) in enumerate(zip(space.spaces, action, strict=True)):
            check_action(sub, a, f"{who}[{k}]")
    elif isinstance(space, spaces.Box):
        a = _numbers(action, who)
        if a.shape != space.shape:
            raise ValueError(f"{who} must have shape {space.shape}, got {a.shape}")
        if not np.isfinite(a).all():
            raise ValueError(f"{who} contains NaN or inf: {a.tolist()}")
    else:
        try:
            value = np.asarray(action).item() if np.ndim(action) == 0 else action
            ok = space.contains(value)
        except (TypeError, ValueError):
            ok = False
        if not ok:
            raise ValueError(f"{who} {action!r} is not in the action space {space}")


def _numbers(action: Any, who: str) -> np.ndarray:
    """``action`` as a numeric array, or TypeError (strings, None, objects, bools)."""
    try:
        a = np.asarray(action)
    except (TypeError, ValueError, OverflowError) as exc:
        raise TypeError(f"{who} must be numbers, got {action!r} ({exc})") from None
    if a.dtype.kind not in "iuf":
        raise TypeError(f"{who} must be numbers, got {action!r} ({a.dtype} values)")
    return a.astype(np.float64)


#: Kinematics features in [-1, 1] by construction.
UNIT_FEATURES = {"presence", "cos_h", "sin_h", "cos_d", "sin_d"}
#: Features a ``Kinematics`` observation can read (highway-env's ``Vehicle.to_dict``).
KINEMATIC_FEATURES = (
    "presence",
    "x",
    "y",
    "vx",
    "vy",
    "heading",
    "cos_h",
    "sin_h",
    "cos_d",
    "sin_d",
    "long_off",
    "lat_off",
    "ang_off",
)
#: Kinematics features that need no lane of the observed vehicles (all but the lane offsets).
LANE_FREE_FEATURES = frozenset(KINEMATIC_FEATURES) - {"long_off", "lat_off", "ang_off"}


def bounded_space(space: spaces.Space, obs_type: Any) -> spaces.Space:
    """[-1, 1] when every Kinematics feature is there: by construction, or normalised and
    clipped (highway-env scales only the features of ``features_range``; without one, its
    defaults cover x, y, vx, vy)."""
    if not (isinstance(obs_type, KinematicObservation) and isinstance(space, spaces.Box)):
        return space
    scaled = set(obs_type.features_range or ("x", "y", "vx", "vy"))
    unit = UNIT_FEATURES | (scaled if obs_type.normalize and obs_type.clip else set())
    if set(obs_type.features) <= unit:
        return spaces.Box(-1.0, 1.0, space.shape, space.dtype)
    return space


def as_highway_action(action: Any) -> Any:
    """highway-env's action types index dicts with ints, use arrays for boxes and tuples for
    several egos."""
    if isinstance(action, tuple):
        return tuple(as_highway_action(a) for a in action)
    if isinstance(action, np.ndarray) and action.ndim == 0:
        return int(action)
    if isinstance(action, np.integer):
        return int(action)
    return action


class RowCappedKinematics(KinematicObservation):
    """highway-env's ``Kinematics`` observation, never more than ``vehicles_count`` rows.

    With ``vehicles_count = 1`` highway-env asks the road for the ``0`` nearest vehicles,
    which it reads as "no limit", and returns every vehicle: an observation outside its
    ``(1, F)`` space. Every other count already gives exactly ``vehicles_count`` rows.

    The rows are computed without pandas (:func:`~counterscene_env.envs.kinematics.
    observe_kinematics`, the same values bit for bit); highway-env's own method runs for the
    options that does not cover.
    """

    def observe(self) -> np.ndarray:
        fast = observe_kinematics(self)
        if fast is not None:
            return fast
        obs = super().observe()
        return obs[: self.vehicles_count] if obs.ndim == 2 else obs


def kept_if_unchanged(old: spaces.Space | None, new: spaces.Space) -> spaces.Space:
    """``old`` if it equals ``new`` (same kind, shape, bounds), else ``new``.

    highway-env builds new spaces at every reset, each with a fresh, unseeded generator; a
    Gymnasium user seeds a space once (``env.action_space.seed(s)``) and expects its samples
    to be reproducible across episodes. Keeping an unchanged space keeps its generator.
    """
    return old if old is not None and old == new else new


def capped_observation_space(obs_type: Any, space: spaces.Space) -> spaces.Space:
    """``space``, highway-env's space of observation type ``obs_type`` (one part per ego
    under ``MultiAgentObservation``, per part under ``TupleObservation``), each part bounded
    by :func:`bounded_space`; every ``Kinematics`` part becomes a :class:`RowCappedKinematics`
    (its rows kept to ``vehicles_count``), and every ``GrayscaleObservation`` part draws
    headless."""
    parts = getattr(obs_type, "agents_observation_types", None)
    parts = parts if parts is not None else getattr(obs_type, "observation_types", None)
    if parts is not None:
        return spaces.Tuple(
            [capped_observation_space(t, s) for t, s in zip(parts, space.spaces, strict=True)]
        )
    if type(obs_type) is KinematicObservation:
        obs_type.__class__ = RowCappedKinematics
    if isinstance(obs_type, GrayscaleObservation):
        # highway-env's viewer turns itself off under SDL_VIDEODRIVER=dummy (its "no window"
        # switch), and the frames would be zeros or not depending on whether anything in the
        # process had set it. This viewer always draws onto an off-screen surface, which
        # needs no display: it is turned back on.
        obs_type.viewer.enabled = True
    return bounded_space(space, obs_type)


def reads_lanes(observation: dict) -> bool:
    """Whether an observation config reads lane coordinates, so that every vehicle's lane
    must be kept up to date (costly on big maps)."""
    obs = observation.get("observation_config", observation)
    features = set(obs.get("features", KinematicObservation.FEATURES))
    return not (obs.get("type") == "Kinematics" and features <= LANE_FREE_FEATURES)
