"""Scenes: the contract (:class:`Scene`, :class:`RoadMap`) and its sources.

- :func:`generate` records highway-env traffic (``highway``, ``merge``, ``intersection``,
  ``roundabout``) as a factual log.
- :func:`load_scenarionet` imports a ScenarioNet scenario pickle (nuScenes, Waymo, ...) safely.
- :func:`save_scenes` / :func:`load_scenes` read and write compressed shards.
"""

from counterscene_env.scene.core import AGENT_TYPES, DEFAULT_DT, Scene, SceneError
from counterscene_env.scene.road import RoadMap

__all__ = [
    "AGENT_TYPES",
    "DEFAULT_DT",
    "SCENARIOS",
    "RoadMap",
    "Scene",
    "SceneError",
    "generate",
    "load_scenarionet",
    "load_scenes",
    "save_scenes",
]


def __getattr__(name: str):
    # Sources are imported on first use: importing the contract stays cheap.
    if name in ("generate", "SCENARIOS"):
        from counterscene_env.scene import highway

        return getattr(highway, name)
    if name == "load_scenarionet":
        from counterscene_env.scene.scenarionet import load_scenarionet

        return load_scenarionet
    if name in ("save_scenes", "load_scenes"):
        from counterscene_env.scene import shards

        return getattr(shards, name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
