"""A Gymnasium loop on CounterScene-v0: a hand-written ego against the guided adversary.

The ego keeps a cruising speed and brakes when the observation shows a vehicle close ahead;
the world model drives everyone else, and the causally selected adversary is steered into
the ego's path. Prints each collision or hard brake, the adversary, and the episode metrics;
``--gif PATH`` saves the frames (ego green, adversary purple, its plan, the conflict point red).

python examples/gym_loop.py --episodes 2 --gif runs/gym_loop.gif
"""

from __future__ import annotations

import argparse

import gymnasium as gym
import numpy as np

import counterscene_env  # noqa: F401  (registers CounterScene-v0)
from counterscene_env.envs.render import save_video


def cautious(obs: np.ndarray) -> np.ndarray:
    """Kinematics rows (presence, x, y, vx, vy, cos_h, sin_h), others relative to the ego and
    scaled by 100 m: brake if one is within 12 m ahead in a 4 m corridor, else cruise."""
    ego, others = obs[0], obs[1:]
    heading = ego[5:7]
    rel = others[:, 1:3] * 100.0
    ahead = rel @ heading
    side = np.abs(rel @ np.array([-heading[1], heading[0]]))
    blocked = ((others[:, 0] > 0) & (ahead > 0) & (ahead < 12) & (side < 2)).any()
    speed = np.hypot(*ego[3:5]) * 20.0
    acceleration = -1.0 if blocked else float(np.clip((8.0 - speed) / 5.0, -1, 1))
    return np.array([acceleration, 0.0], dtype=np.float32)  # normalised [-1, 1]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--scenario", default="intersection")
    parser.add_argument("--episodes", type=int, default=2)
    parser.add_argument("--seed", type=int, default=2)
    parser.add_argument("--gif", help="save the first episode's frames here (.gif or .mp4)")
    args = parser.parse_args()

    env = gym.make(
        "CounterScene-v0",
        config={"scenario": args.scenario},
        render_mode="rgb_array" if args.gif else None,
    )
    frames = []
    for episode in range(args.episodes):
        obs, info = env.reset(seed=args.seed + episode)
        print(f"episode {episode}: {info['scenario_id']}, adversary {info['adversary']} "
              f"({info['conflict_type'] or info['fallback']})")  # fmt: skip
        done, episode_return = False, 0.0
        while not done:
            obs, reward, terminated, truncated, info = env.step(cautious(obs))
            done = terminated or truncated
            episode_return += reward
            if args.gif and episode == 0:
                frames.append(env.render())
            if info["collision"] or info["hard_braking"]:
                print(f"  t={info['time']:4.1f} s collision={info['collision']} "
                      f"with={info['collided_with']} hard_braking={info['hard_braking']} "
                      f"acc={info['ego_acceleration']:+.1f} m/s^2")  # fmt: skip
        m = info["metrics"]
        print(f"  end: {'terminated' if terminated else 'truncated'} at {info['time']:.1f} s; "
              f"CR {m['cr']:.0f}, ego-adversary CR {m['cr_ego_adversary']:.0f}, "
              f"HBR {m['hbr_ego']:.0f}, min clearance to the adversary "
              f"{m['min_clearance_adversary']:.1f} m, return {episode_return:.1f}")  # fmt: skip
    env.close()
    if frames:
        print("wrote", save_video(frames, args.gif))


if __name__ == "__main__":
    main()
