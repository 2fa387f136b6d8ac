"""Honest evaluation of a policy with an executor on a task suite.

Episode seeds depend only on (seed, task index, episode index), never on the executor or the number of
workers: every executor meets the same initial states (a paired comparison), and ``--workers 4`` gives
the same results as ``--workers 1``. Each finished episode is appended to ``episodes.jsonl`` at once, so
an interrupted evaluation resumes where it stopped.
"""

from __future__ import annotations

import contextlib
import itertools
import json
import logging
import multiprocessing as mp
import os
import time
from collections import Counter
from collections.abc import Callable, Iterator
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Annotated, Any, Literal

import numpy as np
import torch
import tyro
from tqdm import tqdm

from pivla.control import run_episode
from pivla.control.asynchronous import ExecutionConfig, SyncConfig, check_execution
from pivla.control.contract import DEFAULT_ETA
from pivla.control.executors import (
    AURDConfig,
    ExecutorConfig,
    config_to_dict,
    make_executor,
)
from pivla.control.latency import parse_latency
from pivla.data.action_space import ActionSpace
from pivla.data.hdf5 import read_episodes, write_episodes
from pivla.envs import family, make_env, seeds, select_tasks
from pivla.envs.backend import BackendConfig, check_backend, ray_map
from pivla.envs.rollout import episode_seed
from pivla.evaluation.stats import wilson_interval
from pivla.io import atomic_write_json, open_log, read_json, write_mp4
from pivla.serving.client import open_policy

log = logging.getLogger(__name__)
PARTS_DIR = ".parts"  # one file per recorded episode, merged per task at the end; hidden from dataset readers


@dataclass
class EvalConfig:
    """One evaluation: a policy, an executor, a task suite, seeded episodes."""

    policy: str
    """Run directory, or ws://HOST:PORT of a served policy."""
    out: str
    """Directory for results.json, episodes.jsonl, traces/ and videos/ (an interrupted evaluation resumes)."""
    env: Literal["tabletop", "so101", "libero"] = "tabletop"
    """The simulated twin of the paper's arm, the SO-101 twin, or LIBERO."""
    suite: str = "pick_place"
    """Task suite (tabletop: pick_place, pick_place_seen, pick_place_unseen, drawer, stack, long; so101:
    pick_place; libero: libero_spatial, libero_object, libero_goal, libero_10, ...)."""
    tasks: str | None = None
    """Task indices or names, comma-separated (default: all)."""
    executor: ExecutorConfig = field(default_factory=AURDConfig)
    """How chunks become actions: --executor aurd | fixed | ensemble | adahorizon, then its options
    (e.g. --executor fixed --executor.horizon 3)."""
    execution: ExecutionConfig = field(default_factory=SyncConfig)
    """When queries go out: --execution sync (wait for each chunk, the arm holding pose) or async (the next query
    in flight while the current chunk executes; then --execution.threshold, --execution.seam; docs/latency.md)."""
    latency_ms: str = "0"
    """Policy latency in control time: MEAN[:JITTER] ms, lognormal, drawn per query from the episode's seed (e.g. 200
    or 200:50; the simulation keeps stepping meanwhile); or real: measured on the wall clock with the loop paced at
    the env's control rate (a served policy, pivla serve --delay-ms)."""
    episodes: int = 10
    """Episodes per task."""
    seed: int = 1000
    """Base seed of the episodes when no seed family is given (legacy seeds)."""
    seed_family: Literal["train", "validation", "test", "holdout"] | None = None
    """Seed the episodes from this family (pivla.envs.seeds: disjoint by construction, one use each) with
    ``condition``; the split must agree (validation rollouts: validation; test: test or holdout)."""
    condition: str | None = None
    """The condition's code in the seed family (pivla.envs.seeds.CONDITIONS), e.g. in_distribution."""
    perturb: str | None = None
    """Twin perturbation spec, e.g. unseen_env,static_distractors,level=3 (docs/twin.md)."""
    realism: Literal["ideal", "servo"] = "ideal"
    """Twin actuation: ideal, or hobby-servo backlash, deadband and noise."""
    workers: int = 1
    """Worker processes, or Ray actors with --backend ray (results do not depend on it)."""
    dispatch: Annotated[BackendConfig, tyro.conf.arg(name="")] = field(default_factory=BackendConfig)
    """Where the episodes run: --backend local | ray, --ray-address HOST:PORT (docs/cluster.md)."""
    videos: int = 2
    """Episodes with an MP4 (the first ones of the first tasks)."""
    max_steps: int | None = None
    """Step limit per episode (default: the task's)."""
    record: str | None = None
    """Also write every rollout (with success and rewards) into this dataset directory."""
    first_init_state: int = 0
    """LIBERO: episode e starts from official init state first_init_state + e (mod 50), whatever the worker."""
    libero_mesh_faces: int = 0
    """LIBERO: draw visual meshes of more triangles simplified to about this many (0: robosuite's full meshes);
    evaluate a policy with the setting its demonstrations were rendered with (``mesh_faces`` in their env_args)."""
    libero_init: Literal["official", "random"] = "official"
    """LIBERO: official init states (the benchmark's protocol), or scenes sampled from the task's placement
    regions with the episode's seed (validation rollouts, which must not reuse the official states)."""
    split: Literal["test", "validation", "train"] = "test"
    """validation: rollouts thresholds are calibrated on; train: rollouts to train on; reports show test only,
    and pivla calibrate refuses recorded test episodes."""
    gripper_head: Literal["continuous", "discrete"] | None = None
    """Head that drives the gripper (default: the discrete one when both were trained)."""
    api_key: str | None = None
    """API key of a served policy (ws://...)."""


def config_dict(cfg: EvalConfig) -> dict[str, Any]:
    """The evaluation's settings as JSON, the executor and the execution mode with their names."""
    return {**asdict(cfg), "executor": config_to_dict(cfg.executor),
            "execution": {"name": cfg.execution.kind, **asdict(cfg.execution)}}


def eval_threads(workers: int) -> int:
    """Torch threads per worker: the cores shared out, never more than OMP_NUM_THREADS when it is set
    (oversubscribed OpenMP threads spin against each other and slow everything on the machine)."""
    share = max(1, (os.cpu_count() or 2) // workers)
    limit = os.environ.get("OMP_NUM_THREADS", "")
    return min(share, int(limit)) if limit.isdigit() and int(limit) > 0 else share


def job_seed(seed: int, task_index: int, episode: int) -> int:
    return episode_seed(seed, task_index * 100_003 + episode)


FAMILY_OF_SPLIT = {"train": ("train",), "validation": ("validation",), "test": ("test", "holdout")}


def episode_seed_of(cfg: EvalConfig, task_index: int, task_name: str, episode: int) -> int:
    """The seed of one episode: from the seed family when one is given, else the legacy (seed, task, episode)."""
    if cfg.seed_family is not None:
        return seeds.seed_for(cfg.seed_family, cfg.condition or "", task_name, episode)
    return job_seed(cfg.seed, task_index, episode)


# -- worker side ------------------------------------------------------------------------------------------
_STATE: dict[str, Any] = {}


def _init_worker(cfg: EvalConfig, threads: int) -> None:
    """Load the policy once per worker and evaluation. A failure is kept and raised by the first job: an
    exception in a Pool initializer would make the pool respawn workers forever instead of reporting it."""
    torch.set_num_threads(threads)
    _STATE.pop("error", None)
    _STATE["cfg"] = cfg
    _STATE["envs"] = {}
    try:
        _STATE["policy"] = open_policy(cfg.policy, cfg.api_key, gripper_head=cfg.gripper_head,
                                       device="cpu" if not torch.cuda.is_available() else "auto")
    except Exception as e:  # noqa: BLE001 - re-raised with context in _run_job
        _STATE["error"] = f"{type(e).__name__}: {e}"


def _env(task_index: int) -> Any:
    cfg, policy = _STATE["cfg"], _STATE["policy"]
    if task_index not in _STATE["envs"]:
        kw: dict[str, Any] = {"image_size": policy.spec.image_size, "cameras": tuple(policy.spec.cameras)}
        if cfg.env in ("tabletop", "so101"):
            kw.update(realism=cfg.realism, perturb=cfg.perturb)
        else:
            kw.update(mesh_faces=cfg.libero_mesh_faces)
            # Jobs come task after task, so a worker is done with the tasks before. Each LIBERO env kept would
            # hold 0.7-1 GB more (measured on LIBERO-Object): ten tasks in two workers would fill 24 GB.
            _close_envs()
        _STATE["envs"][task_index] = make_env(cfg.env, cfg.suite, task_index, **kw)
    return _STATE["envs"][task_index]


def _close_envs() -> None:
    """Close every env this worker holds (a LIBERO env holds ~1 GB)."""
    envs = _STATE.get("envs", {})
    while envs:
        envs.popitem()[1].close()


def _run_shared_job(item: tuple[int, EvalConfig, int, tuple[int, str, int, bool]]) -> dict:
    """A job of an ``evaluation_pool``: the worker sets itself up afresh for each evaluation it serves, so it
    plays an episode as a worker of that evaluation alone would."""
    evaluation, cfg, threads, job = item
    if _STATE.get("evaluation") != evaluation:
        _close_envs()  # the evaluation before's
        _init_worker(cfg, threads)
        _STATE["evaluation"] = evaluation
    return _run_job(job)


def _run_job(job: tuple[int, str, int, bool]) -> dict:
    if "error" in _STATE:
        raise RuntimeError(f"evaluation worker could not load the policy: {_STATE['error']}")
    task_index, task_name, episode, keep_frames = job
    cfg, policy = _STATE["cfg"], _STATE["policy"]
    seed = episode_seed_of(cfg, task_index, task_name, episode)
    t0 = time.perf_counter()
    options = None
    if cfg.env == "libero":
        options = ({"init": "random", "seed": seed} if cfg.libero_init == "random"
                   else {"init_state": cfg.first_init_state + episode})
    result = run_episode(_env(task_index), policy, make_executor(cfg.executor), seed=seed,
                         max_steps=cfg.max_steps, keep_episode=keep_frames or cfg.record is not None,
                         reset_options=options, execution=cfg.execution, latency=cfg.latency_ms)
    row = {"task": task_name, "task_index": task_index, "episode": episode, **(options or {}), **result.summary(),
           "wall_s": time.perf_counter() - t0, "encoder_runtime": getattr(policy, "encoder_runtime", "client"),
           "trace": result.trace, "plan_events": result.plans}
    perturber = getattr(_env(task_index), "perturber", None)
    if perturber is not None:  # twin: the mid-episode events that fired (displacement, push), with their steps
        row["perturb_events"] = [{k: _plain(v) for k, v in ev.items()} for ev in perturber.events]
    if result.episode is not None:
        row["_episode"] = result.episode
        row["_video"] = keep_frames
    return row


def _plain(value: Any) -> Any:
    """A JSON-able copy of an event field (arrays become lists)."""
    return np.asarray(value).tolist() if isinstance(value, (np.ndarray, np.generic)) else value


# -- aggregation ------------------------------------------------------------------------------------------
def auroc(scores: np.ndarray, labels: np.ndarray) -> float | None:
    """Area under the ROC curve of ``scores`` for positive ``labels`` (Mann-Whitney, ties count half)."""
    scores, labels = np.asarray(scores, float), np.asarray(labels, bool)
    pos, neg = scores[labels], scores[~labels]
    if len(pos) == 0 or len(neg) == 0:
        return None
    greater = (pos[:, None] > neg[None, :]).sum() + 0.5 * (pos[:, None] == neg[None, :]).sum()
    return float(greater / (len(pos) * len(neg)))


def acting_rows(trace: list[dict]) -> list[dict]:
    """The trace rows of steps that executed a chunk's action (not the idle steps spent waiting for one)."""
    return [row for row in trace if not row.get("idle")]


def episode_uncertainty(trace: list[dict]) -> np.ndarray:
    """Per-step U (AURD) or U_act (executors that do not encode observations), idle steps left out."""
    return np.array([row["u"] if "u" in row else row["u_act"] for row in acting_rows(trace)], float)


def _leads(rows: list[dict], flagged: Callable[[dict], np.ndarray]) -> tuple[list[int], int]:
    """Steps from the first flagged step to the end of each failed episode, and the successes ever flagged."""
    leads, false_alarms = [], 0
    for r in rows:
        first = np.flatnonzero(flagged(r))
        if r["success"]:
            false_alarms += bool(len(first))
        elif len(first):
            leads.append(r["steps"] - int(first[0]))
    return leads, false_alarms


def failure_prediction(rows: list[dict], tau_high: float | None, v_thresh: float | None = None) -> dict:
    """How well the model's own signals predict that an episode fails (the paper claims it, never measures it):
    AUROC of U and of -min V for failure, and, given the thresholds, how many steps before a failure's end U
    first exceeded tau_high (or V first fell below V_thresh), with the successes that raised the same flag."""
    if not rows:
        return {}
    failed = np.array([not r["success"] for r in rows])
    u_max = np.array([episode_uncertainty(r["trace"]).max(initial=0.0) for r in rows])
    u_mean = np.array([episode_uncertainty(r["trace"]).mean() if r["trace"] else 0.0 for r in rows])
    v_min = np.array([min((row["v"] for row in acting_rows(r["trace"])), default=0.0) for r in rows])
    out = {"auroc_u_max": auroc(u_max, failed), "auroc_u_mean": auroc(u_mean, failed),
           "auroc_neg_v_min": auroc(-v_min, failed), "failures": int(failed.sum())}
    signals = (("failure", tau_high, lambda r: episode_uncertainty(r["trace"]) > tau_high),
               ("v_failure", v_thresh,
                lambda r: np.array([row["v"] for row in acting_rows(r["trace"])], float) < v_thresh))
    for prefix, threshold, flagged in signals:
        if threshold is not None:
            leads, false_alarms = _leads(rows, flagged)
            out[f"{prefix}_lead_steps_mean"] = float(np.mean(leads)) if leads else None
            out[f"{prefix}_flagged"] = len(leads)
            out[f"{prefix}_false_alarms"] = false_alarms
    return out


def aggregate(rows: list[dict], cfg: EvalConfig, tau_high: float | None, v_thresh: float | None = None) -> dict:
    n = len(rows)
    succ = sum(r["success"] for r in rows)
    per_task: dict[str, dict] = {}
    for r in rows:
        per_task.setdefault(r["task"], []).append(r["success"])  # type: ignore[arg-type]
    per_task = {k: {"success_rate": float(np.mean(v)), "ci95": list(wilson_interval(int(np.sum(v)), len(v))),
                    "episodes": len(v)}
                for k, v in sorted(per_task.items())}
    plans = [(h, e) for r in rows for h, e in r["plan_events"]]
    horizons = [h for h, e in plans if e != "pause"]
    steps = sum(r["steps"] for r in rows)
    # median over episodes of each one's mean step time: a worker's first episode also pays one-time warm-up
    # (allocations, the first policy query), which a mean over all steps would spread over the others
    control_ms = float(np.median([r["control_ms_mean"] for r in rows])) if rows else 0.0
    return {
        "success_rate": succ / n if n else 0.0,
        "ci95": list(wilson_interval(succ, n)),
        "successes": succ,
        "episodes": n,
        "per_task": per_task,
        "executor": cfg.executor.kind,
        "executor_options": asdict(cfg.executor),
        "env": cfg.env, "suite": cfg.suite, "perturb": cfg.perturb, "realism": cfg.realism, "seed": cfg.seed,
        "policy": cfg.policy, "split": cfg.split,
        "mean_executed_horizon": float(np.mean(horizons)) if horizons else 0.0,
        "replans": sum(e == "replan" for _, e in plans),
        "prunes": sum(e == "prune" for _, e in plans),
        "pauses": sum(e == "pause" for _, e in plans),
        "plans": len(plans),
        "control_hz": 1e3 / control_ms if control_ms > 0 else 0.0,  # policy + decision time per control step
        "control_ms_per_step": control_ms,
        # episodes logged before queries were counted are left out
        "queries_per_100_steps": (100 * sum(r["queries"] for r in rows if "queries" in r)
                                  / max(sum(r["steps"] for r in rows if "queries" in r), 1)
                                  if any("queries" in r for r in rows) else None),
        "steps": steps,
        "mean_steps": steps / n if n else 0.0,
        "sim_wall_s": float(sum(r["wall_s"] for r in rows)),
        # where the target encoder ran (AURD's U_pred); episodes logged before this field existed are left out
        "encoder_runtime": ",".join(sorted({r["encoder_runtime"] for r in rows if "encoder_runtime" in r})) or None,
        "failure_prediction": failure_prediction(rows, tau_high, v_thresh),
        "failure_stages": failure_stages(rows),
        # episodes in which a mid-episode perturbation actually fired (a small displacement can come too late)
        "perturbed_episodes": sum(bool(r.get("perturb_events")) for r in rows),
        "execution": {"name": cfg.execution.kind, **asdict(cfg.execution)}, "latency_ms": cfg.latency_ms,
        **timing_aggregate(rows),
    }


def timing_aggregate(rows: list[dict]) -> dict:
    """Latency's cost over the episodes that recorded it (control.runner.EpisodeResult.timing_summary): mean steps
    to success, idle steps and their share, queries per minute of control, mean jerk over all seams, chunks
    not executed, mean query-to-answer delay in steps."""
    timed = [r for r in rows if "idle_steps" in r]
    if not timed:
        return {}
    steps = sum(r["steps"] for r in timed)
    minutes = sum(r["steps"] / r["env_control_hz"] / 60 for r in timed if r.get("env_control_hz"))
    to_success = [r["steps_to_success"] for r in timed if r["steps_to_success"] is not None]
    seams = sum(r["seams"] for r in timed)
    delays = [r["delay_steps_mean"] for r in timed if r["delay_steps_mean"] is not None]
    return {
        "steps_to_success_mean": float(np.mean(to_success)) if to_success else None,
        "idle_steps": sum(r["idle_steps"] for r in timed),
        "idle_fraction": sum(r["idle_steps"] for r in timed) / steps if steps else 0.0,
        "queries_per_minute": sum(r["queries"] for r in timed) / minutes if minutes else None,
        "seam_jerk": sum(r["seam_jerk"] * r["seams"] for r in timed if r["seams"]) / seams if seams else None,
        "stale_chunks": sum(r["stale_chunks"] for r in timed),
        "out_of_order_chunks": sum(r["out_of_order_chunks"] for r in timed),
        "failed_queries": sum(r["failed_queries"] for r in timed),
        "delay_steps_mean": float(np.mean(delays)) if delays else None,
    }


def failure_stages(rows: list[dict]) -> dict[str, int]:
    """How far failed episodes got: counts of their final stage progress (twin: 0.25 reached, 0.5 grasped,
    0.75 moved; LIBERO: the fraction of the goal's predicates that hold at the end), which says where a policy
    breaks down. Empty when the env does not report stages."""
    counts = Counter(f"{r['stage_progress']:.2f}" for r in rows
                     if not r["success"] and r.get("stage_progress") is not None)
    return dict(sorted(counts.items()))


# -- driver ----------------------------------------------------------------------------------------------
def _key(row: dict) -> tuple[int, int]:
    return int(row["task_index"]), int(row["episode"])


def load_rows(path: Path) -> list[dict]:
    rows = []
    if path.exists():
        for line in path.read_text().splitlines():
            if not line.strip():
                continue
            try:
                rows.append(json.loads(line))
            except json.JSONDecodeError:
                log.warning("%s: skipping a truncated line (interrupted write)", path)
    return rows


# settings that do not change what an episode does, so a resumed evaluation may differ in them
_RESUME_FREE = frozenset({"out", "episodes", "workers", "dispatch", "videos", "record"})


def _check_resumable(path: Path, cfg: EvalConfig) -> None:
    """Refuse to add episodes to an evaluation run with other settings (policy, executor, seeds, ...):
    the merged results would mean nothing. Fields missing from an older file count as their defaults."""
    if not path.exists():
        return
    before = config_dict(EvalConfig(policy="", out="")) | read_json(path)
    now = config_dict(cfg)
    changed = sorted(k for k in now if k not in _RESUME_FREE and before.get(k) != now[k])
    if changed:
        diff = ", ".join(f"{k}: {before.get(k)!r} -> {now[k]!r}" for k in changed)
        raise SystemExit(f"{path.parent} holds episodes of an evaluation with other settings ({diff}); "
                         "use another --out or delete it")


def _check_settings(cfg: EvalConfig) -> None:
    """Reject executor options and perturbation specs that the episode jobs would trip over, before anything
    is written."""
    try:
        make_executor(cfg.executor)
    except (TypeError, ValueError) as e:
        raise SystemExit(f"executor {cfg.executor}: {e}") from e
    try:
        parse_latency(cfg.latency_ms)
    except ValueError as e:
        raise SystemExit(f"--latency-ms {e}") from None
    try:
        check_execution(cfg.execution, cfg.executor)
    except ValueError as e:
        raise SystemExit(f"--execution {cfg.execution.kind}: {e}") from None
    check_backend(cfg.dispatch)
    if cfg.seed_family is not None:
        if cfg.seed_family not in FAMILY_OF_SPLIT[cfg.split]:
            raise SystemExit(f"seed family {cfg.seed_family!r} cannot give {cfg.split} episodes (allowed: "
                             f"{', '.join(FAMILY_OF_SPLIT[cfg.split])})")
        if cfg.condition not in seeds.CONDITIONS:
            raise SystemExit(f"--condition {cfg.condition!r}: with a seed family, one of {sorted(seeds.CONDITIONS)}")
    if cfg.env in ("tabletop", "so101") and cfg.perturb:
        try:
            family(cfg.env).parse_perturb(cfg.perturb)  # imports the twin only when it is evaluated
        except ValueError as e:
            raise SystemExit(f"--perturb {cfg.perturb!r}: {e}") from e


def evaluation_thresholds(calibration: Any, executor: ExecutorConfig) -> dict | None:
    """AURD's tau_low, tau_high, V_thresh and eta for this evaluation (the executor's options override the calibration),
    kept in results.json so that a report draws the thresholds the traces were judged by; None when the
    policy is uncalibrated and no override gives all of them."""
    keys = ("tau_low", "tau_high", "v_thresh", "eta")
    base = {k: getattr(calibration, k) for k in keys} if calibration is not None else {"eta": DEFAULT_ETA}
    options = asdict(executor)
    out = base | {k: float(options[k]) for k in keys if options.get(k) is not None}
    return out if all(k in out for k in keys) else None


# -- main side --------------------------------------------------------------------------------------------
_SHARED: dict[str, Any] = {}  # an ``evaluation_pool`` block's size, and its pool once an evaluation started it
_EVALUATIONS = itertools.count()


@contextlib.contextmanager
def evaluation_pool(workers: int) -> Iterator[None]:
    """Keep ``workers`` evaluation processes for every local evaluation of that many workers in the block: a
    study of many cells starts its processes (Python, torch, MuJoCo's GL context: ~3 s a cell on 2 cores) once
    instead of once per cell. Each evaluation still loads its policy and envs afresh in every worker. The
    processes start with the first evaluation that has episodes to play: a resumed study whose evaluations are
    all done starts none."""
    if workers < 2 or _SHARED:
        yield
        return
    _SHARED["workers"] = workers
    try:
        yield
    finally:
        pool = _SHARED.pop("pool", None)
        _SHARED.clear()
        if pool is not None:
            pool.terminate()


def _shared_pool() -> Any:
    """The ``evaluation_pool`` block's processes, started on first use."""
    if "pool" not in _SHARED:
        _SHARED["pool"] = mp.get_context("spawn").Pool(_SHARED["workers"])
    return _SHARED["pool"]


def evaluate(cfg: EvalConfig, progress: bool = True) -> dict:
    """Run (or resume) an evaluation; writes results.json, episodes.jsonl, traces/ and videos/ in ``cfg.out``."""
    _check_settings(cfg)
    out = Path(cfg.out)
    tasks = select_tasks(cfg.env, cfg.suite, cfg.tasks)
    (out / "traces").mkdir(parents=True, exist_ok=True)
    if cfg.policy.startswith(("ws://", "wss://")) and cfg.gripper_head is not None:
        raise SystemExit("--gripper-head chooses a local policy's head; a served policy uses the server's choice")
    policy = open_policy(cfg.policy, cfg.api_key, device="cpu", gripper_head=cfg.gripper_head)
    given = {k for k, v in asdict(cfg.executor).items() if v is not None}
    if cfg.executor.kind == "aurd" and policy.calibration is None and not {"tau_low", "tau_high", "v_thresh"} <= given:
        raise SystemExit(f"{cfg.policy}: not calibrated; run `pivla calibrate --policy {cfg.policy} --data VAL` first")
    thresholds = evaluation_thresholds(policy.calibration, cfg.executor)
    tau_high = thresholds["tau_high"] if thresholds else None
    gripper_head = getattr(policy, "gripper_head", None)
    space = policy.spec.action_space  # what recorded rollouts' action rows mean
    del policy
    log_path = out / "episodes.jsonl"
    done = {_key(r): r for r in load_rows(log_path)}
    if done:
        _check_resumable(out / "eval_config.json", cfg)
    atomic_write_json(out / "eval_config.json", config_dict(cfg))
    jobs = []
    for ti, spec in enumerate(tasks):
        for j in range(cfg.episodes):
            if (spec.index, j) not in done:
                jobs.append((spec.index, spec.name, j, ti * cfg.episodes + j < cfg.videos))
    if done:
        log.info("resuming: %d episodes already done, %d to go", len(done), len(jobs))
    workers = max(1, min(cfg.workers, len(jobs)))
    threads = eval_threads(workers)
    bar = tqdm(total=len(jobs), desc=f"eval {cfg.executor.kind}", unit="ep", disable=not progress, leave=False)
    with open_log(log_path) as logf:
        def consume(row: dict) -> None:
            ep, video = row.pop("_episode", None), row.pop("_video", False)
            if ep is not None and video:
                _write_video(out / "videos", row, ep)
            if ep is not None and cfg.record:  # before the row: a logged episode always has its recording
                # which evaluation it came from: pivla calibrate refuses test episodes
                ep.meta.update(split=cfg.split, eval_seed=cfg.seed, perturb=cfg.perturb)
                _record_part(Path(cfg.record), row, ep, space)
            atomic_write_json(out / "traces" / f"{row['task']}_{row['episode']:03d}.json", row)
            logf.write(json.dumps(row) + "\n")
            logf.flush()
            done[_key(row)] = row
            bar.update(1)

        if cfg.dispatch.backend == "ray":  # in job order, as one local process writes them
            for row in ray_map(_run_job, jobs, cfg.dispatch, workers=cfg.workers, setup=_init_worker,
                               setup_args=(cfg, cfg.dispatch.ray_worker_cpus)):
                consume(row)
        elif workers == 1:
            caller_threads = torch.get_num_threads()
            try:
                _init_worker(cfg, threads)
                for job in jobs:
                    consume(_run_job(job))
            finally:  # in-process: the caller (e.g. an ablation that trains next) keeps its own setting
                torch.set_num_threads(caller_threads)
        elif jobs and _SHARED.get("workers") == cfg.workers:
            evaluation = next(_EVALUATIONS)
            for row in _shared_pool().imap_unordered(_run_shared_job, [(evaluation, cfg, threads, j) for j in jobs]):
                consume(row)
        elif jobs:
            with mp.get_context("spawn").Pool(workers, initializer=_init_worker, initargs=(cfg, threads)) as pool:
                for row in pool.imap_unordered(_run_job, jobs):
                    consume(row)
    bar.close()
    rows = sorted(done.values(), key=_key)
    results = (aggregate(rows, cfg, tau_high, thresholds["v_thresh"] if thresholds else None)
               | {"gripper_head": gripper_head, "thresholds": thresholds})
    atomic_write_json(out / "results.json", results)
    if cfg.record:  # after results.json: a missing recording must not cost the evaluation its results
        _merge_rollouts(Path(cfg.record), rows, space)
    return results


def _write_video(folder: Path, row: dict, ep: Any) -> None:
    folder.mkdir(parents=True, exist_ok=True)
    views = [ep.obs[k] for k in _camera_keys(ep.obs)]
    frames = np.concatenate(views, axis=2).repeat(2, axis=1).repeat(2, axis=2)
    tag = "success" if row["success"] else "failure"
    write_mp4(folder / f"{row['task']}_{row['episode']:03d}_{tag}.mp4", frames, 10)


def _camera_keys(obs: dict) -> list[str]:
    """The episode's pictures, side by side in a video: the twin's and LIBERO's agent view then wrist camera, else
    every (T, H, W, 3) uint8 observation (the SO-101 twin's front and wrist) in key order."""
    named = [k for k in ("agentview_rgb", "eye_in_hand_rgb") if k in obs]
    return named or sorted(k for k, v in obs.items()
                           if getattr(v, "ndim", 0) == 4 and v.shape[-1] == 3 and v.dtype == np.uint8)


def _part_path(root: Path, row: dict) -> Path:
    return root / PARTS_DIR / f"{row['task']}_{row['episode']:04d}.hdf5"


def _record_part(root: Path, row: dict, ep: Any, space: ActionSpace) -> None:
    """Write one finished episode at once (atomically), so an interrupted evaluation keeps its recordings."""
    write_episodes(_part_path(root, row), [ep], action_space=space)


def _merge_rollouts(root: Path, rows: list[dict], space: ActionSpace) -> None:
    """``<task>_rollouts.hdf5`` per task from the per-episode parts, in episode order (so the file does not
    depend on which worker finished first). The parts stay (hidden from dataset readers): a later resume with
    more episodes rebuilds the files from them."""
    by_task: dict[str, list] = {}
    for row in rows:
        part = _part_path(root, row)
        if not part.exists():
            raise FileNotFoundError(
                f"{part}: episode {row['episode']} of {row['task']} is in episodes.jsonl but its recording is "
                "missing (evaluated without --record, or by an older version); evaluate into a new --out to record it")
        by_task.setdefault(row["task"], []).extend(read_episodes(part))
    for task, eps in by_task.items():
        write_episodes(root / f"{task}_rollouts.hdf5", eps, action_space=space)
