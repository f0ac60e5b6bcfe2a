"""World-model checkpoints: the round trip and every way a directory can fail to load."""

from __future__ import annotations

import json
import os
import pickle

import numpy as np
import pytest
import torch
from conftest import make_scene
from safetensors.torch import load_file, save_file
from torch.utils.data import default_collate

from counterscene_env.world_model.checkpoint import (
    CONFIG,
    DEFAULT_MODEL_DIR,
    FORMAT,
    VERSION,
    WEIGHTS,
    CheckpointError,
    load_model,
    read_config,
    save_model,
)
from counterscene_env.world_model.config import preset
from counterscene_env.world_model.dataset import SceneWindowDataset
from counterscene_env.world_model.model import WorldModel
from counterscene_env.world_model.records import Normalization

TINY = preset("default").replace(
    d_model=32, num_heads=2, num_blocks=1, num_agents=4, num_lanes=8, sampling_steps=3
)


pytestmark = pytest.mark.usefixtures("one_torch_thread")


def _model(config=TINY, seed=0) -> WorldModel:
    torch.manual_seed(seed)
    return WorldModel(config, Normalization((0.25, -0.01), (1.5, 0.2))).eval()


@pytest.fixture
def saved(tmp_path):
    """A saved tiny model; tests break one thing in it."""
    model = _model()
    out = save_model(model, tmp_path / "m", preset="default", training={"steps": 7})
    return model, out


def _batch(model: WorldModel) -> dict[str, torch.Tensor]:
    t = np.arange(90) * 0.1
    pos = np.zeros((2, 90, 2))
    pos[0, :, 0], pos[1, :, 0], pos[1, :, 1] = 10 * t, 5 + 12 * t, 4.0
    speeds = np.stack([np.full(90, 10.0), np.full(90, 12.0)])
    ds = SceneWindowDataset([make_scene(pos, speeds=speeds)], model.window_config())
    return default_collate([ds[0]])


def _edit_config(directory, edit) -> None:
    path = directory / CONFIG
    meta = json.loads(path.read_text())
    edit(meta)
    path.write_text(json.dumps(meta))


def test_round_trip(saved):
    model, out = saved
    assert sorted(p.name for p in out.iterdir()) == [CONFIG, WEIGHTS]
    loaded = load_model(out)
    assert not loaded.training
    assert loaded.config == model.config
    assert loaded.normalization == model.normalization
    torch.testing.assert_close(loaded.action_mean, torch.tensor([0.25, -0.01]))
    assert loaded.preset == "default" and loaded.training_info == {"steps": 7}
    ref, got = model.state_dict(), loaded.state_dict()
    assert ref.keys() == got.keys()
    for k in ref:
        assert torch.equal(ref[k], got[k]), k
    batch = _batch(model)
    a = model.sample(batch, 2, torch.Generator().manual_seed(3))
    b = loaded.sample(batch, 2, torch.Generator().manual_seed(3))
    assert torch.equal(a.trajectory, b.trajectory)
    meta = read_config(out)
    assert meta["format"] == FORMAT and meta["version"] == VERSION
    assert meta["architecture"] == model.config.to_dict()


def test_loading_leaves_the_global_torch_generator_alone(saved):
    """A user's ``torch.manual_seed(0)`` draws the same after a model load (a ``gym.make``)."""
    torch.manual_seed(0)
    expected = torch.rand(3)
    torch.manual_seed(0)
    load_model(saved[1])
    assert torch.equal(torch.rand(3), expected)


def test_save_overwrites_and_leaves_no_temporary_files(saved):
    _, out = saved
    other = _model(seed=1)
    save_model(other, out)
    assert sorted(p.name for p in out.iterdir()) == [CONFIG, WEIGHTS]
    loaded = load_model(out)
    assert torch.equal(loaded.denoiser.head.weight, other.denoiser.head.weight)
    assert loaded.preset is None


def test_the_same_model_saves_to_the_same_bytes(tmp_path):
    """Two runs of the same training write identical files (byte for byte)."""
    model = _model(seed=1)
    for name in ("a", "b"):
        save_model(model, tmp_path / name, "default", {"steps": 3})
    for name in (CONFIG, WEIGHTS):
        assert (tmp_path / "a" / name).read_bytes() == (tmp_path / "b" / name).read_bytes()


def test_missing_directory(tmp_path):
    with pytest.raises(CheckpointError, match="does not exist"):
        load_model(tmp_path / "nope")
    (tmp_path / "model.safetensors").write_bytes(b"")
    with pytest.raises(CheckpointError, match="is a file: a model is the directory"):
        load_model(tmp_path / "model.safetensors")


def test_missing_config(saved):
    _, out = saved
    (out / CONFIG).unlink()
    with pytest.raises(CheckpointError, match=r"no config\.json"):
        load_model(out)


def test_missing_weights(saved):
    _, out = saved
    (out / WEIGHTS).unlink()
    with pytest.raises(CheckpointError, match=r"no model\.safetensors"):
        load_model(out)


def test_config_not_json(saved):
    _, out = saved
    (out / CONFIG).write_text("{not json")
    with pytest.raises(CheckpointError, match="not valid JSON"):
        load_model(out)
    (out / CONFIG).write_bytes(b"\xff\xfe\x00garbage")
    with pytest.raises(CheckpointError, match="not valid JSON"):
        load_model(out)


@pytest.mark.parametrize("value", ["something-else", None, 3])
def test_wrong_format_field(saved, value):
    _, out = saved
    _edit_config(out, lambda m: m.update(format=value))
    with pytest.raises(CheckpointError, match="format field"):
        load_model(out)


def test_config_that_is_not_an_object(saved):
    _, out = saved
    (out / CONFIG).write_text("[1, 2]")
    with pytest.raises(CheckpointError, match="format field"):
        load_model(out)


@pytest.mark.parametrize("version", [2, 0, "1", None])
def test_wrong_version(saved, version):
    _, out = saved
    _edit_config(out, lambda m: m.update(version=version))
    with pytest.raises(CheckpointError, match="version"):
        load_model(out)


@pytest.mark.parametrize("section", ["architecture", "normalization"])
def test_missing_section(saved, section):
    _, out = saved
    _edit_config(out, lambda m: m.pop(section))
    with pytest.raises(CheckpointError, match=section):
        load_model(out)


def test_unknown_architecture_key(saved):
    _, out = saved
    _edit_config(out, lambda m: m["architecture"].update(hidden_size=64))
    with pytest.raises(CheckpointError, match="hidden_size") as info:
        load_model(out)
    assert "d_model" in str(info.value)  # names the valid keys


def test_invalid_architecture_value(saved):
    _, out = saved
    _edit_config(out, lambda m: m["architecture"].update(num_heads=3))  # does not divide 32
    with pytest.raises(CheckpointError, match="num_heads must divide d_model"):
        load_model(out)


@pytest.mark.parametrize(
    "norm",
    [
        {"action_mean": [0.0, 0.0], "action_std": [1.0, -0.1]},
        {"action_mean": [0.0, 0.0], "action_std": [1.0]},
        {"action_mean": [0.0, float("nan")], "action_std": [1.0, 0.1]},
        {"action_std": [1.0, 0.1]},
        {"action_mean": ["a", 0.0], "action_std": [1.0, 0.1]},
    ],
)
def test_bad_normalization(saved, norm):
    _, out = saved
    _edit_config(out, lambda m: m.update(normalization=norm))
    with pytest.raises(CheckpointError, match="normalization"):
        load_model(out)


@pytest.mark.parametrize(
    "content",
    [
        os.urandom(4096),
        b"",
        b"abc",
        pickle.dumps({"denoiser.head.weight": [[0.0, 1.0]]}),
        b'{"__metadata__": {}}',
    ],
    ids=["random", "empty", "short", "pickle", "json"],
)
def test_weights_not_safetensors(saved, content):
    _, out = saved
    (out / WEIGHTS).write_bytes(content)
    with pytest.raises(CheckpointError, match="not a readable safetensors file"):
        load_model(out)


def test_torch_pickle_is_never_unpickled(saved, tmp_path):
    model, out = saved
    torch.save(model.state_dict(), out / WEIGHTS)
    with pytest.raises(CheckpointError, match="not a readable safetensors file"):
        load_model(out)


def test_truncated_weights(saved):
    _, out = saved
    data = (out / WEIGHTS).read_bytes()
    (out / WEIGHTS).write_bytes(data[: len(data) // 2])
    with pytest.raises(CheckpointError, match="not a readable safetensors file"):
        load_model(out)


def test_missing_tensor(saved):
    _, out = saved
    tensors = load_file(str(out / WEIGHTS))
    del tensors["denoiser.head.weight"]
    save_file(tensors, str(out / WEIGHTS))
    with pytest.raises(CheckpointError, match=r"missing \['denoiser\.head\.weight'\]"):
        load_model(out)


def test_unexpected_tensor(saved):
    _, out = saved
    tensors = load_file(str(out / WEIGHTS))
    tensors["denoiser.extra.weight"] = torch.zeros(3)
    save_file(tensors, str(out / WEIGHTS))
    with pytest.raises(CheckpointError, match=r"unexpected \['denoiser\.extra\.weight'\]"):
        load_model(out)


def test_weights_of_another_architecture(saved, tmp_path):
    _, out = saved
    # Weights of a wider model under the tiny model's config.json: same names, other shapes.
    wide = save_model(_model(TINY.replace(d_model=48)), tmp_path / "wide")
    (out / WEIGHTS).write_bytes((wide / WEIGHTS).read_bytes())
    with pytest.raises(CheckpointError, match=r"has shape \(.*48.*\).*needs \(.*32"):
        load_model(out)
    # Weights of a deeper model: unexpected tensor names.
    deep = save_model(_model(TINY.replace(num_blocks=2)), tmp_path / "deep")
    (out / WEIGHTS).write_bytes((deep / WEIGHTS).read_bytes())
    with pytest.raises(CheckpointError, match=r"unexpected \['denoiser\.blocks\.1\."):
        load_model(out)


@pytest.mark.parametrize("bad", [float("nan"), float("inf")])
def test_non_finite_weights(tmp_path, bad):
    model = _model()
    with torch.no_grad():
        model.denoiser.head.bias[0] = bad
    out = save_model(model, tmp_path / "m")
    with pytest.raises(CheckpointError, match=r"'denoiser\.head\.bias' holds NaN or infinite"):
        load_model(out)


@pytest.mark.parametrize("change", [{"d_model": 32.0}, {"num_heads": 0}, {"mlp_ratio": -1}])
def test_ill_typed_architecture_value(saved, change):
    _, out = saved
    _edit_config(out, lambda m: m["architecture"].update(change))
    with pytest.raises(CheckpointError):
        load_model(out)


def test_shipped_default_model(generated):
    if not (DEFAULT_MODEL_DIR / CONFIG).is_file():
        pytest.skip(f"no shipped default model yet ({DEFAULT_MODEL_DIR / CONFIG} is being trained)")
    implicit, named = load_model(), load_model("default")
    none = load_model(None)
    for model in (implicit, named, none):
        assert isinstance(model, WorldModel) and not model.training
    ref = named.state_dict()
    for model in (implicit, none):
        assert all(torch.equal(ref[k], v) for k, v in model.state_dict().items())
    # The shipped model is the trained one: on one generated scene per road (seed 1, which is
    # inside its training seed range, so this is a sanity check, not the held-out figure of
    # docs/world_model.md) it beats constant velocity at 3 s by a wide margin. The measured
    # ratio is 0.54; an untrained default-preset model is worse than constant velocity.
    from counterscene_env.world_model.evaluate import evaluate_model

    result = evaluate_model(named, list(generated.values()), num_samples=2, seed=0)
    ours, cv = result["model"]["ade"]["3s"], result["constant_velocity"]["ade"]["3s"]
    assert ours < 0.75 * cv, f"shipped model ADE@3s {ours:.2f} m vs constant velocity {cv:.2f} m"


def test_checkpoint_without_the_agent_centric_map_key_loads_as_before(tmp_path):
    """Checkpoints written before ``local_lanes`` existed have no such key: they load with
    the scene-frame map alone and predict as they did."""
    model = _model(TINY.replace(local_lanes=0))
    out = save_model(model, tmp_path / "old", preset="default")
    _edit_config(out, lambda m: [m["architecture"].pop(k) for k in ("local_lanes", "local_radius")])
    loaded = load_model(out)
    assert loaded.config.local_lanes == 0
    batch = _batch(model)
    with torch.no_grad():
        a = model.sample(batch, 1, torch.Generator().manual_seed(0)).trajectory
        b = loaded.sample(batch, 1, torch.Generator().manual_seed(0)).trajectory
    torch.testing.assert_close(a, b, rtol=0, atol=0)


def test_checkpoint_without_lane_anchors_keeps_the_ego_centred_map(tmp_path):
    """Checkpoints written before ``lane_anchors`` existed were trained on the lanes nearest
    the ego: they load with that map, so their windows (and predictions) stay as they were."""
    model = _model(TINY.replace(lane_anchors="ego"))
    out = save_model(model, tmp_path / "old", preset="default")
    _edit_config(out, lambda m: m["architecture"].pop("lane_anchors"))
    loaded = load_model(out)
    assert loaded.config.lane_anchors == "ego"
    assert loaded.window_config().lane_anchors == "ego"
