"""The twin benchmark's report: benchmark.md, benchmark.json and figures/*.png from the finished evaluations.

Each table is built as a value (``pivla.experiments.render.Table``: its cells, its records, the paired
comparisons behind its differences) by one function; ``write_benchmark_report`` puts them in order and renders
the markdown, the JSON and the charts from them. ``pivla report --dir`` on a benchmark directory calls it too,
so both print the same figures.
"""

from __future__ import annotations

import json
from collections.abc import Iterable
from pathlib import Path
from typing import Any

import numpy as np

from pivla.control.executors import CUTS
from pivla.evaluation.stats import format_difference, mcnemar_exact, percent_interval
from pivla.experiments import conditions
from pivla.experiments.layout import TwinLayout
from pivla.experiments.recipes import INCREMENTAL, Kind, Recipe
from pivla.experiments.render import Block, Chart, Curve, Lines, Panel, Table, draw, markdown
from pivla.experiments.results import ResultsStore
from pivla.experiments.studies.twin_config import (
    BASELINES,
    EXECUTORS,
    OTHER_SUITES,
    SENSITIVITY,
    TABLE6_VARIANTS,
    BenchmarkConfig,
    by_variant,
    headline_cells,
    of_kind,
    one,
    recipes,
    sensitivity_label,
    stored_config,
)
from pivla.io import atomic_write_bytes, atomic_write_json

Key = tuple[str, str, str]


class _Paired:
    """One table's paired comparisons: ``self(a, b)`` compares two keys and keeps the comparison as
    benchmark.json records it."""

    def __init__(self, res: ResultsStore, table: str):
        self.res, self.table, self.records = res, table, []

    def __call__(self, a: Key, b: Key) -> dict | None:
        c = self.res.compare(a, b)
        if c is not None:
            self.records.append({"table": self.table, "a": list(a), "b": list(b), **c})
        return c


def _fired(row: dict) -> bool:
    """Whether an episode's displacement or push moved something (level 0 records its step, moving nothing)."""
    return any(np.linalg.norm(ev.get("shift", ev.get("tool_shift", [0.0]))) > 0 for ev in row.get("perturb_events", []))


def _pct(r: dict | None) -> str:
    if r is None:
        return "not run"
    return f"{100 * r['rate']:.1f} {percent_interval(*r['ci95'])}"


def _diff(c: dict | None) -> str:
    return "-" if c is None else format_difference(c)


def _mean(values: list) -> float | None:
    vals = [v for v in values if v is not None]
    return float(np.mean(vals)) if vals else None


def _fmt(x: float | None) -> str:
    return "-" if x is None else f"{x:.2f}"


EXECUTOR_HEADER = ["condition", *EXECUTORS, *(f"AURD - {b}" for b in BASELINES)]


def _executor_rows(res: ResultsStore, vs: _Paired, policy: str, names: Iterable[str]) -> tuple[list, list]:
    """Per cell with any result: every executor's success and AURD against each baseline."""
    rows, recs = [], []
    for name in names:
        rates = {e: res.rate(policy, name, e) for e in EXECUTORS}
        if not any(rates.values()):
            continue
        diffs = {e: vs((policy, name, "aurd"), (policy, name, e)) for e in BASELINES}
        rows.append([name, *(_pct(rates[e]) for e in EXECUTORS), *(_diff(diffs[e]) for e in BASELINES)])
        recs.append({"cell": name, "policy": policy, "success": rates, "aurd_minus": diffs})
    return rows, recs


def _executor_table(res: ResultsStore, key: str, title: str, policy: str, names: Iterable[str]) -> Table:
    vs = _Paired(res, key)
    rows, recs = _executor_rows(res, vs, policy, names)
    return Table(EXECUTOR_HEADER, rows, title=title, key=key, records=recs, comparisons=vs.records)


def _table2(res: ResultsStore, headline: str) -> Table:
    grid = {e: res.task_rates(headline, "in_distribution", e) for e in EXECUTORS}
    tasks = sorted({t for g in grid.values() for t in g})
    return Table(["task", *EXECUTORS], [[t, *(_pct(grid[e].get(t)) for e in EXECUTORS)] for t in tasks],
                 title="Table 2: object x direction, in distribution", key="table2",
                 records=[{"task": t, **{e: grid[e].get(t) for e in EXECUTORS}} for t in tasks])


def _table3(res: ResultsStore, headline: str, seen: str) -> Table:
    vs = _Paired(res, "table3")
    rows, recs = _executor_rows(res, vs, headline, ["static_distractors", "dynamic_distractors", "unseen_env"])
    r2, c2 = _executor_rows(res, vs, seen, ["unseen_tasks"])
    return Table(EXECUTOR_HEADER, r2 + rows, title="Table 3: generalisation (unseen tasks: trained on pick_place_seen)",
                 key="table3", records=c2 + recs, comparisons=vs.records)


def _event_table(res: ResultsStore, event: str, headline: str, names: list[str]) -> Table:
    """Fig. 8 by level, with the episodes in which the event moved something, per executor (an event waits
    while it cannot land, and may come too late to fire)."""
    vs = _Paired(res, event)
    rows, recs = _executor_rows(res, vs, headline, names)
    for row, rec in zip(rows, recs):
        fired = [sum(_fired(r) for _, rows in res.rows(headline, rec["cell"], e) for r in rows) for e in EXECUTORS]
        rec["fired"] = dict(zip(EXECUTORS, fired))
        row.append(" / ".join(map(str, fired)))
    return Table([*EXECUTOR_HEADER, "fired (" + " / ".join(EXECUTORS) + ")"], rows,
                 title=f"Fig. 8: {event.replace('_', ' ')} mid-chunk, by level (cm)", key=event, records=recs,
                 comparisons=vs.records)


def _realism(res: ResultsStore, cfg: BenchmarkConfig, headline: str, hardest: str | None) -> Table:
    secondary = "ideal" if cfg.realism == "servo" else "servo"
    vs, rows, recs = _Paired(res, "realism"), [], []
    for c in ("in_distribution", hardest):
        if c is None:
            continue
        other = conditions.twin(c).with_realism(secondary).name
        for e in EXECUTORS:
            a, b = res.rate(headline, c, e), res.rate(headline, other, e)
            cmp = vs((headline, c, e), (headline, other, e))
            rows.append([c, e, _pct(a), _pct(b), _diff(cmp)])
            recs.append({"cell": c, "executor": e, cfg.realism: a, secondary: b, "difference": cmp})
    return Table(["condition", "executor", cfg.realism, secondary, f"{cfg.realism} - {secondary}"], rows,
                 title=f"Actuation: {cfg.realism} (headline) against {secondary}", key="realism", records=recs,
                 comparisons=vs.records)


def _ablation_tables(res: ResultsStore, rs: dict[str, Recipe], hardest: str) -> list[Table]:
    """Tables 4, 5 (trained variants, AURD and fixed), 6 (execution strategies) and 7 (incremental)."""
    policy, full = by_variant(rs), one(rs, Kind.HEADLINE)
    tables = []
    for key, title, variants in (("table4", "Table 4: action heads", ("full", "discrete_only", "continuous_only")),
                                 ("table5", "Table 5: loss terms", ("full", "no_sp", "no_rl", "il_only"))):
        vs, rows, recs = _Paired(res, key), [], []
        for v in variants:
            a, f = res.rate(policy[v], hardest, "aurd"), res.rate(policy[v], hardest, "fixed")
            d = None if v == "full" else vs((policy[v], hardest, "aurd"), (full, hardest, "aurd"))
            rows.append([v, _pct(a), _pct(f), _diff(d)])
            recs.append({"variant": v, "aurd": a, "fixed": f, "aurd_minus_full": d})
        tables.append(Table(["variant", "AURD", "fixed", "AURD - full"], rows, title=f"{title} ({hardest})", key=key,
                            records=recs, comparisons=vs.records))
    vs, rows, recs = _Paired(res, "table6"), [], []
    for label in TABLE6_VARIANTS:
        r = res.rate(full, hardest, label)
        d = None if label == "fixed" else vs((full, hardest, label), (full, hardest, "fixed"))
        rows.append([label, _pct(r), _diff(d)])
        recs.append({"executor": label, "success": r, "minus_fixed": d})
    tables.append(Table(["executor", "success", "- fixed"], rows,
                        title=f"Table 6: execution strategies of the full model ({hardest})", key="table6",
                        records=recs, comparisons=vs.records))
    vs, rows, recs, above = _Paired(res, "table7"), [], [], None
    for row, variant, executor in INCREMENTAL:
        key = (policy[variant], hardest, "fixed" if executor == "fixed" else "aurd")
        d = vs(key, above) if above else None
        rows.append([row, _pct(res.rate(*key)), _diff(d)])
        recs.append({"row": row, "success": res.rate(*key), "minus_row_above": d})
        above = key
    tables.append(Table(["configuration", "success", "- row above"], rows,
                        title=f"Table 7: components added one at a time ({hardest})", key="table7", records=recs,
                        comparisons=vs.records))
    return tables


def _failure_round(res: ResultsStore, rs: dict[str, Recipe], hardest: str, top: int) -> Table:
    """Success and the failure signals before (the headline recipe) and after training on the policy's own
    rollouts (the failure round)."""
    before_p, after_p = one(rs, Kind.HEADLINE), one(rs, Kind.FAILURE_ROUND)
    signal_keys = ("auroc_neg_v_min", "auroc_u_max", "v_failure_lead_steps_mean", "failure_lead_steps_mean")
    vs, rows, recs = _Paired(res, "failure_round"), [], []
    for cell in dict.fromkeys(("in_distribution", hardest, f"displace_object_{top}")):
        for e in ("aurd", "fixed"):
            before, after = res.rate(before_p, cell, e), res.rate(after_p, cell, e)
            d = vs((after_p, cell, e), (before_p, cell, e))
            signals = {}
            for p in (before_p, after_p):
                fps = [r.get("failure_prediction", {}) for r in res.results(p, cell, e)]
                signals[p] = {k: _mean([f.get(k) for f in fps]) for k in signal_keys}
            rows.append([cell, e, _pct(before), _pct(after), _diff(d),
                         *(f"{_fmt(signals[before_p][k])} -> {_fmt(signals[after_p][k])}"
                           for k in ("auroc_neg_v_min", "v_failure_lead_steps_mean", "auroc_u_max"))])
            recs.append({"cell": cell, "executor": e, "before": before, "after": after, "difference": d,
                         "signals": signals})
    return Table(["condition", "executor", "before", "after", "after - before", "V AUROC", "V lead (steps)", "U AUROC"],
                 rows, title="Failure round: trained again with the policy's own rollouts (before -> after)",
                 key="failure_round", records=recs, comparisons=vs.records)


def _sensitivity(res: ResultsStore, policy: str, hardest: str) -> tuple[Table, dict[str, list]]:
    """Fig. 16 (validation seeds): AURD's success with thresholds calibrated at each swept setting."""
    out, rows = {}, []
    for key, values in SENSITIVITY.items():
        rates = [res.rate(policy, hardest, sensitivity_label(key, v), split="validation") for v in values]
        out[key] = [{"value": v, "success": r} for v, r in zip(values, rates)]
        rows += [[key, f"{v:g}", _pct(r)] for v, r in zip(values, rates)]
    return Table(["setting", "value", "success"], rows,
                 title=f"Fig. 16: sensitivity of AURD (validation seeds, {hardest})", key="sensitivity",
                 records=[out]), out


def _demo_counts(res: ResultsStore, rs: dict[str, Recipe], cfg: BenchmarkConfig,
                 hardest: str) -> tuple[Table, dict[str, list]]:
    """Fig. 17: success against the number of demonstrations per task."""
    policies_by_n = ({rs[p].demos: p for p in of_kind(rs, Kind.DEMO_COUNT)}
                     | {cfg.train_episodes: one(rs, Kind.HEADLINE)})
    out, rows = {}, []
    for cell in dict.fromkeys(("in_distribution", hardest)):
        for e in ("aurd", "fixed"):
            pts = [{"demos": n, "success": res.rate(p, cell, e)} for n, p in sorted(policies_by_n.items())]
            out[f"{cell}/{e}"] = pts
            rows += [[cell, e, str(p["demos"]), _pct(p["success"])] for p in pts]
    return Table(["condition", "executor", "demos", "success"], rows,
                 title="Fig. 17: success against demonstrations per task", key="demo_counts", records=[out]), out


def _departures(res: ResultsStore, policy: str, names: Iterable[str]) -> Table:
    """Where AURD's wins and losses against the fixed horizon start, by its first cut, per condition and pooled."""
    groups = ("none", *CUTS)
    rows, recs, total = [], [], {g: [0, 0, 0] for g in groups}
    for name in names:
        dep = res.departures(policy, name)
        if dep is None:
            continue
        for g in groups:
            total[g] = [t + v for t, v in zip(total[g], dep[g].values())]
        rows.append([name, *(f"{dep[g]['episodes']}: {dep[g]['only_aurd']} / {dep[g]['only_fixed']}" for g in groups)])
        recs.append({"cell": name, **dep})
    if rows:
        rows.append(["all, exact McNemar p", *(f"{n}: {ia} / {ib} (p {mcnemar_exact(ia, ib):.2g})"
                                              for n, ia, ib in total.values())])
        recs.append({"cell": "all", **{g: {"episodes": n, "only_aurd": ia, "only_fixed": ib,
                                           "p_mcnemar": mcnemar_exact(ia, ib)} for g, (n, ia, ib) in total.items()}})
    return Table(["condition", "no cut", *(f"first cut: {g}" for g in CUTS)], rows,
                 title="Where AURD parts from the fixed horizon: episodes by AURD's first cut (episodes: only AURD "
                       "solved / only fixed solved)", key="departures", records=recs)


def _compute(res: ResultsStore, headline: str) -> Table:
    rows, recs = [], []
    for e in EXECUTORS:
        rs = res.results(headline, "in_distribution", e)
        q = [r.get("queries_per_100_steps") for r in rs if r.get("queries_per_100_steps") is not None]
        ms = [r.get("control_ms_per_step") for r in rs if r.get("control_ms_per_step") is not None]
        if rs:
            rows.append([e, f"{np.mean(q):.1f}" if q else "-", f"{np.median(ms):.2f}" if ms else "-"])
            recs.append({"executor": e, "queries_per_100_steps": float(np.mean(q)) if q else None,
                         "control_ms_per_step": float(np.median(ms)) if ms else None})
    return Table(["executor", "queries / 100 steps", "ms / step (median over seeds)"], rows,
                 title="Compute (in distribution): policy queries per 100 control steps, control time per step",
                 key="compute", records=recs)


def _charts(layout: TwinLayout, cm: Iterable[int], levels: dict, sens: dict, counts: dict) -> list[Chart]:
    """Fig. 8 per event, Fig. 16, Fig. 17; curves without results are left out, and charts without any."""
    charts = [Chart(layout.figure(name), (5, 3.5),
                    [Panel(f"{name.replace('_', ' ')} (cm)", "success (%)",
                           [Curve(e, list(cm), rates) for e, rates in per_exec.items()], legend=0)])
              for name, per_exec in levels.items()]
    charts.append(Chart(layout.figure("sensitivity"), (4 * len(sens), 3.2),
                        [Panel(key, "validation success (%)",
                               [Curve("AURD", [p["value"] for p in pts], [p["success"] for p in pts])])
                         for key, pts in sens.items()]))
    charts.append(Chart(layout.figure("demo_counts"), (5, 3.5),
                        [Panel("demonstrations per task", "success (%)",
                               [Curve(key, [p["demos"] for p in pts], [p["success"] for p in pts])
                                for key, pts in counts.items()], legend=7)]))
    return [c for c in charts if c.measured()]


def write_benchmark_report(out: str | Path) -> Path:
    """benchmark.md, benchmark.json and figures/*.png from the finished evaluations (``pivla report --dir`` on a
    benchmark directory calls this too, so both print the same figures)."""
    layout = TwinLayout(Path(out))
    stored = json.loads(layout.config.read_text())
    cfg = stored_config(stored)
    rs = recipes(cfg)
    decisions = json.loads(layout.decisions.read_text()) if layout.decisions.exists() else {}
    res = ResultsStore(layout)
    hardest = decisions.get("hardest", {}).get("cell")
    headline = decisions.get("failure_round", {}).get("headline", one(rs, Kind.HEADLINE))
    cells = headline_cells(cfg)
    top = max(cfg.levels)
    tables = [_executor_table(res, "headline", "Every condition, every executor (pick_place)", headline, cells),
              _table2(res, headline), _table3(res, headline, one(rs, Kind.SEEN_TASKS)),
              _executor_table(res, "suites",
                              "Long-horizon and the other suites (one policy for long, drawer and stack)",
                              one(rs, Kind.OTHER_SUITES),
                              [*OTHER_SUITES, conditions.event("displace_object", top, suite="long").name])]
    levels: dict[str, dict[str, list]] = {}
    for event in conditions.EVENTS:
        names = [conditions.event(event, lv).name for lv in cfg.levels]
        tables.append(_event_table(res, event, headline, names))
        levels[event] = {e: [res.rate(headline, n, e) for n in names] for e in EXECUTORS}
    tables.append(_realism(res, cfg, headline, hardest))
    sens: dict[str, list] = {}
    counts: dict[str, list] = {}
    if hardest:
        tables += _ablation_tables(res, rs, hardest)
        tables.append(_failure_round(res, rs, hardest, top))
        sens_table, sens = _sensitivity(res, headline, hardest)
        counts_table, counts = _demo_counts(res, rs, cfg, hardest)
        tables += [sens_table, counts_table]
    tables += [_departures(res, headline, cells), _compute(res, headline)]
    timings = json.loads(layout.timings.read_text()) if layout.timings.exists() else {}
    charts = _charts(layout, cfg.levels, levels, sens, counts)
    for chart in charts:
        draw(chart, layout.root)
    n_seeds = len(res.seeds)
    blocks: list[Block] = [
        f"# Twin benchmark ({cfg.realism} actuation; {n_seeds} training seed{'s' * (n_seeds != 1)} pooled)",
        ("Success in % with Wilson 95% intervals, pooled over training seeds; differences in points, paired episode "
         "by episode within each seed (Newcombe's method 10 95% interval, exact McNemar p). Test seeds only; every "
         "decision was taken on validation seeds (decisions.json)."),
        f"Headline policy: `{headline}`; hardest condition (lowest mean baseline success on validation): "
        f"`{hardest}`.",
        *(t for t in tables if t.rows),
        "## Seeds",
        ("Demonstrations and the failure round's rollouts: the train family; validation rollouts, calibration, the "
         "hardest condition, the failure round's adoption and Fig. 16: the validation family; every figure above: "
         "the test family (pivla.envs.seeds).")]
    if timings:
        blocks += ["## Wall time (s)", ", ".join(f"{k} {v:.0f}" for k, v in timings.items())]
    blocks.append(Lines(tuple(f"![{Path(c.path).stem}]({c.path})" for c in charts)))
    data: dict[str, Any] = {"config": stored, "decisions": decisions, "seeds": res.seeds, "headline_policy": headline,
                            "hardest_condition": hardest, "tables": {t.key: t.records for t in tables},
                            "comparisons": [c for t in tables for c in t.comparisons], "timings_s": timings,
                            "figures": [c.path for c in charts]}
    atomic_write_json(layout.report_json, data)
    atomic_write_bytes(layout.report_md, markdown(blocks).encode())
    return layout.report_md
