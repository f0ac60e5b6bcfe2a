"""Recording the next episode's scene in a background process (scene/prefetch.py): the env
gives the same episodes with it as without, and takes the recording only when it is the scene
its draw asks for."""

from __future__ import annotations

import multiprocessing
import sys
import time

import numpy as np
import pytest

from counterscene_env.envs.single_agent import CounterSceneEnv
from counterscene_env.scene import prefetch
from counterscene_env.scene.sources import SceneSource

pytestmark = pytest.mark.slow  # starts the worker process (a second or two)


def _run(env: CounterSceneEnv, resets: list[int | None], steps: int = 8) -> list[np.ndarray]:
    """Observations of consecutive episodes (``None``: reset without a seed)."""
    out = []
    for seed in resets:
        while seed is None and env.unwrapped.recording_ahead:  # taken only once recorded
            time.sleep(0.01)
        obs, _ = env.reset(seed=seed)
        out.append(obs)
        for _ in range(steps):
            obs, _, terminated, truncated, _ = env.step(np.array([0.2, 0.0], np.float32))
            out.append(obs)
            if terminated or truncated:
                break
        out.append(env.scene.positions)
    return out


def test_episodes_with_scenes_recorded_ahead_are_the_episodes_without():
    ahead = CounterSceneEnv(config={"prefetch_scenes": True})
    inline = CounterSceneEnv(config={"prefetch_scenes": False})
    resets = [3, None, None, 7, None]  # a re-seeded reset cannot use the scene recorded ahead
    a, b = _run(ahead, resets), _run(inline, resets)
    assert len(a) == len(b)
    for x, y in zip(a, b, strict=True):
        np.testing.assert_array_equal(x, y)
    # Unseeded resets took the recording ahead; the re-seeded one and the first did not.
    assert ahead.unwrapped._source.served_ahead == 3
    assert inline.unwrapped._source.served_ahead == 0


def test_a_recording_ahead_is_taken_only_for_the_draw_it_was_made_for():
    source = SceneSource("merge")
    rng = np.random.default_rng(0)
    source.prefetch(rng)
    other = np.random.default_rng(1)  # a different draw: recorded here, the one ahead dropped
    expected = SceneSource("merge").draw(np.random.default_rng(1))
    np.testing.assert_array_equal(source.draw(other).positions, expected.positions)
    assert source.served_ahead == 0
    source.prefetch(rng)
    same = SceneSource("merge").draw(np.random.default_rng(0))
    while source.recording_ahead:  # taken once begun; waiting makes the test timing-free
        time.sleep(0.01)
    np.testing.assert_array_equal(source.draw(rng).positions, same.positions)
    assert source.served_ahead == 1


def _daemon_check(queue) -> None:
    source = SceneSource("merge")
    source.prefetch(np.random.default_rng(0))
    queue.put((prefetch.available(), source.recording_ahead))


def test_a_daemonic_process_records_nothing_ahead():
    # SB3's SubprocVecEnv and Gymnasium's AsyncVectorEnv run envs in daemonic processes,
    # which may not have children (and whose cores are taken).
    context = multiprocessing.get_context("spawn")
    queue = context.Queue()
    worker = context.Process(target=_daemon_check, args=(queue,), daemon=True)
    worker.start()
    assert queue.get(timeout=120) == (False, False)
    worker.join()


def test_a_stress_runs_scenes_recorded_ahead_are_its_scenes_in_order():
    # Intersection seed 0 is rejected (two cars crash): the seeds scanned and skipped are the same.
    from counterscene_env.scene.sources import scenes_for

    inline = list(scenes_for("intersection", 3, 0))
    ahead = list(scenes_for("intersection", 3, 0, ahead=4))
    assert [s.metadata["seed"] for s in ahead] == [s.metadata["seed"] for s in inline]
    assert [s.metadata["rejected_seeds"] for s in ahead] == [[0], [], []]
    for a, b in zip(ahead, inline, strict=True):
        np.testing.assert_array_equal(a.positions, b.positions)
        assert a.metadata["rejected_seeds"] == b.metadata["rejected_seeds"]


def test_a_recorder_process_that_died_costs_nothing_but_time():
    """Killed mid-way, the background process's scene is recorded here instead, the same; the
    next recording ahead starts a new process."""
    source = SceneSource("merge")
    rng = np.random.default_rng(5)
    expected = SceneSource("merge").draw(np.random.default_rng(5))
    source.prefetch(rng)
    prefetch._RECORDER.child.kill()
    prefetch._RECORDER.child.wait()
    np.testing.assert_array_equal(source.draw(rng).positions, expected.positions)
    assert source.served_ahead == 0
    after = SceneSource("merge").draw(np.random.default_rng(6))
    rng = np.random.default_rng(6)
    source.prefetch(rng)
    while source.recording_ahead:  # the new process starts, then records
        time.sleep(0.01)
    np.testing.assert_array_equal(source.draw(rng).positions, after.positions)
    assert source.served_ahead == 1


def test_where_the_recorder_process_cannot_start_every_scene_is_recorded_here(monkeypatch):
    monkeypatch.setattr(prefetch, "_RECORDER", None)
    monkeypatch.setattr(prefetch, "_UNAVAILABLE", [])
    monkeypatch.setattr(sys, "executable", "/bin/false")  # starts, and exits with 1 at once
    source = SceneSource("merge")
    expected = SceneSource("merge").draw(np.random.default_rng(2))
    rng = np.random.default_rng(2)
    with pytest.warns(RuntimeWarning, match="cannot be recorded in the background"):
        for _ in range(3):  # the first process fails; no second one is started
            source.prefetch(np.random.default_rng(2))
            while source.recording_ahead:
                time.sleep(0.01)
            np.testing.assert_array_equal(source.draw(rng).positions, expected.positions)
            rng = np.random.default_rng(2)
    assert not prefetch.available() and source.served_ahead == 0


def test_the_next_two_draws_are_recorded_ahead_when_the_draws_between_are_known():
    from counterscene_env.envs.single_agent import draw_episode_seed

    def draws(source: SceneSource, rng: np.random.Generator) -> list[np.ndarray]:
        first = source.draw(rng).positions
        draw_episode_seed(rng)  # what an env draws between two scenes
        return [first, source.draw(rng).positions]

    expected = draws(SceneSource("merge"), np.random.default_rng(8))
    source, rng = SceneSource("merge"), np.random.default_rng(8)
    source.prefetch(rng, between=draw_episode_seed)
    while source.recording_ahead:
        time.sleep(0.01)
    for got, want in zip(draws(source, rng), expected, strict=True):
        np.testing.assert_array_equal(got, want)
    assert source.served_ahead == 2


def test_a_recording_ahead_not_yet_begun_is_recorded_here_on_demand():
    """A reset that would wait for the process records the scene after its own meanwhile:
    the same scene, the same seeds skipped (intersection seed 0 is rejected: two cars crash)."""
    from counterscene_env.scene.highway import generate

    recorder = prefetch._recorder()
    blocker = recorder.submit("intersection", 3)  # the process is busy with this one first
    ahead = prefetch.Prefetch("intersection", 0)
    ahead.record_here()
    assert not recorder.started(ahead.ticket) and not ahead.running
    expected = generate("intersection", 0)
    np.testing.assert_array_equal(ahead.take("intersection", 0).positions, expected.positions)
    assert ahead.scene.metadata["rejected_seeds"] == expected.metadata["rejected_seeds"] == [0]
    recorder.withdraw(blocker)
