import dataclasses
import json
import os

import numpy as np
import pytest
import torch

from pivla import load_policy
from pivla.training import checkpoint as ck
from pivla.training.config import TrainConfig, with_twin_inputs
from pivla.training.trainer import Trainer, images_on_disk, train
from tests.conftest import tiny_train_config


def _obs(seed=0):
    rng = np.random.default_rng(seed)
    return {
        "agentview_rgb": rng.integers(0, 255, (32, 32, 3), dtype=np.uint8),
        "eye_in_hand_rgb": rng.integers(0, 255, (48, 48, 3), dtype=np.uint8),  # resized by the policy
        "ee_pos": np.zeros(3), "ee_ori": np.zeros(3), "gripper_states": np.zeros(2),
        "instruction": "move the square left",
    }


def test_overfits_a_tiny_dataset(tmp_path):
    from pivla.data.synthetic import make_synthetic_dataset

    data = make_synthetic_dataset(tmp_path / "d", episodes_per_goal=1, T=10, size=32)
    cfg = tiny_train_config(data, tmp_path / "run", steps=250, batch_size=16, lr=2e-3, warmup=10, val_fraction=0.0,
                            augment_pad=0, eval_every=1000, ckpt_every=1000)
    cfg = dataclasses.replace(cfg, loss=dataclasses.replace(cfg.loss, use_rl=False, use_sp=False, use_recon=False))
    t = Trainer(cfg)
    first = t.train_step()["il"]
    for _ in range(cfg.steps - 1):
        last = t.train_step()["il"]
    assert last < first / 10, (first, last)


def test_run_dir_load_policy_and_identical_outputs(tmp_path, synthetic_data):
    run = train(tiny_train_config(synthetic_data, tmp_path / "run"))
    for name in (ck.MODEL_FILE, ck.CONFIG_FILE, ck.STATS_FILE, ck.TOKENIZER_FILE, ck.STATUS_FILE):
        assert (run / name).exists(), name
    assert json.loads((run / ck.STATUS_FILE).read_text())["done"]
    p1, p2 = load_policy(run, device="cpu"), load_policy(run, device="cpu")
    o1, o2 = p1.infer(_obs()), p2.infer(_obs())
    assert o1["actions"].shape == (8, 7) and o1["discrete_probs"].shape == (8, 7, 256)
    assert o1["latents"].shape == (8, p1.model.latent_dim) and o1["values"].shape == (5,)
    for k in o1:
        np.testing.assert_array_equal(o1[k], o2[k])
    np.testing.assert_allclose(o1["discrete_probs"].sum(-1), 1.0, atol=1e-5)
    assert set(np.unique(o1["actions"][:, 6])) <= {-1.0, 1.0}
    batch = p1.infer_batch([_obs(0), _obs(1)])
    np.testing.assert_allclose(batch["actions"][0], o1["actions"], atol=1e-5)
    assert not any(p.suffix in (".pt", ".pth", ".pkl", ".bin") for p in run.rglob("*"))


def test_runs_written_before_a_default_changed_still_load(tmp_path, synthetic_data):
    """A config.json without ``grid_tokens`` (runs from before the pooled-token default) loads as the grid
    model it was trained as, with identical outputs."""
    base = tiny_train_config(synthetic_data, tmp_path / "run", steps=2)
    grid = dataclasses.replace(base.model.backbone, grid_tokens=True)
    run = train(dataclasses.replace(base, model=dataclasses.replace(base.model, backbone=grid)))
    before = load_policy(run, device="cpu").infer(_obs())
    cfg = json.loads((run / ck.CONFIG_FILE).read_text())
    del cfg["model"]["backbone"]["grid_tokens"]
    (run / ck.CONFIG_FILE).write_text(json.dumps(cfg))
    old = load_policy(run, device="cpu")
    assert old.model.cfg.backbone.grid_tokens
    np.testing.assert_array_equal(old.infer(_obs())["actions"], before["actions"])


def test_resume_matches_uninterrupted_run(tmp_path, synthetic_data):
    full = train(tiny_train_config(synthetic_data, tmp_path / "full", steps=20, ckpt_every=10))
    interrupted = Trainer(tiny_train_config(synthetic_data, tmp_path / "half", steps=20, ckpt_every=10))
    interrupted.run_dir.mkdir(parents=True)
    while interrupted.step < 13:  # dies after step 13; the last checkpoint is step 10
        if interrupted.step % 10 == 0:
            interrupted._refresh_values()
        interrupted.train_step()
        if interrupted.step == 10:
            interrupted._save()
    resumed = train(tiny_train_config(synthetic_data, tmp_path / "half", steps=20, ckpt_every=10), resume=True)
    a, b = ck.load_tensors(full / ck.MODEL_FILE), ck.load_tensors(resumed / ck.MODEL_FILE)
    assert a.keys() == b.keys()
    for k in a:
        torch.testing.assert_close(a[k], b[k], rtol=0, atol=0, msg=k)


def test_a_run_with_a_weight_average_deploys_it_and_resumes_both(tmp_path, synthetic_data):
    """``--ema-decay``: model.safetensors is the average of the live weights, which the checkpoint keeps; a
    run resumed from a checkpoint ends with the uninterrupted run's live weights and average."""
    import shutil

    from pivla.training.average import ema_decay_at

    cfg = tiny_train_config(synthetic_data, tmp_path / "full", steps=20, ckpt_every=10, ema_decay=0.9)
    t = Trainer(cfg)
    t.run_dir.mkdir(parents=True)
    expected = {k: v.detach().clone() for k, v in t.average.shadow.items()}
    for n in range(cfg.steps):
        if n % 10 == 0:
            t._refresh_values()
        t.train_step()
        live = dict(t.model.named_parameters())
        for k in expected:  # the average, spelled out: e <- d e + (1 - d) w, d tempered over the first updates
            d = ema_decay_at(0.9, n)
            expected[k] = d * expected[k] + (1 - d) * live[k].detach()
    t._save(final=True)
    deployed, live = ck.load_tensors(t.run_dir / ck.MODEL_FILE), dict(t.model.named_parameters())
    moved = [k for k in expected if not torch.equal(expected[k], live[k].detach())]
    assert moved, "the average equals the live weights: nothing was averaged"
    for k in expected:
        torch.testing.assert_close(deployed[k], expected[k], rtol=1e-5, atol=1e-6, msg=k)
    kept = ck.load_tensors(ck.latest_checkpoint(t.run_dir) / ck.MODEL_FILE)
    for k in moved:
        torch.testing.assert_close(kept[k], live[k].detach(), rtol=0, atol=0, msg=k)
    full = train(dataclasses.replace(cfg, out=str(tmp_path / "ref")))
    shutil.copytree(full, tmp_path / "killed")
    shutil.rmtree(tmp_path / "killed" / "checkpoints" / "step_00000020")  # killed between steps 10 and 20
    (tmp_path / "killed" / ck.MODEL_FILE).unlink()
    resumed = train(dataclasses.replace(cfg, out=str(tmp_path / "killed")), resume=True)
    for name in (ck.MODEL_FILE, f"checkpoints/step_00000020/{ck.AVERAGE_FILE}"):
        a, b = ck.load_tensors(full / name), ck.load_tensors(resumed / name)
        assert a.keys() == b.keys()
        for k in a:
            torch.testing.assert_close(a[k], b[k], rtol=0, atol=0, msg=k)
    train(tiny_train_config(synthetic_data, tmp_path / "plain", steps=10, ckpt_every=10))
    with pytest.raises(ValueError, match="weight average"):  # a checkpoint without one cannot resume an average
        train(tiny_train_config(synthetic_data, tmp_path / "plain", steps=20, ckpt_every=10, ema_decay=0.9),
              resume=True)
    with pytest.raises(ValueError, match="ema-decay"):
        Trainer(tiny_train_config(synthetic_data, tmp_path / "bad", ema_decay=1.0))


def test_the_clock_adds_checkpoints_a_resume_continues_from(tmp_path, synthetic_data):
    """``ckpt_minutes`` checkpoints at log steps between the step interval's; resuming from one of them trains
    the weights of the uninterrupted run."""
    import shutil

    cfg = tiny_train_config(synthetic_data, tmp_path / "full", steps=12, log_every=4, ckpt_every=100,
                            ckpt_minutes=1e-9, keep_checkpoints=5)
    full = train(cfg)
    assert [p.name for p in sorted((full / "checkpoints").iterdir())] == [
        "step_00000004", "step_00000008", "step_00000012"]
    assert not [p for p in (train(tiny_train_config(synthetic_data, tmp_path / "off", steps=12, log_every=4,
                                                    ckpt_every=100, keep_checkpoints=5)) / "checkpoints").iterdir()
                if p.name != "step_00000012"]  # the default 10 minutes do not pass in a tiny run
    shutil.copytree(full, tmp_path / "killed")
    shutil.rmtree(tmp_path / "killed" / "checkpoints" / "step_00000012")  # killed between steps 8 and 12
    (tmp_path / "killed" / ck.MODEL_FILE).unlink()
    resumed = train(dataclasses.replace(cfg, out=str(tmp_path / "killed")), resume=True)
    a, b = ck.load_tensors(full / ck.MODEL_FILE), ck.load_tensors(resumed / ck.MODEL_FILE)
    for k in a:
        torch.testing.assert_close(a[k], b[k], rtol=0, atol=0, msg=k)


def test_pictures_held_on_disk_train_the_same_model(tmp_path, synthetic_data):
    """``--image-store disk`` (a dataset larger than the RAM) gives the weights of the in-memory store, bit for bit."""
    runs = {where: train(dataclasses.replace(tiny_train_config(synthetic_data, tmp_path / where, steps=6),
                                             image_store=where)) for where in ("memory", "disk")}
    a, b = (ck.load_tensors(run / ck.MODEL_FILE) for run in runs.values())
    for k in a:
        torch.testing.assert_close(a[k], b[k], rtol=0, atol=0, msg=k)
    assert sorted(p.name for p in runs["disk"].iterdir()) == sorted(p.name for p in runs["memory"].iterdir())


def test_auto_picture_store_goes_to_disk_past_a_third_of_the_ram():
    cfg = TrainConfig()
    cfg = dataclasses.replace(cfg, model=with_twin_inputs(cfg.model))  # two cameras at 80 px: 38,400 bytes a frame
    third = os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES") / 3
    assert not images_on_disk(cfg, int(third // 38_400))
    assert images_on_disk(cfg, int(third // 38_400) + 1)
    assert images_on_disk(cfg, int(third // 38_400 // 2) + 1, local_processes=2)  # a copy per process
    assert images_on_disk(dataclasses.replace(cfg, image_store="disk"), 1)
    assert not images_on_disk(dataclasses.replace(cfg, image_store="memory"), 10**12)


def test_extra_data_follows_the_data_in_one_split(tmp_path, synthetic_data):
    from pivla.data.read import read_dataset
    from pivla.data.samples import prepare_episode
    from pivla.data.synthetic import make_synthetic_dataset

    extra = make_synthetic_dataset(tmp_path / "extra", episodes_per_goal=1, T=7, size=32, failures=1)
    t = Trainer(tiny_train_config(synthetic_data, tmp_path / "run", extra_data=(str(extra),), val_fraction=0.0))
    episodes = read_dataset(synthetic_data) + read_dataset(extra)
    assert t.split == {"train_episodes": list(range(len(episodes))), "val_episodes": []}
    for ep, prepared in zip(episodes, t.train_set.episodes, strict=True):
        alone = prepare_episode(ep, t.cfg.model, t.stats, t.text)
        np.testing.assert_array_equal(prepared.images, alone.images)
        assert prepared.imitate == ep.success


def test_task_balance_draws_a_short_task_as_often_as_a_long_one(tmp_path):
    from pivla.data.hdf5 import write_episodes
    from pivla.data.samples import weighted_batch_indices
    from pivla.data.synthetic import synthetic_episode

    rng = np.random.default_rng(0)
    write_episodes(tmp_path / "d" / "left.hdf5", [synthetic_episode(rng, "left", T=20, size=32) for _ in range(4)])
    write_episodes(tmp_path / "d" / "right.hdf5", [synthetic_episode(rng, "right", T=10, size=32)])
    uniform = Trainer(tiny_train_config(tmp_path / "d", tmp_path / "u", val_fraction=0.0))
    assert uniform.train_cdf is None  # the default keeps the epoch-wise permutations
    t = Trainer(tiny_train_config(tmp_path / "d", tmp_path / "b", val_fraction=0.0, task_balance=1.0))
    episode = t.train_set.index[:, 0]
    drawn = np.concatenate([weighted_batch_indices(t.train_cdf, 8, s, t.cfg.seed) for s in range(400)])
    assert np.mean(episode[drawn] == 4) == pytest.approx(0.5, abs=0.05)  # 10 of the 90 frames, half the draws
    t.train_step()  # a step trains on the weighted batch
    with pytest.raises(ValueError, match="task balance"):  # refused before any picture is loaded
        Trainer(tiny_train_config(tmp_path / "d", tmp_path / "bad", val_fraction=0.0, task_balance=1.5))


def test_shift_cameras_are_named_by_key_and_an_unknown_one_is_refused(tmp_path, synthetic_data):
    t = Trainer(tiny_train_config(synthetic_data, tmp_path / "a", augment_shift_cameras=("agentview_rgb",)))
    assert t.shift_cameras == (0,)
    t.train_step()
    with pytest.raises(ValueError, match="wrist_rgb: not among the model's cameras"):
        Trainer(tiny_train_config(synthetic_data, tmp_path / "b", augment_shift_cameras=("wrist_rgb",)))


def test_bad_observations_and_corrupt_model_get_named_errors(tmp_path, synthetic_data):
    run = train(tiny_train_config(synthetic_data, tmp_path / "run", steps=2, ckpt_every=2, eval_every=2))
    policy = load_policy(run, device="cpu")
    obs = _obs()
    del obs["ee_pos"]
    with pytest.raises(ValueError, match="ee_pos"):
        policy.infer(obs)
    obs = _obs()
    obs["ee_pos"] = np.array([np.nan, 0, 0])
    with pytest.raises(ValueError, match="NaN"):
        policy.infer(obs)
    obs = _obs()
    obs["agentview_rgb"] = obs["agentview_rgb"].astype(np.float32)
    with pytest.raises(ValueError, match="agentview_rgb"):
        policy.infer(obs)
    model = run / ck.MODEL_FILE
    model.write_bytes(model.read_bytes()[:1000])
    with pytest.raises(ValueError, match="model.safetensors"):
        load_policy(run, device="cpu")


def test_cli_flags_reach_nested_config(tmp_path, synthetic_data, capsys):
    from pivla.cli import main

    out = tmp_path / "cli"
    rc = main(["train", "--data", str(synthetic_data), "--out", str(out), "--steps", "2", "--batch-size", "4",
               "--model.image_size", "32", "--model.backbone.d_model", "32", "--loss.alpha", "0.2",
               "--no-progress", "--ckpt-every", "2", "--eval-every", "2"])
    assert rc == 0
    cfg = json.loads((out / ck.CONFIG_FILE).read_text())
    assert cfg["model"]["backbone"]["d_model"] == 32 and cfg["loss"]["alpha"] == 0.2 and cfg["batch_size"] == 4
    assert main(["info", "--policy", str(out)]) == 0
    assert "step 2/2" in capsys.readouterr().out


@pytest.mark.parametrize("head", ["continuous", "discrete"])
def test_one_head_policy_executes_its_head_and_has_no_action_uncertainty(tmp_path, synthetic_data, head):
    """Table 4's one-head variants: the trained head is executed, and U_act (the disagreement of two trained
    heads, Eq. 13) is zero instead of a comparison with the untrained head."""
    from pivla.data.read import read_dataset
    from pivla.training.losses import LossConfig

    other = "use_discrete" if head == "continuous" else "use_continuous"
    run = train(tiny_train_config(synthetic_data, tmp_path / "run", steps=2, loss=LossConfig(**{other: False})))
    policy = load_policy(run, device="cpu")
    ep = read_dataset(synthetic_data)[0]
    obs = {k: v[0] for k, v in ep.obs.items()} | {"instruction": ep.instruction}
    out = policy.infer(obs)
    primary = out["continuous_normalized"] if head == "continuous" else out["dequantized"]
    assert policy.action_head == head and np.allclose(out["actions_normalized"], primary)
    assert out["u_act"].shape == (policy.spec.chunk,) and not out["u_act"].any()
    untrained = "discrete" if head == "continuous" else "continuous"
    with pytest.raises(ValueError, match="trained only its"):
        load_policy(run, device="cpu", gripper_head=untrained)
    both_run = train(tiny_train_config(synthetic_data, tmp_path / "both", steps=2))
    both = load_policy(both_run, device="cpu").infer(obs)
    assert both["u_act"].min() > 0
    # two heads: the arm from the continuous head, the gripper (last dimension) from Eq. 12 unless asked otherwise
    assert np.allclose(both["actions_normalized"][:, :-1], both["continuous_normalized"][:, :-1])
    assert np.allclose(both["actions_normalized"][:, -1], both["dequantized"][:, -1])
    assert not np.allclose(both["dequantized"][:, -1], both["continuous_normalized"][:, -1])
    cont = load_policy(both_run, device="cpu", gripper_head="continuous").infer(obs)
    assert np.allclose(cont["actions_normalized"], cont["continuous_normalized"])
    with pytest.raises(ValueError, match="gripper_head"):
        load_policy(both_run, device="cpu", gripper_head="mode")


def test_a_policy_trained_on_actions_in_flight_reads_them_and_names_bad_ones(tmp_path, synthetic_data):
    """``--model.action-prefix P``: samples carry the first d <= P actions of their target chunk (d drawn per
    sample, 0 included); the trained policy plans from the actions it is told, an empty prefix is no prefix, and a
    prefix it cannot read is named."""
    from pivla.data.samples import ChunkDataset
    from pivla.training.trainer import Trainer

    cfg = tiny_train_config(synthetic_data, tmp_path / "run", steps=10)
    cfg = dataclasses.replace(cfg, model=dataclasses.replace(cfg.model, action_prefix=3))
    trainer = Trainer(cfg)
    dataset: ChunkDataset = trainer.train_set
    rng = np.random.default_rng(0)
    samples = [dataset.sample(i, rng) for i in range(0, len(dataset), 3)]
    told = {int(s["prefix_mask"].sum()) for s in samples}
    assert told == {0, 1, 2, 3}
    for s in samples:
        n = int(s["prefix_mask"].sum())
        assert s["prefix_mask"][:n].all() and not s["prefix_mask"][n:].any()
        np.testing.assert_array_equal(s["action_prefix"][:n], s["actions"][:n])
        assert not s["action_prefix"][n:].any()
    run = train(cfg)
    policy = load_policy(run, device="cpu")
    assert policy.spec.action_prefix == 3
    plain = policy.infer(_obs())
    np.testing.assert_array_equal(policy.infer({**_obs(), "action_prefix": np.zeros((0, 7))})["actions"],
                                  plain["actions"])
    told = policy.infer({**_obs(), "action_prefix": plain["actions"][:2]})
    assert not np.allclose(told["continuous_normalized"], plain["continuous_normalized"])
    for bad, problem in [(np.zeros((4, 7)), "at most 3"), (np.zeros((2, 6)), r"\(n, 7\)"),
                         (np.full((1, 7), np.nan), "NaN"), ("left", "array of numbers")]:
        with pytest.raises(ValueError, match=problem):
            policy.infer({**_obs(), "action_prefix": bad})
    plain_run = train(tiny_train_config(synthetic_data, tmp_path / "plain", steps=2))
    with pytest.raises(ValueError, match="not trained to read actions in flight"):
        load_policy(plain_run, device="cpu").infer({**_obs(), "action_prefix": plain["actions"][:1]})


@pytest.mark.parametrize("changes, problem", [
    ({"action_prefix": 8}, "0 to K - 1 = 7"), ({"action_prefix": 2, "relative_actions": True}, "relative_actions")])
def test_an_action_prefix_the_model_cannot_read_is_named(changes, problem):
    from pivla.model.cms import CMSModel
    from pivla.model.config import BackboneConfig, ModelConfig

    cfg = ModelConfig(image_size=32, backbone=BackboneConfig(d_model=64, n_layers=2, vision_channels=(16, 32, 32, 32)),
                      **changes)
    with pytest.raises(ValueError, match=problem):
        CMSModel(cfg, 10)
