"""The studies: ``pivla demo`` (:mod:`.demo`), ``pivla benchmark twin`` (:mod:`.twin`), ``pivla ablate``
(:mod:`.ablate`) and ``pivla libero run`` (:mod:`.libero`), each a plan and a run order over the shared parts
of :mod:`pivla.experiments`."""

from __future__ import annotations

from pathlib import Path


def write_report(root: str | Path) -> Path:
    """The report of the study that wrote ``root``: a twin benchmark's tables (benchmark.md, the same files
    ``pivla benchmark twin`` writes) where its layout is found, else report.md over every evaluation below it."""
    from pivla.experiments.layout import TwinLayout

    if TwinLayout.holds(Path(root)):
        from pivla.experiments.studies.twin_report import write_benchmark_report

        return write_benchmark_report(root)
    from pivla.experiments.report import write_report as write_evaluations_report

    return write_evaluations_report(root)
