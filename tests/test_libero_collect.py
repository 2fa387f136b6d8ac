"""``pivla collect --env libero``: scripted-expert demonstrations on LIBERO into the dataset layout."""

from __future__ import annotations

import json

import h5py
import numpy as np
import pytest

from pivla.cli import main
from pivla.envs.libero import _backend

requires_libero = pytest.mark.skipif(
    not _backend.available(), reason=f"LIBERO not importable; {_backend.INSTALL_HINT}"
)


@pytest.mark.parametrize("flags,message", [(["--perturb", "unseen_env"], "perturb"),
                                           (["--paraphrase"], "paraphrase"),
                                           (["--realism", "servo"], "realism servo")])
def test_twin_only_options_are_refused(tmp_path, flags, message):
    with pytest.raises(SystemExit, match=message):
        main(["collect", "--env", "libero", "--suite", "libero_spatial", "--tasks", "0", "--episodes", "1",
              "--out", str(tmp_path), *flags])
    assert not list(tmp_path.glob("*.hdf5"))


@requires_libero
def test_suites_without_expert_are_refused(tmp_path):
    with pytest.raises(SystemExit, match="scripted experts exist for the libero_spatial, libero_object"):
        main(["collect", "--env", "libero", "--suite", "libero_90", "--tasks", "0", "--episodes", "1",
              "--out", str(tmp_path)])
    assert not list(tmp_path.glob("*.hdf5"))


@requires_libero
@pytest.mark.slow
def test_collect_one_libero_episode(tmp_path):
    """One rendered expert episode (~20 s): stored frames, actions, success and metadata read back."""
    from pivla.data.datasets import read_dataset

    code = main(["collect", "--env", "libero", "--suite", "libero_spatial", "--tasks", "5", "--episodes", "1",
                 "--out", str(tmp_path), "--image-size", "32"])
    assert code == 0
    (path,) = tmp_path.glob("*.hdf5")
    assert path.name == "pick_up_the_black_bowl_on_the_ramekin_and_place_it_on_the_plate_demo.hdf5"
    (ep,) = read_dataset(tmp_path)
    T = len(ep)
    assert ep.success and ep.source == "expert" and 30 < T <= 220
    assert ep.instruction == "pick the akita black bowl on the ramekin and place it on the plate"
    assert ep.obs["agentview_rgb"].shape == (T, 32, 32, 3) and ep.obs["eye_in_hand_rgb"].shape == (T, 32, 32, 3)
    assert ep.obs["joint_states"].shape == (T, 7) and ep.obs["ee_pos"].shape == (T, 3)
    assert ep.obs["agentview_rgb"].std() > 5  # real frames, not blank buffers
    assert np.abs(ep.actions).max() <= 1.0 and set(np.unique(ep.actions[:, 6])) <= {-1.0, 1.0}
    assert ep.rewards.sum() == pytest.approx(1.0) and ep.dones[-1] and ep.meta["init_state"] == 0
    # The gripper closes (grasp) and opens again (release) in a successful pick-and-place.
    grip = ep.actions[:, 6]
    assert grip[0] == -1 and (grip == 1).any() and grip[-1] == -1
    with h5py.File(path) as f:
        meta = json.loads(f["data"].attrs["env_args"])
    assert meta["env"] == "libero" and meta["task_index"] == 5 and meta["attempts"] == 1 and meta["init_states"] == [0]
