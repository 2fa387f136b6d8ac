"""A policy drives an arm in closed loop: ``pivla robot run``, callable from Python.

``run_policy`` takes an environment over the arm (``pivla.robot.env.RobotEnv`` for the pivla arm or its twin,
``pivla.robot.so101_env.SO101Env`` for the SO-101), an opened policy (a local run or a served one) and an
executor config, and runs ``episodes`` episodes, each with a fresh executor and seed ``seed + episode``.
Options of ``pivla.control.run_episode`` (``max_steps``, ``execution``, ``latency``, ...) pass through.
Every command the executor's actions become goes through the arm's safety layer inside the env; whatever
ends the loop (the last episode, an error, Ctrl-C), the arm is stopped (it holds where it is). The caller
opened the env and closes it (``pivla.robot.factory.open_rig`` gives one that closes arm and cameras).
"""

from __future__ import annotations

import logging
from typing import Any

from pivla.control import make_executor, run_episode
from pivla.control.asynchronous import ExecutionConfig
from pivla.control.executors import ExecutorConfig

log = logging.getLogger(__name__)


def run_policy(env: Any, policy: Any, executor: ExecutorConfig, episodes: int = 1, seed: int = 0,
               execution: ExecutionConfig | None = None, **episode_options: Any) -> list[dict]:
    """The summaries of ``episodes`` closed-loop episodes of ``policy`` on ``env`` (see the module doc).

    ``execution``: None or ``SyncConfig`` query and wait (the executor calls the policy directly);
    ``AsyncConfig`` runs the asynchronous loop of ``pivla.control.asynchronous`` on the wall clock (``latency``
    "real" unless given): each query runs on a worker thread while the arm executes the current chunk, paced at
    the env's control rate. A link that is lost (``RemotePolicy`` raises after its reconnection attempts) makes
    the arm hold once the chunk in execution has run its horizon, and it moves again when the link is back."""
    if execution is not None and execution.kind == "async":
        episode_options = {"latency": "real", **episode_options, "execution": execution}
    results = []
    try:
        for ep in range(episodes):
            result = run_episode(env, policy, make_executor(executor), seed=seed + ep, **episode_options)
            results.append(result.summary())
            log.info("episode %d: %s", ep, results[-1])
    finally:
        env.robot.stop()
    return results
