"""The twin benchmark (``pivla benchmark twin``) is a study of :mod:`pivla.experiments`: its run order in
:mod:`pivla.experiments.studies.twin`, its report in :mod:`pivla.experiments.studies.twin_report`. This module
keeps the name the README's command table cites; it holds no code of its own."""

from pivla.experiments.studies.twin import BenchmarkConfig, run_benchmark, write_benchmark_report

__all__ = ["BenchmarkConfig", "run_benchmark", "write_benchmark_report"]
