"""The closed loop: world-model traffic, external egos, a guided adversary.

Everything that decides how a non-ego agent moves lives here:

- ``config.py``: :class:`SimConfig`, the closed-loop settings (one source for the env's config
  keys and the ``counterscene stress`` flags);
- ``state.py``: the public records: :class:`Episode`, :class:`WorldState`,
  :class:`MotionSource`, :class:`ModelWindow`;
- ``loop.py``: :class:`ClosedLoop` (reset / step / scene / infos);
- ``step_info.py``: what every step records for an ego (its info dict);
- ``replan.py``: model windows, one batched world-model call, the choice among samples;
- ``adversaries.py``: each ego's adversary, selected on the log or at replans on the model;
- ``motion.py``: who moves how each step; ``yielding.py`` and ``road_keeping.py``: the
  reflexes of ordinary traffic; ``realism.py``: the realism cost of samples;
- ``traffic.py``: the IDM lane follower for agents that left the model's view;
- ``memory.py``: a replan's memory, estimated before it runs (``memory_limit_gb``).
"""

__all__ = [
    "TTC_HORIZON",
    "ClosedLoop",
    "Episode",
    "ModelWindow",
    "MotionSource",
    "SimConfig",
    "WorldState",
]

#: Where each name lives; imported on first use, so that ``sim.config`` (the settings, which
#: the CLI parser reads) loads without torch and highway-env.
_FROM = {
    "SimConfig": "config",
    "TTC_HORIZON": "step_info",
    "ClosedLoop": "loop",
    "Episode": "state",
    "ModelWindow": "state",
    "MotionSource": "state",
    "WorldState": "state",
}


def __getattr__(name: str):
    if name not in _FROM:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    import importlib

    return getattr(importlib.import_module(f"{__name__}.{_FROM[name]}"), name)
