"""Closed-loop control: AURD (paper Eqs. 12-14, Algorithm 1), the baselines, and the episode loop.

The math is in :mod:`pivla.control.math` as pure functions; executors in :mod:`pivla.control.executors`.
"""

from pivla.control.executors import EXECUTOR_REGISTRY, make_executor
from pivla.control.math import (
    action_uncertainty,
    adahorizon,
    composite_uncertainty,
    decide_horizon,
    dequantize,
    ensemble_weights,
    prediction_uncertainty,
    step_event,
    surprise,
    temporal_ensemble,
)
from pivla.control.runner import EpisodeResult, ExecutorActor, run_episode

__all__ = [
    "EXECUTOR_REGISTRY", "EpisodeResult", "ExecutorActor", "action_uncertainty", "adahorizon", "composite_uncertainty",
    "decide_horizon", "dequantize", "ensemble_weights", "make_executor", "prediction_uncertainty", "run_episode",
    "step_event", "surprise", "temporal_ensemble",
]
