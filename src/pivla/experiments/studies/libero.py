"""``pivla libero run``: one LIBERO suite end to end on the official protocol, resumable stage by stage.

1. **collect**: N scripted-expert demonstrations per task from scenes sampled (seeded) from the task's BDDL
   placement regions, never from the official init states; with the twin's variety (DART noise, recovered
   missed grasps), or those of ``--data``;
2. **train**: the validated recipe at LIBERO's cameras and proprio (``--preset libero``), or a copy of the policy
   of ``--policy``, trained elsewhere (e.g. on several suites);
3. **calibrate**: AURD's thresholds from the policy's own fixed-horizon rollouts on sampled scenes;
4. **evaluate**: every executor on every official init state of every task (50 per task), paired by state;
5. **report**: ``DIR/libero.md`` and ``DIR/libero.json``: per task and suite success with Wilson intervals,
   AURD against each executor paired by init state, the failure AUROC of U, and published figures beside ours.

Every stage writes under ``DIR`` and is skipped when its output exists; an interrupted evaluation continues
from its last finished episode. Progress goes to the log (``nohup pivla libero run ... > DIR/log &``).
"""

from __future__ import annotations

import dataclasses
import logging
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path
from typing import Annotated

import tyro

from pivla.control.calibrate import CalibrationConfig
from pivla.control.executors import executor_config
from pivla.data.hdf5 import read_env_meta
from pivla.envs import select_tasks
from pivla.envs.backend import BackendConfig
from pivla.envs.collect import CollectConfig
from pivla.evaluation.runner import load_rows
from pivla.evaluation.stats import format_difference, percent_interval, wilson_interval
from pivla.experiments import conditions
from pivla.experiments.layout import EPISODES, LiberoLayout, demo_files
from pivla.experiments.plan import Evaluation, EvaluationPlan, eval_config
from pivla.experiments.render import Block, Lines, Table, markdown, write_markdown
from pivla.experiments.results import ResultsStore
from pivla.experiments.stages import (
    Calibrate,
    Collect,
    CopyPolicy,
    Evaluate,
    StageTimes,
    Train,
    perform,
    shared_evaluations,
    validation_rollouts,
)
from pivla.io import atomic_write_json
from pivla.training.checkpoint import copied_from
from pivla.training.config import TrainConfig, libero_preset

log = logging.getLogger(__name__)

# Published success rates (%), Spatial / Object / Goal / Long (LIBERO-10)
PUBLISHED = {
    "PI-VLA (paper, Table 1)": {"libero_spatial": 79.5, "libero_object": 73.4, "libero_goal": 73.3, "libero_10": 66.6},
    "OpenVLA-OFT": {"libero_spatial": 97.6, "libero_object": 98.4, "libero_goal": 97.9, "libero_10": 94.5},
    "pi0": {"libero_spatial": 96.8, "libero_object": 98.8, "libero_goal": 95.8, "libero_10": 85.2},
    "OpenVLA": {"libero_spatial": 84.7, "libero_object": 88.4, "libero_goal": 79.2, "libero_10": 53.7},
}
OFFICIAL_INIT_STATES = 50
# the run's order; the evaluations follow (copy_policy instead of train for a policy trained elsewhere)
STAGES = ("collect", "train", "copy_policy", "validation_rollouts", "calibrate")
POLICY = "policy"  # the run's one policy


@dataclass
class LiberoRunConfig:
    """One LIBERO suite: demonstrations, training, calibration, evaluation on the official init states."""

    suite: str
    """libero_spatial, libero_object, libero_goal or libero_10."""
    out: str
    """Directory of the whole run (data/, policy/, eval/, libero.md)."""
    tasks: str | None = None
    """Task indices, comma-separated (default: all ten)."""
    demos: int = 50
    """Demonstrations per task (LIBERO's own datasets have 50)."""
    seed: int = 0
    """Seed of the sampled demonstration scenes and of training; validation scenes use seed + 1."""
    noise: float = 0.3
    """DART: noise on the expert's executed actions, clean labels (as the twin's demo)."""
    miss: float = 0.3
    """Share of demonstrations whose first grasp misses and is recovered (as the twin's demo)."""
    collect_step_factor: float = 1.5
    """The expert's step limit while collecting, as a multiple of the suite's (the policy keeps the suite's):
    with noise and a missed grasp, LIBERO-Goal's longest task fits 300 steps about one time in five and
    450 about one time in two (docs/experiments.md, "Demonstrations slower than the step limit")."""
    train: TrainConfig = field(default_factory=libero_preset)
    """Training (the recipe at LIBERO's cameras and proprio; data and out are set by the run)."""
    val_episodes: int = 5
    """Validation rollouts per task on sampled scenes, for calibration."""
    calibration: CalibrationConfig = field(default_factory=CalibrationConfig)
    """AURD's calibration."""
    executors: tuple[str, ...] = ("fixed", "aurd")
    """Executors evaluated on the official init states (add ensemble, adahorizon when time allows)."""
    monitor_baselines: bool = False
    """Baselines also encode every observation for the trace (U's AUROC on their episodes too). Off, a fixed
    horizon reads the cameras on its query steps only, and LIBERO renders only what is read: about 3x faster
    on a CPU. AURD's own episodes give U's AUROC either way."""
    init_states: int = OFFICIAL_INIT_STATES
    """Official init states per task, from 0 (50: the whole protocol)."""
    workers: int = 2
    """Worker processes (each LIBERO process holds ~2 GB)."""
    dispatch: Annotated[BackendConfig, tyro.conf.arg(name="")] = field(default_factory=BackendConfig)
    """Where the training, rollouts and evaluations run: --backend local | ray (the training a Ray task, a GPU
    where the cluster has them), --ray-address HOST:PORT (docs/cluster.md); demonstrations are collected by local
    processes."""
    mesh_faces: int = 4000
    """Visual meshes of more triangles are drawn simplified to about this many, in every stage (0: robosuite's
    full meshes): the frames differ by about one grey level on average and a step reading both cameras runs
    about twice as fast on a CPU (docs/libero.md, "Speed"); physics, rays and the success check keep the full
    meshes."""
    max_steps: int | None = None
    """Step limit per episode (default: the suite's, OpenVLA-OFT's 220 / 280 / 300 / 520)."""
    data: str | None = None
    """Demonstrations of this suite collected before (another run's ``data/``, drawn with the same --mesh-faces),
    read where they are instead of collecting into DIR/data."""
    policy: str | None = None
    """A finished training run or ensemble to evaluate instead of training one here, e.g. one policy for several
    suites (``pivla train --preset libero --data A --extra-data B C``): copied to DIR/policy, which is calibrated
    on this suite; of the --train options only --train.model.image-size is then used, as the picture size of any
    demonstrations collected."""


def check_rendering(data: Path, mesh_faces: int) -> None:
    """Refuse to go on when the demonstrations were drawn with other meshes than the run's: its validation and
    evaluation frames would not look like the frames the policy learnt from."""
    for path in demo_files(data):
        drawn = read_env_meta(path).get("mesh_faces", 0)  # collections before the setting drew full meshes
        if drawn != mesh_faces:
            raise ValueError(f"{path} was rendered with mesh_faces={drawn} and this run asks for {mesh_faces}: "
                             f"run with --mesh-faces {drawn}, or collect again into another --out")


def plan(cfg: LiberoRunConfig) -> EvaluationPlan:
    """Every executor on the official init states (baselines monitored only when asked)."""
    cell = conditions.libero(cfg.suite)
    return EvaluationPlan.of([Evaluation(POLICY, cell, name, executor_config(
        name, **({} if name == "aurd" else {"monitor": cfg.monitor_baselines}))) for name in cfg.executors],
        episodes=cfg.init_states, videos=2)


def run_libero(cfg: LiberoRunConfig) -> Path:
    """Run (or resume) every stage; returns the path of libero.md."""
    out = LiberoLayout(Path(cfg.out))
    out.root.mkdir(parents=True, exist_ok=True)
    tasks = select_tasks("libero", cfg.suite, cfg.tasks)
    timings = StageTimes(out.timings)
    timed = timings.run

    # Whole tasks spread over the workers; a finished task's file is kept, so a rerun collects the rest.
    data = Path(cfg.data) if cfg.data else out.data
    demos = CollectConfig(out=str(data), suite=cfg.suite, env="libero", tasks=cfg.tasks, episodes=cfg.demos,
                          seed=cfg.seed, workers=cfg.workers, image_size=cfg.train.model.image_size, noise=cfg.noise,
                          miss=cfg.miss, libero_init="random", libero_mesh_faces=cfg.mesh_faces,
                          libero_step_factor=cfg.collect_step_factor)
    if cfg.data:
        missing = Collect(demos).missing()
        if missing:
            raise ValueError(f"--data {data} has no demonstrations of {cfg.suite} task(s) {', '.join(missing)}: "
                             "collect them into it, or leave --data out")
    else:
        perform(Collect(demos, strict=False), "collect", timed=timed)
    check_rendering(data, cfg.mesh_faces)
    if cfg.policy:
        perform(CopyPolicy(Path(cfg.policy), out.policy), "copy_policy", "copy policy", timed)
    else:
        tc = dataclasses.replace(cfg.train, data=str(data), out=str(out.policy), seed=cfg.seed, progress=False)
        perform(Train(tc, cfg.dispatch), "train", timed=timed)
    with shared_evaluations(cfg.workers, cfg.dispatch):
        perform(validation_rollouts(out.policy, out.val_rollouts, out.val_rollouts_eval,
                                    conditions.libero(cfg.suite, init="random"), episodes=cfg.val_episodes,
                                    seed=cfg.seed + 1, realism="ideal", workers=cfg.workers, family=False,
                                    tasks=cfg.tasks, max_steps=cfg.max_steps, libero_mesh_faces=cfg.mesh_faces,
                                    dispatch=cfg.dispatch),
                "validation_rollouts", "validation rollouts", timed)
        perform(Calibrate(out.policy, out.val_rollouts, data, cfg.calibration), "calibrate", timed=timed)
        test = plan(cfg)
        for ev in test:
            ec = eval_config(ev, test, policy=out.policy, out=out.evaluation(ev.label), realism="ideal", family=False,
                             tasks=cfg.tasks, first_init_state=0, seed=cfg.seed + 1000, workers=cfg.workers,
                             max_steps=cfg.max_steps, libero_mesh_faces=cfg.mesh_faces, dispatch=cfg.dispatch)
            perform(Evaluate(ec, expected=cfg.init_states * len(tasks), progress=True), f"eval_{ev.label}",
                    f"eval {ev.label}", timed)
    return write_libero_report(out.root, cfg.suite, timings.times, data)


def expert_table(results: dict) -> str:
    """``expert_success``'s result as a markdown table: per task and over the suite, success with its Wilson
    95% interval, mean steps and the failed init states (or seeds)."""
    rows = [[f"{t['task']} {t['name'].replace('_', ' ')}", f"{t['successes']} / {t['episodes']}",
             percent_interval(*wilson_interval(t["successes"], t["episodes"])), f"{t['mean_steps']:.0f}",
             ", ".join(str(s) for s in t["failed"]) or "-"] for t in results["tasks"]]
    rows.append([f"**{results['suite']}**", f"**{results['successes']} / {results['episodes']}**",
                 percent_interval(*wilson_interval(results["successes"], results["episodes"])), None, None])
    return markdown([Table(["task", "success", "95% CI", "mean steps", "failed"], rows)]).removesuffix("\n")


def demonstrations(data: Path) -> dict[str, dict[str, int]]:
    """Per task name, the demonstrations its file holds and the expert's attempts that made them: a task whose
    expert often failed on sampled scenes has fewer than asked for, which its success is read against."""
    found = {}
    for path in demo_files(data):
        meta = read_env_meta(path)
        if "task" in meta:
            found[meta["task"]] = {"episodes": len(meta.get("init_seeds", [])), "attempts": meta.get("attempts", 0)}
    return found


def _duration(seconds: float) -> str:
    if seconds >= 3600:
        return f"{seconds / 3600:.1f} h"
    return f"{seconds / 60:.0f} min" if seconds >= 60 else f"{seconds:.0f} s"


def write_libero_report(out: Path, suite: str, timings: dict[str, float] | None = None,
                        data: Path | None = None) -> Path:
    """libero.md and libero.json from the evaluations under ``out/eval``, the suite's demonstrations (``data``,
    by default ``out/data``), the stage times and, for a policy trained elsewhere, where it was copied from."""
    layout = LiberoLayout(Path(out))
    store = ResultsStore(layout)
    names = layout.evaluated()
    results = {name: store.results(name)[0] for name in names}
    rows = {name: load_rows(layout.evaluation(name) / EPISODES) for name in names}
    demos = demonstrations(data or layout.data)
    timings = timings or {}
    source = copied_from(layout.policy)
    report: dict = {"suite": suite, "executors": {}, "paired": {},
                    "published": {k: v.get(suite) for k, v in PUBLISHED.items()},
                    "demonstrations": demos, "timings_s": timings, "policy_copied_from": source}
    for name, res in results.items():
        report["executors"][name] = {
            "success_rate": res["success_rate"], "ci95": res["ci95"], "successes": res["successes"],
            "episodes": res["episodes"], "per_task": res["per_task"], "failure_prediction": res["failure_prediction"],
            "mean_executed_horizon": res["mean_executed_horizon"], "replans": res["replans"], "prunes": res["prunes"],
            "pauses": res["pauses"], "control_hz": res["control_hz"],
        }
    if "aurd" in results:
        for name in names:
            if name != "aurd":
                report["paired"][f"aurd_vs_{name}"] = store.compare(("aurd",), (name,))
    atomic_write_json(layout.report_json, report)
    tasks = sorted({t for r in results.values() for t in r["per_task"]})
    table_rows = []
    for t in tasks:
        cells = []
        for n in names:
            pt = results[n]["per_task"].get(t)
            cells.append(f"{100 * pt['success_rate']:.0f}% ({round(pt['success_rate'] * pt['episodes'])}/"
                         f"{pt['episodes']})" if pt else "-")
        d = demos.get(t)
        table_rows.append([t, f"{d['episodes']} / {d['attempts']}" if d else "-", *cells])
    table_rows.append(["**suite**", None, *(
        f"**{100 * results[n]['success_rate']:.1f}%** "
        f"{percent_interval(*wilson_interval(results[n]['successes'], results[n]['episodes']))}" for n in names)])
    notes = []
    for key, cmp in report["paired"].items():
        notes.append(f"- {key.replace('_', ' ')}: {cmp['successes_a']} / {cmp['successes_b']} of {cmp['n']} paired "
                     f"episodes ({cmp['only_a']} / {cmp['only_b']} discordant), {format_difference(cmp, with_p=False)} "
                     f"points (Newcombe paired), exact McNemar p {cmp['p_mcnemar']:.3g}")
    for n in names:
        fp = results[n].get("failure_prediction") or {}
        if fp.get("auroc_u_max") is not None:
            notes.append(f"- {n}: AUROC of the episode's max U for failure {fp['auroc_u_max']:.2f}, of -min V "
                         f"{fp['auroc_neg_v_min']:.2f}")
    for n in names:
        partial = Counter(r["task"] for r in rows[n] if not r["success"] and 0 < (r.get("stage_progress") or 0) < 1)
        if partial:
            failed = results[n]["episodes"] - results[n]["successes"]
            notes.append(f"- {n}: {partial.total()} of {failed} failures ended with part of the goal met ("
                         + ", ".join(f"{t} {k}" for t, k in sorted(partial.items())) + ")")
    if timings:
        order = sorted(timings, key=lambda k: STAGES.index(k) if k in STAGES else len(STAGES))
        notes.append("- Wall time: " + ", ".join(f"{k.replace('_', ' ')} {_duration(timings[k])}" for k in order)
                     + f"; {_duration(sum(timings.values()))} in all")
    blocks: list[Block] = [
        f"# {suite}: official protocol",
        ("Every official init state of every task, one episode each per executor (paired by init state); the policy "
         "trained on demonstrations from sampled scenes only (demos: kept of the expert's attempts). Success with 95% "
         "Wilson intervals." + (f" The policy is a copy of {source}." if source else "")),
        Table(["task", "demos", *names], table_rows),
        Lines(tuple(notes)),
        "Published figures on the same suite: " + ", ".join(
            f"{k} {v}%" for k, v in report["published"].items() if v is not None) + "."]
    write_markdown(layout.report_md, blocks)
    return layout.report_md
