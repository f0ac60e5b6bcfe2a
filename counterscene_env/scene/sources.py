"""Where an environment's episodes come from: a scenario spec -> one :class:`Scene` per reset.

A spec is a generated road (``highway``, ``merge``, ``intersection``, ``roundabout``: a fresh
highway-env recording per episode), ``scenarionet:DIR`` (real logs converted by ScenarioNet), a
dataset directory or shard file written by ``counterscene generate``, or a list of any of these
(each episode picks one uniformly). All draws come from the generator the env passes, so the
same env seed gives the same scenes.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np

from counterscene_env.scene.core import Scene
from counterscene_env.scene.highway import SCENARIOS

#: Prefix of a ScenarioNet directory in a scenario spec.
SCENARIONET_PREFIX = "scenarionet:"
#: Generated scenes take their seed from [0, SEED_RANGE).
SEED_RANGE = 2**31 - 1


class SceneSource:
    """Draws the factual scene of each episode (module docstring).

    Args:
        spec: a scenario name, ``scenarionet:DIR``, a dataset path, or a non-empty list of them.

    Raises:
        ValueError: an unknown name, or a path that does not exist (checked at construction,
            so a bad config fails at ``gym.make``, not at the first reset).
    """

    def __init__(self, spec: str | Sequence[str]) -> None:
        specs = [spec] if isinstance(spec, str) else list(spec)
        if not specs or not all(isinstance(s, str) for s in specs):
            raise ValueError(f"scenario must be a name, a path or a list of them, got {spec!r}")
        for s in specs:
            if s not in SCENARIOS and not Path(s.removeprefix(SCENARIONET_PREFIX)).exists():
                raise ValueError(
                    f"unknown scenario {s!r}: not one of {list(SCENARIOS)}, and no such path "
                    f"(use '{SCENARIONET_PREFIX}DIR' or a dataset directory)"
                )
        self.specs = specs
        self._cache: dict[str, list[Scene]] = {}

    def draw(self, rng: np.random.Generator) -> Scene:
        """One scene: pick a spec, then a fresh recording (generated) or a stored scene."""
        spec = (
            self.specs[int(rng.integers(len(self.specs)))] if len(self.specs) > 1 else self.specs[0]
        )
        if spec in SCENARIOS:
            from counterscene_env.scene.highway import generate

            return generate(spec, int(rng.integers(SEED_RANGE)))
        scenes = self._scenes(spec)
        return scenes[int(rng.integers(len(scenes)))]

    def _scenes(self, spec: str) -> list[Scene]:
        if spec not in self._cache:
            from counterscene_env.scene.datagen import iter_scenes

            scenes = [scene for scene, _ in iter_scenes(spec.removeprefix(SCENARIONET_PREFIX))]
            if not scenes:
                raise FileNotFoundError(f"{spec}: no scenes")
            self._cache[spec] = scenes
        return self._cache[spec]
