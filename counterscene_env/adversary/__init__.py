"""The adversary: who to perturb (causal conflict mining and baseline selectors) and how
(counterfactual guidance during denoising). DESIGN 3.4 and 3.5."""

from counterscene_env.adversary.guidance import (
    PRESETS as GUIDANCE_PRESETS,
)
from counterscene_env.adversary.guidance import (
    GuidanceConfig,
    guidance_preset,
)
from counterscene_env.adversary.selection import (
    METHODS as SELECTORS,
)
from counterscene_env.adversary.selection import (
    Conflict,
    Selection,
    select_adversary,
)

__all__ = [
    "GUIDANCE_PRESETS",
    "SELECTORS",
    "Conflict",
    "GuidanceConfig",
    "Selection",
    "guidance_preset",
    "select_adversary",
]
