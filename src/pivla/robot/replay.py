"""A recorded episode played back on the arm (``pivla robot replay``).

The episode's actions are read from the LeRobot dataset and sent one per tick at the dataset's fps (the env
paces them), every one through the arm's safety layer like any other command. An arm that records absolute
joint positions (the SO-101) first walks from where it stands to the episode's first goal, within the guard's
step bound, so that the recorded goals are then sent as they were; an arm of end-effector deltas (the pivla
arm) goes home first, where its recordings start. The arm is stopped (it holds) at the end, however it ends.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from pivla.data.action_space import ActionSpace
from pivla.data.episode import DatasetError
from pivla.data.lerobot.reader import iter_lerobot, lerobot_action_space, read_info


@dataclass
class RecordedEpisode:
    actions: np.ndarray  # (T, D)
    fps: int
    action_space: ActionSpace
    instruction: str


def read_episode_actions(root: str | Path, episode: int) -> RecordedEpisode:
    """The actions, fps and action space of episode ``episode`` of a LeRobot dataset (no pictures decoded)."""
    info = read_info(root)
    space = lerobot_action_space(root, info)
    ep = next(iter_lerobot(root, obs_keys=(), episodes=[episode]))
    return RecordedEpisode(ep.actions, int(info["fps"]), space, ep.instruction)


def env_action_names(env: Any) -> tuple[str, ...]:
    from pivla.robot.so101_env import ACTION_SPACE, SO101Env

    if isinstance(env, SO101Env):
        return ACTION_SPACE.names
    from pivla.data.action_space import EE_DELTA

    return EE_DELTA.names


def replay(env: Any, recorded: RecordedEpisode, approach_s: float = 10.0,
           say: Callable[[str], None] = print) -> list[np.ndarray]:
    """Sends ``recorded``'s actions through ``env`` (see the module doc); returns the commands as sent (the
    SO-101: its goals after the guard; the pivla arm: the joint targets after its safety layer)."""
    names = env_action_names(env)
    if tuple(recorded.action_space.names) != tuple(names):
        raise DatasetError(f"the episode's actions are {recorded.action_space.describe()}; this arm takes "
                           f"{', '.join(names)}")
    sent: list[np.ndarray] = []
    try:
        env.reset()
        actions = recorded.actions
        if recorded.action_space.kind.absolute:
            first = np.asarray(actions[0], float)
            for _ in range(max(1, int(approach_s * recorded.fps))):
                _, _, _, _, info = env.step(first)
                if np.allclose(info["command"], first, atol=1e-4):
                    break
            else:
                say("the arm did not reach the episode's first pose in time; replaying from where it is")
        for action in actions:
            _, _, _, _, info = env.step(action)
            sent.append(np.asarray(info["command"] if "command" in info else env.robot.last_command.q, float))
    finally:
        env.robot.stop()
    return sent
