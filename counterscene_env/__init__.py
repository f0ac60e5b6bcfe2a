"""CounterScene: an adversarial multi-agent driving environment.

A diffusion world model drives the traffic; each episode one causally selected adversary has its
safety margins removed by counterfactual guidance while everyone else reacts. See the README.

Importing the package registers (idempotently; gymnasium ignores entry points):

- Gymnasium: ``CounterScene-v0`` (any scenario, default ``intersection``) and the variants
  ``CounterScene-{highway,merge,intersection,roundabout}-v0``; reachable as
  ``gym.make("counterscene_env:CounterScene-v0")`` too. ``gymnasium.make_vec(id, num_envs=N)``
  gives the batched vector env (``counterscene_env.envs.vector``; ``workers=W`` splits it
  over W processes, ``counterscene_env.envs.sharded``).
- PettingZoo: ``pettingzoo.make("parallel", "CounterScene-v0", num_egos=2)``.
"""

from __future__ import annotations

from importlib.metadata import version
from typing import Any

from pettingzoo import ParallelEnv

from counterscene_env.config import Scenario

__version__ = version("counterscene-env")

ENV_ID = "CounterScene-v0"
#: Scenarios with a registered variant ``CounterScene-{scenario}-v0``.
SCENARIO_VARIANTS = Scenario.values()


def parallel_env(num_egos: int = 1, **kwargs: Any) -> ParallelEnv:
    """The PettingZoo ``ParallelEnv``: ``num_egos`` external policies ``ego_0 ..`` each with
    its own causally selected adversary (``counterscene_env.envs.parallel``)."""
    from counterscene_env.envs.parallel import CounterSceneParallelEnv

    return CounterSceneParallelEnv(num_egos=num_egos, **kwargs)


def _register() -> None:
    import gymnasium

    entry = "counterscene_env.envs.single_agent:CounterSceneEnv"
    vector = "counterscene_env.envs.sharded:vector_env"
    if ENV_ID not in gymnasium.registry:
        gymnasium.register(id=ENV_ID, entry_point=entry, vector_entry_point=vector)
    for scenario in SCENARIO_VARIANTS:
        variant = f"CounterScene-{scenario}-v0"
        if variant not in gymnasium.registry:
            gymnasium.register(
                id=variant,
                entry_point=entry,
                vector_entry_point=vector,
                kwargs={"scenario": scenario},
            )
    import pettingzoo

    registry = getattr(pettingzoo, "parallel_registry", None)
    if registry is not None and ENV_ID not in registry:
        pettingzoo.register("parallel", ENV_ID, entry_point="counterscene_env:parallel_env")


_register()
