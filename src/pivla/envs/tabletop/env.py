"""The simulated twin as a gymnasium environment.

Control (10 Hz, 50 physics steps of 2 ms per action). The action is LIBERO-like, 7-D in [-1, 1]:

- ``a[0:3]``: tool-centre translation, world frame, ``TRANS_SCALE`` metres per unit (0.02 m -> 0.2 m/s).
- ``a[3:6]``: rotation, Euler (roll, pitch, yaw) of a world-frame delta rotation, ``ROT_SCALE`` rad per unit;
  the new target orientation is ``R(a[3:6] * ROT_SCALE) @ R_current``.
- ``a[6]``: gripper, -1 fully open ... +1 closed (continuous; the expert and every policy command +-1).

Like the real arm (hobby servos report nothing back), the delta is applied to the *commanded* pose, i.e.
the forward kinematics of the last joint command; the target is clipped to the workspace box
``WORKSPACE`` and turned into joint targets by joint-limited damped-least-squares IK on the arm model.
With ``realism="servo"`` the joint targets then pass through :class:`ServoModel` (deadband, backlash,
noise, speed limit); ``"ideal"`` tracks them exactly (up to the position servos' own dynamics).
"""

from __future__ import annotations

from typing import Any

import gymnasium
import mujoco
import numpy as np

from pivla import arm
from pivla.arm.constants import CONTROL_HZ, IK_ITERATIONS, ROT_SCALE, TRANS_SCALE  # the action convention
from pivla.arm.rotations import yaw_of_quat
from pivla.envs.tabletop import tasks
from pivla.envs.tabletop.perturb import PerturbConfig, Perturber, parse_perturb
from pivla.envs.tabletop.scene import CAB_HALF_W, asset_files, scene_xml
from pivla.envs.tabletop.servo import ServoConfig, ServoModel
from pivla.envs.twin import MujocoTwin, check_twin_args, object_handles, observation_space

PHYSICS_DT = 0.002
SUBSTEPS = int(round(1.0 / (CONTROL_HZ * PHYSICS_DT)))
WORKSPACE = np.array([[0.05, -0.28, 0.005], [0.32, 0.28, 0.30]])  # tool-centre box (m)
CAMERAS = ("agentview_rgb", "eye_in_hand_rgb")
_CAMERA_NAMES = {"agentview_rgb": "agentview", "eye_in_hand_rgb": "eye_in_hand"}
STAGES = ("reached", "grasped", "lifted", "placed")


class TabletopEnv(MujocoTwin):
    """One task of a suite; the model is built once and every reset only re-draws the state."""

    metadata = {"render_modes": ["rgb_array"], "render_fps": CONTROL_HZ}
    scene_camera = "agentview_rgb"

    def __init__(
        self,
        suite: str,
        task: int | str,
        *,
        seed: int | None = None,
        image_size: int = 96,
        realism: str = "ideal",
        perturb: str | PerturbConfig | None = None,
        cameras: tuple[str, ...] = CAMERAS,
        render: bool = True,
        paraphrase: bool = False,
        servo: ServoConfig | None = None,
        render_mode: str | None = None,
    ):
        check_twin_args("tabletop twin", realism, image_size, cameras, CAMERAS)
        self.suite = suite
        self.task = tasks.get_task(suite, task)
        self.task_index = tasks.get_suite(suite).index(self.task)
        self.image_size = int(image_size)
        self.realism = realism
        self.perturb = perturb if isinstance(perturb, PerturbConfig) else parse_perturb(perturb)
        self.cameras = tuple(cameras) if render else ()
        self.paraphrase = paraphrase
        self.servo_config = servo or ServoConfig()
        self.render_mode = render_mode

        xml = scene_xml(self.task, self.perturb.n_distractors, self.perturb.n_clutter)
        self.model = mujoco.MjModel.from_xml_string(xml, asset_files())
        self.model.opt.timestep = PHYSICS_DT
        self.data = mujoco.MjData(self.model)
        self.kin = arm.Kinematics()
        m = self.model
        self._arm_qadr = np.array([m.jnt_qposadr[m.joint(n).id] for n in arm.JOINT_NAMES])
        self._arm_act = np.array([m.actuator(n).id for n in arm.JOINT_NAMES])
        self._finger_qadr = np.array([m.jnt_qposadr[m.joint(n).id] for n in arm.GRIPPER_JOINTS])
        self._finger_act = np.array([m.actuator(n).id for n in arm.GRIPPER_JOINTS])
        self._finger_geoms = [m.geom(m.body(n).geomadr[0]).id for n in arm.GRIPPER_JOINTS]
        self._ee_site = m.site(arm.EE_SITE).id
        self._obj = object_handles(m, self.task.objects)
        if self.task.drawer:
            self._drawer_qadr = m.jnt_qposadr[m.joint("drawer").id]
            self._handle_geoms = {m.geom(g).id for g in ("handle", "handle_post_l", "handle_post_r")}
        protected = [np.array(tasks.OBJECTS[o].rgba) for o in self.task.objects]
        self.perturber = Perturber(m, self.perturb, protected)
        self.camera_ids = {c: m.camera(_CAMERA_NAMES[c]).id for c in CAMERAS}
        vectors = {"ee_pos": 3, "ee_ori": 3, "gripper_states": 2, "joint_states": 6}
        self.observation_space = observation_space(self.cameras, self.image_size, vectors)
        self.action_space = gymnasium.spaces.Box(-1.0, 1.0, (7,), np.float32)
        self.np_random, _ = gymnasium.utils.seeding.np_random(seed)
        self.instruction = self.task.instruction
        self.q_cmd = arm.home_q()
        self.servo: ServoModel | None = None
        self.layout: dict = {}
        self._steps = 0
        self._stages = np.zeros((len(self.task.goals), len(STAGES)), bool)
        self._drawer_start = 0.0

    # ----------------------------------------------------------------------------------------------- reset
    def reset(self, *, seed: int | None = None, options: dict | None = None) -> tuple[dict, dict]:
        """New episode. The episode seed (given, or drawn from the env's generator) fixes everything."""
        rng_task, rng_perturb, rng_servo, rng_lang = self.draw_episode(seed, 4)
        m, d = self.model, self.data
        mujoco.mj_resetData(m, d)
        self.layout = tasks.sample_layout(self.task, rng_task)
        for name, (x, y, yaw) in self.layout["objects"].items():
            qadr = self._obj[name][0]
            d.qpos[qadr : qadr + 3] = [x, y, tasks.OBJECTS[name].rest_z]
            d.qpos[qadr + 3 : qadr + 7] = [np.cos(yaw / 2), 0.0, 0.0, np.sin(yaw / 2)]
        if self.task.drawer:
            d.qpos[self._drawer_qadr] = self.layout["drawer"]
            m.body("cabinet").pos[1] = self.layout["cabinet_y"]
        start_pos = arm.HOME_POSE[0] + rng_task.uniform([-0.015, -0.015, -0.01], [0.015, 0.015, 0.01])
        start_euler = np.array([0.0, 0.0, rng_task.uniform(-0.1, 0.1)])
        self.q_cmd, _, _ = self.kin.solve_ik(start_pos, start_euler, arm.home_q())
        d.qpos[self._arm_qadr] = self.q_cmd
        d.qpos[self._finger_qadr] = arm.GRIPPER_OPEN
        d.ctrl[self._arm_act] = self.q_cmd
        d.ctrl[self._finger_act] = arm.GRIPPER_OPEN
        self.servo = None
        if self.realism == "servo":
            self.servo = ServoModel(self.servo_config, 6, 1.0 / CONTROL_HZ, rng_servo)
            self.servo.reset(self.q_cmd)
        keep_out = [np.array(xy[:2]) for xy in self.layout["objects"].values()]
        keep_out += [tasks.move_target(self.layout["objects"][g.obj][:2], g.direction)
                     for g in self.task.goals if g.kind == "move"]
        if self.task.drawer:
            cy = self.layout["cabinet_y"]
            keep_out += [np.array([x, cy + dy]) for x in (0.14, 0.2, 0.27, 0.33) for dy in (-CAB_HALF_W, 0, CAB_HALF_W)]
        self.perturber.reset(d, rng_perturb, keep_out)
        mujoco.mj_forward(m, d)
        mujoco.mj_step(m, d, nstep=SUBSTEPS)  # let objects settle into their contacts
        self.instruction = (
            str(rng_lang.choice(self.task.paraphrases)) if self.paraphrase and self.task.paraphrases
            else self.task.instruction
        )
        self._steps = 0
        self._stages[:] = False
        if self.task.drawer:
            self._drawer_start = float(d.qpos[self._drawer_qadr])
        self._initial = {n: self._object_pos(n).copy() for n in self.task.objects}
        success, _ = self._evaluate()
        info = {"success": success, "episode_seed": self.episode_seed, "instruction": self.instruction}
        return self._observation(), info

    # ------------------------------------------------------------------------------------------------ step
    def step(self, action: np.ndarray) -> tuple[dict, float, bool, bool, dict]:
        a = np.asarray(action, dtype=np.float64)
        if a.shape != (7,):
            raise ValueError(f"action must have shape (7,), got {a.shape}")
        if not np.all(np.isfinite(a)):
            raise ValueError(f"action contains NaN or inf: {a}")
        if self.episode_seed is None:
            raise RuntimeError("call reset() before step()")
        a = np.clip(a, -1.0, 1.0)
        pos, mat = self.kin.fk_mat(self.q_cmd)
        target_pos = np.clip(pos + a[:3] * TRANS_SCALE, WORKSPACE[0], WORKSPACE[1])
        target_mat = arm.euler_to_mat(a[3:6] * ROT_SCALE) @ mat
        q = self.q_cmd
        for _ in range(IK_ITERATIONS):
            q = self.kin.ik_step(q, target_pos, target_mat)
            pos_err, rot_err = self.kin.pose_error(q, target_pos, target_mat)
            if pos_err < 2e-4 and rot_err < 2e-3:
                break
        self.q_cmd = q
        d = self.data
        d.ctrl[self._arm_act] = self.servo.command(q) if self.servo is not None else q
        d.ctrl[self._finger_act] = arm.GRIPPER_OPEN * (1.0 - a[6]) / 2.0
        for event in self.perturber.step(d, 1.0 / CONTROL_HZ):
            if event["kind"] == "displace_object":  # the task is judged from where the object now starts
                self._initial[event["object"]] = self._initial[event["object"]] + np.asarray(event["shift"])
        mujoco.mj_step(self.model, d, nstep=SUBSTEPS)
        self._steps += 1

        before = self._stages.sum()
        success, stages = self._evaluate()
        self._stages |= stages
        if success:
            self._stages[:] = True
        reward = float(self._stages.sum() - before) * 0.25 / len(self.task.goals)
        truncated = self._steps >= self.task.max_steps and not success
        info = {
            "success": success,
            "stages": {s: bool(self._stages[:, i].all()) for i, s in enumerate(STAGES)},
            "stage_progress": float(self._stages.mean()),
            "step": self._steps,
            "perturb_events": list(self.perturber.events),
        }
        return self._observation(), reward, success, truncated, info

    # ----------------------------------------------------------------------------------------- observation
    def _observation(self) -> dict[str, Any]:
        d = self.data
        obs: dict[str, Any] = self._render_all()
        obs["ee_pos"] = d.site_xpos[self._ee_site].astype(np.float32)
        obs["ee_ori"] = arm.mat_to_euler(d.site_xmat[self._ee_site]).astype(np.float32)
        obs["gripper_states"] = d.qpos[self._finger_qadr].astype(np.float32)
        obs["joint_states"] = d.qpos[self._arm_qadr].astype(np.float32)
        obs["instruction"] = self.instruction
        return obs

    # ------------------------------------------------------------------------------------ privileged state
    def _object_pos(self, name: str) -> np.ndarray:
        return self.data.xpos[self._obj[name][3]]

    def _touching(self, geoms: set[int]) -> tuple[bool, bool]:
        """Whether the left / right finger touch any geom of ``geoms``."""
        d = self.data
        pairs = d.contact.geom[: d.ncon]
        left = right = False
        for g1, g2 in pairs:
            other = g2 if g1 in self._finger_geoms else g1 if g2 in self._finger_geoms else None
            if other is None or other not in geoms:
                continue
            finger = g1 if other == g2 else g2
            left |= finger == self._finger_geoms[0]
            right |= finger == self._finger_geoms[1]
        return left, right

    def privileged_state(self) -> dict[str, Any]:
        """Simulator truth for the scripted expert (never part of the observation)."""
        d = self.data
        state: dict[str, Any] = {
            "ee_pos": d.site_xpos[self._ee_site].copy(),
            "ee_mat": d.site_xmat[self._ee_site].reshape(3, 3).copy(),
            "cmd_pos": self.kin.fk_mat(self.q_cmd)[0],
            "gripper": d.qpos[self._finger_qadr].copy(),
            "objects": {},
            "initial": {n: p.copy() for n, p in self._initial.items()},
        }
        for name, (_qadr, _, geom, body) in self._obj.items():
            state["objects"][name] = {
                "pos": d.xpos[body].copy(),
                "yaw": yaw_of_quat(d.xquat[body]),
                "grasped": all(self._touching({geom})),
            }
        if self.task.drawer:
            opening = float(d.qpos[self._drawer_qadr])
            state["drawer"] = opening
            state["handle_pos"] = d.geom_xpos[self.model.geom("handle").id].copy()
            state["handle_grasped"] = all(self._touching(self._handle_geoms))
        return state

    def _evaluate(self) -> tuple[bool, np.ndarray]:
        """(success, stages reached now) from the simulator state; perturbations never enter here."""
        d = self.data
        stages = np.zeros((len(self.task.goals), len(STAGES)), bool)
        ee = d.site_xpos[self._ee_site]
        done = []
        for gi, goal in enumerate(self.task.goals):
            if goal.kind in ("drawer_open", "drawer_close"):
                opening = float(d.qpos[self._drawer_qadr])
                handle = d.geom_xpos[self.model.geom("handle").id]
                grasped = any(self._touching(self._handle_geoms))
                if goal.kind == "drawer_open":
                    moved = opening > tasks.DRAWER_OPEN_SUCCESS / 2
                    ok = opening >= tasks.DRAWER_OPEN_SUCCESS
                else:
                    moved = opening < self._drawer_start / 2
                    ok = opening <= tasks.DRAWER_CLOSED_SUCCESS
                stages[gi] = [np.linalg.norm(ee - handle) < 0.03, grasped, moved, ok]
                done.append(ok)
                continue
            qadr, dadr, geom, body = self._obj[goal.obj]
            pos = d.xpos[body]
            spec = tasks.OBJECTS[goal.obj]
            touch = self._touching({geom})
            grasped = all(touch)
            resting = np.linalg.norm(d.qvel[dadr : dadr + 3]) < 0.05 and not any(touch)
            if goal.kind == "move":
                placed = tasks.moved_enough(self._initial[goal.obj][:2], pos[:2], goal.direction)
                ok = placed and resting and pos[2] < spec.rest_z + 0.006
            else:  # stack
                base = self._object_pos(goal.onto)
                height = tasks.OBJECTS[goal.onto].size[2] + spec.size[2]
                ok = (
                    np.linalg.norm(pos[:2] - base[:2]) < tasks.OBJECTS[goal.onto].size[0]
                    and abs(pos[2] - base[2] - height) < 0.006
                    and resting
                )
            lifted = grasped and pos[2] > spec.rest_z + 0.02
            stages[gi] = [np.linalg.norm(ee - pos) < 0.025, grasped, lifted, ok]
            done.append(ok)
        return bool(all(done)), stages

