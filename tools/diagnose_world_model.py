"""Why does a world model lose to constant velocity on a source? The measurements behind the
hypotheses table of docs/world_model.md ("Why the first models lost to constant velocity").

    python tools/diagnose_world_model.py --scenarionet nuscenes=../shared/data/nuscenes_mini_scenarionet \
        --data ngsim=data/ngsim_train --data intersection=data/intersection --model default

Windows: every second of each log where 3 s of history and 3 s of future exist (at most
``--scenes`` scenes per source), centred on the scene's ego. Agents moving now (3 m/s or more)
and valid 3 s later are scored; for each:

- ``variants``: ADE over 0-3 s [m], the error 3 s ahead split along the agent's course now
  (``along_mean``, ``along_abs``) and across it (``cross_abs``), speed 3 s ahead [m/s] and the
  course change by then [deg], the speed change over 3 s (mean, mean size, and its
  correlation with the log's: does the prediction know who speeds up and who slows down?), for the model (one sample, as configured), the network alone
  (no final-step lane keeping), the network with no lane map at all, the model with every
  vehicle stopped now taken out of the window (do parked cars read as queued traffic?), and
  with only those on or beside a lane, or only those off the street (more than
  ``parked.KERB_OFFSET[1]`` (1.5) m outside every lane strip of the window, farther than any
  kerbside parked car of the training: lots, driveways) taken
  out, the model with the
  history's past speeds smoothed over 0.5 s ("now" kept: are jumpy real-log speeds what
  misleads it?), the log's own action
  tokens rolled out through the model's unicycle (what the action space can express),
  constant velocity, and constant acceleration at the history's speed change over its last
  1 s (does the history tell the coming speed change?); for each also the share of windows in which it puts two agents' boxes
  on each other within 3 s where the log's do not (every agent of the window);
- ``course``: constant velocity along the course now (a backward difference over 0.1 s),
  along the heading, and along the course over 0.5 s;
- ``actions``: the logged action tokens [m/s^2, rad/s]: median and 90th percentile of their
  size, and their mean and spread in the model's normalised units; the same percentiles of
  the history's frame-to-frame speed changes [m/s];
- ``by_map``: the model's and constant velocity's ADE over 0-3 s of the moving agents, summed
  over each map the scenes name (``metadata["map"]``: nuScenes' Boston and Singapore
  districts; left- against right-hand traffic), and their ratio;
- ``lanes``: lane segments within 30 m of a moving agent, segment lengths and widths, and the
  share of the agents' logged positions over 3 s more than 0.5 m outside every lane the
  model's window holds.

Prints one JSON object per source and writes them to ``--out`` (a .json file) if given.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import torch
from torch.utils.data import default_collate

from counterscene_env.scene.reading import iter_scenes
from counterscene_env.world_model import load_model
from counterscene_env.world_model.dataset import SceneWindowDataset
from counterscene_env.world_model.eval_windows import start_steps
from counterscene_env.world_model.evaluate import constant_velocity
from counterscene_env.world_model.map_guidance import lane_excess
from counterscene_env.world_model.overlap import new_overlaps
from counterscene_env.world_model.parked import KERB_OFFSET
from counterscene_env.world_model.window import lane_segments

HORIZON = 30  # 3 s at 10 Hz
MOVING = 3.0  # m/s
STOPPED = 0.5  # m/s: a vehicle slower than this now is stopped (parked or queued)


def windows(scenes, model) -> dict[str, torch.Tensor]:
    ds = SceneWindowDataset(scenes, model.window_config())
    every = round(1.0 / model.config.dt)  # one start per second
    items = [
        ds.window(i, t0)
        for i, s in enumerate(scenes)
        for t0 in start_steps(s, model.config.history_steps, every, HORIZON)
    ]
    return default_collate(
        [{k: torch.from_numpy(np.asarray(v)) for k, v in w.items()} for w in items]
    )


def scored(model, batch) -> tuple[torch.Tensor, torch.Tensor]:
    """The state now ``[B, K, 4]`` and the moving agents valid 3 s ahead ``[B, K]``."""
    state = model.current_state(batch)
    ok = model.agent_mask(batch) & batch["future_valid"][..., HORIZON - 1]
    return state, ok & (state[..., 3].abs() >= MOVING)


def errors(pred, batch, state, sel) -> dict[str, float]:
    """Error figures of ``pred [B, K, F, >=3]`` (x, y, course) on the agents ``sel``."""
    fut, fok = batch["future"][..., :HORIZON, :], batch["future_valid"][..., :HORIZON]
    err = (pred[..., :HORIZON, :2] - fut[..., :2]).norm(dim=-1)
    ade = (err * fok).sum(-1) / fok.sum(-1).clamp(min=1)
    e = pred[..., HORIZON - 1, :2] - fut[..., HORIZON - 1, :2]
    c, s = torch.cos(state[..., 2]), torch.sin(state[..., 2])
    along, cross = e[..., 0] * c + e[..., 1] * s, -e[..., 0] * s + e[..., 1] * c
    speed = (pred[..., HORIZON - 1, :2] - pred[..., HORIZON - 2, :2]).norm(dim=-1) / 0.1
    turn = torch.atan2(
        torch.sin(pred[..., HORIZON - 1, 2] - state[..., 2]),
        torch.cos(pred[..., HORIZON - 1, 2] - state[..., 2]),
    )
    # Speed change over 3 s, predicted and logged: is it informed (correlated with the log's)?
    logged = (fut[..., HORIZON - 1, :2] - fut[..., HORIZON - 2, :2]).norm(dim=-1) / 0.1
    dv, dv_log = (speed - state[..., 3])[sel].numpy(), (logged - state[..., 3])[sel].numpy()
    informed = float(np.corrcoef(dv, dv_log)[0, 1]) if dv.std() > 0 and dv_log.std() > 0 else None
    return {
        "speed_change_mean": float(dv.mean()),
        "speed_change_abs": float(np.abs(dv).mean()),
        "speed_change_corr_with_log": informed,
        "ade3": float(ade[sel].mean()),
        "along_mean": float(along[sel].mean()),
        "along_abs": float(along[sel].abs().mean()),
        "cross_abs": float(cross[sel].abs().mean()),
        "speed3": float(speed[sel].mean()),
        "course_change_deg": float(torch.rad2deg(turn[sel].abs().mean())),
    }


def cv_track(model, state, course) -> torch.Tensor:
    """Constant velocity along ``course [B, K]`` as ``[B, K, F, 3]`` (x, y, course)."""
    c = model.config
    xy = torch.from_numpy(constant_velocity(state.numpy(), c.future_steps, c.dt, course.numpy()))
    return torch.cat([xy, course[..., None, None].expand(*xy.shape[:-1], 1)], -1)


def ca_track(model, batch, state, window: int = 10) -> torch.Tensor:
    """Constant acceleration along the course now, the acceleration being the history's speed
    change over its last ``window`` frames (1 s), as ``[B, K, F, 3]`` (x, y, course); a car
    that decelerates stops and stays. Does the history tell the coming speed change?"""
    c = model.config
    hist = batch["history"]
    ok = batch["history_valid"][..., -1 - window]
    acc = torch.where(ok, (hist[..., -1, 3] - hist[..., -1 - window, 3]) / (window * c.dt), 0.0)
    t = torch.arange(1, c.future_steps + 1, dtype=hist.dtype) * c.dt  # [F] s
    v, a = state[..., 3, None], acc[..., None]
    stop = torch.where(a < 0, -v / a.clamp(max=-1e-6), torch.inf)  # [B, K, 1] s
    tt = torch.minimum(t, stop)
    dist = (v * tt + 0.5 * a * tt**2).clamp(min=0)  # [B, K, F] m
    yaw = state[..., 2, None]
    xy = state[..., None, :2] + dist[..., None] * torch.stack([yaw.cos(), yaw.sin()], -1)
    return torch.cat([xy, yaw[..., None].expand(*dist.shape, 1)], -1)


def one_sample(model, b, seed: int, **kw) -> torch.Tensor:
    """One sample per window of ``b``, 16 windows per call, as ``[B, K, F, 4]``."""
    g = torch.Generator().manual_seed(seed)
    out = []
    for lo in range(0, b["history"].shape[0], 16):
        part = {k: v[lo : lo + 16] for k, v in b.items()}
        with torch.no_grad():
            out.append(model.sample(part, 1, g, **kw).trajectory[:, 0])
    return torch.cat(out)


def by_map(model, scenes, batch, state, sel, pred) -> dict[str, dict]:
    """ADE over 0-3 s of the moving agents ``sel``, the model's (``pred [B, K, F, >=2]``, one
    sample) and constant velocity's, summed per map the scenes name (``metadata["map"]``)."""
    fut, fok = batch["future"][..., :HORIZON, :2], batch["future_valid"][..., :HORIZON]

    def ade(track):
        err = (track[..., :HORIZON, :2] - fut).norm(dim=-1)
        return (err * fok).sum(-1) / fok.sum(-1).clamp(min=1)  # [B, K]

    model_ade = ade(pred)
    cv_ade = ade(cv_track(model, state, state[..., 2]))
    names = np.array([str(s.metadata.get("map", "?")) for s in scenes])
    window_map = names[batch["scene_index"].numpy()]
    out = {}
    for name in sorted(set(window_map)):
        rows = torch.from_numpy(window_map == name)[:, None] & sel
        m, c = float(model_ade[rows].sum()), float(cv_ade[rows].sum())
        out[name] = {"agents": int(rows.sum()), "model": m, "cv": c, "ratio": m / max(c, 1e-9)}
    return out


def variants(model, batch, state, sel, seed: int, pred) -> dict[str, dict]:
    def sample(b, **kw):
        return one_sample(model, b, seed, **kw)

    no_map = {**batch, "map_valid": torch.zeros_like(batch["map_valid"])}
    # Every vehicle stopped now (mostly parked on real streets) taken out of the window.
    stopped = model.agent_mask(batch) & (state[..., 3].abs() < STOPPED)
    no_stopped = {**batch, "agent_valid": batch["agent_valid"] & ~stopped}
    # ... split by where they stand: off the street (lots, driveways) or on or beside a lane.
    outside = lane_excess(
        state[:, :, None, :2], batch["map"], batch["map_valid"], batch["map_widths"]
    )[..., 0]
    off_street = stopped & (outside > KERB_OFFSET[1])  # beyond the training's kerbside cars
    no_off_street = {**batch, "agent_valid": batch["agent_valid"] & ~off_street}
    no_street_side = {**batch, "agent_valid": batch["agent_valid"] & ~(stopped & ~off_street)}
    smooth = {**batch, "history": smoothed_speeds(batch["history"], batch["history_valid"])}
    actions, _ = model.target_actions(batch)
    with torch.no_grad():
        logged = model.rollout(model.normalize(actions), state)
    preds = {
        "model": pred,
        "network": sample(batch, lane_steering=0),
        "network_no_map": sample(no_map, lane_steering=0),
        "model_without_stopped_cars": sample(no_stopped),
        "model_without_stopped_off_street": sample(no_off_street),
        "model_without_stopped_on_or_beside_lanes": sample(no_street_side),
        "smoothed_history": sample(smooth),
        "logged_actions": logged,
        "constant_velocity": cv_track(model, state, state[..., 2]),
        "constant_acceleration": ca_track(model, batch, state),
    }
    return {
        name: {**errors(p, batch, state, sel), "windows_with_new_overlap": overlapping(p, batch)}
        for name, p in preds.items()
    }


def overlapping(pred, batch) -> float:
    """Share of windows in which ``pred [B, K, F, >=3]`` puts two agents' boxes on each other
    within 3 s where the log's boxes do not overlap (``overlap.new_overlaps``; every agent)."""
    ok = (batch["future_valid"] & batch["agent_valid"][..., None])[..., :HORIZON].numpy()
    p, log = pred[..., :HORIZON, :].numpy(), batch["future"][..., :HORIZON, :].numpy()
    ext = batch["extents"].numpy()
    return float(np.mean([new_overlaps(p[b], log[b], ext[b], ok[b]).any() for b in range(len(ok))]))


def smoothed_speeds(hist: torch.Tensor, ok: torch.Tensor, width: int = 5) -> torch.Tensor:
    """``hist [B, K, H, 4]`` with each past frame's speed replaced by the mean of the valid
    speeds within ``width`` frames centred on it ("now", the last frame, is kept)."""
    v, m = hist[..., 3], ok.float()
    pad = width // 2
    kernel = torch.ones(1, 1, width)

    def conv(x: torch.Tensor) -> torch.Tensor:
        flat = torch.nn.functional.pad(x.reshape(-1, 1, x.shape[-1]), (pad, pad))
        return torch.nn.functional.conv1d(flat, kernel).reshape(x.shape)

    mean = conv(v * m) / conv(m).clamp(min=1)
    mean[..., -1] = v[..., -1]
    out = hist.clone()
    out[..., 3] = torch.where(ok, mean, v)
    return out


def course_test(model, batch, state, sel) -> dict[str, float]:
    hist, ok = batch["history"], batch["history_valid"]
    d = hist[..., -1, :2] - hist[..., -6, :2]
    slow = ok[..., -6] & (d.norm(dim=-1) > 1.0)
    course_05 = torch.where(slow, torch.atan2(d[..., 1], d[..., 0]), state[..., 2])
    out = {}
    for name, course in (
        ("course_0.1s", state[..., 2]),
        ("heading", hist[..., -1, 2]),
        ("course_0.5s", course_05),
    ):
        out[f"cv_ade3_{name}"] = errors(cv_track(model, state, course), batch, state, sel)["ade3"]
    return out


def action_stats(model, batch, sel) -> dict:
    actions, ok = model.target_actions(batch)
    m = ok & sel[..., None]
    a, z = actions[m], model.normalize(actions)[m]
    pct = lambda x: [round(float(v), 3) for v in np.percentile(x.abs().numpy(), [50, 90])]  # noqa: E731
    return {
        "tokens": int(m.sum()),
        "abs_acceleration_p50_p90": pct(a[:, 0]),
        "abs_yaw_rate_p50_p90": pct(a[:, 1]),
        "normalised_mean": [round(float(v), 3) for v in z.mean(0)],
        "normalised_std": [round(float(v), 3) for v in z.std(0)],
        "history_speed_change_p50_p90": pct(speed_changes(batch)),
    }


def speed_changes(batch) -> torch.Tensor:
    """Frame-to-frame speed changes [m/s] over the windows' histories (both frames valid)."""
    v, ok = batch["history"][..., 3], batch["history_valid"]
    return (v[..., 1:] - v[..., :-1])[ok[..., 1:] & ok[..., :-1]]


def lane_stats(scenes, batch, sel) -> dict:
    lengths, widths, near = [], [], []
    for s in scenes:
        segments = lane_segments(s, 20.0, 10)
        seg = segments.points
        if not len(seg):
            continue
        lengths += np.linalg.norm(np.diff(seg, axis=1), axis=-1).sum(1).tolist()
        widths += segments.widths.tolist()
        t = s.current_index
        moving = s.valid[:, t] & (np.abs(s.speeds[:, t]) >= MOVING) & (s.agent_types == "vehicle")
        for i in np.flatnonzero(moving):
            dist = np.linalg.norm(seg - s.positions[i, t], axis=-1).min(1)
            near.append(int((dist < 30).sum()))
    ok = sel[..., None] & batch["future_valid"][..., :HORIZON]  # [B, K, HORIZON]
    outside = 0
    for lo in range(0, ok.shape[0], 16):  # lane_excess holds [16, K, HORIZON, segments]
        part = slice(lo, lo + 16)
        excess = lane_excess(
            batch["future"][part, :, :HORIZON, :2],
            batch["map"][part],
            batch["map_valid"][part],
            batch["map_widths"][part],
        )
        outside += int(((excess > 0.5) & ok[part]).sum())
    total = int(ok.sum())
    pct = lambda x: [round(float(v), 2) for v in np.percentile(x, [10, 50, 90])]  # noqa: E731
    return {
        "segment_length_p10_p50_p90": pct(lengths),
        "width_p10_p50_p90": pct(widths),
        "segments_within_30m_p10_p50_p90": pct(near) if near else None,
        "logged_positions_outside_window_lanes": outside / total if total else None,
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--scenarionet", action="append", default=[], metavar="NAME=DIR")
    ap.add_argument("--data", action="append", default=[], metavar="NAME=DIR")
    ap.add_argument("--model", default="default")
    ap.add_argument("--scenes", type=int, default=100, help="at most this many per source")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", help="write the results here (JSON)")
    args = ap.parse_args()
    torch.set_num_threads(1)
    model = load_model(args.model).eval()
    results = {}
    for spec in args.scenarionet + args.data:
        name, _, path = spec.partition("=")
        scenes = [s for s, _ in iter_scenes(Path(path))][: args.scenes]
        batch = windows(scenes, model)
        state, sel = scored(model, batch)
        pred = one_sample(model, batch, args.seed)  # the model as configured, one sample
        results[name] = {
            "scenes": len(scenes),
            "windows": int(batch["history"].shape[0]),
            "moving_agent_windows": int(sel.sum()),
            "log_speed_now": float(state[..., 3][sel].mean()),
            "log_speed3": float(batch["future"][..., HORIZON - 1, 3][sel].abs().mean()),
            "variants": variants(model, batch, state, sel, args.seed, pred),
            "course": course_test(model, batch, state, sel),
            "by_map": by_map(model, scenes, batch, state, sel, pred),
            "actions": action_stats(model, batch, sel),
            "lanes": lane_stats(scenes, batch, sel),
        }
        print(json.dumps({name: results[name]}), flush=True)
    if args.out:
        Path(args.out).write_text(json.dumps(results, indent=1) + "\n")


if __name__ == "__main__":
    main()
