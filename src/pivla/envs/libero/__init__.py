"""LIBERO (and the LIBERO-PRO robustness suites) behind pivla's env contract; needs the ``libero`` extra.

Importing this package is cheap; the LIBERO stack (robosuite, ~2 GB of assets) is imported on first use
and raises ImportError naming the fix when the extra is missing.
"""

from pivla.envs.libero._backend import INSTALL_HINT, available
from pivla.envs.libero.env import available_suites, list_tasks, make_env
from pivla.envs.libero.expert import ExpertConfig, expert_actor

__all__ = ["INSTALL_HINT", "ExpertConfig", "available", "available_suites", "expert_actor", "list_tasks", "make_env"]
