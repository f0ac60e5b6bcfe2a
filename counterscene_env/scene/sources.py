"""Where episodes come from: a scenario spec -> scenes. The one place specs are resolved.

A spec is a generated road (``highway``, ``merge``, ``intersection``, ``roundabout``: a fresh
highway-env recording per episode), ``scenarionet:DIR`` (real logs converted by ScenarioNet),
``commonroad:DIR`` (CommonRoad XML scenarios, one scene per distinct recording), a
dataset directory or shard file written by ``counterscene generate``, or (for an env) a list of
any of these (each episode picks one uniformly). A stress run takes a mixture as one string,
the specs joined by commas (``highway,merge,intersection,roundabout``): its episodes take the
specs in turn.

- :class:`SceneSource` draws one scene per env reset from the generator the env passes, so the
  same env seed gives the same scenes.
- :func:`scenes_for` gives the scene of each episode of a stress run in order; a stored
  source with fewer scenes than episodes can seat another vehicle as the ego on each pass
  (``egos``, the rule of ``scene/egos.py``).

A stored scene that cannot be played (no step after its "now", its ego absent then, no lane
in its map: ``core.unplayable_reason``; or a CommonRoad file that does not read) is skipped
and counted by reason in :data:`SKIPPED`; an episode on a short log ends
with the log (``ClosedLoop`` caps its length at the log's last step). A stress run can ask for
more: ``scenes_for(..., min_future=S)`` seats only stored scenes with at least ``S`` s of log
after "now" (``Scene.future_duration``).
"""

from __future__ import annotations

import copy
from collections import Counter
from collections.abc import Callable, Iterator, Mapping, Sequence
from pathlib import Path

import numpy as np

from counterscene_env.config import COMMONROAD_PREFIX, SCENARIONET_PREFIX, Scenario
from counterscene_env.scene import prefetch
from counterscene_env.scene.core import TOO_SHORT, Scene, unplayable_reason
from counterscene_env.scene.egos import ego_choices, with_ego

#: Generated scenes take their seed from [0, SEED_RANGE).
SEED_RANGE = 2**31 - 1


#: Joins the specs of a mixed stress run.
MIX_SEPARATOR = ","


def mixed_parts(spec: str) -> list[str]:
    """The specs of a mixture ``a,b,...`` (a path that exists, commas and all, is one spec)."""
    if MIX_SEPARATOR not in spec or spec_path(spec).exists():
        return [spec]
    return [part.strip() for part in spec.split(MIX_SEPARATOR)]


def is_generated(spec: str) -> bool:
    """Whether every part of ``spec`` is a generated road (a new recording each episode)."""
    return all(part in Scenario.values() for part in mixed_parts(spec))


def check_spec(spec: str) -> str:
    """``spec`` if it is a generated road, an existing path (after ``scenarionet:``), or a
    comma-joined mixture of these.

    Raises:
        ValueError: none of these (the message names the bad part, the roads and the path
            forms).
    """
    parts = mixed_parts(spec)
    if len(parts) > 1:
        for part in parts:
            check_spec(part)
        return spec
    bare = spec.removeprefix(SCENARIONET_PREFIX).removeprefix(COMMONROAD_PREFIX)
    if spec not in Scenario.values() and not bare.strip():
        # An empty path would read the working directory.
        raise ValueError(f"scenario {spec!r} names no path")
    if spec not in Scenario.values() and not spec_path(spec).exists():
        raise ValueError(
            f"unknown scenario {spec!r}: not one of {list(Scenario.values())}, and no such "
            f"path (use '{SCENARIONET_PREFIX}DIR', '{COMMONROAD_PREFIX}DIR' or a dataset "
            "directory)"
        )
    return spec


def spec_path(spec: str) -> Path:
    """The path of a stored spec, without its ``scenarionet:`` / ``commonroad:`` prefix."""
    return Path(spec.removeprefix(SCENARIONET_PREFIX).removeprefix(COMMONROAD_PREFIX))


#: Stored scenes skipped, by spec (this process): how many for each reason
#: (``core.unplayable_reason``'s, or a CommonRoad file that does not read).
SKIPPED: dict[str, Counter[str]] = {}
#: The reason of a CommonRoad file that does not read (its message is in the import report).
UNREADABLE = "the file does not read as a scenario"


def skip_text(skipped: Mapping[str, int]) -> str:
    """``"2 skipped: 1 too short for an episode, 1 its map has no lanes"``; "" for none."""
    if not skipped:
        return ""
    reasons = ", ".join(f"{n} {reason}" for reason, n in sorted(skipped.items()))
    return f"{sum(skipped.values())} skipped: {reasons}"


def stored_scenes(spec: str) -> Iterator[Scene]:
    """The playable scenes of a stored spec (``scenarionet:DIR``, ``commonroad:DIR``, a
    dataset directory or shard), in order; the others are counted in :data:`SKIPPED`."""
    report: dict = {}
    skipped: Counter[str] = Counter()
    if spec.startswith(COMMONROAD_PREFIX):
        from counterscene_env.scene.commonroad import iter_commonroad

        scenes: Iterator[Scene] = iter_commonroad(spec_path(spec), report=report)
    else:
        from counterscene_env.scene.reading import iter_scenarionet, iter_scenes

        def count(_name: str) -> None:
            skipped[TOO_SHORT] += 1

        # scenarionet:DIR reads logs only: a dataset under that prefix is refused, not read as
        # if it were one (a bare path may be either).
        read = iter_scenarionet if spec.startswith(SCENARIONET_PREFIX) else iter_scenes
        scenes = (scene for scene, _ in read(spec_path(spec), on_short=count))
    SKIPPED[spec] = skipped
    for scene in scenes:
        reason = unplayable_reason(scene)
        if reason is None:
            yield scene
        else:
            skipped[reason] += 1
    too_short = report.get("too_short", 0)  # CommonRoad files, counted by their reader
    unreadable = len(report.get("skipped", {})) - too_short
    for reason, n in ((TOO_SHORT, too_short), (UNREADABLE, unreadable)):
        if n:
            skipped[reason] += n


class SceneSource:
    """Draws the factual scene of each episode (module docstring).

    Args:
        spec: a scenario name, ``scenarionet:DIR``, a dataset path, or a non-empty list of them.

    Raises:
        ValueError: an unknown name, a path that does not exist, or a stored spec with no
            playable scene (checked at construction: its scenes are read then, once per
            process, so a bad config fails at ``gym.make`` or is refused by ``reset``, not
            at a draw).
    """

    def __init__(self, spec: str | Sequence[str]) -> None:
        specs = [spec] if isinstance(spec, str) else spec
        listed = isinstance(specs, list | tuple) and len(specs) > 0
        if not listed or not all(isinstance(s, str) for s in specs):
            raise ValueError(f"scenario must be a name, a path or a list of them, got {spec!r}")
        self.specs = [check_spec(s) for s in specs]
        self._cache: dict[str, list[Scene]] = {}
        for part in self.specs:
            if part not in Scenario.values():
                try:
                    self._scenes(part)
                except FileNotFoundError as err:
                    raise ValueError(f"scenario {part!r}: {err}") from None
        #: The coming draws, in order: (spec, seed or index), and the recording made ahead
        #: for a generated road's.
        self._ahead: list[tuple[tuple[str, int], prefetch.Prefetch | None]] = []
        #: Draws served by a recording made ahead (:meth:`prefetch`), this process.
        self.served_ahead = 0

    def draw(self, rng: np.random.Generator, prefetching: bool = False) -> Scene:
        """One scene: pick a spec, then a fresh recording (generated) or a stored scene; the
        recording :meth:`prefetch` made if it is this one. ``prefetching``: the caller will
        :meth:`prefetch` after this draw, so the background process is started first (it is
        ready by then: it starts while this scene is recorded)."""
        if prefetching and any(spec in Scenario.values() for spec in self.specs):
            prefetch.start()
        spec, k = self._pick(rng)
        guess, ahead = self._ahead.pop(0) if self._ahead else (None, None)
        if guess != (spec, k):  # the draws went another way: the later guesses are wrong too
            self._ahead.insert(0, (guess, ahead))
            self.drop_prefetch()
            ahead = None
        if spec in Scenario.values():
            after = self._ahead[0][1] if self._ahead else None
            if ahead is not None and ahead.in_progress and after is not None:
                # Rather than wait for the process, record the next draw's scene here.
                after.record_here()
            scene = ahead.take(spec, k) if ahead is not None else None
            self.served_ahead += scene is not None
            if scene is None:
                from counterscene_env.scene.highway import generate

                scene = generate(spec, k)
            return scene
        return self._scenes(spec)[k]

    def prefetch(
        self,
        rng: np.random.Generator,
        between: Callable[[np.random.Generator], object] | None = None,
    ) -> None:
        """Start recording, in a background process, the scenes that the next draws from
        ``rng`` would give (``rng`` is not advanced; ``scene/prefetch.py``): the next one, and
        the one after if ``between`` makes the draws the caller takes from ``rng`` between two
        of ours (an env: its episode seed). Nothing for stored specs or in a daemonic
        process; a recording already made ahead for one of these draws is kept."""
        if not prefetch.available():
            return
        rng = copy.deepcopy(rng)
        keys = [self._pick(rng)]
        if between is not None:
            between(rng)
            keys.append(self._pick(rng))
        n = min(len(keys), len(self._ahead))
        if [key for key, _ in self._ahead[:n]] != keys[:n]:
            self.drop_prefetch()
        for _, ahead in self._ahead[len(keys) :]:  # guesses beyond what can be foreseen now
            if ahead is not None:
                ahead.cancel()
        del self._ahead[len(keys) :]
        for spec, k in keys[len(self._ahead) :]:
            ahead = prefetch.Prefetch(spec, k) if spec in Scenario.values() else None
            self._ahead.append(((spec, k), ahead))

    def drop_prefetch(self) -> None:
        """Withdraw the recordings made ahead that no draw has taken yet."""
        for _, ahead in self._ahead:
            if ahead is not None:
                ahead.cancel()
        self._ahead = []

    @property
    def recording_ahead(self) -> bool:
        """Whether a background process is recording a scene for this source right now.
        Asking also moves a rejected recording on to its next seed (``Prefetch.running``), so
        an env asks at every frame."""
        return any(a is not None and a.running for _, a in self._ahead)

    def __getstate__(self) -> dict:
        # A recording ahead belongs to this process (a copy or a pickle records its own).
        return {**self.__dict__, "_ahead": []}

    def _pick(self, rng: np.random.Generator) -> tuple[str, int]:
        """The spec and the seed (generated) or scene index (stored) of a draw."""
        spec = (
            self.specs[int(rng.integers(len(self.specs)))] if len(self.specs) > 1 else self.specs[0]
        )
        if spec in Scenario.values():
            return spec, int(rng.integers(SEED_RANGE))
        return spec, int(rng.integers(len(self._scenes(spec))))

    def _scenes(self, spec: str) -> list[Scene]:
        if spec not in self._cache:
            self._cache[spec] = loaded_scenes(spec)
        return self._cache[spec]


#: Stored specs read in this process: spec -> (the files' stamp, their playable scenes). The
#: envs of one vector env (and a stress run's envs) draw from one list, not a copy each.
_LOADED: dict[str, tuple[tuple, list[Scene]]] = {}
#: Specs kept in :data:`_LOADED`; the oldest read is dropped first.
LOADED_SPECS = 4


def loaded_scenes(spec: str) -> list[Scene]:
    """The playable scenes of a stored spec (:func:`stored_scenes`), read once per process
    while its files are unchanged (same names, sizes and modification times). Scenes are
    read-only records, so every :class:`SceneSource` of the process shares the one list.

    Raises:
        FileNotFoundError: the spec holds no playable scene.
    """
    stamp = _stamp(spec_path(spec))
    kept = _LOADED.get(spec)
    if kept is not None and kept[0] == stamp:
        return kept[1]
    scenes = list(stored_scenes(spec))
    if not scenes:
        why = skip_text(SKIPPED.get(spec, {})) or "no scene files"
        raise FileNotFoundError(f"no playable scene in {spec_path(spec)} ({why})")
    _LOADED.pop(spec, None)
    _LOADED[spec] = (stamp, scenes)
    while len(_LOADED) > LOADED_SPECS:
        del _LOADED[next(iter(_LOADED))]
    return scenes


def _stamp(path: Path) -> tuple:
    """Names, sizes and modification times [ns] of the files at ``path`` (a file or a tree)."""
    files = [path] if path.is_file() else sorted(f for f in path.rglob("*") if f.is_file())
    return tuple((str(f), st.st_size, st.st_mtime_ns) for f in files for st in [f.stat()])


def scenes_for(
    spec: str,
    episodes: int,
    seed: int,
    egos: int = 1,
    ahead: int = 0,
    min_future: float = 0.0,
) -> Iterator[Scene]:
    """The scene of each of ``episodes`` episodes of a stress run.

    A generated road gives the first ``episodes`` safe seeds from ``seed``, exactly the scenes
    ``counterscene generate --scenario S --scenes N --seed S0`` writes; a stored spec gives its
    scenes in order. Sources with fewer scenes than episodes are cycled: pass k over the
    scenes seats ego choice ``k mod min(egos, choices)`` of each (``scene.egos.ego_choices``:
    choice 0 is the recorded ego), so ``egos = 1`` replays every scene with its own ego. In a
    mixture ``a,b,...`` of n specs, episode i is the ``i // n``-th scene of part ``i % n``.
    With ``ahead > 0`` a generated road's next seeds, up to ``ahead``, are recorded in a
    background process before they are asked for (``scene/prefetch.py``; not in a daemonic
    process): the same scenes, sooner. ``min_future`` [s]: a stored scene with less log after
    its "now" (``Scene.future_duration``) is not seated (a generated road records a whole
    episode's length); a stored spec with no scene that long raises ``ValueError``.
    """
    if egos < 1:
        raise ValueError(f"egos must be >= 1, got {egos}")
    parts = mixed_parts(spec)
    if len(parts) > 1:
        n = len(parts)
        # Part j serves episodes j, j + n, ...: ceil((episodes - j) / n) of them.
        sources = [
            scenes_for(p, -(-(episodes - j) // n), seed, egos, -(-ahead // n), min_future)
            for j, p in enumerate(parts)
        ]
        for i in range(episodes):
            yield next(sources[i % n])
        return
    if spec in Scenario.values() and ahead > 0 and prefetch.available():
        yield from prefetch.safe_scenes_ahead(spec, seed, episodes, ahead)
        return
    if spec in Scenario.values():
        from counterscene_env.scene.highway import generate

        next_seed = seed
        for _ in range(episodes):
            scene = generate(spec, next_seed)
            next_seed = scene.metadata["seed"] + 1
            yield scene
        return
    yield from _stored_for(spec, episodes, egos, min_future)


def _stored_for(spec: str, episodes: int, egos: int, min_future: float) -> Iterator[Scene]:
    """:func:`scenes_for` of a stored spec: its scenes in order, then again with the next
    ego choice on each pass."""
    cache: list[Scene] = []
    short = 0
    for scene in stored_scenes(spec):
        if len(cache) == episodes:
            return
        if scene.future_duration < min_future:
            short += 1
            continue
        cache.append(scene)
        yield scene
    if not cache and short:
        raise ValueError(
            f"{spec_path(spec)}: none of its {short} scenes has min_future = {min_future:g} s "
            "of log after its start"
        )
    if not cache:
        raise FileNotFoundError(f"{spec_path(spec)}: no scenes")
    choices: dict[int, list[int]] = {}
    for i in range(len(cache), episodes):
        j, k = i % len(cache), i // len(cache)
        scene = cache[j]
        if egos > 1:
            rows = choices.setdefault(j, ego_choices(scene)[:egos])
            scene = with_ego(scene, rows[k % len(rows)])
        yield scene
