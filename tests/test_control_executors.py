"""Executors against a scripted policy whose signals are known exactly."""

import numpy as np
import pytest

from pivla.control import make_executor
from pivla.control.contract import Calibration, ChunkPolicy, PolicySpec
from pivla.control.executors import first_cut
from pivla.control.math import action_uncertainty, adahorizon


class ScriptedPolicy:
    """Chunks whose k-th action is (plan id, k, ...); U_act, values and latents set per test."""

    spec = PolicySpec(cameras=(), image_size=0, proprio=(), chunk=8, horizon=5, latent_dim=4)

    def __init__(self, u_act=None, values=None, latent_error=None, calibration=None):
        self.u_act = np.zeros(8) if u_act is None else np.asarray(u_act, float)
        self.values = np.ones(5) if values is None else np.asarray(values, float)
        self.latent_error = latent_error or {}
        self.calibration = calibration or Calibration(tau_low=0.2, tau_high=0.5, v_thresh=0.3, eta=0.7)
        self.queries = 0
        self.encoded = []

    def infer(self, obs):
        self.queries += 1
        a = np.zeros((8, 7), np.float32)
        a[:, 0] = self.queries
        a[:, 1] = np.arange(8)
        a[:, 6] = 1.0
        deq = a.copy()
        deq[:, 2] = self.u_act * 7  # mean |cont - deq| over 7 dims = u_act
        return {"actions": a, "actions_normalized": a / 10, "continuous_normalized": a, "dequantized": deq,
                "u_act": action_uncertainty(a, deq), "values": self.values, "latents": np.zeros((8, 4)),
                "value_now": np.float32(1)}

    def encode(self, obs):
        self.encoded.append(obs["t"])
        z = np.zeros(4)
        z[0] = self.latent_error.get(obs["t"], 0.0)
        return z

    def to_actions(self, normalized):
        return normalized * 10


def run(executor, policy, steps):
    executor.reset()
    return [executor.act(policy, {"t": t}) for t in range(steps)]


def test_fixed_horizon_replans_every_h_steps():
    p = ScriptedPolicy()
    acts = run(make_executor("fixed", horizon=3), p, 7)
    assert [a[0] for a in acts] == [1, 1, 1, 2, 2, 2, 3]
    assert [a[1] for a in acts] == [0, 1, 2, 0, 1, 2, 0]


def test_aurd_completes_nominal_horizon_when_certain():
    p = ScriptedPolicy()
    ex = make_executor("aurd")
    acts = run(ex, p, 11)
    assert [a[0] for a in acts] == [1] * 5 + [2] * 5 + [3]
    assert ex.plans == [(5, "complete"), (5, "complete")]
    assert all(r["u"] == 0 for r in ex.trace)
    # only observations a decision reads are encoded: not a plan's first step, nor the one after its last
    assert p.encoded == [1, 2, 3, 4, 6, 7, 8, 9]


def test_aurd_after_check_encodes_every_executed_step():
    p = ScriptedPolicy()
    ex = make_executor("aurd", check="after")
    run(ex, p, 11)
    assert p.encoded == [1, 2, 3, 4, 5, 6, 7, 8, 9, 10]


def test_aurd_replans_when_prediction_error_exceeds_tau_high():
    # observation at t=2 deviates from the prediction: U = 0.3 * 2.0 = 0.6 > tau_high before step 3
    p = ScriptedPolicy(latent_error={2: 2.0})
    ex = make_executor("aurd")
    acts = run(ex, p, 4)
    assert [a[0] for a in acts] == [1, 1, 2, 2]
    assert ex.plans[0] == (2, "replan")
    assert ex.trace[2]["replanned"] and ex.trace[2]["ended"] == "replan"
    assert ex.trace[1]["u_pred"] == 0.0
    # the untrusted step was never executed; its U and V travel with the row that replanned
    assert ex.trace[2]["ended_u"] == pytest.approx(0.6) and ex.trace[2]["ended_v"] == 1.0


def test_aurd_prunes_in_band_with_low_value():
    # U_act 0.4 at step 2 (0.7 * 0.4 = 0.28 in (0.2, 0.5]) and V[1] = 0.1 < 0.3
    p = ScriptedPolicy(u_act=[0, 0.4, 0, 0, 0, 0, 0, 0], values=[1, 0.1, 1, 1, 1])
    ex = make_executor("aurd", max_pauses=0)
    run(ex, p, 2)
    assert ex.plans[0] == (1, "prune")


def test_aurd_pauses_then_acts_after_max_pauses():
    p = ScriptedPolicy(u_act=[1.0] + [0] * 7)  # first action never trusted: 0.7 > tau_high
    ex = make_executor("aurd", max_pauses=2, commit_after_cut=False)
    acts = run(ex, p, 4)
    assert np.allclose(acts[0][:6], 0) and acts[0][6] == -1.0  # hold pose, gripper as before (open)
    assert np.allclose(acts[1][:6], 0)
    assert acts[2][0] == 3 and ex.trace[2]["event"] == "forced"
    assert [e for _, e in ex.plans[:2]] == ["pause", "pause"]


def test_aurd_after_order_never_pauses():
    p = ScriptedPolicy(u_act=[1.0] * 8)
    ex = make_executor("aurd", check="after", commit_after_cut=False)
    acts = run(ex, p, 3)
    assert [a[0] for a in acts] == [1, 2, 3]
    assert ex.plans == [(1, "replan"), (1, "replan")]


@pytest.mark.parametrize("monitor", [True, False])
def test_aurd_commits_to_the_plan_after_a_cut(monitor):
    # the observations at t=2 and t=3 both deviate (U = 0.6 > tau_high): the first cut replans at t=2; the
    # plan made there is committed, so t=3 does not cut it again, and the plan after it is checked again
    p = ScriptedPolicy(latent_error={2: 2.0, 3: 2.0, 8: 2.0})
    ex = make_executor("aurd", monitor=monitor)
    acts = run(ex, p, 9)
    assert [a[0] for a in acts] == [1, 1, 2, 2, 2, 2, 2, 3, 4]
    assert ex.plans == [(2, "replan"), (5, "complete"), (1, "replan")]
    assert [r["committed"] for r in ex.trace] == [False] * 2 + [True] * 5 + [False, True]
    # a committed step's observation is encoded only for the trace (monitoring, outside the control time)
    assert p.encoded == ([1, 2, 3, 4, 5, 6, 8] if monitor else [1, 2, 8])
    assert ex.trace[3]["u"] == (pytest.approx(0.6) if monitor else 0.0)
    assert (ex.monitor_s > 0) == monitor
    # the old rule cuts the second plan at t=3 too
    old = make_executor("aurd", commit_after_cut=False)
    assert [a[0] for a in run(old, ScriptedPolicy(latent_error={2: 2.0, 3: 2.0}), 4)] == [1, 1, 2, 3]


def test_aurd_pauses_once_then_commits():
    p = ScriptedPolicy(u_act=[1.0] + [0] * 7)  # the first action of every plan is untrusted
    ex = make_executor("aurd")
    acts = run(ex, p, 8)
    assert [a[0] for a in acts] == [0, 2, 2, 2, 2, 2, 0, 4]
    assert ex.plans == [(0, "pause"), (5, "complete"), (0, "pause")]
    assert [r.get("event") for r in ex.trace] == ["pause"] + [None] * 5 + ["pause", None]
    # the paper's order commits too: a replan after one action, then a whole unchecked plan
    ex = make_executor("aurd", check="after")
    acts = run(ex, ScriptedPolicy(u_act=[1.0] * 8), 7)
    assert [a[0] for a in acts] == [1, 2, 2, 2, 2, 2, 3]
    assert ex.plans == [(1, "replan"), (5, "complete")]


def test_aurd_needs_thresholds():
    p = ScriptedPolicy()
    p.calibration = None
    with pytest.raises(ValueError, match="calibrate"):
        run(make_executor("aurd"), p, 1)


def test_ensemble_averages_live_predictions():
    p = ScriptedPolicy()
    ex = make_executor("ensemble", m=0.01)
    acts = run(ex, p, 3)
    # at t=2 predictions from queries 1,2,3 for their steps 2,1,0: normalized (q/10, k/10) averaged, x10 back
    w = np.exp(-0.01 * np.arange(3))
    w /= w.sum()
    np.testing.assert_allclose(acts[2][0], (w * np.array([1, 2, 3])).sum(), rtol=1e-5)
    np.testing.assert_allclose(acts[2][1], (w * np.array([2, 1, 0])).sum(), rtol=1e-5)
    assert ex.trace[2]["n_ensembled"] == 3


def test_adahorizon_executor_follows_rule():
    p = ScriptedPolicy(u_act=[0.01] * 6 + [0.05, 0.05])
    ex = make_executor("adahorizon")
    acts = run(ex, p, 7)
    assert [a[0] for a in acts] == [1] * 6 + [2]
    assert ex.plans[0] == (6, "complete")


def test_adahorizon_uses_calibrated_thresholds_unless_given():
    u = [0.01, 0.02, 0.03, 0.04, 0.05, 0.2, 0.2, 0.2]
    uncalibrated = ScriptedPolicy(u_act=u)  # EverydayVLA's 0.03 / 0.06: extend while < 0.03
    calibrated = ScriptedPolicy(u_act=u, calibration=Calibration(0.2, 0.5, 0.3, act_low=0.1, act_high=0.15))
    assert adahorizon(np.array(u), 4, 0.03, 0.06) == (4, "complete")
    ex = make_executor("adahorizon")
    run(ex, uncalibrated, 1)
    assert ex.plans[0] == (4, "complete")
    run(ex, calibrated, 1)
    assert ex.plans[0] == (5, "complete")  # extends while U_act < act_low = 0.1
    ex = make_executor("adahorizon", replan_above=0.025)
    run(ex, calibrated, 1)
    assert ex.plans[0] == (2, "replan")  # explicit threshold wins: U_act[2] = 0.03 > 0.025


def test_unknown_executor():
    with pytest.raises(ValueError, match="unknown executor"):
        make_executor("magic")


def test_aurd_episode_baseline_ignores_a_constant_prediction_offset():
    """A scene the encoder has never seen: every observation is 2.0 off its prediction. Raw U_pred replans
    after every action; measured above the episode's floor only the first excess counts (then 0)."""
    offset = {t: 2.0 for t in range(20)}
    raw = make_executor("aurd", commit_after_cut=False)
    run(raw, ScriptedPolicy(latent_error=offset), 10)
    assert raw.plans == [(1, "replan")] * 9  # the tenth plan is still executing when the run stops
    # committing after each cut turns the chatter into a cut, a full plan, a cut, ...
    raw = make_executor("aurd")
    run(raw, ScriptedPolicy(latent_error=offset), 8)
    assert raw.plans == [(1, "replan"), (5, "complete"), (1, "replan")]
    rel = make_executor("aurd", pred_baseline="episode")
    run(rel, ScriptedPolicy(latent_error=offset), 12)
    assert rel.plans[0] == (1, "replan") and rel.plans[1:] == [(5, "complete"), (5, "complete")]
    # a jump above the floor still replans
    jump = make_executor("aurd", pred_baseline="episode")
    run(jump, ScriptedPolicy(latent_error={**offset, 8: 4.0}), 10)
    assert (2, "replan") in jump.plans


def test_aurd_takes_the_baseline_from_the_calibration():
    calib = Calibration(tau_low=0.2, tau_high=0.5, v_thresh=0.3, eta=0.7, pred_baseline="episode")
    ex = make_executor("aurd")
    run(ex, ScriptedPolicy(latent_error={t: 2.0 for t in range(20)}, calibration=calib), 12)
    assert ex.plans[1:] == [(5, "complete"), (5, "complete")]
    with pytest.raises(ValueError, match="pred_baseline"):
        make_executor("aurd", pred_baseline="mean")


@pytest.mark.parametrize("name", ["fixed", "adahorizon"])
def test_chunking_baselines_trace_the_u_aurd_would_see(name):
    """Monitoring encodes each observation the plan predicted and writes AURD's U_pred and U into the
    trace; the actions are those of the bare executor, which encodes nothing."""
    p = ScriptedPolicy(latent_error={2: 2.0})
    ex = make_executor(name)
    acts = run(ex, p, 7)
    assert p.encoded == [1, 2, 3, 4, 6] if name == "fixed" else p.encoded[:3] == [1, 2, 3]
    assert ex.trace[2]["u_pred"] == pytest.approx(2.0) and ex.trace[2]["u"] == pytest.approx(0.3 * 2.0)
    assert ex.trace[0]["u_pred"] == 0.0 and ex.trace[1]["u"] == 0.0
    bare, q = make_executor(name, monitor=False), ScriptedPolicy(latent_error={2: 2.0})
    assert np.array_equal(np.stack(run(bare, q, 7)), np.stack(acts))
    assert q.encoded == [] and "u" not in bare.trace[2]
    if name == "fixed":
        assert [r["ended"] for r in ex.trace] == [None] * 5 + ["complete", None]


def test_ensemble_traces_the_error_of_the_previous_query():
    p = ScriptedPolicy(latent_error={1: 1.0})
    ex = make_executor("ensemble")
    run(ex, p, 3)
    assert p.encoded == [1, 2]  # t = 0 has no earlier prediction
    assert [r["u_pred"] for r in ex.trace] == [0.0, 1.0, 0.0]


def test_the_scripted_policy_satisfies_the_contract_executors_rely_on():
    assert isinstance(ScriptedPolicy(), ChunkPolicy)


@pytest.mark.parametrize("name", ["fixed", "ensemble", "adahorizon", "aurd"])
def test_executors_count_their_policy_queries(name):
    """queries (the compute per 100 steps that the benchmark reports) is every forward pass, pauses included."""
    p = ScriptedPolicy(u_act=np.full(8, 0.9) if name == "aurd" else None)
    ex = make_executor(name)
    run(ex, p, 13)
    assert ex.queries == p.queries > 0
    if name == "ensemble":
        assert ex.queries == 13
    ex.reset()
    assert ex.queries == 0


def test_first_cut_names_where_aurd_left_a_fixed_horizons_schedule():
    """None: AURD ran a fixed horizon's actions step for step; otherwise the kind of its first cut."""
    cases = [
        (ScriptedPolicy(), {}, None),
        (ScriptedPolicy(latent_error={2: 2.0}), {}, "replan"),
        (ScriptedPolicy(u_act=[0, 0.4, 0, 0, 0, 0, 0, 0], values=[1, 0.1, 1, 1, 1]), {"max_pauses": 0}, "prune"),
        (ScriptedPolicy(u_act=[1.0] + [0] * 7), {}, "pause"),
    ]
    for policy, options, expected in cases:
        ex = make_executor("aurd", **options)
        acts = run(ex, policy, 11)
        assert first_cut(ex.trace) == expected
        if expected is None:
            fixed = run(make_executor("fixed", horizon=5), ScriptedPolicy(), 11)
            assert all(np.array_equal(a, b) for a, b in zip(acts, fixed))
    # a plan cut at a step whose new plan then pauses: the cut came first
    trace = [{"ended": None, "event": None}, {"ended": "replan", "event": "pause"}, {"ended": "pause", "event": None}]
    assert first_cut(trace) == "replan"
