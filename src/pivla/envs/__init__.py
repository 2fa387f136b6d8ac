"""Environments behind one small interface, so that collection, evaluation and the robot share a runner.

Every environment family (``tabletop``: the simulated twin of the paper's arm; ``so101``: the SO-101 twin;
``libero``: the LIBERO benchmark) is a module ``pivla.envs.<family>`` exposing::

    list_tasks(suite: str) -> list[TaskSpec]
    make_env(suite: str, task: int | str, **kwargs) -> gymnasium.Env

The gymnasium env's observations are dicts under the dataset's key names (``agentview_rgb``,
``eye_in_hand_rgb``, ``ee_pos``, ``ee_ori``, ``gripper_states``, ``joint_states``) plus ``instruction``;
actions are the dataset's 7-D end-effector deltas (gripper -1 open, +1 close); ``info["success"]``
reports task success; ``terminated`` is True on success; ``truncated`` at the task's step limit. The SO-101 twin
keeps the interface with the SO-101's own layout, as the real arm's env has it: observations ``front``, ``wrist``,
``state`` (six joint positions) and ``instruction``, actions six absolute joint positions in LeRobot's units
(``pivla.data.action_space.SO101``).
"""

from __future__ import annotations

import importlib
from dataclasses import dataclass
from typing import Any

FAMILIES = {"tabletop": "pivla.envs.tabletop", "so101": "pivla.envs.so101", "libero": "pivla.envs.libero"}


@dataclass(frozen=True)
class TaskSpec:
    """One goal of a suite: what the CLI's ``--tasks`` selects (by index or name)."""

    suite: str
    index: int
    name: str
    instruction: str
    max_steps: int


def family(env: str) -> Any:
    if env not in FAMILIES:
        raise ValueError(f"unknown env {env!r}; choose from {sorted(FAMILIES)}")
    return importlib.import_module(FAMILIES[env])


def list_tasks(env: str, suite: str) -> list[TaskSpec]:
    return family(env).list_tasks(suite)


def select_tasks(env: str, suite: str, tasks: str | None) -> list[TaskSpec]:
    """Parse ``--tasks`` ("0,3", "pick_block_left", or None for all) against a suite's tasks."""
    all_tasks = list_tasks(env, suite)
    if not tasks:
        return all_tasks
    chosen = []
    by_name = {t.name: t for t in all_tasks}
    for item in (s.strip() for s in tasks.split(",") if s.strip()):
        if item.isdigit():
            idx = int(item)
            if not 0 <= idx < len(all_tasks):
                raise ValueError(f"task index {idx} out of range: suite {suite!r} has {len(all_tasks)} tasks")
            chosen.append(all_tasks[idx])
        elif item in by_name:
            chosen.append(by_name[item])
        else:
            raise ValueError(f"unknown task {item!r} in suite {suite!r}; known: {sorted(by_name)}")
    return chosen


def make_env(env: str, suite: str, task: int | str, **kwargs: Any) -> Any:
    return family(env).make_env(suite, task, **kwargs)
