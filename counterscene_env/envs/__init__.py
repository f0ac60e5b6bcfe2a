"""The environments: ``CounterScene-v0`` (Gymnasium) and the PettingZoo ``ParallelEnv``."""

from counterscene_env.envs.single_agent import CounterSceneEnv

__all__ = ["CounterSceneEnv"]
