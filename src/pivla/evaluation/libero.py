"""``pivla libero run`` is a study of :mod:`pivla.experiments`: :mod:`pivla.experiments.studies.libero`. This
module keeps the name the README's command table cites; it holds no code of its own."""

from pivla.experiments.studies.libero import LiberoRunConfig, run_libero, write_libero_report

__all__ = ["LiberoRunConfig", "run_libero", "write_libero_report"]
