"""Bird's-eye frames (rgb_array, headless) and video export."""

from __future__ import annotations

import sys

import gymnasium as gym
import numpy as np
import pytest
from conftest import make_scene

import counterscene_env
from counterscene_env.envs.render import (
    CONFLICT_COLOR,
    CRASHED_COLOR,
    EGO_COLOR,
    PLAN_COLOR,
    save_video,
)

pytestmark = pytest.mark.usefixtures("one_torch_thread")

ZERO = np.zeros(2, np.float32)


def pixels(frame: np.ndarray, color) -> int:
    """How many pixels have exactly this colour."""
    return int((frame == np.asarray(color, np.uint8)).all(-1).sum())


def assert_frame(frame: np.ndarray, height: int, width: int) -> None:
    assert frame.dtype == np.uint8 and frame.shape == (height, width, 3)
    assert height % 16 == 0 and width % 16 == 0
    packed = frame.astype(np.uint32) @ np.array([1 << 16, 1 << 8, 1], np.uint32)
    colours = np.unique(packed)
    assert len(colours) >= 6, f"a blank frame: only {len(colours)} colours"


@pytest.fixture(scope="module")
def frames():
    """Merge seed 1 (adversary veh3) rendered at reset and after each of 3 steps, with and
    without the adversary's plan layer."""
    out = {}
    for show in (True, False):
        env = gym.make(
            "CounterScene-merge-v0",
            config={"duration": 1.0, "show_adversary_plan": show},
            render_mode="rgb_array",
        )
        _, info = env.reset(seed=1)
        assert info["adversary"] is not None, "the scene must have an adversary"
        out[show] = [env.render()]
        for _ in range(3):
            env.step(ZERO)
            out[show].append(env.render())
        env.close()
    return out


def test_rgb_array_frames_are_drawn_headless(frames):
    """uint8 [H, W, 3] frames of the configured size with real content under
    SDL_VIDEODRIVER=dummy (highway-env's viewer alone would draw nothing there)."""
    for frame in frames[True] + frames[False]:
        assert_frame(frame, 640, 640)
        assert pixels(frame, EGO_COLOR) > 50, "the ego is drawn in green"
    assert not np.array_equal(frames[True][0], frames[True][-1]), "frames follow the episode"


def test_adversary_plan_and_conflict_point_are_drawn(frames):
    """With an adversary, the frame shows its planned path (purple polyline) and the conflict
    point (red ring); show_adversary_plan=False leaves both out."""
    on, off = frames[True][-1], frames[False][-1]
    assert pixels(on, CONFLICT_COLOR) > 50 and pixels(off, CONFLICT_COLOR) == 0
    # The adversary's box is purple too: the plan adds many purple pixels on top of it.
    assert pixels(off, PLAN_COLOR) > 50, "the adversary is drawn"
    assert pixels(on, PLAN_COLOR) > pixels(off, PLAN_COLOR) + 200


def test_frame_size_follows_the_config():
    env = gym.make(
        "CounterScene-merge-v0",
        config={"duration": 1.0, "screen_width": 480, "screen_height": 320},
        render_mode="rgb_array",
    )
    env.reset(seed=0)
    assert_frame(env.render(), 320, 480)
    env.close()


def test_a_crashed_ego_is_drawn_red():
    T = 40
    t = np.arange(T) * 0.1
    ego = np.stack([50 + 10 * t, np.zeros(T)], -1)
    parked = np.tile([64.0, 0.0], (T, 1))
    scene = make_scene(np.stack([ego, parked]), speeds=np.array([np.full(T, 10.0), np.zeros(T)]))
    env = gym.make("CounterScene-merge-v0", config={"duration": 2.0}, render_mode="rgb_array")
    env.reset(seed=0, options={"scene": scene})
    assert pixels(env.render(), EGO_COLOR) > 50 and pixels(env.render(), CRASHED_COLOR) == 0
    for _ in range(20):
        _, _, terminated, truncated, _ = env.step(np.array([1.0, 0.0], np.float32))
        if terminated or truncated:
            break
    assert terminated
    frame = env.render()
    assert pixels(frame, CRASHED_COLOR) > 50 and pixels(frame, EGO_COLOR) == 0
    env.close()


def test_render_without_a_render_mode_warns_and_returns_none():
    env = gym.make("CounterScene-merge-v0", config={"duration": 1.0})
    env.reset(seed=0)
    with pytest.warns(UserWarning, match="render_mode"):
        assert env.unwrapped.render() is None
    env.close()


def test_parallel_env_renders_every_ego():
    env = counterscene_env.parallel_env(
        num_egos=2, config={"duration": 1.0, "scenario": "merge"}, render_mode="rgb_array"
    )
    env.reset(seed=0)
    frame = env.render()
    assert_frame(frame, 640, 640)
    assert pixels(frame, EGO_COLOR) > 50
    env.close()


# ---------------------------------------------------------------------- save_video
def video_frames(n: int = 5, height: int = 32, width: int = 48) -> list[np.ndarray]:
    """Distinct frames (a GIF writer may merge identical consecutive ones)."""
    rng = np.random.default_rng(0)
    return [rng.integers(0, 256, (height, width, 3), dtype=np.uint8) for _ in range(n)]


def test_save_video_writes_a_readable_gif(tmp_path):
    iio = pytest.importorskip("imageio.v3")
    path = save_video(video_frames(), tmp_path / "sub" / "a.gif", fps=5)
    assert path == tmp_path / "sub" / "a.gif" and path.is_file()
    back = iio.imread(path, index=None)
    assert back.shape[:3] == (5, 32, 48)


def test_save_video_writes_mp4(tmp_path):
    pytest.importorskip("imageio_ffmpeg")
    iio = pytest.importorskip("imageio.v3")
    path = save_video(video_frames(height=32, width=48), tmp_path / "a.mp4")
    back = iio.imread(path, index=None)
    assert back.shape[:3] == (5, 32, 48)


def test_gymnasium_record_video_records_an_episode_at_the_policy_rate(tmp_path):
    """``RecordVideo`` (its moviepy comes with the ``[video]`` extra): one frame at reset and one
    per policy step, played at ``policy_frequency`` frames per second, so in real time."""
    pytest.importorskip("moviepy")
    iio = pytest.importorskip("imageio.v3")
    from gymnasium.wrappers import RecordVideo

    config = {"duration": 1.0, "policy_frequency": 5}
    env = gym.make("CounterScene-merge-v0", config=config, render_mode="rgb_array")
    env = RecordVideo(env, str(tmp_path / "videos"), episode_trigger=lambda episode: True)
    env.reset(seed=1)
    steps, done = 0, False
    while not done:
        _, _, terminated, truncated, _ = env.step(ZERO)
        steps, done = steps + 1, terminated or truncated
    env.close()
    (video,) = (tmp_path / "videos").glob("*.mp4")
    assert iio.immeta(video)["fps"] == 5
    assert iio.imread(video, index=None).shape[0] == steps + 1 == 6


def test_save_video_refuses_bad_input(tmp_path):
    with pytest.raises(ValueError, match=r"\.mp4 or \.gif"):
        save_video(video_frames(), tmp_path / "a.avi")
    with pytest.raises(ValueError, match="at least one frame"):
        save_video([], tmp_path / "a.gif")
    mixed = [*video_frames(2), np.zeros((16, 16, 3), np.uint8)]
    with pytest.raises(ValueError, match="one size"):
        save_video(mixed, tmp_path / "a.gif")
    with pytest.raises(ValueError, match="one size"):
        save_video([np.zeros((16, 16), np.uint8)], tmp_path / "a.gif")
    for fps in (0, -5):  # a negative one left a corrupt gif behind
        with pytest.raises(ValueError, match="fps"):
            save_video(video_frames(), tmp_path / "sub" / "a.gif", fps=fps)
    with pytest.raises(TypeError, match="fps"):
        save_video(video_frames(), tmp_path / "a.mp4", fps="10")
    assert not list(tmp_path.iterdir()), "nothing is written on bad input"


def test_save_video_without_imageio_says_what_to_install(tmp_path, monkeypatch):
    monkeypatch.setitem(sys.modules, "imageio", None)
    monkeypatch.setitem(sys.modules, "imageio.v3", None)
    with pytest.raises(ImportError, match=r"imageio.*pip install"):
        save_video(video_frames(), tmp_path / "a.gif")


def test_save_video_mp4_without_imageio_ffmpeg_says_what_to_install(tmp_path, monkeypatch):
    pytest.importorskip("imageio.v3")
    monkeypatch.setitem(sys.modules, "imageio_ffmpeg", None)
    with pytest.raises(ImportError, match=r"imageio-ffmpeg.*pip install"):
        save_video(video_frames(), tmp_path / "a.mp4")


def test_real_map_lanes_render():
    """Lanes built from centre lines (real logs) have line types, so highway-env's renderer
    draws them, also when read back from a road written before they had any."""
    from highway_env.road.lane import LineType

    from counterscene_env.scene.road import RoadMap
    from counterscene_env.scene.road_json import network_from_json, network_to_json

    curve = np.stack([np.linspace(0, 120, 40), 10 * np.sin(np.linspace(0, 2, 40))], -1)
    road = RoadMap.from_centerlines([curve, curve + np.array([0.0, 3.5])], [3.5, 3.5])
    lanes = road.network.lanes_list()
    assert all(lane.line_types == (LineType.STRIPED, LineType.STRIPED) for lane in lanes)
    text = network_to_json(road.network)
    assert '"line_types": [1, 1]' in text
    old = text.replace('"line_types": [1, 1]', '"line_types": null')
    assert all(lane.line_types is not None for lane in network_from_json(old).lanes_list())

    T = 40
    xy = np.stack([np.tile(curve[5], (T, 1)), np.tile(curve[20], (T, 1))])  # two parked cars
    scene = make_scene(xy, road=road, scenario_id="curved")
    env = gym.make("CounterScene-v0", config={"duration": 1.0}, render_mode="rgb_array")
    env.reset(seed=0, options={"scene": scene})
    frame = env.render()
    assert_frame(frame, 640, 640)
    assert pixels(frame, (255, 255, 255)) > 100  # the lane lines
    env.close()
