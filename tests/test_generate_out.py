"""``counterscene generate --out DIR``: a directory that is not a dataset is refused and left
as it was; a dataset, an empty directory or a build stopped before its manifest go on."""

from __future__ import annotations

import shutil

from counterscene_env.cli import main
from counterscene_env.world_model.checkpoint import DEFAULT_MODEL_DIR


def _generate(out, scenes: int = 1) -> int:
    argv = ["generate", "--scenario", "merge", "--scenes", str(scenes), "--out", str(out)]
    return main([*argv, "--quiet"])


def _contents(directory) -> dict[str, bytes]:
    return {p.name: p.read_bytes() for p in sorted(directory.iterdir())}


def test_a_model_run_directory_is_refused_and_left_alone(tmp_path, capsys):
    run = tmp_path / "run"
    shutil.copytree(DEFAULT_MODEL_DIR, run)
    (run / "last.pt").write_bytes(b"state")
    before = _contents(run)
    assert _generate(run) == 1
    err = capsys.readouterr().err
    assert (
        f"--out {run} is not a dataset directory (no manifest.json) and is not empty: it holds "
        "a trained world model (model.safetensors, config.json, last.pt). Nothing was written"
        in err
    )
    assert _contents(run) == before


def test_a_directory_of_other_files_is_refused_naming_them(tmp_path, capsys):
    out = tmp_path / "mine"
    out.mkdir()
    for name in ("a.txt", "b.csv", "c", "d", "e"):
        (out / name).write_text(name)
    before = _contents(out)
    assert _generate(out) == 1
    assert "it holds a.txt, b.csv, c, d and 1 more" in capsys.readouterr().err
    assert _contents(out) == before


def test_an_empty_directory_a_dataset_and_a_build_stopped_early_go_on(tmp_path):
    empty = tmp_path / "empty"
    empty.mkdir()
    assert _generate(empty) == 0 and (empty / "manifest.json").is_file()
    assert _generate(empty, scenes=2) == 0  # a dataset resumes (here: grows)
    # A first build stopped after its first shard, before the manifest naming it.
    stopped = tmp_path / "stopped"
    assert _generate(stopped) == 0
    (stopped / "manifest.json").unlink()
    (stopped / ".shard-00001.npz.123.tmp").write_bytes(b"half")
    assert _generate(stopped) == 0 and (stopped / "manifest.json").is_file()
