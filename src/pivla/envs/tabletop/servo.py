"""Hobby-servo realism: what happens between a joint command and the joint's position setpoint.

An MG996R-class servo ignores command changes smaller than its deadband, its gear train has backlash
(the horn lags the motor by up to half the play, on the side it last moved from), its potentiometer
reading jitters, and it turns at a limited speed. Each effect is a pure step on (state, command); the
defaults make repeated moves of the twin to one target scatter by about the paper's 10 mm
(``repeatability_mm`` measures it; docs/results.md#servo-repeatability-on-the-twin has the figure).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class ServoConfig:
    deadband: float = np.deg2rad(1.3)  # commands closer than this to the current setpoint are ignored
    backlash: float = np.deg2rad(2.8)  # total gear play
    noise_std: float = np.deg2rad(0.4)  # setpoint jitter per control step
    max_speed: float = 5.2  # rad/s (MG996R: 0.2 s / 60 deg at 6 V)


class ServoModel:
    """Deadband, speed limit, noise and backlash applied to joint commands, one control step at a time."""

    def __init__(self, config: ServoConfig, n_joints: int, dt: float, rng: np.random.Generator):
        self.config = config
        self.dt = dt
        self.rng = rng
        self.setpoint = np.zeros(n_joints)
        self.output = np.zeros(n_joints)

    def reset(self, q: np.ndarray) -> None:
        """Start at rest at ``q`` with the gear play centred (as after a calibration)."""
        self.setpoint = np.array(q, dtype=float)
        self.output = np.array(q, dtype=float)

    def command(self, q_cmd: np.ndarray) -> np.ndarray:
        """The joint position the horn is driven to for this control step."""
        cfg = self.config
        delta = np.asarray(q_cmd, float) - self.setpoint
        delta[np.abs(delta) < cfg.deadband] = 0.0
        step = cfg.max_speed * self.dt
        self.setpoint = self.setpoint + np.clip(delta, -step, step)
        motor = self.setpoint + self.rng.normal(0.0, cfg.noise_std, self.setpoint.shape)
        half = cfg.backlash / 2
        self.output = np.clip(self.output, motor - half, motor + half)
        return self.output.copy()
