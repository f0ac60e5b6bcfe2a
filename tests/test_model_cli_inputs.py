"""What ``evaluate-model`` and ``train`` say about the model and the data they are given: the
model evaluated named in the output, ``--model default`` beside a ``./default`` directory,
no interval from one scene, and inputs of the wrong kind refused by name."""

from __future__ import annotations

import json
import math
import pickle

import pytest
import torch
from conftest import crash_scene

from counterscene_env.cli import main
from counterscene_env.scene.shards import save_scenes
from counterscene_env.world_model.checkpoint import DEFAULT_MODEL_DIR, save_model
from counterscene_env.world_model.config import preset
from counterscene_env.world_model.model import WorldModel
from counterscene_env.world_model.records import Normalization
from counterscene_env.world_model.scene_bootstrap import SceneBootstrap, SceneSums

TINY = preset("default").replace(
    d_model=32, num_heads=2, num_blocks=1, num_agents=4, num_lanes=8, sampling_steps=3
)

pytestmark = pytest.mark.usefixtures("one_torch_thread")


def _save_tiny(directory, training=None):
    torch.manual_seed(0)
    model = WorldModel(TINY, Normalization((0.25, -0.01), (1.5, 0.2)))
    return save_model(model, directory, preset="default", training=training)


@pytest.fixture(scope="module")
def tiny_model(tmp_path_factory):
    """A tiny untrained model whose config.json records a fine-tune's provenance."""
    training = {"steps": 9, "step": 7, "init": "default", "data": ["data/merge"]}
    return _save_tiny(tmp_path_factory.mktemp("models") / "tiny", training)


@pytest.fixture(scope="module")
def one_scene(tmp_path_factory):
    """A shard of one scene (crash_scene, "now" at step 10: 29 future frames)."""
    path = tmp_path_factory.mktemp("scenes") / "one.npz"
    return save_scenes([crash_scene().replace(current_index=10)], path)


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    out = tmp_path_factory.mktemp("data") / "merge"
    argv = ["generate", "--scenario", "merge", "--scenes", "1", "--out", str(out), "--quiet"]
    assert main(argv) == 0
    return out


def _evaluate(capsys, data, model, *extra):
    capsys.readouterr()
    argv = ["evaluate-model", "--data", str(data), "--model", str(model), "--quiet"]
    code = main([*argv, "--samples", "1", "--bootstrap", "50", *extra])
    return code, capsys.readouterr()


def test_evaluate_model_names_the_model_it_evaluated(tiny_model, one_scene, capsys):
    code, out = _evaluate(capsys, one_scene, tiny_model, "--json")
    assert code == 0
    assert json.loads(out.out)["checkpoint"] == {
        "given": str(tiny_model),
        "directory": str(tiny_model.resolve()),
        "preset": "default",
        "training_step": 7,
        "init": "default",
        "training_data": ["data/merge"],
    }
    code, out = _evaluate(capsys, one_scene, tiny_model)
    assert code == 0
    first = out.out.splitlines()[0]
    assert first == (
        f"model {tiny_model}: {tiny_model.resolve()} (preset default, 7 training steps, "
        "fine-tuned from the shipped model before it)"
    )


def test_model_default_is_the_shipped_one_and_a_default_directory_is_named_so(
    tiny_model, one_scene, tmp_path, monkeypatch, capsys
):
    """``--model default`` is always the shipped model; a ``./default`` model directory in the
    working directory is said to be passed over, and ``./default`` loads it."""
    _save_tiny(tmp_path / "default")
    monkeypatch.chdir(tmp_path)
    code, out = _evaluate(capsys, one_scene, "default", "--json")
    assert code == 0
    assert json.loads(out.out)["checkpoint"]["directory"] == str(DEFAULT_MODEL_DIR.resolve())
    assert (
        "warning: --model default is the shipped model, not the model directory ./default "
        "here; write --model ./default for that one" in out.err
    )
    code, out = _evaluate(capsys, one_scene, "./default", "--json")
    assert code == 0 and "warning" not in out.err
    assert json.loads(out.out)["checkpoint"]["directory"] == str(tmp_path / "default")


def test_default_without_a_default_directory_says_nothing(one_scene, tmp_path, monkeypatch, capsys):
    (tmp_path / "default").mkdir()  # no model in it: nothing is passed over
    monkeypatch.chdir(tmp_path)
    code, out = _evaluate(capsys, one_scene, "default", "--json")
    assert code == 0 and out.err == ""


def test_one_scene_has_no_interval(tiny_model, one_scene, capsys):
    """Every resample of one scene is that scene: no interval (null), not ``[x, x]``."""
    code, out = _evaluate(capsys, one_scene, tiny_model, "--json")
    assert code == 0
    result = json.loads(out.out)
    assert result["scenes"] == 1 and result["model"]["ade"]["3s"] is not None
    assert set(result["model"]["ci95"]["ade"].values()) == {None}
    assert set(result["constant_velocity"]["ci95"]["fde"].values()) == {None}
    assert set(result["ade_ratio_to_cv_ci95"].values()) == {None}
    assert set(result["sample_overlap_ci95"].values()) == {None}
    code, out = _evaluate(capsys, one_scene, tiny_model)
    assert "ADE / constant velocity's [one scene: no interval]:" in out.out


def test_a_figure_of_one_scene_among_several_has_no_interval():
    """Two scenes, a figure measured in both has an interval; one measured in one has none."""
    sums = SceneSums()
    for scene, value in ((0, 1.0), (1, 3.0)):
        sums.add("all/model/ade/3s", scene, torch.tensor([value]).numpy())
    sums.add("parked/model/ade/3s", 0, torch.tensor([2.0, 4.0]).numpy())
    est = SceneBootstrap(sums, scenes=2, resamples=200, seed=0)
    lo, hi = est.ci("all/model/ade/3s")
    assert lo < hi
    assert est.value("parked/model/ade/3s") == 3.0 and est.ci("parked/model/ade/3s") is None
    assert est.ratio("parked/model/ade/3s", "all/model/ade/3s")[1] is None


def _pickle_file(path):
    path.write_bytes(pickle.dumps({"metadata": {}, "tracks": {}}, protocol=4))
    return path


@pytest.fixture
def no_unpickling(monkeypatch):
    """Any unpickling on the reading paths fails the test."""
    from counterscene_env.scene import safe_pickle, scenarionet

    def refuse(*_args, **_kwargs):
        raise AssertionError("unpickled")

    monkeypatch.setattr(scenarionet, "safe_load", refuse)
    monkeypatch.setattr(safe_pickle, "safe_load", refuse)


@pytest.mark.usefixtures("no_unpickling")
def test_a_pickle_given_as_data_is_named_and_never_unpickled(tiny_model, tmp_path, capsys):
    pkl = _pickle_file(tmp_path / "x.pkl")
    code, out = _evaluate(capsys, pkl, tiny_model)
    assert code == 1
    assert f"{pkl}: a Python pickle, not a CounterScene dataset directory or shard .npz" in out.err
    assert "allow_pickle" not in out.err and "Traceback" not in out.err
    argv = ["train", "--data", str(pkl), "--out", str(tmp_path / "run"), "--steps", "1"]
    assert main([*argv, "--quiet"]) == 1
    err = capsys.readouterr().err
    assert f"{pkl}: a Python pickle, not a CounterScene dataset directory" in err
    assert "allow_pickle" not in err and not (tmp_path / "run").exists()
    # A directory of ScenarioNet logs as --data: not a dataset directory either.
    logs = tmp_path / "logs"
    logs.mkdir()
    _pickle_file(logs / "a.pkl")
    code, out = _evaluate(capsys, logs, tiny_model)
    assert code == 1 and f"{logs}: no manifest.json; not a CounterScene dataset" in out.err


def test_a_file_of_another_kind_given_as_data_is_named(tiny_model, tmp_path, capsys):
    text = tmp_path / "notes.txt"
    text.write_text("hello")
    code, out = _evaluate(capsys, text, tiny_model)
    assert code == 1
    assert f"{text}: not a CounterScene dataset directory or shard .npz" in out.err


def test_scenarionet_refuses_a_counterscene_dataset(dataset, tiny_model, tmp_path, capsys):
    capsys.readouterr()
    argv = ["evaluate-model", "--scenarionet", str(dataset), "--model", str(tiny_model)]
    assert main([*argv, "--quiet", "--samples", "1"]) == 1
    err = capsys.readouterr().err
    assert (
        f"{dataset} is a CounterScene dataset directory (its manifest.json: made by "
        "counterscene generate), not ScenarioNet data" in err
    )
    shard = dataset / "shard-00000.npz"
    argv[2] = str(shard)
    assert main([*argv, "--quiet", "--samples", "1"]) == 1
    assert f"{shard} is a CounterScene shard file" in capsys.readouterr().err
    # Converting it as ScenarioNet logs is refused the same way, and writes nothing.
    out = tmp_path / "converted"
    assert main(["generate", "--from-scenarionet", str(dataset), "--out", str(out)]) == 1
    assert f"{dataset} is a CounterScene dataset directory" in capsys.readouterr().err
    assert not out.exists()


def test_scenarionet_spec_refuses_a_dataset_but_a_bare_path_reads_it(dataset):
    from counterscene_env.config import SCENARIONET_PREFIX
    from counterscene_env.scene.sources import stored_scenes

    with pytest.raises(ValueError, match="is a CounterScene dataset directory"):
        list(stored_scenes(SCENARIONET_PREFIX + str(dataset)))
    assert len(list(stored_scenes(str(dataset)))) == 1


def test_off_road_rates_count_only_points_inside_a_cropped_maps_extent(generated):
    """A real map is a crop: a predicted or logged point beyond its extent is neither on nor
    off its roads, so ``evaluate-model``'s off-road rates leave it out (as the metrics' ORR
    does). A crop that holds none of the scene gives no rate at all, not 0."""
    import dataclasses

    import shapely

    from counterscene_env.world_model.checkpoint import load_model
    from counterscene_env.world_model.evaluate import evaluate_model

    scene = generated["merge"]
    far = dataclasses.replace(scene.road, extent=shapely.box(5e3, 5e3, 5e3 + 10, 5e3 + 10))
    model = load_model("default")
    whole = evaluate_model(model, [scene], num_samples=1, seed=0)
    nowhere = evaluate_model(model, [scene.replace(road=far)], num_samples=1, seed=0)
    assert whole["log_offroad_rate"] is not None and whole["model"]["offroad_rate"] is not None
    assert nowhere["log_offroad_rate"] is None or math.isnan(nowhere["log_offroad_rate"])
    rate = nowhere["model"]["offroad_rate"]
    assert rate is None or math.isnan(rate)


def test_the_text_report_says_when_there_are_no_intervals_and_spells_no_value(
    tiny_model, tmp_path, capsys
):
    """``--bootstrap 0`` asks for no intervals: the header says so (it promised a 95 %
    interval and printed none); an empty speed bin reads n/a, not None."""
    two = tmp_path / "two"
    argv = ["generate", "--scenario", "merge", "--scenes", "2", "--out", str(two), "--quiet"]
    assert main(argv) == 0
    code, out = _evaluate(capsys, two, tiny_model, "--bootstrap", "0")
    assert code == 0
    assert "[no interval: --bootstrap 0]" in out.out and "None" not in out.out
