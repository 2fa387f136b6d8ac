"""An ensemble of training runs as one policy: ``pivla ensemble-runs``, its averaged outputs, AURD on it, bad input;
a run or an ensemble copied for a study of its own."""

import dataclasses
import json
import shutil

import numpy as np
import pytest

from pivla.cli import main
from pivla.control.calibrate import calibrate
from pivla.control.contract import BatchPolicy
from pivla.control.executors import executor_config
from pivla.data.normalize import ActionStats
from pivla.data.read import read_dataset
from pivla.evaluation.runner import EvalConfig, evaluate
from pivla.experiments.stages import CopyPolicy
from pivla.policy import Policy, RunEnsemble, load_policy
from pivla.training.checkpoint import (
    CONFIG_FILE,
    RUN_ENSEMBLE_FILE,
    copied_from,
    copy_policy,
    write_calibration,
    write_run_ensemble,
)
from pivla.training.trainer import train
from tests.conftest import tiny_train_config, twin_pick_place_data


@pytest.fixture(scope="module")
def two_runs(tmp_path_factory):
    """Two tiny twin policies of one recipe, seeds 0 and 1 (different held-out episodes, so different statistics)."""
    root = tmp_path_factory.mktemp("ensemble")
    twin_pick_place_data(root / "data", 3)
    return [train(tiny_train_config(root / "data", root / f"run{s}", steps=6, seed=s, val_fraction=0.34))
            for s in (0, 1)]


def _obs(policy, seed=0):
    rng = np.random.default_rng(seed)
    obs = {c: rng.integers(0, 256, (policy.spec.image_size, policy.spec.image_size, 3), dtype=np.uint8)
           for c in policy.spec.cameras}
    obs.update({k: rng.normal(size=n).astype(np.float32) for k, n in policy.spec.proprio})
    return {**obs, "instruction": "pick up the block and move it away"}


def test_renormalize_maps_one_normalisation_into_another_and_passes_the_gripper():
    a = ActionStats(q01=[-1.0, 0.0, -1.0], q99=[1.0, 2.0, 1.0], gripper_dim=2)
    b = ActionStats(q01=[-2.0, 1.0, -1.0], q99=[2.0, 3.0, 1.0], gripper_dim=2)
    physical = np.array([[0.5, 1.5, 1.0], [-0.8, 1.2, -1.0]], np.float32)
    moved = a.renormalize(b.normalize(physical), b)
    np.testing.assert_allclose(moved[:, :2], a.normalize(physical)[:, :2], atol=1e-6)
    soft = np.array([[0.0, 0.0, 0.3]], np.float32)
    assert a.renormalize(soft, b)[0, 2] == pytest.approx(0.3)  # a vote, not yet thresholded
    with pytest.raises(ValueError, match="gripper dimension"):
        a.renormalize(soft, ActionStats(q01=[0.0] * 3, q99=[1.0] * 3, gripper_dim=None))


def test_an_ensemble_of_one_run_twice_is_that_run(two_runs, tmp_path):
    out = write_run_ensemble([two_runs[0], two_runs[0]], tmp_path / "twice")
    ens, single = load_policy(out, device="cpu"), load_policy(two_runs[0], device="cpu")
    assert isinstance(ens, RunEnsemble) and isinstance(ens, BatchPolicy)
    obs = _obs(single)
    a, b = ens.infer(obs), single.infer(obs)
    for key in ("actions", "actions_normalized", "continuous_normalized", "dequantized", "u_act", "values"):
        np.testing.assert_allclose(a[key], b[key], atol=1e-5, err_msg=key)
    np.testing.assert_array_equal(a["latents"], b["latents"])
    np.testing.assert_array_equal(ens.encode(obs), single.encode(obs))
    assert ens.spec == single.spec
    assert "discrete_probs" not in a


def test_an_ensemble_averages_its_members_actions_in_physical_units(two_runs, tmp_path):
    out = write_run_ensemble(two_runs, tmp_path / "ens")
    ens = load_policy(out, device="cpu")
    members = [load_policy(r, device="cpu") for r in two_runs]
    assert members[0].stats.action.q01 != members[1].stats.action.q01  # the averaging must convert
    obs = _obs(ens, seed=3)
    got, outs = ens.infer(obs), [m.infer(obs) for m in members]
    arm = [d for d in range(ens.spec.action_dim) if d != ens.stats.action.gripper_dim]
    physical = [m.stats.action.unnormalize(o["actions_normalized"]) for m, o in zip(members, outs)]
    inside = np.all([np.abs(o["actions_normalized"][:, arm]) < 0.99 for o in outs], axis=0)
    inside &= np.abs(got["actions_normalized"][:, arm]) < 0.99
    assert inside.any()
    np.testing.assert_allclose(got["actions"][:, arm][inside], np.mean(physical, 0)[:, arm][inside], atol=1e-4)
    g = ens.stats.action.gripper_dim
    vote = np.mean([o["actions_normalized"][:, g] for o in outs], 0)
    np.testing.assert_array_equal(got["actions"][:, g], np.where(vote > 0, 1.0, -1.0))
    np.testing.assert_allclose(got["values"], np.mean([o["values"] for o in outs], 0), atol=1e-6)
    np.testing.assert_array_equal(got["latents"], outs[0]["latents"])  # AURD follows the first member's predictions
    batch = ens.infer_batch([obs, _obs(ens, seed=4)])
    np.testing.assert_allclose(batch["actions"][0], got["actions"], atol=1e-5)


def test_an_ensemble_is_calibrated_and_run_by_aurd(two_runs, tmp_path):
    out = write_run_ensemble(two_runs, tmp_path / "ens")
    data = two_runs[0].parent / "data"
    calib, _ = calibrate(load_policy(out, device="cpu"), read_dataset(data), source="test")
    write_calibration(out, vars(calib))
    assert load_policy(out, device="cpu").calibration.tau_high == calib.tau_high
    cfg = EvalConfig(policy=str(out), out=str(tmp_path / "eval"), tasks="0,1", executor=executor_config("aurd"),
                     episodes=2, seed=7, workers=1, max_steps=12, videos=0)
    res = evaluate(cfg, progress=False)
    assert res["episodes"] == 4 and res["executor"] == "aurd"
    trace = json.loads(next((tmp_path / "eval" / "traces").glob("*.json")).read_text())["trace"]
    assert all(np.isfinite(step["u_pred"]) for step in trace)


def test_pivla_ensemble_writes_a_directory_that_moves_and_describes_itself(two_runs, tmp_path, capsys):
    out = tmp_path / "ens"
    assert main(["ensemble-runs", "--runs", str(two_runs[0]), str(two_runs[1]), "--out", str(out)]) == 0
    assert "ensemble of 2 runs" in capsys.readouterr().out
    moved = out.rename(tmp_path / "moved")  # the members are copies, named relative to the directory
    assert len(load_policy(moved, device="cpu").members) == 2
    assert main(["info", "--policy", str(moved), "--json"]) == 0
    info = json.loads(capsys.readouterr().out)
    assert info["members"] == 2
    single = load_policy(two_runs[0], device="cpu").model.parameter_counts()["total"]
    assert info["parameters"]["total"] == 2 * single
    assert main(["bench", "infer", "--policy", str(moved), "--runs", "2", "--warmup", "1", "--threads", "1",
                 "--json"]) == 0
    bench = json.loads(capsys.readouterr().out)
    assert bench["members"] == 2 and bench["parameters"] == 2 * single and bench["infer_ms_median"] > 0


def test_bad_ensembles_are_refused_by_name(two_runs, tmp_path):
    with pytest.raises(ValueError, match="at least two"):
        write_run_ensemble([two_runs[0]], tmp_path / "one")
    with pytest.raises(ValueError, match="not a trained run directory"):
        write_run_ensemble([two_runs[0], tmp_path], tmp_path / "half")
    assert not (tmp_path / "half").exists()
    out = write_run_ensemble(two_runs, tmp_path / "ens")
    with pytest.raises(ValueError, match="exists"):
        write_run_ensemble(two_runs, out)
    with pytest.raises(ValueError, match="an ensemble itself"):
        write_run_ensemble([out, two_runs[0]], tmp_path / "nested")
    (out / RUN_ENSEMBLE_FILE).write_text(json.dumps({"members": ["members/0"]}))
    with pytest.raises(ValueError, match=RUN_ENSEMBLE_FILE):
        load_policy(out, device="cpu")
    (out / RUN_ENSEMBLE_FILE).write_text("{not json")
    with pytest.raises(ValueError, match=RUN_ENSEMBLE_FILE):
        load_policy(out, device="cpu")
    other = shutil.copytree(two_runs[1], tmp_path / "other")  # another camera name: the same weights, another spec
    config = json.loads((other / CONFIG_FILE).read_text())
    config["model"]["cameras"][0] = "front_rgb"
    (other / CONFIG_FILE).write_text(json.dumps(config))
    with pytest.raises(SystemExit, match="member 1"):
        main(["ensemble-runs", "--runs", str(two_runs[0]), str(other), "--out", str(tmp_path / "unfit")])
    assert not (tmp_path / "unfit").exists()  # refused before the directory took its place
    a, b = (load_policy(r, device="cpu") for r in two_runs)
    b.spec = dataclasses.replace(b.spec, chunk=b.spec.chunk - 1)
    with pytest.raises(ValueError, match="member 1"):
        RunEnsemble([a, b])
    assert isinstance(a, Policy)


def test_a_copied_policy_acts_as_its_source_and_is_calibrated_on_its_own(two_runs, tmp_path):
    """``copy_policy`` (``pivla libero run --policy``): a run or an ensemble copied without its checkpoints or
    calibration; calibrating the copy leaves the source as it was."""
    write_calibration(two_runs[0], {"tau_low": 0.1, "tau_high": 0.2, "v_thresh": 0.0})
    ens = write_run_ensemble(two_runs, tmp_path / "ens")
    for source in (two_runs[0], ens):
        copy = copy_policy(source, tmp_path / f"copy_{source.name}")
        assert copied_from(copy) == str(source.resolve()) and copied_from(source) is None
        assert not (copy / "checkpoints").exists() and not (copy / "calibration.json").exists()
        original, copied = load_policy(source, device="cpu"), load_policy(copy, device="cpu")
        obs = _obs(original, seed=5)
        np.testing.assert_array_equal(copied.infer(obs)["actions"], original.infer(obs)["actions"])
        write_calibration(copy, {"tau_low": 0.3, "tau_high": 0.4, "v_thresh": 0.0})
    assert load_policy(two_runs[0], device="cpu").calibration.tau_high == 0.2
    with pytest.raises(ValueError, match="exists"):
        copy_policy(ens, copy)
    with pytest.raises(ValueError, match="not a trained run directory"):
        copy_policy(tmp_path, tmp_path / "nothing")
    assert not (tmp_path / "nothing").exists()


def test_a_study_refuses_a_policy_directory_that_holds_another_policy(two_runs, tmp_path):
    stage = CopyPolicy(two_runs[0], tmp_path / "policy")
    assert not stage.done()
    stage()
    assert stage.done()
    with pytest.raises(ValueError, match="a copy of .*run0, not a copy of .*run1"):
        CopyPolicy(two_runs[1], tmp_path / "policy").done()
    with pytest.raises(ValueError, match="a policy trained there"):
        CopyPolicy(two_runs[1], two_runs[0]).done()
