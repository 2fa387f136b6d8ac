"""What the two MuJoCo twins (the tabletop arm, ``pivla.envs.tabletop``; the SO-101, ``pivla.envs.so101``) share:
their arguments' checks, task lookup, episode seeding, object handles, the observation space and the cameras.

Each twin keeps its own arm, actions, tasks and success tests; only the gymnasium plumbing lives here, so that a
fix to seeding or rendering reaches both."""

from __future__ import annotations

import string
from collections.abc import Mapping, Sequence
from typing import Any, Protocol, TypeVar

import gymnasium
import mujoco
import numpy as np

REALISM = ("ideal", "servo")


class _Task(Protocol):
    name: str


T = TypeVar("T", bound=_Task)


def check_twin_args(twin: str, realism: str, image_size: int, cameras: Sequence[str], known: Sequence[str]) -> None:
    """Name the first bad constructor argument of a twin (``twin`` as the message calls it)."""
    if realism not in REALISM:
        raise ValueError(f"realism must be one of {REALISM}, got {realism!r}")
    if not 16 <= int(image_size) <= 480:
        raise ValueError(f"image_size must be in 16..480 px, got {image_size}")
    unknown = [c for c in cameras if c not in known]
    if unknown:
        raise ValueError(f"unknown cameras {unknown}; the {twin} has {tuple(known)}")


def get_suite(suites: Mapping[str, list[T]], twin: str, suite: str) -> list[T]:
    """The tasks of ``suite`` among a twin's ``suites``."""
    if suite not in suites:
        raise ValueError(f"unknown {twin} suite {suite!r}; choose from {sorted(suites)}")
    return suites[suite]


def get_task(suites: Mapping[str, list[T]], twin: str, suite: str, task: int | str) -> T:
    """A task of a suite by index (an int or a string of digits) or by name."""
    tasks = get_suite(suites, twin, suite)
    if isinstance(task, (int, np.integer)) or (isinstance(task, str) and task.isdigit()):
        idx = int(task)
        if not 0 <= idx < len(tasks):
            raise ValueError(f"task index {idx} out of range: suite {suite!r} has {len(tasks)} tasks")
        return tasks[idx]
    for t in tasks:
        if t.name == task:
            return t
    raise ValueError(f"unknown task {task!r} in suite {suite!r}; known: {[t.name for t in tasks]}")


def check_share(name: str, share: float) -> None:
    """A share of episodes (a scripted expert's deliberate misses) lies in [0, 1]."""
    if not 0.0 <= share <= 1.0:
        raise ValueError(f"{name} must be a share in [0, 1], got {share}")


def check_misses(miss: float, retries: int) -> None:
    """A scripted expert's deliberate misses: a share of episodes, each needing a retry to recover from."""
    check_share("miss", miss)
    if miss > 0 and retries < 1:
        raise ValueError("a deliberate miss needs retries >= 1 to recover from")


def draw_miss(rng: np.random.Generator, miss: float, offset: tuple[float, float]) -> np.ndarray | None:
    """Whether this episode's first grasp is a deliberate miss (a share ``miss`` of episodes) and, if so, where:
    a horizontal offset (m) from the object in a random direction, at a distance drawn from ``offset``."""
    if not (miss > 0 and rng.uniform() < miss):
        return None
    angle, dist = rng.uniform(-np.pi, np.pi), rng.uniform(*offset)
    return dist * np.array([np.cos(angle), np.sin(angle), 0.0])


def object_handles(model: mujoco.MjModel, names: Sequence[str]) -> dict[str, tuple[int, int, int, int]]:
    """Each free object's (qpos address, dof address, geom id, body id): joint, geom and body share its name."""
    out = {}
    for name in names:
        jnt = model.joint(name).id
        out[name] = (int(model.jnt_qposadr[jnt]), int(model.jnt_dofadr[jnt]), model.geom(name).id, model.body(name).id)
    return out


def observation_space(cameras: Sequence[str], image_size: int, vectors: Mapping[str, int]) -> gymnasium.spaces.Dict:
    """RGB pictures of ``cameras``, float vectors of the given lengths, and the instruction."""
    n = int(image_size)
    spaces: dict[str, gymnasium.Space] = {c: gymnasium.spaces.Box(0, 255, (n, n, 3), np.uint8) for c in cameras}
    for key, dim in vectors.items():
        spaces[key] = gymnasium.spaces.Box(-np.inf, np.inf, (dim,), np.float32)
    spaces["instruction"] = gymnasium.spaces.Text(max_length=256, charset=string.printable)
    return gymnasium.spaces.Dict(spaces)


class MujocoTwin(gymnasium.Env):
    """A twin's episode seeding and cameras. A subclass sets ``model``, ``data``, ``image_size``, ``cameras`` (the
    observed ones), ``camera_ids`` (every camera key's MuJoCo id) and ``scene_camera`` (what ``render`` shows)."""

    metadata: dict[str, Any] = {"render_modes": ["rgb_array"]}
    model: mujoco.MjModel
    data: mujoco.MjData
    image_size: int
    cameras: tuple[str, ...]
    camera_ids: dict[str, int]
    scene_camera: str
    episode_seed: int | None = None
    _renderer: mujoco.Renderer | None = None

    def draw_episode(self, seed: int | None, streams: int) -> tuple[np.random.Generator, ...]:
        """Start an episode: its seed (given, or drawn from the env's generator) fixes everything, through
        ``streams`` independent generators (so that one part's draws never shift another's)."""
        if seed is not None:
            self.np_random, _ = gymnasium.utils.seeding.np_random(seed)
            self.episode_seed = int(seed)
        else:
            self.episode_seed = int(self.np_random.integers(2**31 - 1))
        return tuple(np.random.default_rng(s) for s in np.random.SeedSequence(self.episode_seed).spawn(streams))

    def _picture(self, camera: str) -> np.ndarray:
        if self._renderer is None:
            self._renderer = mujoco.Renderer(self.model, self.image_size, self.image_size)
        self._renderer.update_scene(self.data, self.camera_ids[camera])
        return self._renderer.render().copy()

    def _render_all(self) -> dict[str, np.ndarray]:
        """The observed cameras' pictures now."""
        return {cam: self._picture(cam) for cam in self.cameras}

    def render(self) -> np.ndarray:
        return self._picture(self.scene_camera)

    def close(self) -> None:
        if self._renderer is not None:
            self._renderer.close()
            self._renderer = None
