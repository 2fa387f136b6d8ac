"""The SO-101 twin (MuJoCo): TheRobotStudio's SO-101 arm on a table, pick-and-place tasks, a scripted expert in
joint space, STS3215 servo realism. ``list_tasks(suite)`` and ``make_env(suite, task, ...)`` follow
:mod:`pivla.envs`; importing this module registers ``pivla/SO101-v0`` with gymnasium. Actions and observations
are LeRobot's SO-101 layout (six joint positions; cameras ``front`` and ``wrist``, ``state``), as the real arm's
env (``pivla.robot.so101_env``) has them. Rendering runs on the CPU as the tabletop twin's does. See docs/twin.md.
"""

from __future__ import annotations

import ctypes.util
import os

if "MUJOCO_GL" not in os.environ:
    os.environ["MUJOCO_GL"] = "egl" if ctypes.util.find_library("EGL") else "osmesa"
    os.environ.setdefault("PYOPENGL_PLATFORM", os.environ["MUJOCO_GL"])
os.environ.setdefault("LP_NUM_THREADS", "0")  # as the tabletop twin: llvmpipe renders small pictures faster in-thread

import gymnasium  # noqa: E402

from pivla.envs import TaskSpec  # noqa: E402
from pivla.envs.so101.env import CAMERAS, CONTROL_HZ, STATE_KEY, SO101TwinEnv  # noqa: E402
from pivla.envs.so101.model import ACTION_SPACE  # noqa: E402
from pivla.envs.so101.servo import ServoConfig  # noqa: E402
from pivla.envs.so101.tasks import SUITES, get_suite  # noqa: E402

ENV_ID = "pivla/SO101-v0"


def list_tasks(suite: str) -> list[TaskSpec]:
    """The suite's tasks in index order (``pick_place`` has four)."""
    return [TaskSpec(suite, i, t.name, t.instruction, t.max_steps) for i, t in enumerate(get_suite(suite))]


def make_env(suite: str = "pick_place", task: int | str = 0, *, seed: int | None = None, image_size: int = 80,
             realism: str = "ideal", cameras: tuple[str, ...] = CAMERAS, render: bool = True,
             perturb: str | None = None, **kwargs) -> SO101TwinEnv:
    """One task's environment. ``realism``: "ideal" or "servo" (STS3215); ``render=False`` skips the cameras
    (for the expert and tests that only need the state). The SO-101 twin has no perturbations yet: ``perturb``
    must be empty."""
    parse_perturb(perturb)
    return SO101TwinEnv(suite, task, seed=seed, image_size=image_size, realism=realism, cameras=cameras,
                        render=render, **kwargs)


def parse_perturb(spec: str | None) -> None:
    """The SO-101 twin takes no perturbation spec (the tabletop twin's are defined on its own scenes)."""
    if spec not in (None, "", "none"):
        raise ValueError(f"the so101 twin has no perturbations (got {spec!r}); they exist on the tabletop twin only")


if ENV_ID not in gymnasium.registry:
    gymnasium.register(id=ENV_ID, entry_point=make_env)

__all__ = ["ACTION_SPACE", "CAMERAS", "CONTROL_HZ", "ENV_ID", "STATE_KEY", "SUITES", "SO101TwinEnv", "ServoConfig",
           "list_tasks", "make_env", "parse_perturb"]
