"""A tiny synthetic dataset in the LIBERO layout, for tests and benchmarks that must not need a simulator.

A coloured square moves across the agent-view image towards a goal given by the instruction; the action
is the (normalised) velocity that gets it there, so the mapping from pixels + words to actions is learnable.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from pivla.data.episode import Episode
from pivla.data.hdf5 import write_episodes

GOALS = {"left": (-1.0, 0.0), "right": (1.0, 0.0), "up": (0.0, -1.0), "down": (0.0, 1.0)}


def synthetic_episode(rng: np.random.Generator, goal: str, T: int = 20, size: int = 32,
                      success: bool = True) -> Episode:
    pos = rng.uniform(0.3, 0.7, size=2)
    direction = np.asarray(GOALS[goal])
    frames, wrist, actions, ee = [], [], [], []
    for t in range(T):
        img = np.full((size, size, 3), 40, np.uint8)
        px = np.clip((pos * size).astype(int), 2, size - 3)
        img[px[1] - 2 : px[1] + 2, px[0] - 2 : px[0] + 2] = (220, 60, 30)
        frames.append(img)
        wrist.append(img[::-1].copy())
        step = 0.02 * direction + rng.normal(0, 0.002, 2)
        grip = 1.0 if t > T // 2 else -1.0
        actions.append([step[0], step[1], 0.0, 0.0, 0.0, 0.01 * t / T, grip])
        ee.append([pos[0], pos[1], 0.1])
        pos = np.clip(pos + step, 0.05, 0.95)
    ee = np.asarray(ee, np.float32)
    rewards = np.zeros(T, np.float32)
    rewards[-1] = 1.0 if success else 0.0
    return Episode(
        actions=np.asarray(actions, np.float32),
        obs={
            "agentview_rgb": np.stack(frames),
            "eye_in_hand_rgb": np.stack(wrist),
            "ee_pos": ee,
            "ee_ori": np.zeros((T, 3), np.float32),
            "gripper_states": np.stack([np.asarray(actions)[:, 6] * 0.02] * 2, axis=1).astype(np.float32),
            "joint_states": np.zeros((T, 6), np.float32),
        },
        instruction=f"move the square {goal}",
        rewards=rewards,
        success=success,
        source="expert" if success else "rollout",
    )


def make_synthetic_dataset(out: str | Path, episodes_per_goal: int = 4, T: int = 20, size: int = 32,
                           seed: int = 0, failures: int = 0) -> Path:
    """One file per goal (as LIBERO has one per task); ``failures`` adds failed rollouts per goal."""
    out = Path(out)
    rng = np.random.default_rng(seed)
    for goal in GOALS:
        eps = [synthetic_episode(rng, goal, T, size) for _ in range(episodes_per_goal)]
        eps += [synthetic_episode(rng, goal, T, size, success=False) for _ in range(failures)]
        write_episodes(out / f"move_{goal}_demo.hdf5", eps)
    return out
