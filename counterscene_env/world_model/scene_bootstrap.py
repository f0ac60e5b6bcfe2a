"""Figures pooled over scenes, with 95 % intervals from a bootstrap over scenes (the
statistics of ``counterscene evaluate-model``, ``world_model/evaluate.py``).

The windows of one scene (its start times) and the agents of one window are correlated, so a
figure is kept as per-scene sums and counts, and the scene is the unit resampled. A figure
measured in fewer than :data:`MIN_SCENES` scenes has no interval (``None``, JSON null), as
``report/stats.py``'s ``mean`` has none for fewer than two episodes: every resample of one
scene is that scene, and the interval would be the figure itself, ``[x, x]``, claiming a
certainty that one scene cannot give.
"""

from __future__ import annotations

from collections import defaultdict

import numpy as np

#: Scenes a figure needs measurements in to have an interval (one has no spread to resample).
MIN_SCENES = 2


class SceneSums:
    """Per-scene sums ``[sum, count]`` of named figures, so that intervals can resample scenes.

    A name is ``"<group>/<who>/<key>/<horizon>"`` (``who``: ``model``, ``cv`` or ``log``);
    ``scene`` is the scene's row, shared by its windows (start times).
    """

    def __init__(self) -> None:
        self.sums: dict[str, dict[int, list]] = defaultdict(lambda: defaultdict(lambda: [0.0, 0]))

    def add(self, name: str, scene: int, values: np.ndarray) -> None:
        entry = self.sums[name][scene]
        entry[0] += float(values.sum())
        entry[1] += int(values.size)

    def count(self, name: str, scene: int, hits: int, total: int) -> None:
        entry = self.sums[name][scene]
        entry[0] += hits
        entry[1] += total

    def arrays(self, name: str, scenes: int) -> tuple[np.ndarray, np.ndarray]:
        """``[scenes]`` sums and counts of ``name`` (zero for scenes without it)."""
        s, n = np.zeros(scenes), np.zeros(scenes)
        for i, (a, b) in self.sums.get(name, {}).items():
            s[i], n[i] = a, b
        return s, n


class SceneBootstrap:
    """Pooled figures (sum over scenes of sums / sum of counts) and their 95 % intervals from
    a bootstrap over scenes (``resamples`` draws of the scenes with replacement, the same draws
    for every figure, so ratios between figures are paired). A figure (or either side of a
    ratio) measured in fewer than :data:`MIN_SCENES` scenes has no interval: ``None``."""

    def __init__(self, sums: SceneSums, scenes: int, resamples: int, seed: int) -> None:
        self.sums, self.scenes = sums, scenes
        rng = np.random.default_rng(seed)
        self.draws = rng.integers(0, scenes, (resamples, scenes)) if resamples and scenes else None
        self._draws_of: dict[str, np.ndarray | None] = {}

    def _stats(self, name: str) -> tuple[np.ndarray, np.ndarray]:
        return self.sums.arrays(name, self.scenes)

    def value(self, name: str) -> float | None:
        s, n = self._stats(name)
        return float(s.sum() / n.sum()) if n.sum() else None

    def _boot(self, name: str) -> np.ndarray | None:
        # A figure's draws serve its own interval and every ratio it is part of.
        if name not in self._draws_of:
            self._draws_of[name] = self._resample(name)
        return self._draws_of[name]

    def _resample(self, name: str) -> np.ndarray | None:
        s, n = self._stats(name)
        if self.draws is None or np.count_nonzero(n) < MIN_SCENES:
            return None
        ns = n[self.draws].sum(1)
        with np.errstate(invalid="ignore", divide="ignore"):
            return np.where(ns > 0, s[self.draws].sum(1) / ns, np.nan)

    @staticmethod
    def _interval(draws: np.ndarray | None) -> list[float] | None:
        # A resample without the figure's agents (or, for a ratio, with a zero denominator:
        # constant velocity is exact on still cars) has no value; the others make the interval.
        draws = None if draws is None else draws[np.isfinite(draws)]
        if draws is None or not draws.size:
            return None
        return [float(x) for x in np.percentile(draws, [2.5, 97.5])]

    def ci(self, name: str) -> list[float] | None:
        return self._interval(self._boot(name))

    def ratio(self, num: str, den: str) -> tuple[float | None, list[float] | None]:
        """``value(num) / value(den)`` and its interval (paired draws)."""
        a, b = self.value(num), self.value(den)
        if a is None or not b:
            return None, None
        da, db = self._boot(num), self._boot(den)
        with np.errstate(invalid="ignore", divide="ignore"):
            draws = None if da is None or db is None else da / db
        return a / b, self._interval(draws)
