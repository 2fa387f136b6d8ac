"""``pivla report`` lives in :mod:`pivla.experiments`: :mod:`pivla.experiments.report` over a directory of
evaluations, :func:`pivla.experiments.studies.write_report` for whichever study wrote a directory. This module
keeps the name the README's command table cites; it holds no code of its own."""

from pivla.experiments.report import write_report

__all__ = ["write_report"]
