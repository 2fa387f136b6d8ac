"""LIBERO (and the LIBERO-PRO robustness suites) behind pivla's env contract; needs the ``libero`` extra.

Importing this package is cheap; the LIBERO stack (robosuite, ~2 GB of assets) is imported on first use
and raises ImportError naming the fix when the extra is missing.
"""

from __future__ import annotations

from typing import Any

from pivla.envs.libero._backend import INSTALL_HINT, available


def list_tasks(suite: str) -> list:
    from pivla.envs.libero.env import list_tasks as _list_tasks

    return _list_tasks(suite)


def make_env(suite: str, task: int | str, **kwargs: Any) -> Any:
    from pivla.envs.libero.env import make_env as _make_env

    return _make_env(suite, task, **kwargs)


def available_suites() -> tuple[str, ...]:
    from pivla.envs.libero.env import available_suites as _available_suites

    return _available_suites()


def expert_actor(suite: str, task: int | str, config: Any = None) -> Any:
    """The scripted expert of one task (``pivla.envs.libero.expert.expert_actor``; ``config`` an ExpertConfig)."""
    from pivla.envs.libero.expert import ExpertConfig
    from pivla.envs.libero.expert import expert_actor as _expert_actor

    return _expert_actor(suite, task, config or ExpertConfig())


__all__ = ["INSTALL_HINT", "available", "available_suites", "expert_actor", "list_tasks", "make_env"]
