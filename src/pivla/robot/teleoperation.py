"""Keyboard jogging: key presses become actions, one per control tick.

Each arm jogs in its action space, so that what teleoperation sends is what a recording stores:

- the pivla arm (and its twin): 7-D end-effector deltas at half speed, ``w``/``s`` +x/-x, ``a``/``d``
  +y/-y, ``t``/``g`` up/down, ``z``/``c`` yaw, space toggles the gripper;
- the SO-101: six absolute joint positions, each key moving one joint's target by ``step_deg`` (the
  gripper by ``step_gripper``) from where the arm stood at the episode's start, kept inside the
  calibrated range: ``a``/``d`` shoulder_pan, ``w``/``s`` shoulder_lift, ``t``/``g`` elbow_flex,
  ``i``/``k`` wrist_flex, ``j``/``l`` wrist_roll, ``o``/``c`` gripper.

No key is a tick too: the pivla arm stands still (zero delta), the SO-101 holds its targets. The control
keys (``pivla.robot.keyboard``: keep, redo, stop) are the same for both arms and never jog.
``teleoperate`` is the loop without recording.
"""

from __future__ import annotations

from collections.abc import Iterable
from typing import Any, Protocol

import numpy as np

from pivla.robot.keyboard import CONTROL_HELP, Event, event

EE_KEYS = {"w": (0, 1), "s": (0, -1), "a": (1, 1), "d": (1, -1), "t": (2, 1), "g": (2, -1), "z": (5, 1),
           "c": (5, -1)}
EE_HELP = "w/s: +x/-x  a/d: +y/-y  t/g: up/down  z/c: yaw  space: gripper"
JOINT_KEYS = {"d": (0, 1), "a": (0, -1), "w": (1, 1), "s": (1, -1), "t": (2, 1), "g": (2, -1), "i": (3, 1),
              "k": (3, -1), "l": (4, 1), "j": (4, -1), "o": (5, 1), "c": (5, -1)}
JOINT_HELP = ("a/d: shoulder_pan  w/s: shoulder_lift  t/g: elbow_flex  i/k: wrist_flex  j/l: wrist_roll  "
              "o/c: gripper open/close")


class Jog(Protocol):
    """Key presses to actions for one arm."""

    help: str

    def reset(self, obs: dict[str, Any]) -> None:
        """A new episode starts from ``obs``."""

    def action(self, key: str) -> np.ndarray:
        """The action of one control tick with ``key`` pressed (``""``: none)."""


class EEJog:
    """The pivla arm's end-effector jog (7-D deltas, the gripper -1 open / +1 closed)."""

    help = EE_HELP

    def __init__(self, speed: float = 0.5) -> None:
        self.speed = speed
        self.gripper = -1.0

    def reset(self, obs: dict[str, Any]) -> None:
        self.gripper = -1.0

    def action(self, key: str) -> np.ndarray:
        a = np.zeros(7)
        if key in EE_KEYS:
            axis, sign = EE_KEYS[key]
            a[axis] = self.speed * sign
        elif key == " ":
            self.gripper = -self.gripper
        a[6] = self.gripper
        return a


class JointJog:
    """The SO-101's joint jog: absolute targets moved by keys, clipped to ``lower``..``upper``."""

    help = JOINT_HELP

    def __init__(self, lower, upper, step_deg: float = 2.0, step_gripper: float = 5.0, state_key: str = "state"):
        self.lower, self.upper = np.asarray(lower, float), np.asarray(upper, float)
        self.steps = np.array([step_deg] * (len(self.lower) - 1) + [step_gripper])
        self.state_key = state_key
        self.target: np.ndarray | None = None

    def reset(self, obs: dict[str, Any]) -> None:
        self.target = np.clip(np.asarray(obs[self.state_key], float), self.lower, self.upper)

    def action(self, key: str) -> np.ndarray:
        if self.target is None:
            raise RuntimeError("JointJog.reset(obs) first: the targets start where the arm stands")
        if key in JOINT_KEYS:
            joint, sign = JOINT_KEYS[key]
            self.target[joint] = np.clip(self.target[joint] + sign * self.steps[joint], self.lower[joint],
                                         self.upper[joint])
        return self.target.copy()


def jog_for(env: Any, step_deg: float = 2.0, step_gripper: float = 5.0) -> Jog:
    """The jog of the arm under ``env``: joint jog for an SO-101 env, end-effector jog otherwise."""
    from pivla.robot.so101_env import SO101Env

    if isinstance(env, SO101Env):
        return JointJog(env.lower, env.upper, step_deg, step_gripper)
    return EEJog()


def help_line(jog: Jog, recording: bool) -> str:
    if recording:
        return f"{jog.help}\n{CONTROL_HELP}"
    return f"{jog.help}\nleft/r: start over  esc/q: stop"


def teleoperate(env: Any, jog: Jog, keys: Iterable[str], max_steps: int | None = None) -> int:
    """Jogs the arm from ``keys`` until Esc/``q``, the keys end or ``max_steps``; left/``r`` starts over (the
    pivla arm goes home). Every action passes the env's safety checks; the arm is stopped (it holds) at the
    end. Returns the steps taken."""
    steps = 0
    try:
        obs, _ = env.reset()
        jog.reset(obs)
        for key in keys:
            ev = event(key)
            if ev is Event.STOP:
                break
            if ev is Event.REDO:
                obs, _ = env.reset()
                jog.reset(obs)
                continue
            obs, *_ = env.step(jog.action(key))
            steps += 1
            if max_steps is not None and steps >= max_steps:
                break
    finally:
        env.robot.stop()
    return steps
