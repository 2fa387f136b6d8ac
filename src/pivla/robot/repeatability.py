"""Repeatability: return to the same targets from different directions and measure the scatter.

Targets are random tool poses in front of the arm; each repeat visits every target, going through home
in between, so backlash and deadband act as they do in use. The position used is the arm's *measured*
tool centre: on the twin its physical pose (``measured_ee_pos``); on the real arm, where servos report
nothing, the commanded pose (so the real figure needs an external measurement; docs/robot.md).
"""

from __future__ import annotations

import numpy as np

from pivla import arm


def run_repeatability(robot, repeats: int, n_targets: int, seed: int = 0) -> dict:
    rng = np.random.default_rng(seed)
    home_pos, home_ori = arm.HOME_POSE
    targets = []
    while len(targets) < n_targets:
        pos = home_pos + rng.uniform([-0.04, -0.08, -0.10], [0.10, 0.08, 0.02])
        q, err, _ = robot.kinematics.solve_ik(pos, home_ori, robot.home_q, iterations=100)
        if err < 1e-3:
            targets.append(q)
    measure = getattr(robot, "measured_ee_pos", None)
    reached = np.zeros((n_targets, repeats, 3))
    for r in range(repeats):
        for t, q in enumerate(targets):
            robot.home()
            st = robot.move_to(q, 1.0, settle_s=0.0)
            if hasattr(robot, "wait"):
                robot.wait(5)  # let the physical arm settle (twin)
            reached[t, r] = measure() if measure else st.ee_pos
    dev = np.linalg.norm(reached - reached.mean(axis=1, keepdims=True), axis=2) * 1000
    return {"targets": n_targets, "repeats": repeats, "measured": "physical" if measure else "commanded",
            "scatter_mm_mean": round(float(dev.mean()), 2), "scatter_mm_p95": round(float(np.percentile(dev, 95)), 2),
            "scatter_mm_max": round(float(dev.max()), 2),
            "per_target_mm_max": [round(float(x), 2) for x in dev.max(axis=1)]}
