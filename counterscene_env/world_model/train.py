"""Training loop of the world model (``counterscene train``).

Adam at 1e-4 with an EMA of decay 0.995 (the paper's values) over windows of generated or
imported scenes. Everything is seeded; the run is resumable: every ``checkpoint_every`` steps
``DIR/last.pt`` (plain containers, read back with ``torch.load(weights_only=True)``) and the EMA
model as ``DIR/model.safetensors`` + ``DIR/config.json`` are written, and rerunning the same
command continues from the last checkpoint and reproduces the same run. ``DIR/log.jsonl`` gets one
line per validation, each step once: a resumed run drops the records past its ``last.pt`` (a
run stopped between its record and its ``last.pt`` reruns those steps), and a fresh run
replaces any log it finds. A fresh run writes ``last.pt`` at step 0 before anything else and
refuses a directory that holds a model but no ``last.pt`` (``run_dir.check_fresh_out``):
that model is not its own.

Validation: a held-out slice of the scenes of each dataset (the last ``val_fraction``), one
sample per window from the EMA model with the default sampler, ADE over the whole horizon and
FDE at its end [m], over valid agents.
"""

from __future__ import annotations

import copy
import dataclasses
import json
import os
import platform
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import torch
from torch.utils.data import default_collate

from counterscene_env.scene.smoothing import smooth_tracks
from counterscene_env.world_model.batches import batches, weighted_batches
from counterscene_env.world_model.checkpoint import save_model
from counterscene_env.world_model.config import preset as get_preset
from counterscene_env.world_model.dataset import SceneWindowDataset, load_sources
from counterscene_env.world_model.loss import training_loss
from counterscene_env.world_model.model import WorldModel
from counterscene_env.world_model.parked import add_parked_cars
from counterscene_env.world_model.records import Normalization
from counterscene_env.world_model.run_dir import (
    LOG_FILE,
    STATE_FILE,
    check_fresh_out,
    check_resume,
    data_fingerprint,
    read_state,
    save_state,
    trim_log,
)
from counterscene_env.world_model.train_config import (
    UNSIZED_FIELDS,
    TrainConfig,
    learning_rate,
    plain_settings,
)

#: ``ModelConfig`` switches that a fine-tune (``--init``) may turn on: each adds input columns
#: that start at zero, so the fine-tune starts from the initial model's exact predictions.
ADDED_INPUTS = ("lane_priority", "source_flag")
#: Offset of the parked cars' seeds from the batch draws' (``seed * 100003 + step``).
PARKED_STREAM = 2**40


def _windows(ds: SceneWindowDataset, rows: Sequence[int]) -> dict[str, torch.Tensor]:
    """All windows ``rows`` of ``ds`` collated into one batch (kept in memory)."""
    return default_collate([ds[i] for i in rows])


def _split(ds: SceneWindowDataset, val_fraction: float) -> tuple[list[int], list[int]]:
    """Window rows of one dataset's training and validation scenes: the last
    ``val_fraction`` of its scenes validate."""
    n = len(ds.scenes)
    k = max(1, round(n * val_fraction)) if val_fraction > 0 else 0
    train = [i for i, (s, _, _) in enumerate(ds.index) if s < n - k]
    val = [i for i, (s, _, _) in enumerate(ds.index) if s >= n - k]
    return train, val


def action_statistics(model: WorldModel, batch: dict[str, torch.Tensor]) -> Normalization:
    """Mean and standard deviation of the valid ground-truth action tokens of ``batch``."""
    actions, ok = model.target_actions(batch)
    a = actions[ok]
    mean, std = a.mean(0), a.std(0).clamp(min=1e-3)
    return Normalization(tuple(mean.tolist()), tuple(std.tolist()))


@torch.no_grad()
def validate(
    model: WorldModel, batch: dict[str, torch.Tensor], seed: int, chunk: int = 64
) -> dict[str, float]:
    """ADE (whole horizon) and FDE [m] of one sample per window, over valid agents."""
    model.eval()
    g = torch.Generator(device=batch["history"].device).manual_seed(seed)
    total, n, fde, nf = 0.0, 0, 0.0, 0
    B = batch["history"].shape[0]
    for lo in range(0, B, chunk):
        part = {k: v[lo : lo + chunk] for k, v in batch.items()}
        pred = model.sample(part, 1, g).trajectory[:, 0]
        ok = part["future_valid"] & model.agent_mask(part)[..., None]
        err = (pred[..., :2] - part["future"][..., :2]).norm(dim=-1)
        total += float((err * ok).sum())
        n += int(ok.sum())
        fde += float((err[..., -1] * ok[..., -1]).sum())
        nf += int(ok[..., -1].sum())
    return {"val_ade": total / max(n, 1), "val_fde": fde / max(nf, 1)}


def torch_device(name: str) -> torch.device:
    """``--device``: a torch device this machine has.

    Raises:
        ValueError: naming the flag (an unknown name, or CUDA / MPS that is not here)."""
    try:
        device = torch.device(name)
    except RuntimeError as exc:
        raise ValueError(f"--device {name!r} is not a torch device: {exc}") from None
    here = {"cuda": torch.cuda.is_available, "mps": torch.backends.mps.is_available}
    if device.type in here and not here[device.type]():
        raise ValueError(f"--device {name!r}: this torch build or machine has no {device.type}")
    return device


def train(cfg: TrainConfig, progress: bool = True) -> dict[str, Any]:
    """Run (or resume) training; returns the final record (losses, validation, wall time)."""
    out = Path(cfg.out)
    if out.exists() and not out.is_dir():
        raise ValueError(f"--out {out} is a file, not a directory")
    device = torch_device(cfg.device)
    # The directory first: a refused run reads no data and writes nothing.
    state_path = out / STATE_FILE
    fingerprint = data_fingerprint(cfg.data)
    state = read_state(state_path, device) if state_path.is_file() else None
    if state is not None:
        check_resume(state, cfg, state_path, fingerprint)
    else:
        check_fresh_out(out, cfg.init)
    torch.manual_seed(cfg.seed)
    model_cfg = get_preset(cfg.preset).replace(**dict(cfg.model_overrides))

    probe = WorldModel(model_cfg)
    train_parts, val_parts, sources, sizes, per_source = [], [], [], [], []
    for j, d in enumerate(cfg.data):
        scenes = load_sources(d)
        if cfg.marked("smooth_tracks", d):
            scenes = [smooth_tracks(s, cfg.smooth_sigma) for s in scenes]
        ds = SceneWindowDataset(
            scenes,
            probe.window_config(cfg.window_stride),
            min_future_steps=cfg.min_future_steps,
            centres="agents" if cfg.marked("agent_centred", d) else "ego",
        )
        rows, val = _split(ds, cfg.val_fraction)
        sizes.append(len(ds.scenes))
        per_source.append(len(rows))
        if rows:
            train_parts.append(_windows(ds, rows))
            sources += [j] * len(rows)
        if val:  # each dataset validates on an equal share of val_windows, evenly spaced
            quota = max(1, cfg.val_windows // len(cfg.data))
            val_parts.append(_windows(ds, val[:: max(1, len(val) // quota)][:quota]))
    if not train_parts:
        held = sum(len(p["history"]) for p in val_parts)
        raise ValueError(
            f"no training windows in {[str(d) for d in cfg.data]} ({sum(sizes)} scenes): "
            + (
                f"the last {cfg.val_fraction:g} of each dataset's scenes (at least one) "
                "validates, which leaves none to train on; give more scenes"
                if held
                else "no scene is long enough for a window (history plus --min-future)"
            )
        )
    train_data = {k: torch.cat([p[k] for p in train_parts]).to(device) for k in train_parts[0]}
    val_data = (
        {k: torch.cat([p[k] for p in val_parts]).to(device) for k in val_parts[0]}
        if val_parts
        else None
    )

    if state is not None:
        normalization = Normalization(
            *(tuple(state["normalization"][k]) for k in ("action_mean", "action_std"))
        )
    elif cfg.init is not None:
        normalization = None  # from the initial model
    else:
        normalization = action_statistics(probe, train_data)

    if cfg.init is not None:
        from counterscene_env.world_model.checkpoint import load_model

        start = load_model(cfg.init)
        # Which lanes the window holds and how it samples size no tensor, so a fine-tune may
        # change them. A model without the agent-centric map may seed one with it: the new
        # modules start at zero output, so the fine-tune starts from the initial model's exact
        # predictions.
        same = start.config.replace(**{k: getattr(model_cfg, k) for k in UNSIZED_FIELDS})
        adds_local = start.config.local_lanes == 0 and model_cfg.local_lanes > 0
        # How many lanes each agent's own map holds, and how near they must be, size no
        # tensor either (attention keys), as long as both models have that map.
        if adds_local or start.config.local_lanes > 0 < model_cfg.local_lanes:
            same = same.replace(
                local_lanes=model_cfg.local_lanes, local_radius=model_cfg.local_radius
            )
        # So may a model without the plan features seed one with them (zero output too). The
        # two kinds of plan ("noisy", "self") read the same tensors: either may seed the other.
        adds_plan = start.config.plan_features == "none" != model_cfg.plan_features
        if model_cfg.plan_features != "none":
            same = same.replace(plan_features=model_cfg.plan_features)
        # And one without an input of ADDED_INPUTS (its columns start at zero).
        added = {
            k: True for k in ADDED_INPUTS if getattr(model_cfg, k) and not getattr(start.config, k)
        }
        same = same.replace(**added)
        # And a network with more blocks: the new ones are appended and start as the identity
        # (their residual branches at zero), so the fine-tune starts from the exact predictions.
        kept_blocks = start.config.num_blocks
        grown = model_cfg.num_blocks > kept_blocks
        if grown:
            same = same.replace(num_blocks=model_cfg.num_blocks)
        if same != model_cfg:
            differ = ", ".join(
                f"{f.name} {getattr(same, f.name)!r} there, {getattr(model_cfg, f.name)!r} here"
                for f in dataclasses.fields(model_cfg)
                if getattr(same, f.name) != getattr(model_cfg, f.name)
            )
            raise ValueError(
                f"--init model {cfg.init!r} has another architecture than preset "
                f"{cfg.preset!r} with the given overrides ({differ})"
            )
        normalization = normalization or start.normalization
        model = WorldModel(model_cfg, normalization).to(device)
        missing, unexpected = model.load_state_dict(
            start.state_dict(), strict=not (adds_local or adds_plan or added or grown)
        )
        for block in model.denoiser.blocks[kept_blocks:]:
            block.start_as_identity()
        new_modules = (
            ".local",
            "denoiser.plan_in.",
            "denoiser.pair_mlp.",
            "denoiser.priority_in.",
            "denoiser.local_priority_in.",
            "denoiser.source_in.",
            *(f"denoiser.blocks.{i}." for i in range(kept_blocks, model_cfg.num_blocks)),
        )
        if unexpected or any(not any(m in k for m in new_modules) for k in missing):
            raise ValueError(f"--init model {cfg.init!r}: tensors do not match the new model")
    else:
        model = WorldModel(model_cfg, normalization).to(device)
    ema = copy.deepcopy(model).eval()
    opt = torch.optim.Adam(model.parameters(), lr=cfg.lr)
    noise = torch.Generator(device=device).manual_seed(cfg.seed)
    step, elapsed = 0, 0.0
    if state is not None:
        model.load_state_dict(state["model"])
        ema.load_state_dict(state["ema"])
        opt.load_state_dict(state["optimizer"])
        noise.set_state(state["noise"].cpu() if device.type == "cpu" else state["noise"])
        step, elapsed = int(state["step"]), float(state["elapsed"])

    n_train = len(sources)
    info = {
        "data": [str(d) for d in cfg.data],
        "scenes": sum(sizes),
        "train_windows": n_train,
        "train_windows_per_source": per_source,
        "agent_centred": [str(d) for d in cfg.agent_centred],
        "data_weights": None if cfg.data_weights is None else list(cfg.data_weights),
        "val_windows": 0 if val_data is None else int(val_data["history"].shape[0]),
        "parameters": sum(p.numel() for p in model.parameters()),
        "batch_size": cfg.batch_size,
        "lr": cfg.lr,
        "lr_decay_start": cfg.lr_decay_start,
        "ema_decay": cfg.ema_decay,
        "ema_start": cfg.ema_start,
        "seed": cfg.seed,
        "device": str(device),
        "hardware": f"{platform.machine()} {os.cpu_count()} cores"
        + (f", {torch.cuda.get_device_name(device)}" if device.type == "cuda" else ""),
        "torch": torch.__version__,
    }
    # What shaped the loss and the windows, where set (a shipped model's record of its run).
    for key in (
        "off_lane_weight",
        "off_lane_by_course",
        "overlap_weight",
        "min_future_steps",
        "parked_cars",
    ):
        if getattr(cfg, key):
            info[key] = getattr(cfg, key)
    if cfg.smooth_tracks:
        info.update(
            smooth_tracks=[str(d) for d in cfg.smooth_tracks], smooth_sigma=cfg.smooth_sigma
        )
    if cfg.init is not None:  # provenance of a fine-tune: where it started
        info.update(init=cfg.init, init_training=dict(start.training_info))
    t_start = time.perf_counter() - elapsed

    def snapshot() -> dict[str, Any]:
        """The resumable state at ``step`` (plain containers: ``weights_only``)."""
        return {
            "step": step,
            "elapsed": time.perf_counter() - t_start,
            "config": plain_settings(cfg),
            "data_files": fingerprint,
            "normalization": normalization.to_dict(),
            "model": model.state_dict(),
            "ema": ema.state_dict(),
            "optimizer": opt.state_dict(),
            "noise": noise.get_state(),
        }

    out.mkdir(parents=True, exist_ok=True)  # every check is done: a refused run writes nothing
    if state is None:
        # A fresh run's log starts empty (one left here is another run's), and its last.pt
        # comes before its first model, so that a stop in between still resumes.
        (out / LOG_FILE).unlink(missing_ok=True)
        save_state(out, snapshot())
    else:
        trim_log(out / LOG_FILE, step)
    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(total=cfg.steps, initial=step, desc="train", unit="step", dynamic_ncols=True)
    draws = (
        batches(n_train, cfg.batch_size, cfg.seed, step)
        if cfg.data_weights is None
        else weighted_batches(
            torch.tensor(sources), cfg.data_weights, cfg.batch_size, cfg.seed, step
        )
    )
    running: dict[str, float] = {}
    record: dict[str, Any] = {}
    model.train()
    while step < cfg.steps:
        for group in opt.param_groups:
            group["lr"] = learning_rate(cfg, step)
        rows = next(draws).to(device)
        batch = {k: v[rows] for k, v in train_data.items()}
        if cfg.parked_cars > 0:  # a stream of its own, seeded by the step: resumes exactly
            g = torch.Generator().manual_seed(PARKED_STREAM + cfg.seed * 100003 + step)
            batch = add_parked_cars(batch, cfg.parked_cars, g)
        losses = training_loss(
            model, batch, noise, cfg.off_lane_weight, cfg.overlap_weight, cfg.off_lane_by_course
        )
        opt.zero_grad(set_to_none=True)
        losses["loss"].backward()
        torch.nn.utils.clip_grad_norm_(model.parameters(), cfg.grad_clip)
        opt.step()
        step += 1
        with torch.no_grad():
            decay = cfg.ema_decay if step > cfg.ema_start else 0.0
            for pe, pm in zip(ema.parameters(), model.parameters(), strict=True):
                pe.lerp_(pm, 1 - decay)
        values = {k: float(v.detach()) for k, v in losses.items()}
        for k, v in values.items():
            running[k] = running.get(k, 0.0) + v
        running["n"] = running.get("n", 0) + 1
        if bar is not None:
            bar.update(1)
            if step % 10 == 0:
                bar.set_postfix(loss=f"{values['loss']:.3f}", pos=f"{values['position']:.2f}m")
        if step % cfg.checkpoint_every == 0 or step == cfg.steps:
            record = {"step": step, **{k: v / running["n"] for k, v in running.items() if k != "n"}}
            running = {}
            if val_data is not None:
                record.update(validate(ema, val_data, cfg.seed))
            record["wall_time_s"] = round(time.perf_counter() - t_start, 1)
            # Record, model, then state: a stop in between resumes from the previous last.pt,
            # whose rerun steps replace their records (trim_log) and the model.
            with open(out / LOG_FILE, "a") as fh:
                fh.write(json.dumps(record) + "\n")
            save_model(ema, out, cfg.preset, {**info, "steps": step, **record})
            save_state(out, snapshot())
            if bar is not None and "val_ade" in record:
                bar.write(
                    f"step {step}: loss {record['loss']:.4f}  val ADE {record['val_ade']:.3f} m  "
                    f"FDE {record['val_fde']:.3f} m"
                )
            model.train()
    if bar is not None:
        bar.close()
    if not record:  # finished before: the last logged record ({} if its log was removed)
        log = out / LOG_FILE
        lines = log.read_text().splitlines() if log.is_file() else []
        record = json.loads(lines[-1]) if lines else {}
    return record
