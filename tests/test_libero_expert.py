"""Scripted LIBERO experts on a few tasks, without rendering (slow: ~10-30 s per task)."""

from __future__ import annotations

import pytest

from pivla.envs.libero import _backend

pytestmark = pytest.mark.skipif(not _backend.available(), reason=f"LIBERO not importable; {_backend.INSTALL_HINT}")


@pytest.mark.slow
@pytest.mark.parametrize("suite,task", [("libero_object", 0), ("libero_object", 7), ("libero_spatial", 0),
                                        ("libero_spatial", 6)])
def test_expert_solves_task(suite, task):
    from pivla.envs.libero.expert import measure_experts

    result = measure_experts(suite, [task], episodes=3)["tasks"][0]
    assert result["successes"] == 3, result


def test_expert_rejects_other_suites():
    from pivla.envs.libero import expert_actor

    with pytest.raises(ValueError, match="libero_spatial and libero_object"):
        expert_actor("libero_goal", 0)
