"""Memory of a replan, estimated before it runs, so that a request the machine cannot hold is
refused with a figure instead of taking the machine down.

A replan samples ``num_samples`` futures of every model window of every episode in one call;
its peak memory grows linearly with samples x windows. Per sample and window the denoiser
holds, for each of its K agents x T tokens, the MLP's hidden layer (``d_model x mlp_ratio``)
and one attention row per head over the tokens it attends to (T along time, K across agents,
the window's lanes and the agent's own lanes). Measured with the shipped default model (one
intersection replan, peak RSS over ``num_samples`` 64 and 256: 5.7 MB per sample and window),
about :data:`LIVE_COPIES` such sets are alive at the peak.
"""

from __future__ import annotations

import os

#: Live copies of the per-token activations at the peak of a sampling call (measured, above).
LIVE_COPIES = 8
#: The process itself (torch, highway-env, the model) before any replan, bytes.
BASE_BYTES = 400 * 2**20
#: Share of the machine's total memory a replan may take when no limit is given.
DEFAULT_SHARE = 0.5


def replan_bytes(model_config, num_samples: int, windows: int) -> int:
    """Estimated peak bytes of one replan of ``windows`` model windows x ``num_samples``
    samples, for a model of ``model_config`` (``world_model.ModelConfig``)."""
    c = model_config
    tokens = c.history_tokens + c.action_tokens
    attended = tokens + c.num_agents + (c.num_lanes + 1) + (c.local_lanes + 1)
    per_token = c.d_model * c.mlp_ratio + c.num_heads * attended
    per_sample = LIVE_COPIES * 4 * c.num_agents * tokens * per_token  # float32
    return BASE_BYTES + num_samples * windows * per_sample


def total_memory_bytes() -> int:
    """This machine's total memory (not its free memory: the answer must not depend on
    load)."""
    return os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")


def check_replan_memory(
    model_config, num_samples: int, windows: int, limit_gb: float | None
) -> None:
    """Refuse a replan whose estimate exceeds ``limit_gb`` (None: :data:`DEFAULT_SHARE` of
    the machine's total memory).

    Raises:
        ValueError: naming ``num_samples``, the estimate and the limit (``memory_limit_gb``).
    """
    need = replan_bytes(model_config, num_samples, windows)
    limit = DEFAULT_SHARE * total_memory_bytes() if limit_gb is None else limit_gb * 2**30
    if need > limit:
        per = (need - BASE_BYTES) / (num_samples * windows) / 1e6  # MB, as the docs give it
        raise ValueError(
            f"num_samples = {num_samples} x {windows} model window(s) would need about "
            f"{need / 2**30:.3g} GB per replan ({per:.1f} MB per sample and window), more "
            f"than the limit of {limit / 2**30:.3g} GB (memory_limit_gb; default half of "
            "this machine's memory): use fewer samples or raise memory_limit_gb"
        )
