"""`pivla benchmark twin`: pooled paired statistics, the evaluation plan, and a miniature run end to end."""

import dataclasses
import json

import pytest

from pivla.envs import seeds
from pivla.experiments.layout import TwinLayout
from pivla.experiments.results import ResultsStore
from pivla.experiments.studies import twin as benchmark
from pivla.experiments.studies.twin import BenchmarkConfig
from pivla.io import atomic_write_json


def _write_eval(root, seed, policy, cell, label, successes, traces=None):
    d = root / f"seed{seed}" / "test" / policy / cell / label
    d.mkdir(parents=True)
    rows = [{"task": "block_away", "task_index": 0, "episode": i, "success": bool(s),
             "seed": seeds.seed_for("test", "in_distribution", "block_away", i),
             "trace": traces[i] if traces else []} for i, s in enumerate(successes)]
    (d / "episodes.jsonl").write_text("".join(json.dumps(r) + "\n" for r in rows))
    atomic_write_json(d / "results.json", {"successes": sum(successes), "episodes": len(successes)})


def test_comparisons_pair_episodes_within_each_seed_and_pool_the_seeds(tmp_path):
    """Seed 0: A = 1100, B = 1001; seed 1: A = 111, B = 001. Pooled: 3 pairs only A solved, 1 only B, n 7,
    difference 2/7, exact McNemar p = 2 * (C(4,0) + C(4,1)) / 2**4 = 0.625."""
    _write_eval(tmp_path, 0, "main", "in_distribution", "aurd", [1, 1, 0, 0])
    _write_eval(tmp_path, 0, "main", "in_distribution", "fixed", [1, 0, 0, 1])
    _write_eval(tmp_path, 1, "main", "in_distribution", "aurd", [1, 1, 1])
    _write_eval(tmp_path, 1, "main", "in_distribution", "fixed", [0, 0, 1])
    res = ResultsStore(TwinLayout(tmp_path))
    c = res.compare(("main", "in_distribution", "aurd"), ("main", "in_distribution", "fixed"))
    assert (c["n"], c["only_a"], c["only_b"]) == (7, 3, 1)
    assert c["diff"] == pytest.approx(2 / 7) and c["p_mcnemar"] == pytest.approx(0.625)
    rate = res.rate("main", "in_distribution", "aurd")
    assert (rate["successes"], rate["episodes"]) == (5, 7)
    assert res.compare(("main", "in_distribution", "aurd"), ("main", "unseen_env", "fixed")) is None  # not run
    # benchmark.json names both sides of every comparison beside its counts
    atomic_write_json(tmp_path / "benchmark_config.json", dataclasses.asdict(BenchmarkConfig(out=str(tmp_path))))
    benchmark.write_benchmark_report(tmp_path)
    records = json.loads((tmp_path / "benchmark.json").read_text())["comparisons"]
    assert [(r["a"], r["b"], r["only_a"], r["only_b"]) for r in records if r["table"] == "headline"] == [
        (["main", "in_distribution", "aurd"], ["main", "in_distribution", "fixed"], 3, 1)]


def test_departures_group_aurds_paired_episodes_by_its_first_cut(tmp_path):
    """Seed 0: AURD cuts nothing in episode 0 (both solve it), replans first in 1 (only AURD solves it) and 2
    (only fixed); seed 1: it pauses first in episode 0 (only fixed). Pooled: none 1: 0 / 0, replan 2: 1 / 1,
    pause 1: 0 / 1, prune 0."""
    traces = {0: [[{"ended": "complete"}], [{"ended": "replan"}],
                  [{"ended": "complete"}, {"ended": "replan", "event": "pause"}]],
              1: [[{"event": "pause", "ended": "complete"}]]}
    _write_eval(tmp_path, 0, "main", "unseen_env", "aurd", [1, 1, 0], traces[0])
    _write_eval(tmp_path, 0, "main", "unseen_env", "fixed", [1, 0, 1])
    _write_eval(tmp_path, 1, "main", "unseen_env", "aurd", [0], traces[1])
    _write_eval(tmp_path, 1, "main", "unseen_env", "fixed", [1])
    dep = ResultsStore(TwinLayout(tmp_path)).departures("main", "unseen_env")
    assert {g: tuple(v.values()) for g, v in dep.items()} == {
        "none": (1, 0, 0), "replan": (2, 1, 1), "prune": (0, 0, 0), "pause": (1, 0, 1)}
    assert ResultsStore(TwinLayout(tmp_path)).departures("main", "in_distribution") is None  # not run
    atomic_write_json(tmp_path / "benchmark_config.json", dataclasses.asdict(BenchmarkConfig(out=str(tmp_path))))
    benchmark.write_benchmark_report(tmp_path)
    rows = json.loads((tmp_path / "benchmark.json").read_text())["tables"]["departures"]
    assert [r["cell"] for r in rows] == ["unseen_env", "all"]
    assert rows[-1]["replan"] == {"episodes": 2, "only_aurd": 1, "only_fixed": 1, "p_mcnemar": 1.0}


def test_a_report_of_a_run_stopped_early_draws_no_empty_figures(tmp_path):
    """Before the test stage (every evaluation still missing) the report has its tables and no figures."""
    atomic_write_json(tmp_path / "benchmark_config.json", dataclasses.asdict(BenchmarkConfig(out=str(tmp_path))))
    benchmark.write_benchmark_report(tmp_path)
    data = json.loads((tmp_path / "benchmark.json").read_text())
    assert data["figures"] == [] and not (tmp_path / "figures").exists()
    assert "not run" in (tmp_path / "benchmark.md").read_text()


def test_every_decision_is_taken_on_validation_seeds_and_the_plan_tests_each_table(tmp_path):
    cfg = BenchmarkConfig(out=str(tmp_path))
    b = benchmark.Benchmark(cfg)
    b.decisions = {"hardest": {"cell": "push_arm_6"}, "failure_round": {"headline": "round2"}}
    plan = b.test_plan("push_arm_6")
    keys = {(p, c.name, label) for p, c, label, _ in plan}
    assert len(keys) == len(plan)  # no evaluation twice
    for cell in benchmark.headline_cells(cfg):
        assert all(("round2", cell, e) in keys for e in benchmark.EXECUTORS)
    assert ("round2", "in_distribution_ideal", "aurd") in keys and ("main", "push_arm_6", "aurd") in keys
    assert all(("seen", "unseen_tasks", e) in keys for e in benchmark.EXECUTORS)
    assert all((f"abl_{v}", "push_arm_6", "fixed") in keys for v in ("discrete_only", "no_rl", "continuous_il_only"))
    unseen = next(c for p, c, _, _ in plan if c.name == "unseen_tasks")
    assert unseen.suite == "pick_place_unseen" and unseen.condition == "unseen_tasks"

    # which seed family each stage evaluates on: both decisions on validation, the failure round's rollouts on
    # train, the tables on test
    calls: list[tuple[str, str, str, str]] = []

    def fake_evaluate(seed, split, policy, cell, label, executor, record=None):
        calls.append((split, policy, cell.name, label))
        return {"successes": len(cell.name) % 7, "episodes": 10}  # a made-up success rate per condition

    b.evaluate = fake_evaluate
    hardest = b.choose_hardest()
    rates = {n: len(n) % 7 for n in benchmark.candidate_cells(cfg)}
    assert hardest["cell"] == min(rates, key=rates.get) and {c[0] for c in calls} == {"validation"}
    calls.clear()
    b.choose_round(hardest["cell"])
    assert {c[0] for c in calls} == {"validation"} and {c[1] for c in calls} == {"main", "round2"}
    calls.clear()
    b.record_rollouts(0)
    assert {c[0] for c in calls} == {"train"} and len(calls) == len(benchmark.ROLLOUT_CELLS)
    calls.clear()
    b.test("push_arm_6", ["round2", "seen"])
    assert {c[0] for c in calls} == {"test"} and {c[1] for c in calls} == {"round2", "seen"}


def test_the_other_suites_policy_balances_its_tasks_shifts_its_agent_view_and_averages_its_weights(tmp_path):
    b = benchmark.Benchmark(BenchmarkConfig(out=str(tmp_path)))
    others = b._train_config("others", 0)
    assert others.task_balance == 1.0 and len(others.extra_data) == 2  # long, then drawer and stack
    assert others.augment_shift_cameras == ("agentview_rgb",) and others.ema_decay == 0.999  # the wrist view unshifted
    assert b._train_config("main", 0).augment_shift_cameras == () and b._train_config("main", 0).ema_decay == 0.0
    assert b._train_config("main", 0).task_balance == 0.0 and b._train_config("abl_no_rl", 0).task_balance == 0.0


@pytest.mark.timeout(1200)
def test_quick_benchmark_writes_a_complete_benchmark_json(tmp_path):
    """The smoke sizes, smaller still (about 2 min on 2 cores): every stage runs for real (collection, 13
    trainings, calibration, decisions, tests) and every table of benchmark.json is filled; `pivla report
    --dir` rewrites the same."""
    from pivla.cli import main

    cfg = dataclasses.replace(benchmark.quick(), out=str(tmp_path / "b"), train_episodes=2, steps=3, batch_size=4,
                              max_steps=4, tasks="ball_left", workers=1)
    report = benchmark.run_benchmark(cfg)
    data = json.loads((tmp_path / "b" / "benchmark.json").read_text())
    tables = ("headline", "table2", "table3", "suites", "displace_object", "push_arm", "realism", "table4", "table5",
              "table6", "table7", "failure_round", "sensitivity", "demo_counts", "departures", "compute")
    assert set(tables) <= set(data["tables"]) and all(data["tables"][t] for t in tables)
    assert data["hardest_condition"] in benchmark.candidate_cells(cfg)
    assert data["headline_policy"] in ("main", "round2")
    for rec in data["tables"]["headline"]:
        assert all(rec["success"][e] is not None for e in benchmark.EXECUTORS)
        assert all(rec["aurd_minus"][b] is not None for b in benchmark.BASELINES)
    assert all(r["queries_per_100_steps"] > 0 for r in data["tables"]["compute"])
    assert [r["task"] for r in data["tables"]["table2"]] == ["ball_left"]
    assert all((tmp_path / "b" / f).exists() for f in data["figures"]) and len(data["figures"]) == 4
    # the failure round trained on the main policy's recorded rollouts
    rollouts = list((tmp_path / "b" / "seed0" / "train_rollouts").rglob("*_rollouts.hdf5"))
    assert rollouts
    config = json.loads((tmp_path / "b" / "seed0" / "policies" / "round2" / "config.json").read_text())
    assert len(config["extra_data"]) == len(benchmark.ROLLOUT_CELLS)
    before = data["tables"]
    assert main(["report", "--dir", str(tmp_path / "b")]) == 0
    assert json.loads((tmp_path / "b" / "benchmark.json").read_text())["tables"] == before
    assert "Table 7" in report.read_text()


def test_the_training_demonstrations_take_the_configured_perturbation_and_validation_ones_none(tmp_path, monkeypatch):
    made = []
    monkeypatch.setattr(benchmark, "Collect", lambda cfg: made.append(cfg) or (lambda: None))
    b = benchmark.Benchmark(BenchmarkConfig(out=str(tmp_path), train_perturb="randomized_scene,recovery=1"))
    b.collect("main")
    train, val = made
    assert (train.suite, train.seed_family, train.perturb) == ("pick_place", "train", "randomized_scene,recovery=1")
    assert (val.seed_family, val.perturb, val.noise, val.miss) == ("validation", None, 0.0, 0.0)
    assert BenchmarkConfig().train_perturb == "randomized_scene"
