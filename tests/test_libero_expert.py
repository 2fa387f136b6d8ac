"""Scripted LIBERO experts on a few tasks, without rendering (slow: ~10-30 s per task)."""

from __future__ import annotations

import numpy as np
import pytest

from pivla.envs.libero import _backend

pytestmark = pytest.mark.skipif(not _backend.available(), reason=f"LIBERO not importable; {_backend.INSTALL_HINT}")


@pytest.mark.slow
@pytest.mark.parametrize("suite,task", [("libero_object", 0), ("libero_object", 7), ("libero_spatial", 0),
                                        ("libero_spatial", 4), ("libero_spatial", 6)])
def test_expert_solves_task(suite, task):
    from pivla.envs.libero.expert import measure_experts

    result = measure_experts(suite, [task], episodes=3)["tasks"][0]
    assert result["successes"] == 3, result


def test_expert_rejects_other_suites():
    from pivla.envs.libero import expert_actor

    with pytest.raises(ValueError, match="libero_spatial and libero_object"):
        expert_actor("libero_goal", 0)


def test_goals_are_kept_within_reach():
    """Goals beyond the arm's reach are lowered onto its boundary (or pulled in when no height reaches them)."""
    from types import SimpleNamespace

    from pivla.envs.libero.expert import ARM_REACH, PickPlaceExpert

    expert = PickPlaceExpert()
    expert.scene = SimpleNamespace(shoulder=np.array([-0.66, 0.0, 1.245]))  # the Panda's joint 2 in LIBERO's scenes
    reachable = np.array([0.0, -0.1, 1.2])
    assert np.allclose(expert._within_reach(reachable), reachable)
    above_drawer = np.array([0.1, -0.1, 1.3])
    lowered = expert._within_reach(above_drawer)
    assert np.allclose(lowered[:2], above_drawer[:2]) and lowered[2] < above_drawer[2]
    assert expert._wrist_distance(lowered) == pytest.approx(ARM_REACH)
    assert expert._wrist_distance(expert._within_reach(np.array([0.4, 0.0, 1.0]))) == pytest.approx(ARM_REACH)
