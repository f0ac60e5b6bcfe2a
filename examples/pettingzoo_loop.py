"""A PettingZoo parallel loop: two egos, each with its own causally selected adversary.

``ego_0`` is the scene's ego, ``ego_1`` the vehicle nearest to it; each is driven here by a
constant-speed policy, and each has its own adversary among the world-model agents. An ego that
collides is terminated and leaves ``env.agents``; the others drive on.

python examples/pettingzoo_loop.py --egos 2 --seed 2
"""

from __future__ import annotations

import argparse

import numpy as np

import counterscene_env


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--scenario", default="intersection")
    parser.add_argument("--egos", type=int, default=2)
    parser.add_argument("--seed", type=int, default=2)
    args = parser.parse_args()

    env = counterscene_env.parallel_env(num_egos=args.egos, config={"scenario": args.scenario})
    _, infos = env.reset(seed=args.seed)
    returns = dict.fromkeys(env.agents, 0.0)
    for agent, info in infos.items():
        print(
            f"{agent}: adversary {info['adversary']} ({info['conflict_type'] or info['fallback']})"
        )
    while env.agents:
        # Keep speed and course: zero acceleration and steering (normalised actions).
        actions = {agent: np.zeros(2, dtype=np.float32) for agent in env.agents}
        _, rewards, terminations, truncations, infos = env.step(actions)
        for agent, reward in rewards.items():
            returns[agent] += reward
        for agent in terminations:
            if terminations[agent] or truncations[agent]:
                m = infos[agent]["metrics"]
                how = (
                    "collided"
                    if infos[agent]["collision"]
                    else "off road"
                    if infos[agent]["off_road"]
                    else "time limit"
                )
                print(f"{agent}: done at {infos[agent]['time']:.1f} s ({how}); CR {m['cr']:.0f}, "
                      f"ego-adversary CR {m['cr_ego_adversary']:.0f}, return {returns[agent]:.1f}")  # fmt: skip
    env.close()


if __name__ == "__main__":
    main()
