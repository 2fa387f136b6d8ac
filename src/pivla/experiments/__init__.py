"""The parts every study shares, and the studies built from them.

A *study* (``pivla demo``, ``pivla benchmark twin``, ``pivla ablate``, ``pivla libero run``) is a plan and a run
order over these parts:

- :mod:`~pivla.experiments.layout`: run layouts, the one place where a run directory's paths are spelled;
- :mod:`~pivla.experiments.conditions`: the registry of evaluation conditions (cells), twin and LIBERO;
- :mod:`~pivla.experiments.recipes`: typed policy recipes (the kind is a field, not a name prefix), the loss and
  head variants, the execution variants and the validated training recipe;
- :mod:`~pivla.experiments.plan`: a plan, a list of evaluations that share their settings;
- :mod:`~pivla.experiments.stages`: idempotent stages (collect, train, calibrate, evaluate), each skipped when
  its output exists, and the wall time per stage of a resumable run;
- :mod:`~pivla.experiments.results`: the results store (rates pooled over training seeds, paired comparisons);
- :mod:`~pivla.experiments.render`: tables and charts as values, the one renderer of markdown and figures;
- :mod:`~pivla.experiments.report`: ``pivla report`` on a directory of evaluations;
- :mod:`~pivla.experiments.studies`: the four studies, and the report of whichever study wrote a directory.
"""
