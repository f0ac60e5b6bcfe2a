"""The world-model subcommands in-process: train (and resume), evaluate-model, bench."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
import torch
from conftest import crash_scene
from safetensors.torch import load_file

from counterscene_env.cli import main
from counterscene_env.scene.shards import save_scenes
from counterscene_env.world_model.bench import synthetic_batch
from counterscene_env.world_model.checkpoint import load_model
from counterscene_env.world_model.config import preset
from counterscene_env.world_model.train_config import TrainConfig

TINY = ["--set", "d_model=32", "--set", "num_heads=2", "--set", "num_blocks=1"]


pytestmark = pytest.mark.usefixtures("one_torch_thread")


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    out = tmp_path_factory.mktemp("data") / "merge"
    argv = ["generate", "--scenario", "merge", "--scenes", "3", "--out", str(out), "--quiet"]
    assert main(argv) == 0
    return out


def _train(data, out, steps, *extra):
    argv = [
        "train",
        "--data",
        str(data),
        "--out",
        str(out),
        "--steps",
        str(steps),
        "--checkpoint-every",
        "2",
        "--batch-size",
        "4",
        *TINY,
        "--quiet",
        *extra,
    ]
    return main(argv)


def _log(out):
    return (out / "log.jsonl").read_text().splitlines()


@pytest.fixture(scope="module")
def trained(dataset, tmp_path_factory):
    """A 4-step tiny run (checkpoints at steps 2 and 4)."""
    out = tmp_path_factory.mktemp("runs") / "o"
    assert _train(dataset, out, 4) == 0
    return out


def test_train_writes_checkpoint_log_and_state(trained):
    names = {p.name for p in trained.iterdir()}
    assert {"model.safetensors", "config.json", "last.pt", "log.jsonl"} <= names
    assert not any(n.endswith(".tmp") for n in names)
    lines = [json.loads(line) for line in _log(trained)]
    assert [r["step"] for r in lines] == [2, 4]
    for r in lines:
        assert math.isfinite(r["loss"]) and r["loss"] > 0
        assert r["val_ade"] >= 0 and r["val_fde"] >= 0
    model = load_model(trained)
    assert model.config.d_model == 32 and model.config.num_blocks == 1
    assert model.preset == "default" and model.training_info["steps"] == 4
    assert model.training_info["scenes"] == 3
    state = torch.load(trained / "last.pt", weights_only=True)
    assert state["step"] == 4


@pytest.mark.slow
def test_resume_extends_the_run_and_matches_an_uninterrupted_one(dataset, tmp_path, capsys):
    resumed = tmp_path / "resumed"
    assert _train(dataset, resumed, 4) == 0
    before = _log(resumed)
    assert len(before) == 2
    assert _train(dataset, resumed, 6) == 0  # the same command with a larger --steps
    after = _log(resumed)
    assert len(after) == 3 and after[:2] == before
    assert json.loads(after[2])["step"] == 6
    assert torch.load(resumed / "last.pt", weights_only=True)["step"] == 6

    fresh = tmp_path / "fresh"
    assert _train(dataset, fresh, 6) == 0
    a = load_file(str(resumed / "model.safetensors"))
    b = load_file(str(fresh / "model.safetensors"))
    assert a.keys() == b.keys()
    for k in a:
        assert torch.equal(a[k], b[k]), k
    # Same losses and validation along the way (wall time aside).
    for x, y in zip(_log(resumed), _log(fresh), strict=True):
        x, y = json.loads(x), json.loads(y)
        x.pop("wall_time_s"), y.pop("wall_time_s")
        assert x == y

    # A finished run rerun with the same --steps does nothing more, and prints its last record.
    capsys.readouterr()
    assert _train(dataset, fresh, 6) == 0
    assert len(_log(fresh)) == 3
    assert json.loads(capsys.readouterr().out) == json.loads(_log(fresh)[-1])
    # ... and with its log emptied or removed, does nothing more either (no IndexError).
    log = fresh / "log.jsonl"
    kept = log.read_bytes()
    for emptied in (lambda: log.write_text(""), log.unlink):
        emptied()
        assert _train(dataset, fresh, 6) == 0
        assert json.loads(capsys.readouterr().out) == {}
    log.write_bytes(kept)
    # A smaller --steps than the run holds is refused, as stress refuses fewer --episodes.
    assert _train(dataset, fresh, 4) == 1
    assert "holds a run at step 6, more than --steps 4" in capsys.readouterr().err
    # A damaged state is named, and nothing is changed.
    state = fresh / "last.pt"
    state.write_bytes(state.read_bytes()[:100])
    before = {p.name: p.read_bytes() for p in fresh.iterdir()}
    assert _train(dataset, fresh, 8) == 1
    assert f"{state} is not a readable training state" in capsys.readouterr().err
    assert {p.name: p.read_bytes() for p in fresh.iterdir()} == before


def test_parked_cars_change_the_run_and_resume_exactly(dataset, tmp_path, capsys):
    parked = ("--parked-cars", "1")
    resumed, fresh, plain = tmp_path / "resumed", tmp_path / "fresh", tmp_path / "plain"
    assert _train(dataset, resumed, 2, *parked) == 0
    assert _train(dataset, resumed, 4, *parked) == 0
    assert _train(dataset, fresh, 4, *parked) == 0
    assert _train(dataset, plain, 4) == 0
    strip = [json.loads(x) for x in _log(resumed)], [json.loads(x) for x in _log(fresh)]
    for x, y in zip(*strip, strict=True):
        x.pop("wall_time_s"), y.pop("wall_time_s")
        assert x == y
    assert _log(fresh)[-1].split('"wall_time_s"')[0] != _log(plain)[-1].split('"wall_time_s"')[0]
    # The model's record names the share (docs/world_model.md, "The shipped default").
    assert load_model(fresh).training_info["parked_cars"] == 1.0
    assert "parked_cars" not in load_model(plain).training_info
    # A run without parked cars does not resume with them, and a share outside [0, 1] is refused.
    capsys.readouterr()
    assert _train(dataset, plain, 6, *parked) == 1
    assert "different settings" in capsys.readouterr().err
    assert _train(dataset, tmp_path / "bad", 2, "--parked-cars", "2") == 1
    err = capsys.readouterr().err
    assert "parked_cars" in err and "Traceback" not in err


def test_resume_with_other_settings_is_refused(trained, dataset, capsys):
    weights = (trained / "model.safetensors").read_bytes()
    capsys.readouterr()
    assert _train(dataset, trained, 6, "--lr", "0.001") == 1
    err = capsys.readouterr().err
    assert "different settings" in err and "Traceback" not in err
    assert len(_log(trained)) == 2
    assert (trained / "model.safetensors").read_bytes() == weights


def test_train_unknown_set_key(dataset, tmp_path, capsys):
    code = main(["train", "--data", str(dataset), "--out", str(tmp_path / "o"), "--set", "widht=3"])
    assert code == 1
    err = capsys.readouterr().err
    assert "widht" in err and "valid keys" in err and "d_model" in err
    assert not (tmp_path / "o").exists()


def test_train_bad_set_syntax_and_missing_data(dataset, tmp_path, capsys):
    argv = ["train", "--data", str(dataset), "--out", str(tmp_path / "o"), "--set", "d_model"]
    assert main(argv) == 1
    assert "KEY=VALUE" in capsys.readouterr().err
    argv = ["train", "--data", str(tmp_path / "none"), "--out", str(tmp_path / "o")]
    assert main(argv) == 1
    assert "no dataset at" in capsys.readouterr().err


def test_evaluate_model_json(trained, dataset, capsys):
    capsys.readouterr()
    argv = ["evaluate-model", "--data", str(dataset), "--model", str(trained), "--json"]
    assert main([*argv, "--samples", "2", "--quiet"]) == 0
    out = capsys.readouterr().out.strip()
    assert "\n" not in out  # one JSON object on one line
    result = json.loads(out)
    assert result["scenes"] == 3 and result["samples"] == 2 and result["agents"] > 0
    model, cv = result["model"], result["constant_velocity"]
    hz = {"1s", "2s", "3s", "full"}
    one_draw = ("ade", "fde", "ade_all_samples", "fde_all_samples", "min_ade_2", "min_fde_2")
    for block, keys in ((model, one_draw), (cv, ("ade", "fde"))):
        for key in keys:
            assert set(block[key]) == hz, key
            for h, v in block[key].items():
                assert isinstance(v, float) and math.isfinite(v) and v >= 0, (key, h, v)
        assert 0.0 <= block["offroad_rate"] <= 1.0
    # Errors grow with the horizon; the best of 2 samples is no worse than the first.
    assert model["ade"]["1s"] <= model["ade"]["full"]
    assert cv["ade"]["1s"] <= cv["ade"]["full"]
    for h in hz:
        assert model["min_ade_2"][h] <= model["ade"][h] + 1e-9
        assert model["min_ade_2"][h] <= model["ade_all_samples"][h] + 1e-9
    # The best-of keys name the sample count they are the best of (--samples 2), nowhere 6.
    assert "min_ade_2_ratio_to_cv" in result and "min_ade_6_ratio_to_cv" not in result
    for block in (result, *result["by_speed"].values(), result["still"]):
        assert "min_fde_2" in block["model"] and "min_ade_6" not in block["model"]
    # The mean over the samples is another estimate of one draw's error: with one sample it
    # is that sample's.
    assert model["ade_all_samples"] != model["ade"]
    assert main([*argv, "--samples", "1", "--quiet"]) == 0
    single = json.loads(capsys.readouterr().out)["model"]
    assert single["ade_all_samples"] == single["ade"]
    assert single["fde_all_samples"] == single["fde"]
    # The share of windows whose sample overlaps two boxes only grows with the horizon.
    overlap = result["sample_overlap"]
    assert set(overlap) == hz and all(0.0 <= overlap[h] <= 1.0 for h in hz)
    assert overlap["1s"] <= overlap["3s"] <= overlap["full"]
    # The tiny model samples with the preset's lane keeping; --lane-steering 0 turns it off
    # (the network alone), which changes the trajectories and so the errors.
    assert result["lane_steering"] == preset("default").lane_steering > 0
    assert main([*argv, "--samples", "2", "--quiet", "--lane-steering", "0"]) == 0
    raw = json.loads(capsys.readouterr().out)
    assert raw["lane_steering"] == 0 and raw["model"]["ade"] != model["ade"]
    assert main([*argv, "--quiet", "--lane-steering", "-1"]) == 1
    assert "--lane-steering must be >= 0" in capsys.readouterr().err
    # The hold on parked cars is the model's (the preset's 1.5 m); --hold-parked sets it.
    assert result["hold_parked_m"] == preset("default").hold_parked == 1.5
    assert main([*argv, "--samples", "2", "--quiet", "--hold-parked", "0"]) == 0
    assert json.loads(capsys.readouterr().out)["hold_parked_m"] == 0
    assert main([*argv, "--quiet", "--hold-parked", "-1"]) == 1
    assert "--hold-parked must be >= 0 m" in capsys.readouterr().err
    for bad in ("0", "-3"):
        assert main([*argv, "--quiet", "--samples", bad]) == 1
        assert f"--samples must be >= 1, got {bad}" in capsys.readouterr().err
    # The speed split: three bins, every agent in exactly one, each with the top level's keys.
    assert result["speed_bins_m_s"] == [0.5, 3.0] and result["skipped_scenes"] == 0
    by_speed = result["by_speed"]
    assert list(by_speed) == ["parked", "slow", "moving"]
    assert sum(b["agents"] for b in by_speed.values()) == result["agents"]
    for block in by_speed.values():
        assert (
            set(block)
            == set(result["by_speed"]["moving"])
            >= {
                "agents",
                "model",
                "constant_velocity",
                "log_offroad_rate",
                "ade_ratio_to_cv",
                "ade_ratio_to_cv_ci95",
            }
        )
        assert set(block["model"]) == set(model) and set(block["constant_velocity"]) == set(cv)
    assert by_speed["moving"]["agents"] > 0  # generated merge traffic drives


def test_evaluate_model_every_second_with_intervals(trained, dataset, capsys):
    """``--every 1``: every second of each 13 s log with 3 s of history and 3 s of future is a
    start (t0 = 30, 40, ..., 100: 8 per scene); every figure has a 95 % interval around it, and
    the ratio to constant velocity is the ratio of the two ADEs."""
    argv = ["evaluate-model", "--data", str(dataset), "--model", str(trained), "--json"]
    capsys.readouterr()
    assert main([*argv, "--samples", "2", "--quiet", "--every", "1", "--bootstrap", "200"]) == 0
    result = json.loads(capsys.readouterr().out)
    assert (result["scenes"], result["windows"], result["every_s"]) == (3, 24, 1.0)
    model, cv = result["model"], result["constant_velocity"]
    for block in (model, cv):
        lo, hi = block["ci95"]["ade"]["3s"]
        assert lo <= block["ade"]["3s"] <= hi
    ratio = result["ade_ratio_to_cv"]["3s"]
    assert ratio == pytest.approx(model["ade"]["3s"] / cv["ade"]["3s"])
    lo, hi = result["ade_ratio_to_cv_ci95"]["3s"]
    assert lo <= ratio <= hi
    assert main([*argv, "--quiet", "--every", "0"]) == 1
    assert "--every must be > 0" in capsys.readouterr().err


def test_evaluate_model_speed_bins_and_short_logs(trained, tmp_path, capsys):
    # Row 0 (ego) and row 1 drive at 10 m/s, row 2 is parked (crash_scene). "Now" at step 10:
    # 11 history frames of the model's 31 (padded) and 29 future frames of its 52 (the rest
    # invalid). The same scene with "now" at its last step has no future: skipped, counted.
    scene = crash_scene()
    shard = save_scenes(
        [scene.replace(current_index=10), scene.replace(current_index=scene.num_steps - 1)],
        tmp_path / "short.npz",
    )
    argv = ["evaluate-model", "--data", str(shard), "--model", str(trained), "--quiet"]
    capsys.readouterr()
    assert main([*argv, "--samples", "2", "--json"]) == 0
    result = json.loads(capsys.readouterr().out)
    assert (result["scenes"], result["skipped_scenes"], result["agents"]) == (1, 1, 3)
    by_speed = result["by_speed"]
    assert [by_speed[b]["agents"] for b in ("parked", "slow", "moving")] == [1, 0, 2]
    for h in ("1s", "full"):
        assert math.isfinite(result["model"]["ade"][h]) and result["model"]["ade"][h] >= 0
        # Constant velocity keeps the parked car exactly where the log has it.
        assert by_speed["parked"]["constant_velocity"]["ade"][h] < 1e-3
    assert by_speed["slow"]["model"]["ade"]["1s"] is None  # an empty bin has no figure
    # The parked car is logged for 1 s after "now" only: whether it stays put 3 s later is
    # unknown, so it is not counted "still".
    assert result["still"]["agents"] == 0 and result["still"]["model"]["fde"]["3s"] is None
    # The text report prints one ADE block per bin.
    assert main([*argv, "--samples", "1"]) == 0
    out = capsys.readouterr().out
    assert "1 skipped" in out and "parked (1 agents)" in out and "moving (2 agents)" in out


def test_evaluate_model_still_agents(trained, tmp_path, capsys):
    """A car parked now and logged in place 3 s later is "still": its FDE at 3 s is reported
    on its own (constant velocity keeps it exactly there)."""
    scene = crash_scene(60)
    positions = scene.positions.copy()
    positions[2] = [64.0, 0.0]  # parked for the whole log
    scene = scene.replace(positions=positions, valid=np.ones_like(scene.valid), current_index=10)
    shard = save_scenes([scene], tmp_path / "still.npz")
    argv = ["evaluate-model", "--data", str(shard), "--model", str(trained), "--quiet"]
    capsys.readouterr()
    assert main([*argv, "--samples", "1", "--json"]) == 0
    still = json.loads(capsys.readouterr().out)["still"]
    assert still["agents"] == 1
    assert still["constant_velocity"]["fde"]["3s"] < 1e-3
    assert still["model"]["fde"]["3s"] >= 0


def test_evaluate_model_commonroad_flag(capsys, tmp_path):
    with pytest.raises(SystemExit):
        main(["evaluate-model", "--help"])
    assert "--commonroad DIR" in capsys.readouterr().out
    # A missing directory is refused before the CommonRoad loader is imported.
    assert main(["evaluate-model", "--commonroad", str(tmp_path / "none"), "--quiet"]) == 1
    err = capsys.readouterr().err
    assert "none" in err and "no such file" in err and "Traceback" not in err
    argv = ["evaluate-model", "--commonroad", str(tmp_path), "--scenarionet", str(tmp_path)]
    with pytest.raises(SystemExit):  # one source at a time
        main(argv)


def test_evaluate_model_missing_model(dataset, capsys):
    argv = ["evaluate-model", "--data", str(dataset), "--model", "/nonexistent", "--quiet"]
    assert main(argv) == 1
    err = capsys.readouterr().err
    assert "/nonexistent" in err and "does not exist" in err and "Traceback" not in err


def test_bench_json(capsys):
    capsys.readouterr()
    argv = ["bench", "--preset", "default", "--runs", "2", "--json", "--threads", "1"]
    assert main(argv) == 0
    result = json.loads(capsys.readouterr().out)
    assert result["runs"] == 2 and result["threads"] == 1
    assert result["latency_median_s"] > 0 and result["latency_p90_s"] >= result["latency_median_s"]
    assert result["flops_per_forward"] > 0
    assert result["flops_per_call"] == result["flops_per_forward"] * result["sampling_steps"]
    assert result["sampling_steps"] == 10 and result["sampler"] == "ddim"
    assert result["peak_gflops"] > 0 and result["peak_fraction"] > 0
    assert "untrained" in result["model"]


def test_init_starts_from_a_model_and_refuses_another_architecture(
    trained, dataset, tmp_path, capsys
):
    # A zero-step run from --init writes the initial weights back: the fine-tune starts there.
    out = tmp_path / "fine"
    assert _train(dataset, out, 2, "--init", str(trained), "--lr", "0") == 0
    start, fine = load_model(trained), load_model(out)
    for (name, a), (_, b) in zip(
        start.state_dict().items(), fine.state_dict().items(), strict=True
    ):
        assert torch.equal(a, b), name
    assert fine.normalization == start.normalization
    capsys.readouterr()
    assert (
        main(
            [
                "train",
                "--data",
                str(dataset),
                "--out",
                str(tmp_path / "x"),
                "--steps",
                "1",
                "--init",
                "default",
                *TINY,
                "--quiet",
            ]
        )
        == 1
    )
    err = capsys.readouterr().err
    assert "another architecture" in err
    assert "d_model 96 there, 32 here" in err  # the field that differs, both values


def test_init_adds_the_agent_centric_map_but_never_drops_it(dataset, tmp_path, capsys):
    plain = tmp_path / "plain"
    assert _train(dataset, plain, 2, "--set", "local_lanes=0") == 0
    # A model without the agent-centric map seeds one with it: every old tensor carries over
    # and the new output projections start at zero.
    fine = tmp_path / "fine"
    assert _train(dataset, fine, 2, "--init", str(plain), "--lr", "0") == 0
    start, model = load_model(plain), load_model(fine)
    assert start.config.local_lanes == 0 and model.config.local_lanes > 0
    assert model.training_info["init"] == str(plain)  # the provenance names the start
    assert model.training_info["init_training"]["steps"] == 2
    new = model.state_dict()
    for name, tensor in start.state_dict().items():
        assert torch.equal(tensor, new[name]), name
    assert all(not new[f"denoiser.blocks.{i}.local.out.weight"].any() for i in range(1))
    # How many lanes that map holds sizes no tensor: a fine-tune may widen it.
    wide = tmp_path / "wide"
    argv = ["--init", str(fine), "--lr", "0", "--set", "local_lanes=20", "--set", "local_radius=40"]
    assert _train(dataset, wide, 2, *argv) == 0
    widened = load_model(wide)
    assert (widened.config.local_lanes, widened.config.local_radius) == (20, 40.0)
    for name, tensor in new.items():
        assert torch.equal(tensor, widened.state_dict()[name]), name
    # The other way round would throw trained weights away: refused.
    capsys.readouterr()
    assert _train(dataset, tmp_path / "back", 2, "--init", str(fine), "--set", "local_lanes=0") == 1
    assert "another architecture" in capsys.readouterr().err


def test_init_adds_the_plan_features_but_never_drops_them(trained, dataset, tmp_path, capsys):
    fine = tmp_path / "fine"
    assert (
        _train(dataset, fine, 2, "--init", str(trained), "--lr", "0", "--set", "plan_features=self")
        == 0
    )
    start, model = load_model(trained), load_model(fine)
    assert (start.config.plan_features, model.config.plan_features) == ("none", "self")
    new = model.state_dict()
    for name, tensor in start.state_dict().items():
        assert torch.equal(tensor, new[name]), name
    assert (
        not new["denoiser.plan_in.2.weight"].any() and not new["denoiser.pair_mlp.2.weight"].any()
    )
    # The other kind of plan reads the same tensors: a fine-tune may switch, every tensor kept.
    other = tmp_path / "noisy"
    argv = ["--init", str(fine), "--lr", "0", "--set", "plan_features=noisy"]
    assert _train(dataset, other, 2, *argv) == 0
    switched = load_model(other)
    assert switched.config.plan_features == "noisy"
    for name, tensor in new.items():
        assert torch.equal(tensor, switched.state_dict()[name]), name
    capsys.readouterr()
    assert _train(dataset, tmp_path / "back", 2, "--init", str(fine)) == 1
    assert "another architecture" in capsys.readouterr().err


@pytest.mark.parametrize(
    ("key", "columns"),
    [
        ("lane_priority", ["denoiser.local_priority_in.weight", "denoiser.priority_in.weight"]),
        ("source_flag", ["denoiser.source_in.weight"]),
    ],
)
def test_init_adds_an_input_but_never_drops_it(trained, dataset, tmp_path, capsys, key, columns):
    """The lanes' right of way and the source flag: a fine-tune may switch either on, every
    tensor kept and its new columns at zero; a model with it cannot seed one without."""
    fine = tmp_path / "fine"
    args = ("--init", str(trained), "--lr", "0", "--set", f"{key}=true")
    assert _train(dataset, fine, 2, *args) == 0
    start, model = load_model(trained), load_model(fine)
    assert (getattr(start.config, key), getattr(model.config, key)) == (False, True)
    new = model.state_dict()
    for name, tensor in start.state_dict().items():
        assert torch.equal(tensor, new[name]), name
    added = sorted(set(new) - set(start.state_dict()))
    assert added == columns
    assert not any(new[name].any() for name in added)
    capsys.readouterr()
    assert _train(dataset, tmp_path / "back", 2, "--init", str(fine)) == 1
    assert "another architecture" in capsys.readouterr().err


def test_init_appends_blocks_that_start_as_the_identity(trained, dataset, tmp_path, capsys):
    """A deeper network seeded from a trained one: every tensor kept, the new blocks appended,
    and the same samples as the initial model to rounding (they start as the identity); the
    deeper model cannot seed a shallower one."""
    deep = tmp_path / "deep"
    assert (
        _train(dataset, deep, 2, "--init", str(trained), "--lr", "0", "--set", "num_blocks=3") == 0
    )
    start, model = load_model(trained).eval(), load_model(deep).eval()
    assert (start.config.num_blocks, model.config.num_blocks) == (1, 3)
    new = model.state_dict()
    for name, tensor in start.state_dict().items():
        assert torch.equal(tensor, new[name]), name
    assert {k.split(".")[2] for k in set(new) - set(start.state_dict())} == {"1", "2"}
    batch = synthetic_batch(start, torch.Generator().manual_seed(0))
    with torch.no_grad():
        a = start.sample(batch, 2, torch.Generator().manual_seed(1)).trajectory
        b = model.sample(batch, 2, torch.Generator().manual_seed(1)).trajectory
    torch.testing.assert_close(a, b)
    capsys.readouterr()
    assert _train(dataset, tmp_path / "back", 2, "--init", str(deep)) == 1
    assert "another architecture" in capsys.readouterr().err


def test_init_may_change_which_lanes_the_window_holds(dataset, tmp_path):
    # The window's lanes size no tensor: a model trained on the ego-centred map of 32 lanes
    # seeds the default's agent-anchored 48, every tensor carried over.
    old = tmp_path / "old"
    assert _train(dataset, old, 2, "--set", "lane_anchors=ego", "--set", "num_lanes=32") == 0
    fine = tmp_path / "fine"
    assert (
        _train(
            dataset,
            fine,
            2,
            "--init",
            str(old),
            "--lr",
            "0",
            "--off-lane-weight",
            "1",
            "--off-lane-by-course",
            "--overlap-weight",
            "1",
        )
        == 0
    )
    start, model = load_model(old), load_model(fine)
    assert (start.config.lane_anchors, start.config.num_lanes) == ("ego", 32)
    assert (model.config.lane_anchors, model.config.num_lanes) == ("agents", 48)
    for (name, a), (_, b) in zip(
        start.state_dict().items(), model.state_dict().items(), strict=True
    ):
        assert torch.equal(a, b), name
    # The off-lane and overlap terms are logged with the other losses.
    record = json.loads(_log(fine)[-1])
    assert math.isfinite(record["off_lane"]) and record["off_lane"] >= 0
    assert math.isfinite(record["overlap"]) and record["overlap"] >= 0
    assert model.training_info["off_lane_by_course"] is True  # recorded with the run


@pytest.mark.slow
def test_full_bench_json_has_every_figure(capsys):
    """``counterscene bench --json``: the anchor, the env, replans, stress and RSS in one run."""
    capsys.readouterr()
    argv = ["bench", "--steps", "12", "--episodes", "1", "--runs", "1", "--json"]
    argv += ["--vector-envs", "2", "--vector-steps", "2"]
    assert main(argv) == 0
    r = json.loads(capsys.readouterr().out)
    assert set(r["vector_env_steps_per_s"]) == set(r["vector_env_stored_scenes_steps_per_s"])
    assert r["vector_env_steps_per_s"]["2"] > 0
    assert r["vector_env_stored_scenes_workers_steps_per_s"]["2"] > 0  # split over 2 processes
    assert r["highway_env_steps_per_s"] > 0 and r["env_steps_per_s"] > 0
    # The anchor is timed before and after ours, and the figure is their mean.
    runs = r["runs"]["anchor"]["runs_steps_per_s"]
    assert len(runs) == 2 and r["highway_env_steps_per_s"] == pytest.approx(sum(runs) / 2)
    assert r["env_vs_highway_env"] == pytest.approx(
        r["env_steps_per_s"] / r["highway_env_steps_per_s"]
    )
    assert r["replan_ms"]["count"] >= 1 and r["replan_ms"]["p95"] >= r["replan_ms"]["median"] > 0
    assert r["flops_per_replan"] > 0 and 0 < r["peak_fraction"] < 1
    assert r["stress_s_per_episode"] > 0 and r["peak_rss_mb"] > 100
    with pytest.raises(SystemExit) as refused:  # refused by the parser, named
        main(["bench", "--steps", "0"])
    assert refused.value.code == 2 and "--steps" in capsys.readouterr().err
    assert main(["bench", "--vector-envs", "4,x"]) == 1
    assert "--vector-envs" in capsys.readouterr().err


@pytest.mark.slow
def test_weighted_agent_centred_mixture_trains_records_and_resumes(dataset, tmp_path):
    """Two sources, the second agent-centred with its tracks smoothed, mixed 1:3 per batch:
    the record says so, and a resumed run equals an uninterrupted one (the weighted draw is
    seeded by the step)."""
    extra = ["--agent-centred", str(dataset), "--data-weights", "1", "3"]
    extra += ["--smooth-tracks", str(dataset), "--smooth-sigma", "0.3"]

    def run(out, steps):
        argv = ["train", "--data", str(dataset.parent / "ego"), str(dataset), "--out", str(out)]
        argv += ["--steps", str(steps), "--checkpoint-every", "2", "--batch-size", "4"]
        return main([*argv, *TINY, "--quiet", *extra])

    (dataset.parent / "ego").mkdir(exist_ok=True)
    for f in dataset.iterdir():  # the same scenes, read ego-centred
        target = dataset.parent / "ego" / f.name
        if not target.exists():
            target.symlink_to(f)
    assert run(tmp_path / "a", 2) == 0 and run(tmp_path / "a", 4) == 0
    assert run(tmp_path / "b", 4) == 0
    for x, y in zip(_log(tmp_path / "a"), _log(tmp_path / "b"), strict=True):
        x, y = json.loads(x), json.loads(y)
        x.pop("wall_time_s"), y.pop("wall_time_s")
        assert x == y
    info = load_model(tmp_path / "b").training_info
    ego_windows, agent_windows = info["train_windows_per_source"]
    assert agent_windows > ego_windows > 0  # every merge vehicle centres windows, not the ego only
    assert info["data_weights"] == [1.0, 3.0] and info["agent_centred"] == [str(dataset)]
    assert info["smooth_tracks"] == [str(dataset)] and info["smooth_sigma"] == 0.3


def test_train_mixture_settings_are_checked(dataset, tmp_path, capsys):
    base = ["train", "--data", str(dataset), "--out", str(tmp_path / "o"), *TINY, "--quiet"]
    assert main([*base, "--data-weights", "1", "2"]) == 1
    assert "data_weights has 2 values for 1 data entries" in capsys.readouterr().err
    assert main([*base, "--data-weights", "-1"]) == 1
    assert "data_weights must be >= 0" in capsys.readouterr().err
    assert main([*base, "--agent-centred", str(tmp_path)]) == 1
    assert "agent_centred names datasets not in data" in capsys.readouterr().err
    assert main([*base, "--smooth-tracks", str(tmp_path)]) == 1
    assert "smooth_tracks names datasets not in data" in capsys.readouterr().err
    assert main([*base, "--smooth-tracks", str(dataset), "--smooth-sigma", "0"]) == 1
    assert "smooth_sigma" in capsys.readouterr().err
    assert not (tmp_path / "o").exists()
    # The same dataset spelt with a trailing slash is the same dataset.
    config = TrainConfig(data=(f"{dataset}/",), out="o", smooth_tracks=(str(dataset),))
    assert config.marked("smooth_tracks", f"{dataset}/")
    assert not config.marked("agent_centred", f"{dataset}/")
