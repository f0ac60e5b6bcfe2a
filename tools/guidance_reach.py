"""How far the counterfactual guidance can move the adversary, and what decides its step.

    python tools/guidance_reach.py --scenario merge --episodes 20 --seed 5000 [--set KEY=VALUE ...]

For each scene with an adversary, the first replan (from pure noise, "now" = the scene's
current step) is sampled twice with the same seed: with the full guidance and unguided. It
reports:

- **reach**: how far the guided (``--guidance``, default ``full``) adversary's plan lies from the unguided one [m] at 1-5 s,
  next to how far the conflict asks it to move: the distance between the unguided plan and
  the conflict point at the compressed arrival step (``adversary/guidance.py``);
- **who decides the step**: the guidance takes a sign-like step per action coordinate
  (``lr * g / |g|``), so where terms of the loss disagree only the largest gradient counts.
  For every guided denoising step it compares the sign of the whole loss's gradient with
  that of its adversarial terms alone (spatial and synchronisation, without the jerk and
  off-lane terms), over the adversary's action coordinates: the share where they agree, and
  the mean magnitude of each gradient.

The figures of docs/history/closed_loop.md ("Why the guidance did not bite harder").
"""

from __future__ import annotations

import argparse
import dataclasses
import json

import numpy as np
import torch

from counterscene_env.adversary import guidance as guidance_module
from counterscene_env.cli.common import parse_overrides
from counterscene_env.scene.sources import scenes_for
from counterscene_env.sim import ClosedLoop, SimConfig
from counterscene_env.sim import replan as replan_module
from counterscene_env.world_model import load_model

SECONDS = (1, 2, 3, 4, 5)


def first_plan(loop: ClosedLoop, scene, seed: int):
    """The episode after its first replan: (plan positions ``[N, F, 2]`` m, the selection)."""
    loop.reset([scene], [seed])
    loop.step(np.zeros((1, 2)))
    ep = loop.episodes[0]
    return ep.plan_positions.copy(), loop.selection(0)


def recording_hook(record: list):
    """A ``make_guidance_hook`` that also records, at every guided step, the agreement of the
    whole loss's gradient sign with its adversarial terms' (module docstring)."""
    make = guidance_module.make_guidance_hook

    def wrapped(model, batch, targets, num_samples, config):
        hook = make(model, batch, targets, num_samples, config)
        parts = dataclasses.replace(config, jerk=False, map_weight=0.0)
        tg, state, mask = hook.targets, hook.state, hook.mask
        has = tg.adversary_row >= 0

        def grad_of(cfg, mean):
            x = mean.detach().requires_grad_(True)
            with torch.enable_grad():
                ego, adv = guidance_module.pair_paths(
                    model, torch.where(mask, x, x.detach()), state, tg
                )
                lanes = hook.lanes if cfg.map_weight > 0 else None
                loss = guidance_module.guidance_loss(
                    ego, adv, tg, cfg, model.config.dt, None, lanes, hook.on_lane
                )
                (g,) = torch.autograd.grad(loss.sum(), x)
            return g[mask.expand_as(g)]

        def recorded(mean, sigma, t, x0):
            if sigma > 0 and has.any():
                whole, adversarial = grad_of(config, mean), grad_of(parts, mean)
                on = adversarial != 0
                record.append(
                    {
                        "t": int(t),
                        "agree": float((whole.sign() == adversarial.sign())[on].float().mean()),
                        "grad_whole": float(whole.abs().mean()),
                        "grad_adversarial": float(adversarial.abs().mean()),
                    }
                )
            return hook(mean, sigma, t, x0)

        for name in ("on_lane", "lanes", "state", "targets", "mask"):
            setattr(recorded, name, getattr(hook, name))
        return recorded

    return wrapped


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--scenario", default="merge")
    parser.add_argument("--episodes", type=int, default=20)
    parser.add_argument("--seed", type=int, default=5000)
    parser.add_argument("--guidance", default="full", help="the guided preset (default full)")
    parser.add_argument("--model", default="default")
    parser.add_argument("--set", nargs="*", default=[], metavar="KEY=VALUE")
    parser.add_argument("--json", action="store_true")
    args = parser.parse_args()
    model = load_model(args.model)
    base = parse_overrides(args.set)
    guided = ClosedLoop(model, SimConfig.from_mapping({**base, "guidance": args.guidance}))
    unguided = ClosedLoop(model, SimConfig.from_mapping({**base, "guidance": "none"}))
    record: list[dict] = []
    replan_module.make_guidance_hook = recording_hook(record)
    shifts, asks = [], []
    for i, scene in enumerate(scenes_for(args.scenario, args.episodes, args.seed)):
        plain, sel = first_plan(unguided, scene, args.seed + i)
        if sel.conflict is None:
            continue
        plan, _ = first_plan(guided, scene, args.seed + i)
        a, c = sel.conflict.agent, sel.conflict
        now = scene.current_index
        steps = [round(s / scene.dt) - 1 for s in SECONDS]
        shifts.append(np.linalg.norm(plan[a, steps] - plain[a, steps], axis=-1))
        # Where the conflict wants the adversary: at c when the ego is there (full compression).
        j = int(np.clip(min(c.ego_step, c.adversary_step) - now - 1, 0, plan.shape[1] - 1))
        asks.append(float(np.linalg.norm(plain[a, j] - c.conflict_point)))
    shift = np.median(np.array(shifts), axis=0) if shifts else np.full(len(SECONDS), np.nan)
    out = {
        "scenes_with_adversary": len(shifts),
        "median_shift_m": dict(
            zip([f"{s}s" for s in SECONDS], shift.round(2).tolist(), strict=True)
        ),
        "median_distance_to_conflict_point_m": float(np.median(asks)) if asks else None,
        "agree_share": float(np.mean([r["agree"] for r in record])) if record else None,
        "median_grad_whole": float(np.median([r["grad_whole"] for r in record]))
        if record
        else None,
        "median_grad_adversarial": (
            float(np.median([r["grad_adversarial"] for r in record])) if record else None
        ),
        "guided_steps": len(record),
    }
    print(
        json.dumps(out, indent=1) if args.json else "\n".join(f"{k}: {v}" for k, v in out.items())
    )


if __name__ == "__main__":
    main()
