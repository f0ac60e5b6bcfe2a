"""Read, check and repair the tracks of a ScenarioNet scenario (``scene/scenarionet.py`` turns
them into a :class:`~counterscene_env.scene.core.Scene`).

``VEHICLE``/``PEDESTRIAN``/``CYCLIST`` map to ``"vehicle"``/``"pedestrian"``/``"cyclist"``;
every other type (``TRAFFIC_CONE``, ``TRAFFIC_BARRIER``, ...) becomes ``"other"`` and is kept
for collision checks. The ego (``metadata["sdc_id"]``) is row 0, the other tracks follow in
file order. Speed is the norm of the logged velocity, negative where it points backwards
relative to the heading (a reversing car) (m/s). Box arrays may be ``(T,)`` or ``(T, 1)``.

One bad track never costs the scene. Each track is repaired where it can be, and every repair
is listed in ``metadata["repairs"]`` (track id -> what was done):

- a non-finite position, heading or velocity at a valid step: that step is made invalid;
- a box dimension that is zero, negative or NaN at every valid step: the type's default from
  :data:`DEFAULT_BOX` (a vehicle takes the median of its valid sizes where some are good);
- a vehicle whose length is below its width (the nuScenes ego box is stored as 1.73 x 4.08):
  the two are swapped;
- a position that jumps faster than any road user: the lone sample, or the track outside its
  longest consistent piece, is made invalid (``core.drop_impossible_jumps``, on the 0.1 s grid,
  by ``scene/scenarionet.py``);
- a velocity of exactly (0, 0) at the last valid step of a piece of track that is still
  moving (at least half the previous step's displacement, after a step with a velocity of
  1 m/s or more): the previous step's velocity. ScenarioNet's nuScenes converter writes
  (0, 0) at the last step of every track (287 tracks filled in nuScenes mini, docs/scenes.md:
  a stop from 10 m/s in one frame), which would read as a hard brake.

A track that cannot be repaired (no state dict, a missing or misshapen field, a length other
than the ego's, no valid step left) is dropped, with the reason in
``metadata["dropped_tracks"]`` (track id -> reason). Only a broken ego track fails the file.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np

from counterscene_env.geometry import wrap_angle
from counterscene_env.scene.core import SceneError

__all__ = ["DEFAULT_BOX", "TRACK_TYPES", "ScenarioNetError", "ScenarioNetTracks", "read_tracks"]


class ScenarioNetError(SceneError):
    """A ScenarioNet file is malformed; the message names the file and the field."""


#: Agent type of each ScenarioNet track type; anything else is ``"other"``.
TRACK_TYPES = {"VEHICLE": "vehicle", "PEDESTRIAN": "pedestrian", "CYCLIST": "cyclist"}
#: (length, width) m for a box dimension a track never gives: typical sizes of each type.
DEFAULT_BOX = {
    "vehicle": (4.5, 2.0),
    "pedestrian": (0.7, 0.7),
    "cyclist": (1.8, 0.7),
    "other": (0.5, 0.5),
}
_STATE_FIELDS = ("position", "heading", "velocity", "valid", "length", "width")


@dataclass
class ScenarioNetTracks:
    """Every usable track at the source rate; rows align, the ego is row 0.

    ``position [N, T_src, 2] m``, ``heading [N, T_src] rad``, ``velocity [N, T_src, 2] m/s``,
    ``valid [N, T_src]``, ``extents [N, 2] m``.
    """

    ids: list[str]
    types: list[str]
    position: np.ndarray
    heading: np.ndarray
    velocity: np.ndarray
    valid: np.ndarray
    extents: np.ndarray
    repairs: dict[str, list[str]]
    dropped: dict[str, str]

    @property
    def num_source_steps(self) -> int:
        return self.valid.shape[1]

    def repair(self, track: str, what: str) -> None:
        self.repairs.setdefault(track, []).append(what)

    def drop_empty(self, valid: np.ndarray) -> None:
        """Drop every non-ego track left with no valid step on the 10 Hz grid."""
        if not valid[0].any():
            raise ScenarioNetError(f"the sdc track {self.ids[0]!r} has no valid step at 10 Hz")
        for row in np.flatnonzero(~valid.any(axis=1)):
            self.dropped[self.ids[row]] = "no valid step on the 0.1 s grid"
            self.repairs.pop(self.ids[row], None)


def read_tracks(
    tracks: Mapping[Any, Any], meta: Mapping[str, Any], source: str
) -> ScenarioNetTracks:
    """Read, check and repair every track (module docstring); the ego's problems are fatal."""
    sdc = meta.get("sdc_id")
    if sdc is None:
        raise ScenarioNetError(f"{source}: missing metadata.sdc_id (the ego's track id)")
    if sdc not in tracks:
        raise ScenarioNetError(f"{source}: metadata.sdc_id {sdc!r} is not a key of tracks")
    rows: list[tuple[str, str, dict[str, np.ndarray]]] = []
    repairs: dict[str, list[str]] = {}
    dropped: dict[str, str] = {}
    for key in [sdc, *(k for k in tracks if k != sdc)]:
        tid, track = str(key), tracks[key]
        where = f"{source}: tracks[{key!r}]"
        try:
            agent_type, state, notes = _read_track(track, where)
            if rows and len(state["valid"]) != rows[0][2]["valid"].shape[0]:
                raise ScenarioNetError(
                    f"{where}.state has {len(state['valid'])} steps, the ego track "
                    f"{rows[0][2]['valid'].shape[0]}"
                )
        except ScenarioNetError as exc:
            if key == sdc:
                raise
            dropped[tid] = str(exc).removeprefix(f"{where}").lstrip(".: ") or "unreadable"
            continue
        if key == sdc and agent_type != "vehicle":
            raise ScenarioNetError(f"{where}: the sdc track has type {track.get('type')!r}")
        if tid in {r[0] for r in rows}:
            raise ScenarioNetError(f"{source}: track ids are not unique as strings")
        if notes:
            repairs[tid] = notes
        rows.append((tid, agent_type, state))
    return ScenarioNetTracks(
        ids=[r[0] for r in rows],
        types=[r[1] for r in rows],
        position=np.stack([r[2]["position"] for r in rows]),
        heading=np.stack([r[2]["heading"] for r in rows]),
        velocity=np.stack([r[2]["velocity"] for r in rows]),
        valid=np.stack([r[2]["valid"] for r in rows]),
        extents=np.stack([r[2]["extent"] for r in rows]),
        repairs=repairs,
        dropped=dropped,
    )


def _read_track(track: Any, where: str) -> tuple[str, dict[str, np.ndarray], list[str]]:
    """One track: its agent type, its arrays at the source rate, and the repairs made."""
    if not isinstance(track, Mapping) or not isinstance(track.get("state"), Mapping):
        raise ScenarioNetError(f"{where}: has no 'state' dict")
    agent_type = TRACK_TYPES.get(str(track.get("type", "")), "other")
    state = _read_state(track["state"], f"{where}.state")
    notes = []
    valid = state["valid"]
    finite = (
        np.isfinite(state["position"]).all(axis=1)
        & np.isfinite(state["heading"])
        & np.isfinite(state["velocity"]).all(axis=1)
    )
    bad = valid & ~finite
    if bad.any():
        notes.append(
            f"{int(bad.sum())} steps with a non-finite position, heading or velocity made invalid"
        )
        valid = valid & finite
    if not valid.any():
        raise ScenarioNetError(f"{where}: no valid step")
    extent, box_notes = _box(state["length"][valid], state["width"][valid], agent_type)
    notes += box_notes
    filled = _fill_final_velocities(state["position"], state["velocity"], valid)
    if filled:
        notes.append(
            f"{filled} zero velocities at the last step of a moving piece of track set to the "
            "step before's"
        )
    state["valid"] = valid
    for name in ("position", "velocity"):
        state[name] = np.where(valid[:, None], state[name], 0.0)
    state["heading"] = wrap_angle(np.where(valid, state["heading"], 0.0))
    state["extent"] = extent
    return agent_type, state, notes


#: A piece of track whose velocity one step before its end is at least this is moving [m/s].
MOVING_VELOCITY = 1.0


def _fill_final_velocities(position: np.ndarray, velocity: np.ndarray, valid: np.ndarray) -> int:
    """Put the previous step's velocity where a moving piece of track ends on (0, 0); edits
    ``velocity [T, 2]`` m/s in place and returns how many steps it filled. ``position
    [T, 2]`` m, ``valid [T]``: the source's own rate (no step length is needed: the last
    displacement is compared with the one before)."""
    ends = np.flatnonzero(valid & ~np.append(valid[1:], False))  # last step of each piece
    filled = 0
    for i in ends:
        if i < 2 or not (valid[i - 1] and valid[i - 2]) or velocity[i].any():
            continue
        if np.hypot(*velocity[i - 1]) < MOVING_VELOCITY:
            continue
        last = np.hypot(*(position[i] - position[i - 1]))
        before = np.hypot(*(position[i - 1] - position[i - 2]))
        if last >= 0.5 * before > 0:
            velocity[i] = velocity[i - 1]
            filled += 1
    return filled


def _read_state(state: Mapping[str, Any], where: str) -> dict[str, np.ndarray]:
    """One track's per-step arrays at the source rate: position [T, 2] m, heading [T] rad,
    velocity [T, 2] m/s, valid [T] bool, length/width [T] m (``(T,)`` or ``(T, 1)`` in)."""
    out: dict[str, np.ndarray] = {}
    for name in _STATE_FIELDS:
        if name not in state:
            raise ScenarioNetError(f"{where}: missing field {name!r}")
        try:
            out[name] = np.asarray(state[name], dtype=np.float64)
        except (TypeError, ValueError) as exc:
            raise ScenarioNetError(f"{where}.{name}: not a numeric array ({exc})") from None
    pos, vel = out["position"], out["velocity"]
    if pos.ndim != 2 or pos.shape[1] not in (2, 3):
        raise ScenarioNetError(f"{where}.position: expected shape (T, 2|3), got {pos.shape}")
    t = pos.shape[0]
    if t == 0:
        raise ScenarioNetError(f"{where}.position: no steps")
    if vel.ndim != 2 or vel.shape[0] != t or vel.shape[1] < 2:
        raise ScenarioNetError(f"{where}.velocity: expected shape ({t}, 2), got {vel.shape}")
    for name in ("heading", "valid", "length", "width"):
        if out[name].shape not in ((t,), (t, 1)):
            raise ScenarioNetError(
                f"{where}.{name}: expected shape ({t},) or ({t}, 1), got {out[name].shape}"
            )
        out[name] = out[name].reshape(t)
    out["valid"] = np.isfinite(out["valid"]) & (out["valid"] != 0)
    out["position"], out["velocity"] = pos[:, :2], vel[:, :2]
    return out


def _box(lengths: np.ndarray, widths: np.ndarray, agent_type: str) -> tuple[np.ndarray, list]:
    """``[2]`` (length, width) m: the median of the good sizes at valid steps, else the type's
    default; a vehicle's swapped box is put right. Returns it and the repairs made."""
    notes = []
    box = []
    for dim, values, default in zip(
        ("length", "width"), (lengths, widths), DEFAULT_BOX[agent_type], strict=True
    ):
        good = values[np.isfinite(values) & (values > 0)]
        if good.size:
            box.append(float(np.median(good)))
        else:
            box.append(default)
            notes.append(f"{dim} missing (0 or NaN): {agent_type} default {default} m")
    if agent_type == "vehicle" and box[0] < box[1]:
        box.reverse()
        notes.append("length and width swapped")
    return np.array(box), notes
