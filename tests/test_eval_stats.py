"""Paired statistics of the benchmark, against values computed by hand (in the comments) and published ones; the
stage clock of resumable runs; the experts' success table."""

import time

import numpy as np
import pytest

from pivla.evaluation.stats import (
    compare,
    mcnemar_exact,
    newcombe_paired_interval,
    paired_difference,
    paired_rows,
    paired_successes,
    wilson_interval,
)
from pivla.experiments.stages import StageTimes
from pivla.experiments.studies.libero import expert_table
from pivla.io import read_json

Z2 = 1.959963984540054**2  # 3.841459


def _outcomes(both, a_only, b_only, neither):
    """Success vectors realising a paired 2x2 table, in a shuffled episode order."""
    a = [1] * both + [1] * a_only + [0] * b_only + [0] * neither
    b = [1] * both + [0] * a_only + [1] * b_only + [0] * neither
    order = np.random.default_rng(0).permutation(len(a))
    return np.array(a, bool)[order], np.array(b, bool)[order]


def test_wilson_matches_hand_values():
    # 8 of 10: denom = 1 + z^2/10 = 1.384146; centre = (0.8 + z^2/20) / denom = 0.992073 / 1.384146 = 0.716740;
    # half = z * sqrt(0.8 * 0.2 / 10 + z^2 / 400) / denom = 1.959964 * 0.160011 / 1.384146 = 0.226578
    assert wilson_interval(8, 10) == pytest.approx((0.716740 - 0.226578, 0.716740 + 0.226578), abs=2e-6)
    # 10 of 10: lower = n / (n + z^2) = 10 / 13.841459 = 0.722467, upper 1
    assert wilson_interval(10, 10) == pytest.approx((0.722467, 1.0), abs=1e-6)
    assert wilson_interval(0, 0) == (0.0, 1.0)
    for bad in ((3, 2), (-1, 4), (0, -1)):
        with pytest.raises(ValueError, match="successes"):
            wilson_interval(*bad)


def test_mcnemar_exact_by_hand():
    # b = 1, c = 6: n = 7, P(X <= 1) = (C(7,0) + C(7,1)) / 2^7 = 8 / 128 = 0.0625, two-sided 0.125
    assert mcnemar_exact(1, 6) == pytest.approx(0.125)
    assert mcnemar_exact(6, 1) == pytest.approx(0.125)
    # b = 0, c = 5: 2 * (1 / 32) = 0.0625
    assert mcnemar_exact(0, 5) == pytest.approx(0.0625)
    # b = 2, c = 8: (1 + 10 + 45) / 1024 = 56 / 1024, doubled 0.109375
    assert mcnemar_exact(2, 8) == pytest.approx(0.109375)
    assert mcnemar_exact(0, 0) == 1.0 and mcnemar_exact(3, 3) == 1.0 and mcnemar_exact(4, 5) == 1.0
    assert 0 < mcnemar_exact(2000, 2200) < 0.01  # exact integers: no overflow or underflow at this size
    with pytest.raises(ValueError):
        mcnemar_exact(-1, 2)


def test_mcnemar_agrees_with_scipys_binomial_test():
    stats = pytest.importorskip("scipy.stats")
    for b, c in ((10, 30), (17, 9), (250, 300), (0, 12)):
        assert mcnemar_exact(b, c) == pytest.approx(stats.binomtest(b, b + c, 0.5).pvalue, rel=1e-9)


def test_newcombe_paired_interval_by_hand():
    """Table (both, only A, only B, neither) = (5, 3, 1, 1), n = 10: p_A = 8/10 = 0.8, p_B = 6/10 = 0.6.
    Wilson 8/10 = (0.490162, 0.943318) (previous test); Wilson 6/10: centre = (0.6 + 0.192073) / 1.384146 =
    0.572247, half = 1.959964 * sqrt(0.024 + 0.009604) / 1.384146 = 0.259574 -> (0.312674, 0.831820).
    ad - bc = 5 - 3 = 2 <= n/2 = 5, so phi = 0:
    lower = 0.2 - sqrt((0.8 - 0.490162)^2 + (0.831820 - 0.6)^2) = 0.2 - sqrt(0.095999 + 0.053740) = -0.186962
    upper = 0.2 + sqrt((0.943318 - 0.8)^2 + (0.6 - 0.312674)^2) = 0.2 + sqrt(0.020540 + 0.082556) = 0.521086"""
    assert newcombe_paired_interval(5, 3, 1, 1) == pytest.approx((-0.186962, 0.521086), abs=2e-6)
    # Same margins, more concordance: (6, 2, 0, 2). ad - bc = 12 > 5, so phi = (12 - 5) / sqrt(8 * 2 * 6 * 4) =
    # 7 / 19.595918 = 0.357217:
    # lower = 0.2 - sqrt(0.149740 - 2 * 0.357217 * 0.309838 * 0.231820) = 0.2 - sqrt(0.098424) = -0.113727
    # upper = 0.2 + sqrt(0.103096 - 2 * 0.357217 * 0.143318 * 0.287326) = 0.2 + sqrt(0.073677) = 0.471434
    assert newcombe_paired_interval(6, 2, 0, 2) == pytest.approx((-0.113727, 0.471434), abs=2e-6)


def test_newcombe_paired_interval_reproduces_published_values():
    # Fagerland, Lydersen & Laake, "Statistical Analysis of Contingency Tables" (2017), ch. 8, Cavo et al. (2012):
    # table [[59, 6], [16, 80]], Newcombe square-and-add -0.0621 (-0.1186 to -0.0046); and [[1, 0], [0, 1]]:
    # 0 (-0.5734 to 0.5734)
    assert newcombe_paired_interval(59, 6, 16, 80) == pytest.approx((-0.1186, -0.0046), abs=6e-5)
    assert newcombe_paired_interval(1, 0, 0, 1) == pytest.approx((-0.5734, 0.5734), abs=6e-5)


def test_paired_difference_edge_cases():
    # All success, n = 10: p_A = p_B = 1, a margin is empty so phi = 0, and both half-widths are 1 - 0.722467:
    assert paired_difference([True] * 10, [True] * 10) == pytest.approx((0.0, -0.277533, 0.277533), abs=1e-6)
    # All failure is the mirror image
    assert paired_difference([0] * 10, [0] * 10) == pytest.approx((0.0, -0.277533, 0.277533), abs=1e-6)
    # No discordant pairs, 5 both / 5 neither: phi = (25 - 5) / sqrt(5^4) = 0.8; Wilson 5/10 = (0.236593, 0.763407),
    # so each half-width is 0.263407 * sqrt(2 - 2 * 0.8) = 0.263407 * 0.632456 = 0.166593
    diff, lo, hi = paired_difference(*_outcomes(5, 0, 0, 5))
    assert (diff, lo, hi) == pytest.approx((0.0, -0.166593, 0.166593), abs=1e-6)
    # A always, B never (n = 4): the interval stays inside [-1, 1] and excludes 0
    diff, lo, hi = paired_difference([1] * 4, [0] * 4)
    assert diff == 1.0 and 0 < lo < hi <= 1.0
    # concordance narrows the interval against phi = 0 with the same margins
    width = {table: np.diff(paired_difference(*_outcomes(*table))[1:])[0] for table in ((6, 2, 0, 2), (5, 3, 1, 1))}
    assert width[(6, 2, 0, 2)] < width[(5, 3, 1, 1)]
    for a, b, msg in (([1, 0], [1], "same episodes"), ([], [], "no paired"), ([[1]], [[1]], "1-D"),
                      ([2, 0], [1, 0], "0/1")):
        with pytest.raises(ValueError, match=msg):
            paired_difference(a, b)


def test_compare_reports_the_table_the_interval_and_the_test():
    a, b = _outcomes(5, 3, 1, 1)
    out = compare(a, b)
    assert {k: out[k] for k in ("n", "successes_a", "successes_b", "only_a", "only_b")} == {
        "n": 10, "successes_a": 8, "successes_b": 6, "only_a": 3, "only_b": 1}
    assert out["diff"] == pytest.approx(0.2)
    assert out["ci95"] == pytest.approx([-0.186962, 0.521086], abs=2e-6)
    assert out["p_mcnemar"] == pytest.approx(0.625)  # b = 3, c = 1: 2 * (1 + 4) / 16
    reverse = compare(b, a)
    assert reverse["diff"] == pytest.approx(-0.2) and reverse["ci95"] == pytest.approx([-0.521086, 0.186962], abs=2e-6)
    assert compare([1, 1, 1], [1, 1, 1]) | {"ci95": None} == {
        "n": 3, "successes_a": 3, "successes_b": 3, "only_a": 0, "only_b": 0, "diff": 0.0, "ci95": None,
        "p_mcnemar": 1.0}


def test_paired_successes_aligns_rows_and_refuses_other_episodes():
    rows_a = [{"task_index": t, "episode": e, "seed": 10 * t + e, "success": (t + e) % 2 == 0}
              for t in range(2) for e in range(3)]
    rows_b = [dict(r, success=True) for r in reversed(rows_a)]
    a, b = paired_successes(rows_a, rows_b)
    assert a.tolist() == [True, False, True, False, True, False] and b.all()
    assert all(ra["task_index"] == rb["task_index"] and ra["episode"] == rb["episode"]
               for ra, rb in paired_rows(rows_a, rows_b))
    with pytest.raises(ValueError, match="same episodes"):
        paired_successes(rows_a, rows_b[:-1])
    with pytest.raises(ValueError, match="other seeds"):
        paired_successes(rows_a, [dict(r, seed=r["seed"] + 1) for r in rows_b])


def test_stage_times_are_saved_while_a_stage_runs_and_summed_over_invocations(tmp_path):
    """A resumable run killed mid-stage keeps the stage's time up to the last save; a rerun adds to it."""
    path = tmp_path / "timings.json"
    seen = {}

    def stage() -> str:
        time.sleep(0.3)
        seen.update(read_json(path))  # written by the clock while the stage still runs
        return "done"

    assert StageTimes(path, every=0.05).run("train", stage) == "done"
    first = read_json(path)["train"]
    assert 0 < seen["train"] <= first

    def crash() -> None:
        raise RuntimeError("stage failed")

    with pytest.raises(RuntimeError, match="stage failed"):
        StageTimes(path).run("train", crash)
    StageTimes(path).run("eval", lambda: None)
    times = read_json(path)
    assert set(times) == {"train", "eval"} and times["train"] >= first


def test_expert_table_reports_each_task_and_the_suite_with_wilson_intervals():
    results = {"suite": "libero_10", "successes": 92, "episodes": 100, "tasks": [
        {"task": 3, "name": "put_the_bowl_in_the_drawer", "successes": 42, "episodes": 50, "mean_steps": 254.2,
         "failed": [0, 13]},
        {"task": 4, "name": "mugs_on_plates", "successes": 50, "episodes": 50, "mean_steps": 165.0, "failed": []}]}
    lines = expert_table(results).splitlines()
    # Wilson by hand: 42/50 -> [71.49, 91.66]; 50/50 -> [92.87, 100]; 92/100 -> [85.00, 95.89]
    assert lines[2] == "| 3 put the bowl in the drawer | 42 / 50 | [71.5, 91.7] | 254 | 0, 13 |"
    assert lines[3] == "| 4 mugs on plates | 50 / 50 | [92.9, 100.0] | 165 | - |"
    assert lines[4] == "| **libero_10** | **92 / 100** | [85.0, 95.9] | | |"
