"""STS3215 realism for the SO-101 twin: what the arm's six Feetech STS3215 bus servos do with a goal position.

With ``realism="ideal"`` the twin's joints are the MJCF's ``<position>`` actuators (kp 17.8 N m/rad, +-3.35 N m)
and a goal is used as given. With ``realism="servo"`` every goal goes through what the servo firmware does,
one physics step (2 ms) at a time:

- **resolution**: a goal is written in encoder steps, 4096 per turn (0.088 deg), and the present position the
  firmware regulates on and the host reads back (the observation's ``state``) is the 12-bit magnetic encoder's
  reading, rounded to a step;
- **speed cap**: the firmware moves its internal setpoint towards the goal in a trapezoidal profile, at most the
  no-load speed and LeRobot's acceleration setting (``Acceleration`` = 254, register 41, in units of
  100 steps/s^2);
- **position loop**: torque = kp x (setpoint - present position), kp for LeRobot's P coefficient 16 (register 21;
  the firmware default is 32), clipped to the stall torque, the gripper to half of it (LeRobot writes
  ``Max_Torque_Limit`` = 500 of 1000 to the gripper so that it does not burn out holding an object);
- **deadband**: no torque while the setpoint is within the dead zone of the present position (registers 26/27,
  CW/CCW dead zone, default 1 step), so a joint comes to rest anywhere within +-1 step of its goal, or sags
  further under load until the loop's torque holds it.

Datasheet and control-table figures used (Feetech STS3215, the SO-101 follower's 7.4 V, 1:345 version, C001):
stall torque 19.5 kg cm (1.91 N m) at 7.4 V; no-load speed 0.222 s/60 deg (45 rpm, 4.72 rad/s) at 7.4 V; 12-bit
magnetic encoder, 4096 steps/turn; dead zone 1 step (registers 26/27); acceleration unit 100 steps/s^2
(register 41). ``ServoConfig.c018()`` gives the 12 V, 30 kg cm version (SO-101 "Pro" kits), 0.133 s/60 deg.
The proportional gain is in no datasheet: the MJCF's kp, 17.8 N m/rad, sits in its "sts3215" class, whose
parameters upstream took from the Open Duck Mini project (NOTICE), with a comment that LeRobot's Kp = 16 would
need an identification of its own. Assuming the firmware's default P = 32 there and a torque linear in P, LeRobot's
P = 16 gives 8.9 N m/rad. The joints' passive damping, friction loss and armature (0.60 N m s/rad, 0.052 N m,
0.028 kg m^2, same class) stay as the MJCF has them in both modes. Backlash (spec
<= 0.5 deg, about 1 deg measured on 12 V servos: TheRobotStudio/SO-ARM100 issue #134) is not modelled.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

STEPS_PER_TURN = 4096
RAD_PER_STEP = 2 * np.pi / STEPS_PER_TURN
KG_CM = 9.80665e-2  # N m per kg cm


def _speed(seconds_per_60deg: float) -> float:
    return float(np.pi / 3 / seconds_per_60deg)


@dataclass(frozen=True)
class ServoConfig:
    """One STS3215 as LeRobot configures it for an SO-101 follower."""

    stall_torque: float = 19.5 * KG_CM  # N m at 7.4 V (C001)
    max_speed: float = _speed(0.222)  # rad/s, no-load at 7.4 V
    acceleration: float = 254 * 100 * RAD_PER_STEP  # rad/s^2: LeRobot's Acceleration = 254 (x 100 steps/s^2)
    kp: float = 17.8 * 16 / 32  # N m/rad: the MJCF's gain, taken as P = 32's, at LeRobot's P = 16
    deadband_steps: int = 1  # CW/CCW dead zone (registers 26/27), factory default
    gripper_torque_share: float = 0.5  # LeRobot's Max_Torque_Limit 500 / 1000 on the gripper

    @classmethod
    def c018(cls) -> ServoConfig:
        """The 12 V, 30 kg cm STS3215 (C018/C047) of SO-101 Pro kits: 0.133 s/60 deg."""
        return replace(cls(), stall_torque=30.0 * KG_CM, max_speed=_speed(0.133))


def to_steps(q: np.ndarray) -> np.ndarray:
    """Joint angles (rad) -> encoder steps, rounded (the goal register and the present-position reading)."""
    return np.round(np.asarray(q, float) / RAD_PER_STEP)


class STS3215Bus:
    """The six servos of one arm: ``command(goal)`` once per control step, then ``torque(q)`` every physics step.

    Joints and goals are MJCF joint angles in radians (``pivla.envs.so101.arm.JOINTS`` order); the gripper is
    the last joint."""

    def __init__(self, config: ServoConfig, n_joints: int = 6):
        self.config = config
        self.n = n_joints
        limit = np.full(n_joints, config.stall_torque)
        limit[-1] *= config.gripper_torque_share
        self.torque_limit = limit
        self.goal = np.zeros(n_joints)
        self.setpoint = np.zeros(n_joints)
        self.velocity = np.zeros(n_joints)

    def reset(self, q: np.ndarray) -> None:
        """At rest at ``q``, goal = present position (as after torque on)."""
        self.goal = to_steps(q) * RAD_PER_STEP
        self.setpoint = self.goal.copy()
        self.velocity = np.zeros(self.n)

    def command(self, goal: np.ndarray) -> None:
        """A new goal position (sync write): quantised to the servo's steps."""
        self.goal = to_steps(goal) * RAD_PER_STEP

    def _profile(self, dt: float) -> None:
        """Advance the setpoint towards the goal: accelerate up to the speed cap, brake to stop at the goal."""
        cfg = self.config
        err = self.goal - self.setpoint
        # the fastest speed from which the profile can still stop at the goal
        stop = np.sqrt(2.0 * cfg.acceleration * np.abs(err))
        want = np.sign(err) * np.minimum(cfg.max_speed, stop)
        dv = np.clip(want - self.velocity, -cfg.acceleration * dt, cfg.acceleration * dt)
        self.velocity = self.velocity + dv
        step = self.velocity * dt
        arrive = np.abs(step) >= np.abs(err)
        self.setpoint = np.where(arrive, self.goal, self.setpoint + step)
        self.velocity = np.where(arrive, 0.0, self.velocity)

    def torque(self, q: np.ndarray, dt: float) -> np.ndarray:
        """Motor torques for one physics step of ``dt`` s at joint angles ``q`` (rad)."""
        self._profile(dt)
        present = to_steps(q)
        err = to_steps(self.setpoint) - present  # steps
        err[np.abs(err) <= self.config.deadband_steps] = 0.0
        return np.clip(self.config.kp * err * RAD_PER_STEP, -self.torque_limit, self.torque_limit)
