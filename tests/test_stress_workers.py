"""`counterscene stress --workers N` and Ctrl-C: the serial run's batches in other processes,
with the serial run's results; a stopped run's partial summary, and ``--resume``."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time

import pytest

from counterscene_env.cli import main
from counterscene_env.scene.road import RoadMap
from counterscene_env.scene.shards import save_scenes
from counterscene_env.sim import SimConfig
from counterscene_env.stress import StressConfig, chunks, run_parallel

pytestmark = pytest.mark.usefixtures("one_torch_thread")

#: The short closed loop of these tests: 0.5 s episodes, 2 samples per replan.
SHORT = ["--duration", "0.5", "--samples", "2", "--quiet"]


@pytest.fixture(scope="module")
def shard(generated, tmp_path_factory):
    path = tmp_path_factory.mktemp("workers") / "scenes.npz"
    save_scenes([generated["merge"], generated["intersection"]], path)
    return str(path)


def test_chunks_are_whole_batches_at_fixed_episodes(shard, tmp_path):
    config = StressConfig(shard, episodes=7, batch=3)
    got = [(first, len(scenes)) for first, scenes in chunks(config, [])]
    assert got == [(0, 3), (3, 3), (6, 1)]
    # Resumed after the first batch: the same boundaries from there.
    done = [{"episode": i} for i in range(3)]
    assert [(f, len(s)) for f, s in chunks(config, done)] == [(3, 3), (6, 1)]
    # A kill in the middle of the second batch: that batch runs again whole.
    done = [{"episode": i} for i in range(5)]
    assert [(f, len(s)) for f, s in chunks(config, done)] == [(3, 3), (6, 1)]
    assert list(chunks(config, [{"episode": i} for i in range(7)])) == []
    # The shard's two scenes, cycled: episode i runs scene i % 2 whichever batch it is in.
    ids = [s.scenario_id for _, scenes in chunks(config, []) for s in scenes]
    assert ids == [ids[0], ids[1]] * 3 + [ids[0]] and ids[0] != ids[1]
    # An sb3 policy's batches are the same (each runs in one vector env).
    policy = tmp_path / "p.zip"
    policy.write_bytes(b"")
    sb3 = StressConfig(shard, episodes=3, batch=2, planner=f"sb3:{policy}")
    assert [(f, len(s)) for f, s in chunks(sb3, [])] == [(0, 2), (2, 1)]


@pytest.mark.slow
def test_two_workers_give_the_serial_runs_files(shard, tmp_path, capsys):
    """Same metrics.json byte for byte, same records in the same order; batches of 2 so that
    each worker's world-model calls hold the serial run's pairs of episodes."""
    args = ["stress", "--scenario", shard, "--episodes", "5", "--batch", "2", *SHORT]
    assert main([*args, "--out", str(tmp_path / "serial")]) == 0
    assert main([*args, "--workers", "2", "--out", str(tmp_path / "parallel")]) == 0
    capsys.readouterr()
    serial, parallel = tmp_path / "serial", tmp_path / "parallel"
    assert (serial / "metrics.json").read_bytes() == (parallel / "metrics.json").read_bytes()
    lines = [(d / "episodes.jsonl").read_text().splitlines() for d in (serial, parallel)]
    assert lines[0] == lines[1]  # timings are in episode_timings.jsonl
    assert json.loads((parallel / "timings.json").read_text())["workers"] == 2


@pytest.mark.slow
def test_two_workers_run_real_maps_with_other_egos(generated, tmp_path, capsys):
    """Real maps' spline lanes do not pickle as highway-env builds them: a real log's batch
    still reaches the workers, and with ego choices (``--egos``) gives the serial run."""
    scene = generated["intersection"]
    road = RoadMap.from_centerlines(scene.road.lane_centerlines, scene.road.lane_widths)
    path = tmp_path / "real.npz"
    save_scenes([scene.replace(road=road)], path)
    args = ["stress", "--scenario", str(path), "--episodes", "4", "--batch", "2", *SHORT]
    args += ["--egos", "2"]
    assert main([*args, "--out", str(tmp_path / "serial")]) == 0
    assert main([*args, "--workers", "2", "--out", str(tmp_path / "parallel")]) == 0
    capsys.readouterr()
    lines = [
        (tmp_path / d / "episodes.jsonl").read_text().splitlines() for d in ("serial", "parallel")
    ]
    assert lines[0] == lines[1]
    records = [json.loads(x) for x in lines[0]]
    ids = [r["scenario_id"] for r in records]
    assert ids[0] == ids[2] == scene.scenario_id and ids[1] == ids[3] != ids[0]


class ExplodingPlanner:
    """A planner whose reset fails (module level, so the workers can unpickle it)."""

    name = "exploding"
    replays_log = False

    def reset(self, scene, seed: int) -> None:
        raise RuntimeError("the planner blew up")

    def act(self, state):
        raise AssertionError("never reached")


class VanishingPlanner(ExplodingPlanner):
    """A planner that takes its worker down with it (a crash, an out-of-memory kill)."""

    def reset(self, scene, seed: int) -> None:
        os._exit(3)


@pytest.mark.slow
@pytest.mark.parametrize(
    ("planner", "message"),
    [(ExplodingPlanner, "the planner blew up"), (VanishingPlanner, "exit code 3")],
)
def test_a_failing_worker_stops_the_run_with_its_error(shard, planner, message):
    config = StressConfig(shard, episodes=2, batch=1, sim=SimConfig(duration=0.5, num_samples=2))
    start = time.monotonic()
    with pytest.raises(RuntimeError, match=message):
        run_parallel(config, 1, planner_factory=planner, progress=False)
    assert time.monotonic() - start < 60  # reported, not waited on forever


#: Runs the command with Python's own SIGINT handler, whatever the test runner's is (a
#: background job may have SIGINT ignored, which a child would inherit).
INTERRUPTIBLE = (
    "import signal; signal.signal(signal.SIGINT, signal.default_int_handler); "
    "from counterscene_env.cli import main; raise SystemExit(main())"
)


@pytest.mark.slow
def test_ctrl_c_leaves_a_partial_summary_and_resume_finishes_the_run(shard, tmp_path):
    """Ctrl-C in a two-worker run once its first batch is on disk: exit 130, metrics.json of
    the finished episodes marked incomplete, a message naming --resume. A rerun without
    --resume is refused; with it the run ends with the metrics.json of a run never stopped."""
    args = ["stress", "--scenario", shard, "--episodes", "8", "--batch", "1", *SHORT]
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    run = tmp_path / "stopped"
    log = run / "episodes.jsonl"
    cmd = [sys.executable, "-c", INTERRUPTIBLE, *args, "--out", str(run)]
    proc = subprocess.Popen([*cmd, "--workers", "2"], env=env, stderr=subprocess.PIPE, text=True)
    deadline = time.time() + 120
    while time.time() < deadline and proc.poll() is None:
        if log.is_file() and log.stat().st_size > 0:
            break
        time.sleep(0.05)
    proc.send_signal(signal.SIGINT)
    _, err = proc.communicate(timeout=60)
    assert proc.returncode == 130, err[-2000:]
    assert "--resume" in err and str(run) in err
    kept = log.read_text().splitlines()
    partial = json.loads((run / "metrics.json").read_text())
    assert partial["complete"] is False
    assert partial["episodes"] == len(kept) and 1 <= len(kept) < 8
    assert partial["episodes_requested"] == 8
    assert json.loads((run / "timings.json").read_text())["episodes"] == len(kept)

    # The partial report is there to read, and a refused rerun changes no file.
    assert "unfinished" in (run / "report.md").read_text()
    before = {p.relative_to(run): p.read_bytes() for p in run.rglob("*") if p.is_file()}
    refused = subprocess.run(cmd, env=env, capture_output=True, text=True)
    assert refused.returncode == 1 and "pass --resume" in refused.stderr
    assert {p.relative_to(run): p.read_bytes() for p in run.rglob("*") if p.is_file()} == before

    assert subprocess.run([*cmd, "--resume"], env=env).returncode == 0
    assert main([*args, "--out", str(tmp_path / "whole")]) == 0
    resumed = log.read_text().splitlines()
    assert resumed[: len(kept)] == kept  # nothing redone
    whole = tmp_path / "whole"
    assert (run / "metrics.json").read_bytes() == (whole / "metrics.json").read_bytes()
    assert json.loads((run / "metrics.json").read_text())["complete"] is True


@pytest.mark.slow
@pytest.mark.parametrize(
    "args",
    [
        # Fresh scenes: the next one is recorded by a background process (scene/prefetch.py).
        ["stress", "--scenario", "merge", "--episodes", "6", "--batch", "1", *SHORT],
        ["generate", "--scenario", "merge", "--scenes", "12", "--shard-size", "1", "--workers",
         "2", "--quiet"],
    ],
)  # fmt: skip
def test_a_terminals_ctrl_c_stops_every_process_in_one_line(tmp_path, args):
    """A terminal sends Ctrl-C to the whole process group, helpers included: the command
    says it stopped, in one line and no traceback, and no process of it is left."""
    out = tmp_path / "out"
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    cmd = [sys.executable, "-c", INTERRUPTIBLE, *args, "--out", str(out)]
    proc = subprocess.Popen(cmd, env=env, stderr=subprocess.PIPE, text=True, start_new_session=True)
    deadline = time.time() + 120
    while time.time() < deadline and proc.poll() is None:
        if any(p.suffix in (".jsonl", ".npz") and p.stat().st_size for p in out.glob("*")):
            break
        time.sleep(0.05)
    os.killpg(proc.pid, signal.SIGINT)
    _, err = proc.communicate(timeout=60)
    assert proc.returncode == 130, err[-2000:]
    assert "Traceback" not in err and f"counterscene {args[0]}: stopped" in err
    time.sleep(1)
    left = subprocess.run(["pgrep", "-g", str(proc.pid)], capture_output=True, text=True)
    assert left.stdout.split() == []
