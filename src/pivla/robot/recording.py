"""Teleoperated demonstrations written straight into a LeRobot v3.0 dataset (``pivla robot record``).

``record`` jogs the arm from a key source (``pivla.robot.teleoperation``) and stores every control tick as one
frame: the observation before the tick and the action of the tick (the pivla arm: the 7-D end-effector delta;
the SO-101: the six joint goals as sent, after the arm's guard, so that a replay sends the same goals).
LeRobot's keys end an episode: right arrow or ``n`` keeps it, left arrow or ``r`` redoes it, Esc or ``q``
stops (``b`` keeps it marked as a failure; an episode not kept when recording stops is discarded). An
episode is also kept when it reaches ``episode_steps``, and recording stops after ``episodes`` kept ones.

Each kept episode is committed to the dataset at once (``pivla.data.lerobot_append``): a crash, a pulled
cable or Ctrl-C loses at most the episode in progress, and recording into the same folder again continues
the dataset. Between episodes the pivla arm goes home; the SO-101 stays where it is.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from pivla.data.action_space import EE_DELTA, ActionSpace
from pivla.data.episode import Episode
from pivla.data.lerobot.writer import LeRobotWriteConfig
from pivla.data.lerobot_append import LeRobotAppender
from pivla.robot.keyboard import Event, event
from pivla.robot.teleoperation import Jog

PIVLA_ARM_TYPE = "pivla_arm"  # info.json robot_type of the pivla arm's recordings


@dataclass
class RecordResult:
    root: Path
    kept: int  # episodes kept by this recording
    redone: int  # episodes discarded with left/r
    episodes: int  # episodes the dataset holds now (a continued dataset had some before)
    frames: int  # frames this recording kept


def dataset_format(env: Any, fps: float | None = None, vcodec: str = "libx264") -> tuple[LeRobotWriteConfig,
                                                                                         ActionSpace]:
    """How ``env``'s episodes are written: LeRobot's SO-101 layout (``observation.state`` named
    ``shoulder_pan.pos`` ..., the cameras ``front`` and ``wrist``) or the pivla arm's (the dataset keys of the
    twin), at the env's control rate unless ``fps``."""
    from pivla.robot.so101_env import ACTION_SPACE, JOINT_NAMES, ROBOT_TYPE, STATE_KEY, SO101Env

    rate = int(round(fps or env.control_hz))
    if isinstance(env, SO101Env):
        return LeRobotWriteConfig(fps=rate, state_keys=(STATE_KEY,), state_names=JOINT_NAMES, robot_type=ROBOT_TYPE,
                                  vcodec=vcodec), ACTION_SPACE
    return LeRobotWriteConfig(fps=rate, robot_type=PIVLA_ARM_TYPE, vcodec=vcodec), EE_DELTA


def _episode(frames: list[tuple[dict, np.ndarray]], instruction: str, success: bool, meta: dict) -> Episode:
    keys = [k for k in frames[0][0] if k != "instruction"]
    obs = {k: np.stack([np.asarray(o[k]) for o, _ in frames]) for k in keys}
    return Episode(np.stack([a for _, a in frames]).astype(np.float32), obs, instruction, success=success,
                   source="teleop", meta=meta)


def record(env: Any, jog: Jog, keys: Iterable[str], root: str | Path, instruction: str, episodes: int = 0,
           episode_steps: int = 0, fps: float | None = None, vcodec: str = "libx264",
           say: Callable[[str], None] = print) -> RecordResult:
    """Records episodes from ``keys`` into the LeRobot dataset at ``root`` (see the module doc); ``episodes``
    and ``episode_steps`` of 0 mean no limit. The arm is stopped (it holds) when recording ends, however."""
    cfg, space = dataset_format(env, fps, vcodec)
    robot_type = cfg.robot_type
    kept = redone = frames_kept = 0
    with LeRobotAppender(root, cfg, space) as dataset:
        if dataset.episodes:
            say(f"continuing {root}: {dataset.episodes} episodes already")
        try:
            obs, _ = env.reset()
            jog.reset(obs)
            frames: list[tuple[dict, np.ndarray]] = []
            for key in keys:
                ev = event(key)
                if ev is None and episode_steps and len(frames) >= episode_steps:
                    ev = Event.KEEP
                if ev in (Event.KEEP, Event.KEEP_FAILED):
                    if not frames:
                        say("nothing recorded yet: jog the arm first")
                        continue
                    success = ev is Event.KEEP
                    index = dataset.add(_episode(frames, instruction, success, {"robot_type": robot_type}))
                    kept, frames_kept = kept + 1, frames_kept + len(frames)
                    say(f"episode {index} kept: {len(frames)} frames" + ("" if success else " (a failure)"))
                    frames = []
                    if episodes and kept >= episodes:
                        break
                    obs, _ = env.reset()
                    jog.reset(obs)
                    continue
                if ev is Event.REDO:
                    say(f"episode discarded ({len(frames)} frames): recording it again")
                    redone, frames = redone + 1, []
                    obs, _ = env.reset()
                    jog.reset(obs)
                    continue
                if ev is Event.STOP:
                    if frames:
                        say(f"stopped: the episode in progress ({len(frames)} frames) was not kept")
                    break
                action = jog.action(key)
                nxt, _, _, _, info = env.step(action)
                frames.append((obs, np.asarray(info.get("command", action), np.float32)))
                obs = nxt
        finally:
            env.robot.stop()
        total = dataset.episodes
    return RecordResult(Path(root), kept, redone, total, frames_kept)
