"""The counterscene command: help for every subcommand, generate then inspect."""

from __future__ import annotations

import json
import subprocess
import sys

import pytest

from counterscene_env.cli import main


def _run(*args):
    return subprocess.run(
        [sys.executable, "-m", "counterscene_env.cli", *args],
        capture_output=True,
        text=True,
        timeout=120,
    )


@pytest.mark.parametrize("sub", [[], ["generate"], ["inspect"]])
def test_help_for_every_subcommand(sub):
    out = _run(*sub, "--help")
    assert out.returncode == 0 and "usage: counterscene" in out.stdout


def test_generate_then_inspect_json(tmp_path, capsys):
    out = tmp_path / "d"
    assert (
        main(
            [
                "generate",
                "--scenario",
                "roundabout",
                "--scenes",
                "2",
                "--seed",
                "3",
                "--out",
                str(out),
                "--quiet",
            ]
        )
        == 0
    )
    assert "2 scenes" in capsys.readouterr().out
    assert main(["inspect", str(out), "--json"]) == 0
    report = json.loads(capsys.readouterr().out)
    assert report["summary"]["scenes"] == 2
    assert report["summary"]["cr"]["max"] == 0.0
    assert {r["scenario_id"] for r in report["scenes"]} == {
        "roundabout/seed=3",
        "roundabout/seed=4",
    }


def test_errors_are_one_clear_line(tmp_path):
    out = _run("inspect", str(tmp_path / "nothing"))
    assert out.returncode == 1
    assert "error:" in out.stderr and "Traceback" not in out.stderr
    bad = tmp_path / "bad.pkl"
    bad.write_bytes(b"not a pickle at all")
    out = _run("inspect", str(bad))
    assert out.returncode == 1 and bad.name in out.stderr and "Traceback" not in out.stderr
    xml = tmp_path / "scenario.xml"  # CommonRoad: read by converting, said so
    xml.write_text("<commonRoad/>")
    out = _run("inspect", str(xml))
    assert out.returncode == 1 and "--from-commonroad" in out.stderr


@pytest.mark.parametrize(
    ("args", "words"),
    [
        (["stress", "--scenario", "merge", "--seed", "-5"], ["--seed", ">= 0", "-5"]),
        (["generate", "--scenario", "merge", "--seed", "-1", "--out", "X"], ["--seed", ">= 0"]),
        (["stress", "--scenario", "merge", "--seed", str(2**32)], ["--seed", "<= 4294967295"]),
        (["train", "--data", "X", "--out", "Y", "--seed", str(2**32)], ["--seed", "<="]),
        (["bench-env", "--steps", "0"], ["--steps", ">= 1"]),
        (["bench-env", "--threads", "0"], ["--threads", ">= 1"]),
        (["bench", "--samples", "0"], ["--samples", ">= 1"]),
        (["stress", "--scenario", "merge", "--videos", "2"], ["--videos needs --out"]),
        (["train", "--data", "X", "--out", "Y", "--steps", "0"], ["steps must be >= 1"]),
        (["train", "--data", "X", "--out", "Y", "--lr", "-1"], ["lr must be >= 0"]),
        (["train", "--data", "X", "--out", "Y", "--device", "banana"], ["--device", "'banana'"]),
        (["generate", "--scenario", "merge", "--out", "Y", "--duration", "inf"], ["duration"]),
        (["generate", "--scenario", "merge", "--out", "Y", "--duration", "2"], [">= 13.0"]),
        (["generate", "--from-scenarionet", "X", "--out", "Y", "--scenes", "2"], ["--scenes"]),
        (["generate", "--scenario", "merge", "--out", "Y", "--all-egos"], ["--all-egos"]),
        (["inspect", "X", "--smooth", "nan"], ["--smooth", "nan"]),
        (["evaluate-model", "--data", "X", "--seed", "5"], ["--seed", "--scenario"]),
        (["bench", "--preset", "default", "--model", "X"], ["--preset", "--model"]),
        (["bench", "--model-only", "--episodes", "2"], ["--episodes", "--model-only"]),
    ],
)
def test_bad_flags_are_refused_in_one_line_before_any_work(tmp_path, args, words):
    """Each refusal names its flag and comes before anything runs or is written."""
    args = [str(tmp_path / a) if a in ("X", "Y") else a for a in args]
    (tmp_path / "X").mkdir()
    out = _run(*args)
    assert out.returncode != 0 and "Traceback" not in out.stderr, out.stderr
    assert out.stderr.strip().count("\n") == 0 or "usage:" in out.stderr
    for word in words:
        assert word in out.stderr, (word, out.stderr)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["X"]  # nothing written


def test_a_directory_being_written_refuses_a_second_command(tmp_path, capsys):
    """Two commands writing one --out would interleave their records: the second is refused
    at once and writes nothing; the directory is free again when the first ends."""
    from counterscene_env.cli.lock import out_lock

    out = tmp_path / "run"
    argv = ["generate", "--scenario", "merge", "--scenes", "1", "--quiet", "--out", str(out)]
    with out_lock(out, "generate"):
        assert main(argv) == 1
        assert f"{out} is being written by counterscene generate (pid " in capsys.readouterr().err
        assert not out.exists()
        with out_lock(tmp_path / "other", "stress"):  # another directory is another lock
            pass
    with out_lock(out, "generate"):  # released
        pass


def test_os_errors_and_a_closed_pipe_end_in_one_line_or_quietly(tmp_path):
    """An output path that cannot be made is one line, not a traceback; a reader that goes
    away (``| head``) ends the command quietly with the shell's SIGPIPE status."""
    blocker = tmp_path / "file"
    blocker.write_text("")
    out = _run("generate", "--scenario", "merge", "--scenes", "1", "--out", str(blocker / "sub"))
    assert out.returncode == 1 and "Traceback" not in out.stderr, out.stderr
    assert "Not a directory" in out.stderr
    shards = tmp_path / "scenes"
    assert (
        _run(
            "generate", "--scenario", "merge", "--scenes", "1", "--quiet", "--out", str(shards)
        ).returncode
        == 0
    )
    proc = subprocess.Popen(
        [sys.executable, "-m", "counterscene_env.cli", "inspect", str(shards)],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
    )
    proc.stdout.close()
    assert proc.wait(timeout=120) == 141
    assert proc.stderr.read() == b""


def test_ctrl_c_stops_a_resumable_command_in_one_line(monkeypatch, capsys):
    """Ctrl-C in generate, train or paper-tables: no traceback, the shell's exit code, and how
    to go on (what finished is on disk: rerunning the command resumes)."""
    from counterscene_env.scene import datagen

    def interrupted(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(datagen, "generate_dataset", interrupted)
    code = main(["generate", "--scenario", "merge", "--scenes", "1", "--out", "never"])
    assert code == 130
    assert capsys.readouterr().err.strip() == (
        "counterscene generate: stopped. The finished shards are kept: rerun the same command "
        "to go on"
    )


def test_the_command_line_loads_no_heavy_module_before_a_command_runs():
    """``counterscene --help`` stays instant: torch, shapely and the scene and report modules
    load when a command needs them, not when the parser is built."""
    code = (
        "import sys, counterscene_env.cli as c; c._parser(); "
        "print(sorted(m for m in ('torch', 'shapely', 'counterscene_env.scene.core', "
        "'counterscene_env.report.document') if m in sys.modules))"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "[]"
