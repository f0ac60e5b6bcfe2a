"""``counterscene train``'s output directory: a stop at any point resumes with each step logged
once, a new run starts its own log and never overwrites a model, and a resume compares its
datasets as files (their paths and their shards)."""

from __future__ import annotations

import json
import shutil

import pytest
from safetensors.torch import load_file

from counterscene_env.cli import main
from counterscene_env.world_model import train as train_module

TINY = ["--set", "d_model=32", "--set", "num_heads=2", "--set", "num_blocks=1"]
#: The exit code of a command stopped by Ctrl-C (``cli.main``).
STOPPED = 130

pytestmark = pytest.mark.usefixtures("one_torch_thread")


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    out = tmp_path_factory.mktemp("data") / "merge"
    argv = ["generate", "--scenario", "merge", "--scenes", "3", "--out", str(out), "--quiet"]
    assert main(argv) == 0
    return out


def _train(data, out, steps, *extra):
    argv = ["train", "--data", str(data), "--out", str(out), "--steps", str(steps)]
    argv += ["--checkpoint-every", "2", "--batch-size", "4", *TINY, "--quiet", *extra]
    return main(argv)


def _records(out):
    """The log's records without their wall times (which differ between runs)."""
    records = [json.loads(line) for line in (out / "log.jsonl").read_text().splitlines()]
    for r in records:
        r.pop("wall_time_s")
    return records


def _files(directory):
    return {p.name: p.read_bytes() for p in directory.iterdir()}


@pytest.fixture(scope="module")
def uninterrupted(dataset, tmp_path_factory):
    """A 4-step run that never stopped (checkpoints at steps 2 and 4)."""
    out = tmp_path_factory.mktemp("runs") / "whole"
    assert _train(dataset, out, 4) == 0
    return out


@pytest.mark.parametrize("stop_at", [2, 4])
def test_a_run_stopped_before_its_state_logs_each_step_once(
    dataset, uninterrupted, tmp_path, monkeypatch, stop_at
):
    """Stopped after writing step ``stop_at``'s record and model, before its ``last.pt``
    (at the first checkpoint, or at the last): rerun, the log holds steps 2 and 4 once each
    and the run ends where the uninterrupted one does."""
    save = train_module.save_state

    def stop(out, state):
        if state["step"] == stop_at:
            raise KeyboardInterrupt  # Ctrl-C between the model and last.pt
        save(out, state)

    out = tmp_path / "run"
    with monkeypatch.context() as m:
        m.setattr(train_module, "save_state", stop)
        assert _train(dataset, out, 4) == STOPPED
    assert [r["step"] for r in _records(out)] == [2, 4][: stop_at // 2]
    assert _train(dataset, out, 4) == 0
    assert [r["step"] for r in _records(out)] == [2, 4]
    assert _records(out) == _records(uninterrupted)
    a = load_file(str(out / "model.safetensors"))
    b = load_file(str(uninterrupted / "model.safetensors"))
    assert all((a[k] == b[k]).all() for k in b)


def test_a_new_run_replaces_the_log_it_finds(dataset, uninterrupted, tmp_path):
    """A run started over (its last.pt and model deleted, its log left) logs only itself."""
    out = tmp_path / "run"
    assert _train(dataset, out, 2) == 0
    for name in ("last.pt", "model.safetensors", "config.json"):
        (out / name).unlink()
    assert _train(dataset, out, 4) == 0
    assert _records(out) == _records(uninterrupted)


def test_a_new_run_refuses_a_directory_that_holds_a_model(dataset, tmp_path, capsys):
    """A model without last.pt is someone's model: a new run into its directory is refused,
    naming the directory and what to do, and leaves every byte there as it was; with last.pt
    back the run resumes."""
    out = tmp_path / "model"
    assert _train(dataset, out, 2) == 0
    state = (out / "last.pt").read_bytes()
    (out / "last.pt").unlink()
    before = _files(out)
    capsys.readouterr()
    for extra in ((), ("--init", str(out), "--lr", "0")):
        assert _train(dataset, out, 4, *extra) == 1
        err = capsys.readouterr().err
        assert f"{out} already holds a model" in err and "Use another --out" in err
        assert ("this run's --init" in err) == bool(extra)
        assert _files(out) == before
    (out / "last.pt").write_bytes(state)
    assert _train(dataset, out, 4) == 0
    assert [r["step"] for r in _records(out)] == [2, 4]


def test_a_resume_compares_dataset_paths_as_files(dataset, tmp_path, monkeypatch):
    """``--data DIR/``, ``--data DIR`` and a relative path to DIR are one dataset."""
    out = tmp_path / "run"
    assert _train(f"{dataset}/", out, 2) == 0
    assert _train(dataset, out, 4) == 0
    monkeypatch.chdir(dataset.parent)
    assert _train(dataset.name, out, 6, "--agent-centred", f"{dataset}/") == 1  # a new setting
    assert _train(dataset.name, out, 6) == 0
    assert [r["step"] for r in _records(out)] == [2, 4, 6]


def test_a_resume_refuses_a_dataset_whose_shards_changed(dataset, tmp_path, capsys):
    """A dataset grown since the run started (its validation scenes would move) is named."""
    data = tmp_path / "merge"
    shutil.copytree(dataset, data)
    out = tmp_path / "run"
    assert _train(data, out, 2) == 0
    argv = ["generate", "--scenario", "merge", "--scenes", "4", "--out", str(data), "--quiet"]
    assert main(argv) == 0
    before = _files(out)
    capsys.readouterr()
    assert _train(data, out, 4) == 1
    err = capsys.readouterr().err
    assert f"the files of --data {data} changed" in err and "Traceback" not in err
    assert _files(out) == before
