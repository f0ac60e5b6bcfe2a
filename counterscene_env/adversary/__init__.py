"""The adversary: who to perturb (causal conflict mining and baseline selectors, ``selection``)
and how (counterfactual guidance during denoising, ``guidance``); docs/design.md, "Causal
adversary selection" and "Counterfactual guidance".

The two modules sit on different layers (selection below the world model, guidance above
it), so the names here are imported on first use.
"""

__all__ = [
    "GUIDANCE_PRESETS",
    "SELECTORS",
    "Conflict",
    "GuidanceConfig",
    "Selection",
    "guidance_preset",
    "select_adversary",
]

_FROM = {
    "GUIDANCE_PRESETS": ("guidance", "PRESETS"),
    "GuidanceConfig": ("guidance", "GuidanceConfig"),
    "guidance_preset": ("guidance", "guidance_preset"),
    "SELECTORS": ("selection", "METHODS"),
    "Conflict": ("selection", "Conflict"),
    "Selection": ("selection", "Selection"),
    "select_adversary": ("selection", "select_adversary"),
}


def __getattr__(name: str):
    if name not in _FROM:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    import importlib

    module, attr = _FROM[name]
    return getattr(importlib.import_module(f"{__name__}.{module}"), attr)
