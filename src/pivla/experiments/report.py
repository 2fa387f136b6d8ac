"""``pivla report DIR``: report.md with the paper's plots, from every evaluation found below DIR.

An evaluation is a directory with ``results.json`` and ``episodes.jsonl`` (written by ``pivla eval``);
its parent directory names the condition (e.g. ``eval/unseen_env/aurd``). ``pivla demo`` writes its report
this way too.
"""

from __future__ import annotations

import json
import logging
import re
from pathlib import Path

import numpy as np

from pivla.evaluation.runner import acting_rows, load_rows
from pivla.evaluation.stats import format_difference
from pivla.experiments.layout import EPISODES, EvaluationsLayout
from pivla.experiments.render import Block, Table, new_figure, save_figure, write_markdown
from pivla.experiments.results import ResultsStore

log = logging.getLogger(__name__)


def find_evaluations(root: Path) -> dict[tuple[str, str], Path]:
    """(condition, executor) -> evaluation directory, test evaluations only (validation rollouts that
    thresholds were calibrated on are not results)."""
    return EvaluationsLayout(Path(root)).found


def fmt(x: float | None, digits: int = 2) -> str:
    return "-" if x is None else f"{x:.{digits}f}"


def _execution(execution: dict | None) -> str:
    """An evaluation's execution mode in a few words: sync, or async with its threshold and seam."""
    if not execution or execution.get("name") != "async":
        return "sync"
    return f"async g={execution['threshold']} {execution['seam']}"


def _level(condition: str) -> int | None:
    m = re.fullmatch(r"distraction_level_(\d+)", condition)
    return int(m.group(1)) if m else None


def plot_timeline(row: dict, calib: dict | None, path: Path) -> None:
    """Paper Fig. 15: U, U_act, U_pred over one episode, thresholds, and where AURD replanned, pruned or
    paused; a cut plan's untrusted step (never executed, so not on the curves) is marked by its U, and the
    steps of plans AURD committed to after a cut (run unchecked) are shaded."""
    tr = acting_rows(row["trace"])
    t = np.array([r["t"] for r in tr])
    fig, ax = new_figure((8, 3.2))
    ax.plot(t, [r.get("u", np.nan) for r in tr], label="U", color="k")
    ax.plot(t, [r["u_act"] for r in tr], label="U_act", alpha=0.7)
    ax.plot(t, [r.get("u_pred", np.nan) for r in tr], label="U_pred", alpha=0.7)
    if calib:
        ax.axhline(calib["tau_high"], color="r", ls="--", lw=1, label="tau_high")
        ax.axhline(calib["tau_low"], color="orange", ls="--", lw=1, label="tau_low")
    committed = [r["t"] for r in tr if r.get("committed")]
    for i, step in enumerate(committed):
        ax.axvspan(step - 0.5, step + 0.5, color="grey", alpha=0.15, lw=0, label="committed" if i == 0 else None)
    colours = {"replan": "r", "prune": "orange", "pause": "purple"}
    for r in tr:
        for ev in {r.get("ended"), r.get("event")} & set(colours):
            ax.axvline(r["t"], color=colours[ev], alpha=0.25)
        if r.get("ended") in ("replan", "prune") and "ended_u" in r:
            ax.plot(r["t"] - 0.5, r["ended_u"], "x", color=colours[r["ended"]], ms=5)
    ax.set_xlabel("control step")
    ax.set_ylabel("uncertainty")
    ax.set_title(f"{row['task']} episode {row['episode']} ({'success' if row['success'] else 'failure'})")
    ax.legend(fontsize=7, ncol=6, loc="upper left")
    save_figure(fig, path)


def plot_horizons(evals: dict[str, list[dict]], path: Path) -> None:
    """Paper Fig. 14 (right): distribution of executed horizons per executor."""
    fig, ax = new_figure((6, 3.2))
    bins = np.arange(-0.5, 9.5, 1)
    for name, rows in evals.items():
        hs = [h for r in rows for h, e in r["plan_events"]]
        if hs:
            ax.hist(hs, bins=bins, alpha=0.5, label=name, density=True)
    ax.set_xlabel("executed horizon (actions per plan; 0 = pause)")
    ax.set_ylabel("fraction of plans")
    ax.legend(fontsize=8)
    save_figure(fig, path)


def plot_u_by_step(rows: list[dict], path: Path) -> None:
    """Paper Fig. 13: uncertainty against the step inside the plan."""
    by: dict[int, list[tuple[float, float, float]]] = {}
    for r in rows:
        for s in r["trace"]:
            if "u" in s:
                by.setdefault(s["plan_step"], []).append((s["u"], s["u_act"], s["u_pred"]))
    if not by:
        return
    ks = sorted(by)
    arr = [np.array(by[k]) for k in ks]
    fig, ax = new_figure((5, 3.2))
    for i, name in enumerate(("U", "U_act", "U_pred")):
        ax.plot([k + 1 for k in ks], [a[:, i].mean() for a in arr], marker="o", label=name)
    ax.set_xlabel("horizon step k")
    ax.set_ylabel("mean uncertainty")
    ax.legend(fontsize=8)
    save_figure(fig, path)


def plot_levels(levels: dict[str, dict[int, dict]], path: Path) -> None:
    """Paper Fig. 8: success against distraction level, with 95% intervals."""
    fig, ax = new_figure((5, 3.2))
    for name, by_level in levels.items():
        ls = sorted(by_level)
        p = np.array([by_level[lv]["success_rate"] for lv in ls])
        lo = np.array([by_level[lv]["ci95"][0] for lv in ls])
        hi = np.array([by_level[lv]["ci95"][1] for lv in ls])
        ax.errorbar(ls, p, yerr=[p - lo, hi - p], marker="o", capsize=3, label=name)
    ax.set_xlabel("distraction level (number of distractors)")
    ax.set_ylabel("success rate")
    ax.set_ylim(0, 1.05)
    ax.legend(fontsize=8)
    save_figure(fig, path)


def _tables(results: dict, store: ResultsStore, conditions: list[str], executors: list[str]) -> list[Table]:
    """Success, AURD against each executor, execution statistics, latency (when measured), failure prediction."""
    success = []
    for c in conditions:
        cells = []
        for e in executors:
            r = results.get((c, e))
            cells.append(f"{100 * r['success_rate']:.1f}% [{100 * r['ci95'][0]:.0f}, {100 * r['ci95'][1]:.0f}] "
                         f"(n={r['episodes']})" if r else "-")
        success.append([c, *cells])
    tables = [Table(["condition", *executors], success, title="Success rate (95% Wilson interval)")]
    paired = []
    for c in conditions:
        for e in executors:
            if e == "aurd" or (c, "aurd") not in results or (c, e) not in results:
                continue
            cmp = store.compare((c, "aurd"), (c, e))
            paired.append([c, e, f"{cmp['successes_a']}/{cmp['n']}", f"{cmp['successes_b']}/{cmp['n']}",
                           str(cmp["only_a"]), str(cmp["only_b"]), format_difference(cmp, with_p=False),
                           f"{cmp['p_mcnemar']:.3g}"])
    tables.append(Table(
        ["condition", "AURD vs", "AURD", "other", "only AURD", "only other", "AURD - other (points)", "McNemar p"],
        paired, title="Each executor against AURD, episode by episode",
        note=("Same test episodes (same seeds) for every executor: the difference in success is paired (Newcombe's "
              "method 10 95% interval) and tested with the exact McNemar test on the discordant episodes.")))
    tables.append(Table(
        ["condition", "executor", "mean horizon", "replans", "prunes", "pauses", "plans", "control Hz"],
        [[c, e, f"{r['mean_executed_horizon']:.2f}", str(r["replans"]), str(r["prunes"]), str(r["pauses"]),
          str(r["plans"]), f"{r['control_hz']:.0f}"] for (c, e), r in sorted(results.items())],
        title="Execution statistics"))
    timed = {k: r for k, r in sorted(results.items()) if "idle_steps" in r}
    if timed:
        tables.append(Table(
            ["condition", "executor", "execution", "latency ms", "success", "steps to success", "idle",
             "queries/min", "seam jerk", "stale", "out of order", "lost"],
            [[c, e, _execution(r.get("execution")), str(r.get("latency_ms", "0")), f"{100 * r['success_rate']:.1f}%",
              fmt(r["steps_to_success_mean"], 1), f"{100 * r['idle_fraction']:.1f}%", fmt(r["queries_per_minute"], 1),
              fmt(r["seam_jerk"], 3), str(r["stale_chunks"]), str(r["out_of_order_chunks"]), str(r["failed_queries"])]
             for (c, e), r in timed.items()],
            title="Latency and execution",
            note=("Per evaluation (docs/latency.md): steps to success over the successes, the share of steps the arm "
                  "held waiting for a chunk, policy queries per minute of control, the mean jerk at chunk seams "
                  "(action units per step^2), and the chunks dropped: stale (arrived past all of their actions), out "
                  "of order (not the observation in flight), queries the link lost.")))
    failure = []
    for (c, e), r in sorted(results.items()):
        fp = r.get("failure_prediction", {})
        failure.append([c, e, fmt(fp.get("auroc_u_max")), fmt(fp.get("auroc_u_mean")), fmt(fp.get("auroc_neg_v_min")),
                        str(fp.get("failures", "-")), str(fp.get("failure_flagged", "-")),
                        fmt(fp.get("failure_lead_steps_mean"))])
    tables.append(Table(["condition", "executor", "AUROC max U", "AUROC mean U", "AUROC -min V", "failures",
                         "flagged (U > tau_high)", "mean lead (steps)"], failure,
                        title="Failure prediction (AUROC of the episode's signals for predicting failure)"))
    return tables


def write_report(root: str | Path) -> Path:
    root = Path(root)
    layout = EvaluationsLayout(root)
    evals = layout.found
    if not evals:
        raise SystemExit(f"{root}: no evaluations (results.json) found")
    figs = layout.figures
    figs.mkdir(parents=True, exist_ok=True)
    store = ResultsStore(layout)
    results = {k: store.results(*k)[0] for k in evals}
    conditions = sorted({c for c, _ in evals if _level(c) is None})
    executors = sorted({e for _, e in evals})
    blocks: list[Block] = ["# PI-VLA evaluation report", f"Source: `{root}`",
                           *_tables(results, store, conditions, executors)]
    # figures
    main_cond = "in_distribution" if "in_distribution" in conditions else (conditions[0] if conditions else None)
    if main_cond:
        rows_by_exec = {e: load_rows(evals[(main_cond, e)] / EPISODES) for e in executors if (main_cond, e) in evals}
        plot_horizons(rows_by_exec, figs / "executed_horizons.png")
        blocks += [f"## Executed horizons ({main_cond}, paper Fig. 14)", "![](figures/executed_horizons.png)"]
        aurd_rows = [r for c in conditions if (c, "aurd") in evals for r in load_rows(evals[(c, "aurd")] / EPISODES)]
        if aurd_rows:
            plot_u_by_step(aurd_rows, figs / "uncertainty_by_step.png")
            blocks += ["## Uncertainty against horizon step (AURD, all conditions, paper Fig. 13)",
                       "![](figures/uncertainty_by_step.png)"]
            pick = next((r for r in aurd_rows if not r["success"]), aurd_rows[0])
            calib = _calibration(results, root)
            plot_timeline(pick, calib, figs / "uncertainty_timeline.png")
            blocks += ["## Uncertainty timeline of one AURD episode (paper Fig. 15)",
                       ("Vertical lines: replans (red), prunes (orange), pauses (purple); crosses: the U of the step a "
                        "replan or prune did not execute."),
                       "![](figures/uncertainty_timeline.png)"]
    levels: dict[str, dict[int, dict]] = {}
    for (c, e), r in results.items():
        lv = _level(c)
        if lv is not None:
            levels.setdefault(e, {})[lv] = r
    borrowed = sorted(e for e in levels if 0 not in levels[e] and ("in_distribution", e) in results)
    for e in borrowed:  # no distractors is the in-distribution condition: its episodes need not be played twice
        levels[e][0] = results[("in_distribution", e)]
    if levels:
        plot_levels(levels, figs / "distraction_levels.png")
        blocks.append("## Success against distraction level (paper Fig. 8)")
        if borrowed:
            blocks.append(f"Level 0 of {', '.join(borrowed)} is the in_distribution evaluation.")
        blocks.append("![](figures/distraction_levels.png)")
    write_markdown(layout.report_md, blocks)
    return layout.report_md


def _calibration(results: dict, root: Path) -> dict | None:
    """The thresholds of the AURD evaluations: as results.json records them; older results only name the
    policy, whose calibration.json is read if that path still resolves from here."""
    for r in results.values():
        if r.get("thresholds"):
            return r["thresholds"]
    for r in results.values():
        calib = Path(r["policy"]) / "calibration.json"
        if calib.exists():
            return json.loads(calib.read_text())
    log.warning("%s: no thresholds in results.json and no calibration.json at the recorded policy paths; "
                "the uncertainty timeline is drawn without them", root)
    return None
