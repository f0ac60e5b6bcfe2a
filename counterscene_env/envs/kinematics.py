"""highway-env's ``Kinematics`` observation without pandas, bit for bit.

Why this module exists: the project's rule is to use highway-env, not re-implement it. This is
a deliberate, measured exception. highway-env's ``KinematicObservation.observe`` builds a pandas
DataFrame per call (one ``to_dict`` record per vehicle, concatenated, normalised and reindexed
column by column): 10-17 % of a ``CounterScene-v0`` step in the profiles of the second
fast-replans session, 3.5 ms a call against 0.09 ms here (docs/history/performance.md, item 5
of "What changed in the second fast-replans session"). Here the same rows are built in one
float64 array, with the same arithmetic in the same order, so the result is identical, not
approximately equal (``tests/test_kinematics_obs.py`` checks it bit for bit against
highway-env's own method, in every scenario, for many option combinations).

What is still highway-env's: the choice and order of the observed objects
(``Road.close_objects_to``), the default ``features_range`` (``normalize_obs``), every vehicle
property a feature reads (``position``, ``velocity``, ``direction``, ...), ``to_dict`` of any
object whose class overrides it, and the random row shuffle (``env.np_random.shuffle`` on an
array of the same shape). Options not reproduced exactly (listed in ``_supported`` and
``_scaling``) are left to highway-env's method: ``observe_kinematics`` returns None.

Tested against highway-env 1.12.0 and 1.12.1 (pyproject: ``>=1.12,<1.13``). The code it
mirrors (``observe``, ``normalize_obs``, ``close_objects_to``, ``to_dict``, ``lmap``) is the
same since 1.10.1, but the env itself needs 1.12's config keys; a new release must pass
``tests/test_kinematics_obs.py`` before the pin is widened.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from highway_env.envs.common.observation import KinematicObservation
from highway_env.vehicle.kinematics import Vehicle

#: Feature -> (the property ``Vehicle.to_dict`` reads, index into it or None). ``"one"`` and
#: ``"zero"`` are constants: presence, and the intentions when they are not observed.
SOURCES: dict[str, tuple[str, int | None]] = {
    "presence": ("one", None),
    "x": ("position", 0),
    "y": ("position", 1),
    "vx": ("velocity", 0),
    "vy": ("velocity", 1),
    "heading": ("heading", None),
    "cos_h": ("direction", 0),
    "sin_h": ("direction", 1),
    "cos_d": ("destination_direction", 0),
    "sin_d": ("destination_direction", 1),
    "long_off": ("lane_offset", 0),
    "lat_off": ("lane_offset", 1),
    "ang_off": ("lane_offset", 2),
}
#: The features ``to_dict(origin)`` makes relative to the origin vehicle.
RELATIVE = ("x", "y", "vx", "vy")
_INTENTIONS = ("cos_d", "sin_d")
_CONSTANTS = {"one": 1, "zero": 0}
#: highway-env's ``space()``: a float32 box. Known, so no Box is built per call to read it.
_FLOAT32_SPACE = KinematicObservation.space


def observe_kinematics(obs: KinematicObservation) -> np.ndarray | None:
    """What ``KinematicObservation.observe`` returns for ``obs``, capped to
    ``obs.vehicles_count`` rows; None when highway-env must compute it (no road, an
    unusual option or range: the caller falls back to highway-env's method).

    Returns:
        ``[vehicles_count, F]`` array of ``obs.space()``'s dtype, one row per observed object
        (the observer first, zero rows for missing objects), one column per ``obs.features``
        entry: positions in m, speeds in m/s, angles in rad (or in [-1, 1] when normalised).
        With ``vehicles_count = 1`` highway-env returns every nearby object: this is its
        first row (the random stream is still advanced as for all of them).
    """
    env, count, features = obs.env, obs.vehicles_count, list(obs.features)
    ego = obs.observer_vehicle
    if not _supported(obs, ego, count, features):
        return None
    scaling = _scaling(obs, features) if obs.normalize else ([], 0.0, 1.0)
    if scaling is None:
        return None
    # highway-env's own selection and order of the nearby objects (count - 1 = 0 means all).
    close = env.road.close_objects_to(
        ego,
        env.PERCEPTION_DISTANCE,
        count=count - 1,
        see_behind=obs.see_behind,
        sort=obs.order == "sorted",
        vehicles_only=not obs.include_obstacles,
    )
    shown = close[-count + 1 :][: count - 1] if close else []
    # The observer's row is its plain to_dict(): absolute, intentions observed.
    ego_row = _values(ego, _sources(features, True))
    rows = [ego_row]
    origin = None if obs.absolute else ego
    relative = [j for j, f in enumerate(features) if f in RELATIVE and origin is not None]
    sources = _sources(features, bool(obs.observe_intentions))
    for v in shown:
        if type(v).to_dict is Vehicle.to_dict:
            row = _values(v, sources)
            for j in relative:  # to_dict(origin): d[key] -= origin.to_dict()[key], same scalars
                row[j] = row[j] - ego_row[j]
            rows.append(row)
        else:  # an obstacle, or a class with its own to_dict: exactly its record, NaN if missing
            d = v.to_dict(origin, observe_intentions=obs.observe_intentions)
            rows.append([d.get(f, np.nan) for f in features])
    out = np.zeros((count, len(features)))  # float64, as pandas; padding rows stay 0
    filled = out[: len(rows)]
    filled[:] = rows
    cols, low, width = scaling
    if cols:
        # utils.lmap(v, [low, high], [-1, 1]) = -1 + (v - low) * 2 / (high - low), same order.
        scaled = -1 + (filled[:, cols] - low) * 2 / width
        filled[:, cols] = np.clip(scaled, -1, 1) if obs.clip else scaled
    if obs.order == "shuffled":
        # highway-env shuffles rows 1: of its whole array, which with vehicles_count = 1 holds
        # every nearby object: shuffle the same shape so the generator advances the same way.
        rest = out[1:] if count > 1 else np.empty((len(close), len(features)))
        env.np_random.shuffle(rest)
    dtype = np.float32 if type(obs).space is _FLOAT32_SPACE else obs.space().dtype
    return out.astype(dtype)


def _supported(obs: KinematicObservation, ego: Any, count: Any, features: list[str]) -> bool:
    """Whether this module reproduces highway-env for ``obs``'s options."""
    return (
        bool(obs.env.road)
        and isinstance(count, int | np.integer)
        and count >= 1
        and len(set(features)) == len(features)  # pandas treats repeated columns its own way
        and all(f in SOURCES for f in features)
        and type(ego).to_dict is Vehicle.to_dict  # the origin of every relative row
        and type(obs).normalize_obs is KinematicObservation.normalize_obs
    )


def _sources(features: list[str], intentions: bool) -> list[tuple[str, int | None]]:
    """Where ``Vehicle.to_dict(observe_intentions=intentions)`` takes each feature from."""
    return [("zero", None) if f in _INTENTIONS and not intentions else SOURCES[f] for f in features]


def _values(vehicle: Vehicle, sources: list[tuple[str, int | None]]) -> list[Any]:
    """``vehicle.to_dict()``'s values at ``sources``, in their order, reading only the
    properties they need (pure properties: the same values to_dict reads)."""
    got = dict(_CONSTANTS)
    for name, _ in sources:
        if name not in got:
            got[name] = getattr(vehicle, name)
    return [got[name] if i is None else got[name][i] for name, i in sources]


def _scaling(obs: KinematicObservation, features: list[str]) -> tuple | None:
    """(columns, low ``[C]``, high - low ``[C]``) of the features ``normalize_obs`` scales,
    or None for a range this module does not reproduce exactly."""
    if not obs.features_range:
        # highway-env's lazy default range (from the observer's side lanes), set on obs as it
        # does: normalize_obs only tests ``feature in df``, so an empty dict stands for df.
        KinematicObservation.normalize_obs(obs, {})
    cols, low, width = [], [], []
    for feature, f_range in obs.features_range.items():
        if feature not in features:
            continue
        lo, hi = f_range[0], f_range[1]
        if not (_plain(lo) and _plain(hi)) or hi == lo:
            return None
        cols.append(features.index(feature))
        low.append(lo)
        width.append(hi - lo)  # computed as lmap computes it, then used as a float64
    return cols, np.array(low, dtype=np.float64), np.array(width, dtype=np.float64)


def _plain(x: Any) -> bool:
    """A bound that numpy turns into the same float64 in a scalar and an array operation
    (float, float64, or an int a float64 holds exactly)."""
    return type(x) in (float, np.float64) or (type(x) is int and abs(x) <= 2**53)
