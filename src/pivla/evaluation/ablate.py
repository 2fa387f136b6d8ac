"""``pivla ablate`` is a study of :mod:`pivla.experiments`: :mod:`pivla.experiments.studies.ablate`. This module
keeps the name the README's command table cites; it holds no code of its own."""

from pivla.experiments.studies.ablate import AblationConfig, run_ablation

__all__ = ["AblationConfig", "run_ablation"]
