"""A checkpoint's config.json is checked value by value on loading: a refusal names the file
and the key."""

from __future__ import annotations

import json

import pytest
import torch

from counterscene_env.world_model.checkpoint import CONFIG, CheckpointError, load_model, save_model
from counterscene_env.world_model.config import check_preset_name, preset
from counterscene_env.world_model.model import WorldModel
from counterscene_env.world_model.records import Normalization

TINY = preset("default").replace(
    d_model=32, num_heads=2, num_blocks=1, num_agents=4, num_lanes=8, sampling_steps=3
)

pytestmark = pytest.mark.usefixtures("one_torch_thread")


@pytest.fixture
def saved(tmp_path):
    """A saved tiny model (untrained); tests change one value of its config.json."""
    torch.manual_seed(0)
    model = WorldModel(TINY, Normalization((0.25, -0.01), (1.5, 0.2)))
    return save_model(model, tmp_path / "m", preset="default")


def _edit(directory, edit) -> None:
    path = directory / CONFIG
    meta = json.loads(path.read_text())
    edit(meta)
    path.write_text(json.dumps(meta))


@pytest.mark.parametrize(
    ("key", "value", "rule"),
    [
        ("dt", 0.2, "dt must be 0.1 s"),  # the scenes' step: every count is of 10 Hz frames
        ("dt", 0.0, "dt must be 0.1 s"),
        ("lane_steering", -5, "lane_steering must be >= 0"),
        ("map_guidance", -0.3, "map_guidance must be >= 0"),
        ("clip_sample", -1.0, "clip_sample must be >= 0"),
    ],
)
def test_an_architecture_value_out_of_range_is_refused_naming_file_and_key(saved, key, value, rule):
    load_model(saved)  # as saved, it loads
    _edit(saved, lambda meta: meta["architecture"].update({key: value}))
    with pytest.raises(CheckpointError) as refused:
        load_model(saved)
    message = str(refused.value)
    assert str(saved / CONFIG) in message and rule in message and repr(value) in message


def test_the_presets_and_the_shipped_model_keep_the_scenes_step():
    assert preset("default").dt == preset("paper").dt == 0.1
    assert load_model("default").config.dt == 0.1


def test_a_preset_name_is_one_of_the_presets_or_none():
    assert check_preset_name("preset", "paper") == "paper"
    assert check_preset_name("preset", None) is None
    for bad in ("bogus", 3, ""):
        with pytest.raises(ValueError, match=r"preset must be one of \['default', 'paper'\]"):
            check_preset_name("preset", bad)


def test_an_unknown_preset_is_refused_naming_file_and_key(saved):
    _edit(saved, lambda meta: meta.update(preset="bogus"))
    with pytest.raises(CheckpointError, match="preset must be one of") as refused:
        load_model(saved)
    assert str(saved / CONFIG) in str(refused.value)
