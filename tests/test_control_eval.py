"""Evaluation end to end on the twin with a tiny trained policy: results.json, workers, report, collect --policy."""

import dataclasses
import json
import os

import pytest

from pivla.control.calibrate import calibrate
from pivla.control.executors import executor_config
from pivla.data.hdf5 import write_episodes
from pivla.data.read import read_dataset
from pivla.evaluation.runner import EvalConfig, auroc, evaluate
from pivla.policy import load_policy
from pivla.training.checkpoint import write_calibration
from pivla.training.trainer import train
from tests.conftest import tiny_train_config, twin_pick_place_data

KEYS = {"success_rate", "ci95", "episodes", "per_task", "executor", "mean_executed_horizon", "replans", "prunes",
        "pauses", "control_hz", "failure_prediction", "failure_stages"}


@pytest.fixture(scope="module")
def tiny_policy(tmp_path_factory):
    root = tmp_path_factory.mktemp("evalpolicy")
    twin_pick_place_data(root / "data", 2)
    run = train(tiny_train_config(root / "data", root / "run", steps=10, val_fraction=0.0))
    calib, stats = calibrate(load_policy(run, device="cpu"), read_dataset(root / "data"), source="test")
    write_calibration(run, vars(calib), stats)
    return run


def _eval(run, out, executor="aurd", workers=1, seed=7, **kw):
    cfg = EvalConfig(policy=str(run), out=str(out), tasks="0,1", executor=executor_config(executor), episodes=2,
                     seed=seed, workers=workers, max_steps=12, videos=1, **kw)
    return evaluate(cfg, progress=False)


def test_eval_writes_complete_results(tiny_policy, tmp_path):
    res = _eval(tiny_policy, tmp_path / "e")
    assert KEYS <= set(res)
    assert res["episodes"] == 4 and set(res["per_task"]) == {"block_away", "block_left"}
    lo, hi = res["ci95"]
    assert 0 <= lo <= res["success_rate"] <= hi <= 1
    on_disk = json.loads((tmp_path / "e" / "results.json").read_text())
    assert on_disk["episodes"] == 4 and on_disk["executor"] == "aurd"
    assert on_disk["encoder_runtime"] in {"onnx", "torch"}  # where AURD's observed latents were computed
    assert len(list((tmp_path / "e" / "traces").glob("*.json"))) == 4
    assert len(list((tmp_path / "e" / "videos").glob("*.mp4"))) == 1
    trace = json.loads(next((tmp_path / "e" / "traces").glob("*.json")).read_text())["trace"]
    assert {"u_act", "u_pred", "u", "v", "event", "replanned"} <= set(trace[0])
    rows = [json.loads(line) for line in (tmp_path / "e" / "episodes.jsonl").read_text().splitlines()]
    assert all(0.0 <= r["stage_progress"] <= 1.0 for r in rows)
    failed = [r for r in rows if not r["success"]]
    assert sum(res["failure_stages"].values()) == len(failed)


def test_bench_control_on_a_calibrated_run_times_the_same_plans(tiny_policy, capsys):
    """A calibrated run would replan on the bench's random observations; the bench lifts its thresholds so
    that fixed and AURD query the policy equally often and the gap is pure per-step overhead, both for the
    controller alone and in closed loop with the twin."""
    from pivla.cli import main

    assert main(["bench", "control", "--policy", str(tiny_policy), "--steps", "12", "--repeats", "1",
                 "--loop-episodes", "1", "--json"]) == 0
    out = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert out["policy_queries"]["aurd"] == out["policy_queries"]["fixed"]
    assert out["encode_ms_median"] > 0 and out["query_ms_median"] > 0
    # closed loop in the twin: identical plans give identical episodes, so the timing compares like with like
    assert out["loop_same_episodes"] is True and out["loop_steps"] > 0
    assert out["loop_aurd_ms_per_step"] > 0 and out["loop_fixed_ms_per_step"] > 0
    # the executors' own time is part of the step (AURD's includes its encodings)
    assert 0 < out["loop_fixed_executor_ms"] < out["loop_fixed_ms_per_step"]
    assert 0 < out["loop_aurd_executor_ms"] < out["loop_aurd_ms_per_step"]
    # on a CPU with onnxruntime installed the target encoder runs there, and PyTorch's encoding is timed too
    if out["encoder_runtime"] == "onnx":
        assert out["encode_ms_median_torch"] > 0


def _episodes(d):
    """Everything an episode did (outcome, plans, every traced signal), without timings."""
    rows = [json.loads(line) for line in (d / "episodes.jsonl").read_text().splitlines()]
    return sorted(({k: v for k, v in r.items() if k not in ("wall_s", "control_ms_mean")} for r in rows),
                  key=lambda r: (r["task_index"], r["episode"]))


def _same_episodes(a, b):
    assert [(r["task"], r["episode"], r["seed"], r["success"], r["steps"], r["plan_events"]) for r in a] == \
           [(r["task"], r["episode"], r["seed"], r["success"], r["steps"], r["plan_events"]) for r in b]
    for ra, rb in zip(a, b):
        for sa, sb in zip(ra["trace"], rb["trace"], strict=True):
            assert sa.keys() == sb.keys()
            for k in sa:
                if isinstance(sa[k], float):
                    assert sa[k] == pytest.approx(sb[k], rel=1e-4, abs=1e-6), k
                else:
                    assert sa[k] == sb[k], k


def test_workers_give_the_same_results_as_one_process(tiny_policy, tmp_path):
    one = _eval(tiny_policy, tmp_path / "one")
    two = _eval(tiny_policy, tmp_path / "two", workers=2)
    _same_episodes(_episodes(tmp_path / "one"), _episodes(tmp_path / "two"))
    assert one["success_rate"] == two["success_rate"] and one["replans"] == two["replans"]
    # the comparison can tell runs apart: other seeds give other traces (seed labels aside)
    _eval(tiny_policy, tmp_path / "other", seed=8)
    other = [r | {"seed": o["seed"]} for r, o in zip(_episodes(tmp_path / "other"), _episodes(tmp_path / "one"))]
    with pytest.raises(AssertionError):
        _same_episodes(_episodes(tmp_path / "one"), other)


def test_eval_resumes_from_episode_log(tiny_policy, tmp_path, monkeypatch):
    """After a write torn mid-line, the rerun plays only the missing episodes, and the log ends up holding
    every episode once (the first new row is not glued to the torn line)."""
    from pivla.evaluation import runner

    _eval(tiny_policy, tmp_path / "r", executor="fixed")
    log = tmp_path / "r" / "episodes.jsonl"
    lines = log.read_text().splitlines()
    log.write_text("\n".join(lines[:2]) + "\n" + lines[2][:20])  # interrupted mid-write
    played, real = [], runner._run_job
    monkeypatch.setattr(runner, "_run_job", lambda job: played.append(job[:3]) or real(job))
    res = _eval(tiny_policy, tmp_path / "r", executor="fixed")
    assert res["episodes"] == 4 and len(played) == 2
    rows = runner.load_rows(log)
    assert sorted(runner._key(r) for r in rows) == sorted(runner._key(json.loads(line)) for line in lines)


def test_every_executor_runs_and_report_renders(tiny_policy, tmp_path):
    from pivla.experiments.report import write_report

    for ex in ("fixed", "ensemble", "adahorizon"):
        assert _eval(tiny_policy, tmp_path / "cond" / ex, executor=ex)["executor"] == ex
    _eval(tiny_policy, tmp_path / "cond" / "aurd")
    report = write_report(tmp_path).read_text()
    assert "Each executor against AURD" in report and (tmp_path / "figures" / "uncertainty_timeline.png").exists()
    # the paired table: the condition against every other executor, with the interval and McNemar's p
    assert "episode by episode" in report and "| cond | fixed |" in report and "| cond | ensemble |" in report


def test_report_takes_distraction_level_0_from_in_distribution(tiny_policy, tmp_path, monkeypatch):
    """The demo does not replay its in-distribution episodes as level 0 of the Fig. 8 sweep: the report
    borrows them, and says so."""
    from pivla.experiments import report as rep

    _eval(tiny_policy, tmp_path / "in_distribution" / "aurd")
    _eval(tiny_policy, tmp_path / "distraction_level_2" / "aurd", perturb="level=2")
    seen = {}
    monkeypatch.setattr(rep, "plot_levels", lambda levels, path: seen.update(levels))
    text = rep.write_report(tmp_path).read_text()
    in_dist = json.loads((tmp_path / "in_distribution" / "aurd" / "results.json").read_text())
    assert sorted(seen["aurd"]) == [0, 2] and seen["aurd"][0] == in_dist
    assert "Level 0 of aurd is the in_distribution evaluation" in text


def test_rollouts_are_recorded_with_failures_for_training(tiny_policy, tmp_path):
    from pivla.cli import main

    assert main(["collect", "--env", "tabletop", "--suite", "pick_place", "--tasks", "0", "--episodes", "2",
                 "--policy", str(tiny_policy), "--out", str(tmp_path / "roll"), "--seed", "3"]) == 0
    eps = read_dataset(tmp_path / "roll")
    assert len(eps) == 2 and all(e.source == "policy" for e in eps)
    assert all(len(e.rewards) == len(e) for e in eps)
    assert all(e.meta["split"] == "train" for e in eps)  # training rollouts, not test episodes
    for flag in (["--miss", "0.3"], ["--paraphrase"], ["--image-size", "64"]):  # expert-only: refused, not ignored
        with pytest.raises(SystemExit, match=flag[0]):
            main(["collect", "--env", "tabletop", "--suite", "pick_place", "--episodes", "1", *flag,
                  "--policy", str(tiny_policy), "--out", str(tmp_path / "roll2")])


def test_recordings_survive_an_interrupted_evaluation(tiny_policy, tmp_path):
    """A resumed evaluation records every episode, not only those run after the resume; in episode order."""
    import numpy as np

    out, rec = tmp_path / "e", tmp_path / "rec"
    cfg = EvalConfig(policy=str(tiny_policy), out=str(out), tasks="0", executor=executor_config("fixed"), episodes=1,
                     seed=7, max_steps=6, videos=0, record=str(rec))
    evaluate(cfg, progress=False)  # "interrupted" after one episode
    first = read_dataset(rec)
    cfg.episodes = 3
    evaluate(cfg, progress=False)
    eps = read_dataset(rec)
    logged = [json.loads(line) for line in (out / "episodes.jsonl").read_text().splitlines()]
    assert [e.meta["seed"] for e in eps] == [r["seed"] for r in logged]
    assert len(eps) == 3 and np.array_equal(eps[0].actions, first[0].actions)
    assert len(list((rec / ".parts").glob("*.hdf5"))) == 3  # kept for later resumes, not read as data
    # more episodes and another worker count resume; another head or seed would mix two evaluations
    for change, name in (({"gripper_head": "continuous"}, "gripper_head"), ({"seed": 8}, "seed")):
        with pytest.raises(SystemExit, match=name):
            evaluate(dataclasses.replace(cfg, episodes=4, **change), progress=False)
    assert len((out / "episodes.jsonl").read_text().splitlines()) == 3
    # recorded test rollouts say so, and thresholds are never calibrated on them
    assert all(e.meta["split"] == "test" and e.meta["eval_seed"] == 7 for e in eps)
    with pytest.raises(ValueError, match="test rollouts"):
        calibrate(load_policy(tiny_policy, device="cpu"), eps)


def test_auroc_hand_computed():
    assert auroc([0.9, 0.8, 0.1], [1, 1, 0]) == 1.0
    assert auroc([0.1, 0.8, 0.9], [1, 0, 0]) == 0.0
    assert auroc([0.5, 0.5], [1, 0]) == 0.5
    assert auroc([0.5], [1]) is None


def test_calibrate_on_the_runs_held_out_episodes(synthetic_data, tmp_path, capsys):
    """``pivla calibrate --held-out`` uses exactly the episodes split.json kept out of training."""
    from pivla.cli import main
    from pivla.cli.evaluate import held_out_episodes
    from pivla.control.calibrate import CalibrationConfig

    run = train(tiny_train_config(synthetic_data, tmp_path / "run", steps=2, val_fraction=0.25))
    split = json.loads((run / "split.json").read_text())
    episodes = read_dataset(synthetic_data)
    held = held_out_episodes(str(run), episodes)
    assert len(held) == len(split["val_episodes"]) > 0
    assert all(h is episodes[i] for h, i in zip(held, split["val_episodes"]))
    assert main(["calibrate", "--policy", str(run), "--data", str(synthetic_data), "--held-out"]) == 0
    saved = json.loads((run / "calibration.json").read_text())
    assert saved["source"].endswith("(held-out split)") and saved["tau_high"] >= saved["tau_low"]
    stats = json.loads((run / "calibration_stats.json").read_text())
    defaults = CalibrationConfig()
    assert stats["percentiles"] == {"tau_low": defaults.tau_low_pct, "tau_high": defaults.tau_high_pct,
                                    "v_thresh": defaults.v_pct}
    assert main(["calibrate", "--policy", str(run), "--data", str(synthetic_data), "--held-out",
                 "--calibration.tau-high-pct", "60"]) == 0
    lower = json.loads((run / "calibration.json").read_text())
    assert json.loads((run / "calibration_stats.json").read_text())["percentiles"]["tau_high"] == 60
    assert lower["tau_low"] == saved["tau_low"] and lower["tau_high"] <= saved["tau_high"]
    with pytest.raises(SystemExit, match="trained on"):
        held_out_episodes(str(run), episodes[:-1])


def test_demo_calibrates_on_successful_rollouts_else_on_demos(tiny_policy, tmp_path):
    """The demo's thresholds come from the policy's own successful validation rollouts; with none, from the
    validation demonstrations (and the source recorded says which)."""
    import shutil

    from pivla.experiments.stages import calibrate_on_rollouts

    demos = tiny_policy.parent / "data"
    run = shutil.copytree(tiny_policy, tmp_path / "run")  # the fixture stays as is
    failed = [dataclasses.replace(ep, success=False) for ep in read_dataset(demos)]
    write_episodes(tmp_path / "failed" / "r_rollouts.hdf5", failed)
    assert calibrate_on_rollouts(run, tmp_path / "failed", demos) == str(demos)
    assert load_policy(run, device="cpu").calibration.source == str(demos)
    write_episodes(tmp_path / "mixed" / "r_rollouts.hdf5", failed[:1] + read_dataset(demos)[:1])
    calibrate_on_rollouts(run, tmp_path / "mixed", demos)
    calib = load_policy(run, device="cpu").calibration
    assert calib.source == str(tmp_path / "mixed") and calib.pred_baseline == "episode"


def test_calibration_with_episode_baseline_is_recorded_and_not_above_raw(tiny_policy):
    from pivla.control.calibrate import CalibrationConfig

    policy, demos = load_policy(tiny_policy, device="cpu"), read_dataset(tiny_policy.parent / "data")
    raw, _ = calibrate(policy, demos, CalibrationConfig(pred_baseline="none"))
    rel, _ = calibrate(policy, demos, CalibrationConfig(pred_baseline="episode"))
    assert raw.pred_baseline == "none" and rel.pred_baseline == "episode"
    assert rel.tau_high <= raw.tau_high and rel.tau_low <= raw.tau_low


def test_report_leaves_out_validation_rollouts(tmp_path):
    from pivla.experiments.report import find_evaluations

    for cond, split in (("in_distribution", "test"), ("val_rollouts_eval", "validation")):
        (tmp_path / cond / "fixed").mkdir(parents=True)
        (tmp_path / cond / "fixed" / "results.json").write_text(json.dumps({"executor": "fixed", "split": split}))
    assert list(find_evaluations(tmp_path)) == [("in_distribution", "fixed")]


def test_ablation_trains_calibrates_and_tabulates_variants(tiny_policy, tmp_path):
    """`pivla ablate` in miniature: every trained variant goes through the demo's recipe (its own validation
    rollouts, then calibration), the table has one row per variant, and a second run reuses everything."""
    from pivla.experiments.studies.ablate import AblationConfig, run_ablation
    from tests.conftest import tiny_train_config

    data = tiny_policy.parent / "data"
    cfg = AblationConfig(data=str(data), val=str(data), out=str(tmp_path / "abl"), tasks="0",
                         episodes=1, val_episodes=1, workers=1, max_steps=8,
                         variants=("full", "il_only", "continuous_il_only", "fixed_h5"),
                         train=tiny_train_config(data, tmp_path, steps=4, batch_size=4))
    table = run_ablation(cfg)
    for row in ("| full |", "| il_only |", "| fixed_h5 |"):
        assert row in table
    # Table 7 builds PI-VLA up from the OFT-like row, each row against the one above it
    t7 = table.split("## Table 7")[1].split("##")[0].strip().splitlines()[4:]
    assert [r.split(" | ")[0] for r in t7] == ["| continuous head, IL only, fixed H=5 (OpenVLA-OFT)",
                                              "| + dual heads (discrete + continuous)",
                                              "| + unified loss (L_IL + alpha L_RL + beta L_SP)",
                                              "| + AURD (full PI-VLA)"]
    assert t7[0].split(" | ")[2] == "" and all(r.split(" | ")[2].startswith(("+", "-")) for r in t7[1:])
    runs = tmp_path / "abl" / "runs"
    il_loss = json.loads((runs / "il_only" / "config.json").read_text())["loss"]
    assert not (il_loss["use_rl"] or il_loss["use_sp"] or il_loss["use_recon"])
    oft = json.loads((runs / "continuous_il_only" / "config.json").read_text())["loss"]
    assert not (oft["use_discrete"] or oft["use_rl"] or oft["use_sp"]) and oft["use_continuous"]
    for name in ("full", "il_only"):
        assert (tmp_path / "abl" / "val_rollouts_eval" / name / "results.json").exists()
        assert load_policy(runs / name, device="cpu").calibration.pred_baseline == "episode"
    weights = (runs / "full" / "model.safetensors").stat().st_mtime_ns
    assert run_ablation(cfg) == table
    assert (runs / "full" / "model.safetensors").stat().st_mtime_ns == weights
    assert (tmp_path / "abl" / "ablation.md").read_text() == table


def test_eval_threads_respect_omp_and_in_process_eval_restores_them(tiny_policy, tmp_path, monkeypatch):
    """An in-process evaluation must not leave its thread count behind: an ablation trains right after it,
    and two processes each running two OpenMP threads on two cores slowed training ~5x."""
    import torch

    from pivla.evaluation.runner import eval_threads

    monkeypatch.setenv("OMP_NUM_THREADS", "1")
    assert eval_threads(1) == 1
    monkeypatch.delenv("OMP_NUM_THREADS")
    assert eval_threads(1) == max(1, os.cpu_count() or 2)
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        _eval(tiny_policy, tmp_path / "ev", executor="fixed")
        assert torch.get_num_threads() == 1
    finally:
        torch.set_num_threads(before)


def test_an_evaluation_pool_plays_each_evaluation_as_its_own_workers_would(tiny_policy, tmp_path):
    """One pool serves consecutive evaluations (the demo's cells): every evaluation loads its own policy and
    envs in each worker, so its episodes are those of an evaluation alone, also when the policy changed. Its
    processes start with the first evaluation and end with the block."""
    import multiprocessing
    import shutil

    from safetensors.torch import load_file, save_file

    from pivla.evaluation.runner import evaluation_pool

    other = tmp_path / "other_policy"
    shutil.copytree(tiny_policy, other, ignore=shutil.ignore_patterns("checkpoints"))
    weights = load_file(other / "model.safetensors")
    save_file({k: v + 0.01 if v.is_floating_point() else v for k, v in weights.items()}, other / "model.safetensors")
    with evaluation_pool(2):
        assert not multiprocessing.active_children()  # nothing to play yet: no process started
        _eval(tiny_policy, tmp_path / "pooled_a", workers=2)
        _eval(other, tmp_path / "pooled_b", workers=2)
    assert not multiprocessing.active_children()
    _eval(tiny_policy, tmp_path / "alone_a")
    _eval(other, tmp_path / "alone_b")
    _same_episodes(_episodes(tmp_path / "pooled_a"), _episodes(tmp_path / "alone_a"))
    _same_episodes(_episodes(tmp_path / "pooled_b"), _episodes(tmp_path / "alone_b"))
    with pytest.raises(AssertionError):  # the two policies play differently: a worker kept from before would show
        _same_episodes(_episodes(tmp_path / "alone_b"), _episodes(tmp_path / "alone_a"))
