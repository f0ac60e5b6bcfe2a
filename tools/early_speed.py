"""Where in the first 3 s a world model loses to constant velocity, and what its first speed
changes cost (docs/world_model_experiments.md, "Tracking noise in the training data").

Moving agents (3 m/s or more now) with their whole 3 s logged, every second of each log
(as ``counterscene evaluate-model --every 1``), one sample of 6 per sampling call:

- displacement error by horizon, one sample, the mean of the 6 and constant velocity, split
  along and across the agent's course;
- the first action token's acceleration (0-0.4 s) against the log's: spread, correlation;
- by speed now: the log's and one sample's speed change over 3 s (mean, spread,
  correlation) and the ADE ratio to constant velocity;
- what the track alone says (no model): the correlation of the log's speed change over the
  last 0.5 s of history with its change over the first 0.4 s of the future, and constant
  velocity against a continuation of that recent acceleration decaying with time constant
  ``tau`` (``--tau``); on real logs a driver's last half second of speed change says nothing
  about the next, where highway-env's IDM traffic continues it; and constant velocity at
  the speed of the last 0.5 s of positions instead of the logged speed now;
- ADE over 0-3 s with the sample's accelerations over its first ``--tokens`` tokens scaled by
  each ``--scale`` and rolled out again (1: the sample re-rolled from its token means, the
  reference; a diagnosis, not a sampler setting: how much of the
  error is the sample's early speed changes):

    python tools/early_speed.py scenarionet:path/to/nuscenes_mini_scenarionet [--model DIR]
    python tools/early_speed.py SOURCE --track-only     # the track-alone lines only
"""

from __future__ import annotations

import argparse
import itertools

import numpy as np
import torch

from counterscene_env.dynamics import actions_from_states
from counterscene_env.scene.sources import stored_scenes
from counterscene_env.world_model.checkpoint import load_model
from counterscene_env.world_model.eval_windows import window_batches, window_jobs
from counterscene_env.world_model.evaluate import MOVING_SPEED, constant_velocity

HORIZON = 30  # steps (3 s at 10 Hz)
SAMPLES = 6
REPORTED = (1, 2, 4, 9, 19, 29)  # steps: 0.2, 0.3, 0.5, 1, 2, 3 s
SPEED_BINS = (3.0, 6.0, 9.0, 12.0, 16.0, 40.0)  # m/s, speed now


def frame_errors(d: np.ndarray, course: float) -> tuple[np.ndarray, np.ndarray]:
    """Along- and across-course parts of displacement errors ``d [H, 2]`` m."""
    along = np.array([np.cos(course), np.sin(course)])
    return d @ along, d @ np.array([-along[1], along[0]])


def scaled_rollouts(model, state, acts, tokens: int, scales) -> dict[float, torch.Tensor]:
    """The first sample's token actions ``acts [B, S, K, Ta, 2]`` with the accelerations of the
    first ``tokens`` tokens times each scale, rolled out from ``state`` as the model rolls its
    own tokens out (``WorldModel.rollout``): ``[B, K, F, 4]``."""
    out = {}
    for f in scales:
        a = acts[:, 0].clone()
        a[..., :tokens, 0] *= f
        out[f] = model.rollout(model.normalize(a), state)
    return out


def track_alone(scenes, jobs, taus) -> dict[str, np.ndarray]:
    """Per moving vehicle-window of ``jobs`` with 0.5 s of history and 3 s of future logged:
    ``recent`` and ``next`` accelerations [m/s^2] (the speed change over the last 0.5 s of
    history and over the first 0.4 s of the future), and per ``tau`` (0: constant velocity)
    the displacement errors ``[n, HORIZON]`` m of a drive along the heading "now" at the
    speed ``v(t) = v0 + a tau (1 - exp(-t / tau))``, ``a`` the recent acceleration; and
    (``"positions"``) of constant velocity at the speed of the last 0.5 s of positions
    instead of the logged speed now."""
    out: dict = {"recent": [], "next": [], "positions": []} | {tau: [] for tau in (0.0, *taus)}
    for k, now in jobs:
        sc = scenes[k]
        if now < 5 or now + HORIZON >= sc.num_steps:
            continue
        dt = sc.dt
        t = np.arange(1, HORIZON + 1) * dt
        span = slice(now - 5, now + HORIZON + 1)
        for i in np.nonzero(sc.valid[:, span].all(-1) & (sc.speeds[:, now] >= MOVING_SPEED))[0]:
            if sc.agent_types[i] != "vehicle":
                continue
            v, p = sc.speeds[i], sc.positions[i]
            recent = (v[now] - v[now - 5]) / (5 * dt)
            out["recent"].append(recent)
            out["next"].append((v[now + 4] - v[now]) / (4 * dt))
            heading = np.array([np.cos(sc.yaws[i, now]), np.sin(sc.yaws[i, now])])
            truth = p[now + 1 : now + HORIZON + 1]
            for tau in (0.0, *taus):
                gain = tau * (1 - np.exp(-t / tau)) if tau else 0.0 * t
                travelled = np.cumsum(np.maximum(v[now] + recent * gain, 0.0)) * dt
                drive = p[now] + travelled[:, None] * heading
                out[tau].append(np.linalg.norm(drive - truth, axis=-1))
            speed = np.linalg.norm(p[now] - p[now - 5]) / (5 * dt)
            drive = p[now] + (speed * t)[:, None] * heading
            out["positions"].append(np.linalg.norm(drive - truth, axis=-1))
    return {key: np.array(val) for key, val in out.items()}


def report_track_alone(rows: dict[str, np.ndarray], taus) -> None:
    recent, nxt, cv = rows["recent"], rows["next"], rows[0.0]
    print(
        f"the track alone ({len(recent)} moving vehicle-windows): correlation of the last 0.5 s's "
        f"speed change with the next 0.4 s's {np.corrcoef(recent, nxt)[0, 1]:+.2f} "
        f"(std {recent.std():.2f} and {nxt.std():.2f} m/s^2)"
    )
    e = rows["positions"]
    print(
        f"  constant velocity at the speed of the last 0.5 s of positions, not the logged "
        f"speed now: ADE 0-3 s {e.mean() / cv.mean():.3f}x"
    )
    for tau in taus:
        e = rows[tau]
        print(
            f"  recent acceleration continued, decaying over {tau:g} s: error at 0.5 s "
            f"{e[:, 4].mean() / cv[:, 4].mean():.2f}x constant velocity's, ADE 0-3 s "
            f"{e.mean() / cv.mean():.3f}x"
        )


def measure(model, scenes, seed: int, tokens: int, scales) -> dict[str, list]:
    """Per moving agent-window: error by step (one sample, mean of the samples, constant
    velocity; along and across), first-token accelerations, and the scaled rollouts' ADE."""
    c = model.config
    s = c.action_stride
    jobs = window_jobs(scenes, c.history_steps, 10, HORIZON)
    g = torch.Generator().manual_seed(seed)
    keys = ("one", "mean", "cv", "al", "ac", "cal", "cac", "first", "logged", "speed")
    rows: dict = {k: [] for k in keys} | {f: [] for f in scales}
    for _, batch in window_batches(model, scenes, jobs):
        with torch.no_grad():
            pred = model.sample(batch, SAMPLES, g)
            state = model.current_state(batch)
            target, target_ok = model.target_actions(batch)
        traj = pred.trajectory  # [B, S, K, F, 4]
        now = state[:, None, :, None].expand(-1, SAMPLES, -1, -1, -1)
        acts = actions_from_states(torch.cat([now, traj[..., s - 1 :: s, :]], -2), c.dt * s)
        redone = scaled_rollouts(model, state, acts, tokens, scales)
        future = batch["future"][..., :HORIZON, :2].numpy()
        ok = batch["future_valid"][..., :HORIZON].numpy()
        st = state.numpy()
        cv = constant_velocity(st, HORIZON, c.dt)
        xy = traj[..., :HORIZON, :2].numpy()
        moving = pred.valid.numpy() & ok.all(-1) & (np.abs(st[..., 3]) >= MOVING_SPEED)
        for b, k in zip(*np.nonzero(moving), strict=True):
            truth = future[b, k]
            d_one, d_cv = xy[b, 0, k] - truth, cv[b, k] - truth
            # speed now, and the speed 3 s later of the log and of the first sample [m/s]
            v0 = float(st[b, k, 3])
            v_log = batch["future"][b, k, HORIZON - 1, 3].item()
            v_one = traj[b, 0, k, HORIZON - 1, 3].item()
            rows["speed"].append((v0, v_log - v0, v_one - v0))
            rows["one"].append(np.linalg.norm(d_one, axis=-1))
            rows["mean"].append(np.linalg.norm(xy[b, :, k].mean(0) - truth, axis=-1))
            rows["cv"].append(np.linalg.norm(d_cv, axis=-1))
            for key, d in (("a", d_one), ("ca", d_cv)):
                al, ac = frame_errors(d, st[b, k, 2])
                rows[f"{key}l"].append(al)
                rows[f"{key}c"].append(ac)
            if target_ok[b, k, 0]:
                rows["first"].append(acts[b, :, k, 0, 0].numpy())
                rows["logged"].append(float(target[b, k, 0, 0]))
            for f in scales:
                err = np.linalg.norm(redone[f][b, k, :HORIZON, :2].numpy() - truth, axis=-1)
                rows[f].append(err.mean())
    return rows


def report(rows: dict, tokens: int, scales) -> None:
    r = {k: np.array(rows[k]) for k in ("one", "mean", "cv", "al", "ac", "cal", "cac")}
    rms = lambda x: float(np.sqrt((x**2).mean()))  # noqa: E731
    print(f"{len(r['one'])} moving agent-windows with 3 s logged")
    print("horizon  one sample  mean of 6  const. vel.  ratio   along rms (cv)   across rms (cv)")
    for t in REPORTED:
        print(
            f"{(t + 1) / 10:5.1f} s  {r['one'][:, t].mean():8.3f} m {r['mean'][:, t].mean():8.3f} m"
            f" {r['cv'][:, t].mean():9.3f} m  {r['one'][:, t].mean() / r['cv'][:, t].mean():5.2f}x"
            f"  {rms(r['al'][:, t]):6.3f} ({rms(r['cal'][:, t]):.3f})"
            f"   {rms(r['ac'][:, t]):6.3f} ({rms(r['cac'][:, t]):.3f})"
        )
    fa, la = np.array(rows["first"]), np.array(rows["logged"])
    print(
        f"first token's acceleration, m/s^2 (n={len(la)}): log std {la.std():.2f}; one sample "
        f"std {fa[:, 0].std():.2f}, correlation with the log {np.corrcoef(fa[:, 0], la)[0, 1]:.2f};"
        f" spread of the {SAMPLES} samples about their mean {fa.std(1).mean():.2f}"
    )
    print(
        f"  rms error: one sample {rms(fa[:, 0] - la):.2f}, mean of {SAMPLES} "
        f"{rms(fa.mean(1) - la):.2f}, zero (constant speed) {rms(la):.2f}"
    )
    v = np.array(rows["speed"])  # [n, 3]: speed now, 3 s change logged, one sample's
    print("by speed now: the 3 s speed change, log and one sample (mean / spread, correlation)")
    for lo, hi in itertools.pairwise(SPEED_BINS):
        m = (v[:, 0] >= lo) & (v[:, 0] < hi)
        if m.sum() < 5:
            continue
        log, one = v[m, 1], v[m, 2]
        print(
            f"  {lo:2.0f}-{hi:2.0f} m/s, {m.sum():4d}: log {log.mean():+.2f} / {log.std():.2f}, "
            f"sample {one.mean():+.2f} / {one.std():.2f}, correlation "
            f"{np.corrcoef(log, one)[0, 1]:+.2f}; ADE 0-3 s "
            f"{r['one'][m].mean() / r['cv'][m].mean():.2f}x constant velocity"
        )
    ade_one, ade_cv = r["one"].mean(), r["cv"].mean()
    print(f"ADE 0-3 s: one sample {ade_one:.3f} m ({ade_one / ade_cv:.3f}x constant velocity)")
    for f in scales:
        v = float(np.mean(rows[f]))
        print(f"  its first {tokens} tokens' accelerations x{f:g}: {v:.3f} m ({v / ade_cv:.3f}x)")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("source", help="scenario spec: scenarionet:DIR, commonroad:DIR or a dataset")
    ap.add_argument("--model", default=None, help="model directory (default: shipped)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--tokens", type=int, default=3, help="early tokens scaled (default 3)")
    ap.add_argument("--scale", type=float, nargs="+", default=[1.0, 0.5, 0.0])
    ap.add_argument("--tau", type=float, nargs="+", default=[0.5, 1.0], help="decay times [s]")
    ap.add_argument("--track-only", action="store_true", help="what the track alone says; no model")
    args = ap.parse_args()
    if min(args.tau) <= 0:
        ap.error(f"--tau: decay times must be > 0 s, got {min(args.tau):g}")
    model = load_model(args.model).eval()
    scenes = list(stored_scenes(args.source))
    jobs = window_jobs(scenes, model.config.history_steps, 10, HORIZON)
    report_track_alone(track_alone(scenes, jobs, args.tau), args.tau)
    if args.track_only:
        return
    rows = measure(model, scenes, args.seed, args.tokens, args.scale)
    report(rows, args.tokens, args.scale)


if __name__ == "__main__":
    main()
