"""The SO-101 twin as a gymnasium environment, with the real arm's interface (``pivla.robot.so101_env``).

Actions are LeRobot's SO-101 actions: six absolute joint positions (``shoulder_pan.pos`` ... ``gripper.pos``;
degrees for the body joints, the gripper 0 closed .. 100 open; ``pivla.data.action_space.SO101``), clipped to
the MJCF's joint ranges. Observations are LeRobot's SO-101 layout under pivla's keys, as the real arm's env
gives them: the cameras ``front`` and ``wrist`` and ``state``, the six present joint positions in the same units.

Control runs at 10 Hz, the tabletop twin's rate, not LeRobot's 30 fps: an action holds for 50 physics steps of
2 ms. The twin's recipe (chunk length, horizons, image size, step budgets) was validated at 10 Hz, and a third
of the frames makes collection and evaluation on a CPU renderer three times cheaper; the rate is recorded in
every dataset (``control_hz``), and a policy meant for 30 fps recordings is trained on those.

``realism="ideal"``: the MJCF's position actuators track each goal as given. ``"servo"``: every goal goes through
the STS3215 model of :mod:`pivla.envs.so101.servo` (resolution, speed and acceleration profile, position loop
with LeRobot's gain, torque cap, dead zone), run at the physics rate, and ``state`` is the encoders' reading.
"""

from __future__ import annotations

from typing import Any

import gymnasium
import mujoco
import numpy as np

from pivla.arm.rotations import yaw_of_quat
from pivla.envs.so101 import model as arm
from pivla.envs.so101 import tasks
from pivla.envs.so101.scene import PHYSICS_DT, asset_files, scene_xml
from pivla.envs.so101.servo import RAD_PER_STEP, ServoConfig, STS3215Bus, to_steps
from pivla.envs.twin import MujocoTwin, check_twin_args, object_handles, observation_space

CONTROL_HZ = 10
SUBSTEPS = int(round(1.0 / (CONTROL_HZ * PHYSICS_DT)))
CAMERAS = ("front", "wrist")
STATE_KEY = "state"
STAGES = ("reached", "grasped", "lifted", "placed")
# Where an episode starts (LeRobot units): the tool point 0.17 m ahead of the base and 0.075 m up, the jaws open,
# pointing down and closing across the arm's heading; each episode adds up to START_JITTER degrees per body joint.
START_POSE = np.array([7.0, -31.0, 30.0, 90.0, 100.0, 40.0])
START_JITTER = 3.0


class SO101TwinEnv(MujocoTwin):
    """One task of a suite; the model is built once and every reset only re-draws the state."""

    metadata = {"render_modes": ["rgb_array"], "render_fps": CONTROL_HZ}
    scene_camera = "front"

    def __init__(
        self,
        suite: str = "pick_place",
        task: int | str = 0,
        *,
        seed: int | None = None,
        image_size: int = 80,
        realism: str = "ideal",
        cameras: tuple[str, ...] = CAMERAS,
        render: bool = True,
        paraphrase: bool = False,
        servo: ServoConfig | None = None,
        render_mode: str | None = None,
    ):
        check_twin_args("SO-101 twin", realism, image_size, cameras, CAMERAS)
        self.suite = suite
        self.task = tasks.get_task(suite, task)
        self.task_index = tasks.get_suite(suite).index(self.task)
        self.image_size = int(image_size)
        self.realism = realism
        self.cameras = tuple(cameras) if render else ()
        self.paraphrase = paraphrase
        self.servo_config = servo or ServoConfig()
        self.render_mode = render_mode

        self.model = mujoco.MjModel.from_xml_string(scene_xml(self.task), asset_files())
        m = self.model
        self.data = mujoco.MjData(m)
        self.kin = arm.Kinematics(m)
        self._qadr = np.array([m.jnt_qposadr[m.joint(n).id] for n in arm.JOINTS])
        self._dadr = np.array([m.jnt_dofadr[m.joint(n).id] for n in arm.JOINTS])
        self._act = np.array([m.actuator(n).id for n in arm.JOINTS])
        self._kp_ideal = float(m.actuator_gainprm[self._act[0], 0])
        for pad in arm.PADS:  # upstream's fingertip pads, inert in the MJCF: they are what holds a cube (NOTICE)
            m.geom_contype[m.geom(pad).id] = m.geom_conaffinity[m.geom(pad).id] = 1
        self.bus: STS3215Bus | None = None
        if realism == "servo":  # the actuators become torque motors driven by the servo model
            limit = STS3215Bus(self.servo_config).torque_limit
            m.actuator_gainprm[self._act] = 0.0
            m.actuator_gainprm[self._act, 0] = 1.0
            m.actuator_biasprm[self._act] = 0.0
            m.actuator_ctrlrange[self._act] = np.stack([-limit, limit], axis=1)
            m.actuator_forcerange[self._act] = np.stack([-limit, limit], axis=1)
        self._jaw_geoms = [self._collision_geoms(arm.GRIPPER_BODY), self._collision_geoms(arm.MOVING_JAW_BODY)]
        self._obj = object_handles(m, self.task.objects)
        self._target_mocap = int(m.body_mocapid[m.body(self.task.target).id])
        self.camera_ids = {c: m.camera(c).id for c in CAMERAS}
        self.lower, self.upper = arm.lerobot_limits()
        self.observation_space = observation_space(self.cameras, self.image_size, {STATE_KEY: len(arm.JOINTS)})
        self.action_space = gymnasium.spaces.Box(self.lower.astype(np.float32), self.upper.astype(np.float32),
                                                 (len(arm.JOINTS),), np.float32)
        self.np_random, _ = gymnasium.utils.seeding.np_random(seed)
        self.instruction = self.task.instruction
        self.layout: dict = {}
        self.command = START_POSE.copy()
        self._steps = 0
        self._stages = np.zeros(len(STAGES), bool)

    @property
    def control_hz(self) -> float:
        return float(CONTROL_HZ)

    @property
    def servo_kp(self) -> float:
        """The joints' position gain (N m/rad) in this realism: what the expert's gravity feed-forward divides by."""
        return self.servo_config.kp if self.bus is not None else self._kp_ideal

    def _collision_geoms(self, body: str) -> set[int]:
        m = self.model
        b = m.body(body).id
        return {g for g in range(m.ngeom) if m.geom_bodyid[g] == b and m.geom_contype[g]}

    # ----------------------------------------------------------------------------------------------- reset
    def reset(self, *, seed: int | None = None, options: dict | None = None) -> tuple[dict, dict]:
        """New episode. The episode seed (given, or drawn from the env's generator) fixes everything."""
        rng_task, rng_lang = self.draw_episode(seed, 2)
        m, d = self.model, self.data
        mujoco.mj_resetData(m, d)
        self.layout = tasks.sample_layout(self.task, rng_task)
        for name, (x, y, yaw) in self.layout["objects"].items():
            qadr = self._obj[name][0]
            d.qpos[qadr: qadr + 3] = [x, y, tasks.CUBE_HALF]
            d.qpos[qadr + 3: qadr + 7] = [np.cos(yaw / 2), 0.0, 0.0, np.sin(yaw / 2)]
        d.mocap_pos[self._target_mocap] = [*self.layout["target"], 0.0]
        start = START_POSE.copy()
        start[:5] += rng_task.uniform(-START_JITTER, START_JITTER, 5)
        q0 = arm.from_lerobot(start)
        d.qpos[self._qadr] = q0
        self.bus = STS3215Bus(self.servo_config) if self.realism == "servo" else None
        if self.bus is not None:
            self.bus.reset(q0)
        mujoco.mj_forward(m, d)
        self.command = self.hold_command(start)  # the goals the servos hold: the start pose despite gravity
        self._actuate(self.command, settle=True)  # the arm settles on its servos, the cubes on the table
        self.instruction = (str(rng_lang.choice(self.task.paraphrases)) if self.paraphrase and self.task.paraphrases
                            else self.task.instruction)
        self._steps = 0
        self._stages[:] = False
        self._initial = {n: self._object_pos(n).copy() for n in self.task.objects}
        success, _ = self._evaluate()
        info = {"success": success, "episode_seed": self.episode_seed, "instruction": self.instruction}
        return self._observation(), info

    def hold_command(self, target: np.ndarray) -> np.ndarray:
        """The joint command (LeRobot units) under which the arm comes to rest at ``target`` despite gravity:
        each body joint's goal raised by the gravity torque over the position gain (the servos' steady-state
        sag). Privileged (it reads the model): for the scripted expert and the reset pose only."""
        target = np.asarray(target, float)
        q = arm.from_lerobot(target)
        out = target.copy()
        out[:5] += np.degrees(self.kin.gravity(q)[:5] / self.servo_kp)
        return np.clip(out, self.lower, self.upper)

    # ------------------------------------------------------------------------------------------------ step
    def _actuate(self, command: np.ndarray, settle: bool = False) -> None:
        """Hold joint goals ``command`` (LeRobot units) for one control period."""
        m, d = self.model, self.data
        goal = arm.from_lerobot(command)
        if self.bus is None:
            d.ctrl[self._act] = goal
            mujoco.mj_step(m, d, nstep=SUBSTEPS)
            return
        self.bus.command(goal)
        if settle:
            self.bus.reset(goal)
        for _ in range(SUBSTEPS):
            d.ctrl[self._act] = self.bus.torque(d.qpos[self._qadr], PHYSICS_DT)
            mujoco.mj_step(m, d)

    def step(self, action: np.ndarray) -> tuple[dict, float, bool, bool, dict]:
        a = np.asarray(action, dtype=np.float64)
        if a.shape != (len(arm.JOINTS),):
            raise ValueError(f"action must be the {len(arm.JOINTS)} joint positions {list(arm.ACTION_SPACE.names)}, "
                             f"got shape {a.shape}")
        if not np.all(np.isfinite(a)):
            raise ValueError(f"action contains NaN or inf: {a}")
        if self.episode_seed is None:
            raise RuntimeError("call reset() before step()")
        self.command = np.clip(a, self.lower, self.upper)
        self._actuate(self.command)
        self._steps += 1
        before = self._stages.sum()
        success, stages = self._evaluate()
        self._stages |= stages
        if success:
            self._stages[:] = True
        reward = float(self._stages.sum() - before) * 0.25
        truncated = self._steps >= self.task.max_steps and not success
        info = {
            "success": success,
            "stages": {s: bool(self._stages[i]) for i, s in enumerate(STAGES)},
            "stage_progress": float(self._stages.mean()),
            "step": self._steps,
            "command": self.command.astype(np.float32),
            "perturb_events": [],
        }
        return self._observation(), reward, success, truncated, info

    # ----------------------------------------------------------------------------------------- observation
    def joint_positions(self) -> np.ndarray:
        """The six present positions in LeRobot units, as the arm reports them (the encoders' steps with servo
        realism, exact with ideal)."""
        q = self.data.qpos[self._qadr]
        if self.bus is not None:
            q = to_steps(q) * RAD_PER_STEP
        return arm.to_lerobot(q)

    def _observation(self) -> dict[str, Any]:
        obs: dict[str, Any] = self._render_all()
        obs[STATE_KEY] = self.joint_positions().astype(np.float32)
        obs["instruction"] = self.instruction
        return obs

    # ------------------------------------------------------------------------------------ privileged state
    def _object_pos(self, name: str) -> np.ndarray:
        return self.data.xpos[self._obj[name][3]]

    def _touching(self, geom: int) -> tuple[bool, bool]:
        """Whether the fixed / the moving jaw touches ``geom``."""
        d = self.data
        fixed = moving = False
        for g1, g2 in d.contact.geom[: d.ncon]:
            if geom not in (g1, g2):
                continue
            other = g2 if g1 == geom else g1
            fixed |= other in self._jaw_geoms[0]
            moving |= other in self._jaw_geoms[1]
        return fixed, moving

    def privileged_state(self) -> dict[str, Any]:
        """Simulator truth for the scripted expert (never part of the observation)."""
        d = self.data
        tcp, rot = self.kin.tcp(d)
        state: dict[str, Any] = {
            "tcp": tcp.copy(),
            "tcp_mat": rot,
            "q": d.qpos[self._qadr].copy(),
            "command": self.command.copy(),
            "target": np.array(self.layout["target"]),
            "objects": {},
            "initial": {n: p.copy() for n, p in self._initial.items()},
        }
        for name, (_qadr, dadr, geom, body) in self._obj.items():
            state["objects"][name] = {
                "pos": d.xpos[body].copy(),
                "yaw": yaw_of_quat(d.xquat[body]),
                "speed": float(np.linalg.norm(d.qvel[dadr: dadr + 3])),
                "grasped": all(self._touching(geom)),
            }
        return state

    def _evaluate(self) -> tuple[bool, np.ndarray]:
        """(success, stages reached now) from the simulator state."""
        d = self.data
        _qadr, dadr, geom, body = self._obj[self.task.cube]
        pos = d.xpos[body]
        touch = self._touching(geom)
        grasped = all(touch)
        resting = np.linalg.norm(d.qvel[dadr: dadr + 3]) < tasks.REST_SPEED and not any(touch)
        ok = resting and tasks.placed(self.task.target, np.array(self.layout["target"]), pos)
        lifted = grasped and pos[2] > tasks.CUBE_HALF + 0.02
        tcp = self.kin.tcp(d)[0]
        stages = np.array([np.linalg.norm(tcp - pos) < 0.025, grasped, lifted, ok])
        return bool(ok), stages
