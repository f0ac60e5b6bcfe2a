"""The worst episodes of a run, most severe first.

Severity is :func:`counterscene_env.metrics.severity`: in turn the ego collided (``cr``), it
collided with the adversary (``cr_ego_adversary``), the smallest time to collision
(``min_ttc``), the smallest clearance to the adversary (``min_clearance_adversary``) and hard
braking (``hbr_ego``). Ties keep episode order, so the ranking of a run is fixed.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

from counterscene_env.metrics import severity


def severity_key(record: dict) -> tuple[float, ...]:
    """Sort key of an episode record: smaller is more severe (module docstring)."""
    return (*severity(record), float(record["episode"]))


def worst_episodes(records: Sequence[dict], k: int | None = None) -> list[dict]:
    """The ``k`` most severe episode records (all when None), most severe first."""
    ranked = sorted(records, key=severity_key)
    return ranked if k is None else ranked[: max(0, k)]


def describe(record: dict) -> str:
    """One line on why an episode ranks where it does, e.g. ``collision with the adversary,
    min TTC 0 s, clearance 0 m``."""
    parts = []
    if record.get("cr") == 1.0:
        parts.append(
            "collision with the adversary" if record.get("cr_ego_adversary") == 1.0 else "collision"
        )
    ttc = record.get("min_ttc", math.nan)
    parts.append("no projected conflict" if ttc == math.inf else f"min TTC {_num(ttc)} s")
    clearance = record.get("min_clearance_adversary", math.nan)
    if not math.isnan(clearance):
        parts.append(f"clearance {_num(clearance)} m")
    if record.get("hbr_ego") == 1.0:
        parts.append("hard braking")
    return ", ".join(parts)


def _num(v: float) -> str:
    return "n/a" if v is None or math.isnan(v) else f"{v:.2g}" if v < 10 else f"{v:.0f}"
