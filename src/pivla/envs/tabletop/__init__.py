"""The simulated twin of the low-cost arm (MuJoCo): task suites, perturbations, scripted experts.

``list_tasks(suite)`` and ``make_env(suite, task, ...)`` follow :mod:`pivla.envs`; importing this module
registers ``pivla/Tabletop-v0`` with gymnasium (``gymnasium.make("pivla/Tabletop-v0", suite=..., task=...)``).
Rendering runs on the CPU: ``MUJOCO_GL`` defaults to ``egl`` (Mesa llvmpipe) when libEGL is present,
else ``osmesa``; llvmpipe renders in the calling thread (``LP_NUM_THREADS=0``) unless the user sets it. See
docs/twin.md.
"""

from __future__ import annotations

import ctypes.util
import os

if "MUJOCO_GL" not in os.environ:
    os.environ["MUJOCO_GL"] = "egl" if ctypes.util.find_library("EGL") else "osmesa"
    os.environ.setdefault("PYOPENGL_PLATFORM", os.environ["MUJOCO_GL"])
# llvmpipe rasterises the twin's small pictures faster in the rendering thread than across its worker
# threads: same pixels, and env.step took 0.3-1.3 ms less at 80 px on 2 cores (docs/experiments.md#one-thread-rendering)
os.environ.setdefault("LP_NUM_THREADS", "0")

import gymnasium  # noqa: E402

from pivla.envs import TaskSpec  # noqa: E402
from pivla.envs.tabletop.env import TabletopEnv  # noqa: E402
from pivla.envs.tabletop.perturb import PerturbConfig, parse_perturb  # noqa: E402
from pivla.envs.tabletop.tasks import SUITES, get_suite  # noqa: E402

ENV_ID = "pivla/Tabletop-v0"


def list_tasks(suite: str) -> list[TaskSpec]:
    """The suite's tasks in index order (``pick_place`` has nine)."""
    return [TaskSpec(suite, i, t.name, t.instruction, t.max_steps) for i, t in enumerate(get_suite(suite))]


def make_env(
    suite: str = "pick_place",
    task: int | str = 0,
    *,
    seed: int | None = None,
    image_size: int = 96,
    realism: str = "ideal",
    perturb: str | PerturbConfig | None = None,
    cameras: tuple[str, ...] = ("agentview_rgb", "eye_in_hand_rgb"),
    render: bool = True,
    **kwargs,
) -> TabletopEnv:
    """One task's environment. ``realism``: "ideal" or "servo"; ``perturb``: spec (docs/twin.md) or config;
    ``render=False`` skips the cameras (for experts and tests that only need the state)."""
    return TabletopEnv(suite, task, seed=seed, image_size=image_size, realism=realism, perturb=perturb,
                       cameras=cameras, render=render, **kwargs)


if ENV_ID not in gymnasium.registry:
    gymnasium.register(id=ENV_ID, entry_point=make_env)

__all__ = ["ENV_ID", "SUITES", "PerturbConfig", "TabletopEnv", "list_tasks", "make_env", "parse_perturb"]
