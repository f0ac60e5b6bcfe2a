"""Dataset directories: the first N safe seeds, resumable, the same with any worker count."""

from __future__ import annotations

import json

import numpy as np
import pytest

from counterscene_env.scene import load_scenes
from counterscene_env.scene.datagen import generate_dataset
from counterscene_env.scene.manifest import read_manifest, shard_paths
from counterscene_env.scene.shards import ShardError


def _seeds(directory):
    return [s for shard in read_manifest(directory)["shards"] for s in shard["seeds"]]


@pytest.mark.slow
def test_first_n_safe_seeds_skipping_rejected(tmp_path):
    m = generate_dataset(
        tmp_path / "d", "intersection", scenes=4, seed=0, shard_size=2, progress=False
    )
    # Intersection seed 0 is an unsafe log (see test_highway): it is listed, and replaced.
    assert m["scenes"] == 4 and _seeds(tmp_path / "d") == [1, 2, 3, 5]
    assert [r[0] for s in m["shards"] for r in s["rejected"]] == [0, 4]
    scenes = [sc for p in shard_paths(tmp_path / "d") for sc in load_scenes(p)]
    assert [sc.metadata["seed"] for sc in scenes] == [1, 2, 3, 5]
    assert m["format"] == "counterscene-dataset" and m["scenario"] == "intersection"


@pytest.mark.slow
def test_resume_skips_finished_shards_and_workers_do_not_change_the_data(tmp_path):
    out = tmp_path / "d"
    generate_dataset(out, "merge", scenes=3, seed=10, shard_size=1, progress=False)
    first = (out / "shard-00000.npz").stat().st_mtime_ns
    # Simulate an interruption: the last shard is lost and the manifest forgets it.
    (out / "shard-00002.npz").unlink()
    manifest = json.loads((out / "manifest.json").read_text())
    manifest["shards"] = manifest["shards"][:2]
    (out / "manifest.json").write_text(json.dumps(manifest))
    generate_dataset(out, "merge", scenes=3, seed=10, shard_size=1, progress=False)
    assert (out / "shard-00000.npz").stat().st_mtime_ns == first, "finished shards are not redone"
    assert _seeds(out) == [10, 11, 12]

    parallel = tmp_path / "p"
    generate_dataset(parallel, "merge", scenes=3, seed=10, shard_size=1, workers=2, progress=False)
    assert _seeds(parallel) == [10, 11, 12]
    a = [s for p in shard_paths(out) for s in load_scenes(p)]
    b = [s for p in shard_paths(parallel) for s in load_scenes(p)]
    for x, y in zip(a, b, strict=True):
        np.testing.assert_array_equal(x.positions, y.positions)


def test_a_directory_of_another_dataset_is_not_overwritten(tmp_path):
    out = tmp_path / "d"
    generate_dataset(out, "merge", scenes=1, seed=0, shard_size=1, progress=False)
    with pytest.raises(ValueError, match="different dataset"):
        generate_dataset(out, "roundabout", scenes=1, seed=0, shard_size=1, progress=False)


def test_manifest_errors(tmp_path):
    with pytest.raises(ShardError, match=r"no manifest\.json"):
        read_manifest(tmp_path)
    (tmp_path / "manifest.json").write_text('{"format": "counterscene-dataset", "version": 99}')
    with pytest.raises(ShardError, match="newer"):
        read_manifest(tmp_path)
    (tmp_path / "manifest.json").write_text("{not json")
    with pytest.raises(ShardError, match="corrupt manifest"):
        read_manifest(tmp_path)


def test_a_larger_rerun_extends_the_dataset_like_a_fresh_run(tmp_path):
    small = tmp_path / "small"
    generate_dataset(small, "merge", scenes=2, seed=0, shard_size=5, progress=False)
    assert _seeds(small) == [0, 1], "a block stops once it has the scenes asked for"
    generate_dataset(small, "merge", scenes=3, seed=0, shard_size=5, progress=False)
    fresh = tmp_path / "fresh"
    generate_dataset(fresh, "merge", scenes=3, seed=0, shard_size=5, progress=False)
    assert _seeds(small) == _seeds(fresh) == [0, 1, 2]


def test_asking_for_fewer_scenes_never_deletes_any(tmp_path):
    out = tmp_path / "d"
    generate_dataset(out, "merge", scenes=2, seed=0, shard_size=1, progress=False)
    with pytest.raises(ValueError, match="already holds a dataset of 2 scenes"):
        generate_dataset(out, "merge", scenes=1, seed=0, shard_size=1, progress=False)
    assert _seeds(out) == [0, 1]


def test_rerunning_a_finished_command_redoes_nothing(tmp_path):
    out = tmp_path / "d"
    generate_dataset(out, "merge", scenes=2, seed=0, shard_size=5, progress=False)
    before = {p.name: p.stat().st_mtime_ns for p in out.glob("*.npz")}
    generate_dataset(out, "merge", scenes=2, seed=0, shard_size=5, progress=False)
    assert {p.name: p.stat().st_mtime_ns for p in out.glob("*.npz")} == before
    manifest = read_manifest(out)
    assert manifest["shards"][0]["num_steps"] == [131, 131]


def _write_scenarionet(path, sd):
    import pickle

    with open(path, "wb") as f:
        pickle.dump(sd, f, protocol=4)


def test_conversion_lists_bad_files_and_refuses_a_changed_folder(tmp_path):
    from test_scenarionet import _scenario

    from counterscene_env.scene.datagen import convert_scenarionet

    src = tmp_path / "src"
    src.mkdir()
    _write_scenarionet(src / "b.pkl", _scenario())
    (src / "c.pkl").write_bytes(b"garbage")
    m = convert_scenarionet(src, tmp_path / "out", shard_size=1, progress=False)
    assert m["scenes"] == 1 and [r[0] for s in m["shards"] for r in s["rejected"]] == ["c.pkl"]
    _write_scenarionet(src / "a.pkl", _scenario())
    with pytest.raises(ValueError, match="different dataset"):
        convert_scenarionet(src, tmp_path / "out", shard_size=1, progress=False)


def test_the_command_names_refused_logs_and_fails_when_none_converts(tmp_path, capsys):
    from test_scenarionet import _scenario

    from counterscene_env.cli import main

    src = tmp_path / "src"
    src.mkdir()
    _write_scenarionet(src / "b.pkl", _scenario())
    (src / "c.pkl").write_bytes(b"garbage")
    argv = ["generate", "--from-scenarionet", str(src), "--quiet", "--shard-size", "1"]
    assert main([*argv, "--out", str(tmp_path / "out")]) == 0
    assert "refused c.pkl: " in capsys.readouterr().err
    (src / "b.pkl").unlink()
    assert main([*argv, "--out", str(tmp_path / "none")]) == 1
    assert "no log converted: every file was refused" in capsys.readouterr().err


def test_a_gap_acceptance_dataset_says_so_and_is_not_mixed_with_a_stock_one(tmp_path):
    out = tmp_path / "d"
    m = generate_dataset(
        out,
        "intersection",
        scenes=1,
        seed=1,
        shard_size=1,
        yielding="gap-acceptance",
        progress=False,
    )
    assert m["yielding"] == "gap-acceptance"
    scene = next(iter(load_scenes(shard_paths(out)[0])))
    assert scene.metadata["yielding"] == "gap-acceptance"
    with pytest.raises(ValueError, match="different dataset"):
        generate_dataset(out, "intersection", scenes=1, seed=1, shard_size=1, progress=False)
    with pytest.raises(ValueError, match="intersection only"):
        generate_dataset(tmp_path / "m", "merge", scenes=1, yielding="gap-acceptance")
    assert not (tmp_path / "m").exists(), "a refused call writes nothing"


def test_a_dataset_made_before_the_yielding_option_still_resumes(tmp_path):
    out = tmp_path / "d"
    generate_dataset(out, "merge", scenes=1, seed=0, shard_size=1, progress=False)
    manifest = json.loads((out / "manifest.json").read_text())
    del manifest["yielding"]  # as written before 27 Nov 2026
    (out / "manifest.json").write_text(json.dumps(manifest))
    assert (
        generate_dataset(out, "merge", scenes=2, seed=0, shard_size=1, progress=False)["scenes"]
        == 2
    )
