"""A policy step's simulation frames (highway-env's ``_simulate``), for ``CounterScene-v0``.

A policy step is ``simulation_frequency // policy_frequency`` frames of 0.1 s. Each frame,
every ego's highway-env vehicle moves one frame by its policy's controls, the closed loop
steps this env's episode with the egos' new states (the world model's traffic moves), the
env's highway-env road is synced from the loop, and every ego's closed-loop info of the frame
is recorded (``frame_infos``, what ``envs/outcome.py`` turns into the step's info, rewards
and end). The frames stop early when the episode is done or every ego's episode has ended.

:class:`SimulationFrames` is mixed into :class:`~counterscene_env.envs.single_agent.
CounterSceneEnv`. Its parts are public so that a vector env (``envs/vector.py``) runs the
frames of all its envs with one closed-loop step each: ``begin_frames``, then per frame
``advance_egos`` of every env, one ``ClosedLoop.step``, ``end_frame`` of every env.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from highway_env.vehicle.kinematics import Vehicle

from counterscene_env.envs.spaces import as_highway_action
from counterscene_env.scene.prefetch import one_thread_if
from counterscene_env.sim import ClosedLoop
from counterscene_env.sim.state import Episode


class SimulationFrames:
    """The frames of a policy step (module docstring), as methods of the env.

    It reads and writes the env's attributes below (``CounterSceneEnv`` sets them at reset)
    and highway-env's (``action_type``, ``_automatic_rendering``), and calls the env's
    ``sync_road`` and ``EgoOutcomes``'s ``stop_ended_egos`` and ``all_egos_ended``.
    """

    config: dict[str, Any]
    loop: ClosedLoop
    slot: int  # this env's episode in ``loop``
    egos: list[int]
    controlled_vehicles: list[Vehicle]  # the egos' highway-env vehicles
    frame_infos: list[list[dict]]  # [frame][ego]: the closed loop's infos of the policy step
    episode: Episode
    steps: int  # frames simulated in the episode (highway-env's counter)
    recording_ahead: bool  # a scene is recorded in the background (scene/prefetch.py)
    frames_per_step: int  # frames of a policy step, fixed at reset (policy_frequency then)
    #: Frames of the current policy step still to simulate (set by ``begin_frames``).
    _frames_left: int = 0

    def _simulate(self, action: Any = None) -> None:
        """highway-env's template method: the policy step's frames (after ``begin_frames``),
        this env's episode alone; ``action``, if given, is applied first."""
        if action is not None and not self.config["manual_control"]:
            self.action_type.act(as_highway_action(action))
        B, E = len(self.loop.episodes), len(self.egos)
        only = np.arange(B) == self.slot
        while True:
            states = np.full((B, E, 4), np.nan)
            states[self.slot] = self.advance_egos()
            with one_thread_if(self.recording_ahead):
                self.loop.step(ego_states=states, only=only)
            if self.end_frame():
                break
            self._automatic_rendering()
        self.enable_auto_render = False

    def begin_frames(self) -> None:
        """Start a policy step's simulation frames (after the action is applied)."""
        self.frame_infos = []
        self._frames_left = self.frames_per_step

    def advance_egos(self) -> np.ndarray:
        """Step every ego's highway-env vehicle by one frame; ``[E, 4]`` their new states
        (x m, y m, yaw rad, speed m/s), for ``ClosedLoop.step(ego_states=...)``."""
        dt = 1 / self.config["simulation_frequency"]
        states = np.empty((len(self.egos), 4))
        for k, v in enumerate(self.controlled_vehicles):
            v.act()  # lane-following vehicles recompute their low-level controls
            v.step(dt)
            states[k] = (*v.position, v.heading, v.speed)
        return states

    def end_frame(self) -> bool:
        """Take in the closed loop's step of this env's episode; True when the policy step's
        frames are over (all simulated, the episode done, or every ego ended)."""
        self.frame_infos.append([dict(i) for i in self.loop.infos(self.slot)])
        self.sync_road()
        self.steps += 1
        self._frames_left -= 1
        self.stop_ended_egos()
        return self._frames_left <= 0 or self.episode.done or self.all_egos_ended()
