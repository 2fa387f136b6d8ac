import numpy as np
import pytest

from pivla.control import (
    action_uncertainty,
    adahorizon,
    composite_uncertainty,
    decide_horizon,
    dequantize,
    ensemble_weights,
    surprise,
    temporal_ensemble,
)
from pivla.evaluation.stats import wilson_interval
from pivla.model.tokenizer import bin_centers

TL, TH, VT = 0.2, 0.5, 0.3


@pytest.mark.parametrize("u,v,check,expected", [
    # all trusted: the whole nominal horizon
    ([0.1, 0.1, 0.1, 0.1, 0.1], [1, 1, 1, 1, 1], "before", (5, "complete")),
    # step 3 above tau_high: stop before executing it
    ([0.1, 0.1, 0.6, 0.1, 0.1], [1, 1, 1, 1, 1], "before", (2, "replan")),
    # step 2 in the band with a low value: prune before it
    ([0.1, 0.3, 0.1, 0.1, 0.1], [1, 0.2, 1, 1, 1], "before", (1, "prune")),
    # in the band but the value is fine: keep going
    ([0.3, 0.3, 0.3, 0.3, 0.3], [1, 1, 1, 1, 1], "before", (5, "complete")),
    # low value but certain: keep going (prune needs both)
    ([0.1, 0.1, 0.1, 0.1, 0.1], [0, 0, 0, 0, 0], "before", (5, "complete")),
    # not even the first action is trusted: pause
    ([0.9, 0.1, 0.1, 0.1, 0.1], [1, 1, 1, 1, 1], "before", (0, "pause")),
    ([0.3, 0.1, 0.1, 0.1, 0.1], [0, 1, 1, 1, 1], "before", (0, "pause")),
    # the paper's literal order: execute, then test; never a pause
    ([0.9, 0.1, 0.1, 0.1, 0.1], [1, 1, 1, 1, 1], "after", (1, "replan")),
    ([0.1, 0.1, 0.6, 0.1, 0.1], [1, 1, 1, 1, 1], "after", (3, "replan")),
    ([0.1, 0.3, 0.1, 0.1, 0.1], [1, 0.2, 1, 1, 1], "after", (2, "prune")),
    ([0.1, 0.1, 0.1, 0.1, 0.1], [1, 1, 1, 1, 1], "after", (5, "complete")),
    # exactly tau_high is inside the band (U <= tau_high), exactly tau_low is not
    ([0.5, 0.1], [0.0, 1], "before", (0, "pause")),
    ([0.2, 0.1], [0.0, 1], "before", (2, "complete")),
])
def test_decide_horizon_events(u, v, check, expected):
    assert decide_horizon(np.array(u), np.array(v), TL, TH, VT, check=check) == expected


def test_decide_horizon_rejects_unknown_order():
    with pytest.raises(ValueError, match="check"):
        decide_horizon(np.zeros(3), np.zeros(3), TL, TH, VT, check="sometimes")


def test_composite_uncertainty_hand_computed():
    cont = np.array([[0.5, -0.5], [0.0, 0.0]])
    deq = np.array([[0.3, -0.1], [0.0, 0.2]])
    obs = np.array([[1.0, 0.0], [0.0, 0.0]])
    pred = np.array([[0.0, 0.0], [3.0, 4.0]])
    u_act = np.array([(0.2 + 0.4) / 2, 0.1])
    np.testing.assert_allclose(action_uncertainty(cont, deq), u_act)
    np.testing.assert_allclose(composite_uncertainty(cont, deq, obs, pred, eta=0.7),
                               0.7 * u_act + 0.3 * np.array([1.0, 5.0]))
    # no observation yet: U_pred = 0
    assert composite_uncertainty(cont[0], deq[0], None, None, eta=0.7) == pytest.approx(0.7 * 0.3)


def test_dequantize_matches_expectation_over_bins():
    c = bin_centers(256)
    p = np.zeros((2, 256))
    p[0, 10], p[0, 20] = 0.5, 0.5
    p[1, 255] = 1.0
    np.testing.assert_allclose(dequantize(p, c), [(c[10] + c[20]) / 2, c[255]], atol=1e-6)


def test_temporal_ensembling_weights_hand_computed():
    w = ensemble_weights(3, m=0.01)
    raw = np.array([1.0, np.exp(-0.01), np.exp(-0.02)])
    np.testing.assert_allclose(w, raw / raw.sum())
    preds = np.array([[1.0, 0.0], [0.0, 1.0], [1.0, 1.0]])  # oldest first
    np.testing.assert_allclose(temporal_ensemble(preds, 0.01), (raw[:, None] * preds).sum(0) / raw.sum())
    assert w[0] > w[-1]  # the oldest prediction weighs most, as in ACT


def test_adahorizon_rule():
    assert adahorizon(np.array([0.01] * 8)) == (8, "complete")  # extends while MAD < 0.03
    assert adahorizon(np.array([0.01, 0.01, 0.01, 0.01, 0.02, 0.05, 0.01, 0.01])) == (5, "complete")
    assert adahorizon(np.array([0.05] * 8)) == (4, "complete")  # at least 4, no extension
    assert adahorizon(np.array([0.01, 0.01, 0.07, 0.01, 0.01, 0.01, 0.01, 0.01])) == (2, "replan")
    assert adahorizon(np.array([0.09] + [0.01] * 7)) == (1, "replan")  # never fewer than one action


def test_wilson_interval_values():
    lo, hi = wilson_interval(8, 10)
    assert lo == pytest.approx(0.4902, abs=1e-4) and hi == pytest.approx(0.9433, abs=1e-4)
    assert wilson_interval(0, 10) == (0.0, pytest.approx(0.2775, abs=1e-4))
    assert wilson_interval(10, 10)[1] == pytest.approx(1.0)
    assert wilson_interval(0, 0) == (0.0, 1.0)


def test_surprise_is_prediction_error_above_the_episode_floor():
    assert surprise(0.3, None) == 0.3  # nothing seen yet: the raw error
    assert surprise(0.5, 0.2) == pytest.approx(0.3)
    assert surprise(0.1, 0.2) == 0.0  # never negative


def test_control_math_does_not_import_torch():
    """The control math is numpy in, numpy out: using it (analysis scripts, the arm's host) costs no torch."""
    import subprocess
    import sys

    code = ("import sys, numpy as np, pivla.control as c; "
            "p = np.full((2, 7, 4), 0.25); c.dequantize(p, np.linspace(-1, 1, 4)); "
            "assert 'torch' not in sys.modules, 'pivla.control imported torch'")
    subprocess.run([sys.executable, "-c", code], check=True)
