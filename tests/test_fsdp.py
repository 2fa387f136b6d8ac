"""FSDP2 on this CPU: two processes (``torchrun``, gloo) train the tiny ``small`` stack with ``fsdp=True``.
Parameters must really be sharded (each rank holds about half), the run directory must hold the gathered full
parameters and load with ``load_policy``, and resuming from a mid-run checkpoint must reproduce the
uninterrupted run bit for bit (so the optimizer moments survive the full-tensor round trip)."""

from __future__ import annotations

import dataclasses
import logging
from pathlib import Path

import pytest

from pivla.cli import main
from pivla.cli.train import TrainCommand  # a module-level name: the command line reads capture's type hint
from pivla.data.synthetic import make_synthetic_dataset
from pivla.training.trainer import Trainer, _fsdp_blocks, _fsdp_plugin
from tests.conftest import run_two_process, tiny_train_config

WORKER = '''
import dataclasses, json, sys
import torch
from torch.distributed.fsdp import FSDPModule
from torch.distributed.tensor import DTensor
from pivla import config as cfgmod, load_policy
from pivla.training import checkpoint as ck
from pivla.training.trainer import Trainer, TrainConfig

cfg = cfgmod.from_dict(TrainConfig, json.load(open(sys.argv[1])))
full_params = lambda m: {n: p.detach().full_tensor() for n, p in m.named_parameters()}

trainer = Trainer(cfg)
model = trainer.model
params = dict(model.named_parameters())
result = {
    "wrapped": isinstance(model, FSDPModule) and trainer.ddp_model is model,
    "blocks_wrapped": all(isinstance(layer, FSDPModule) for layer in model.backbone.fusion.layers),
    "all_dtensor": all(isinstance(p, DTensor) for p in params.values()),
    "local_fraction": sum(p.to_local().numel() for p in params.values()) / sum(p.numel() for p in params.values()),
}
before = full_params(model)
trainer.run()
after = full_params(model)
result["still_sharded"] = all(isinstance(p, DTensor) for p in model.parameters())
result["moved"] = max(float((after[n] - before[n]).abs().max()) for n, p in params.items() if p.requires_grad)
result["losses"] = [h["total"] for h in trainer.history if "total" in h]

# interrupted after step 4 (last checkpoint: step 3), then resumed to the end
half = dataclasses.replace(cfg, out=cfg.out + "_half")
interrupted = Trainer(half)
interrupted.run_dir.mkdir(parents=True, exist_ok=True)
while interrupted.step < 4:
    if interrupted.step % cfg.value_refresh_every == 0:
        interrupted._refresh_values()
    interrupted.train_step()
    if interrupted.step == 3:
        interrupted._save()
resumed = Trainer(half, resume=True)
result["resumed_at"] = resumed.step
resumed.run()

if trainer.acc.is_main_process:
    saved = ck.load_tensors(trainer.run_dir / ck.MODEL_FILE)
    policy = load_policy(trainer.run_dir, device="cpu")
    result["saved_keys_match"] = sorted(saved) == sorted(model.state_dict_for_checkpoint())
    result["saved_equals_gathered"] = all(torch.equal(saved[n], after[n]) for n in after)
    result["policy_equals_gathered"] = all(torch.equal(p, after[n]) for n, p in policy.model.named_parameters())
    again = ck.load_tensors(resumed.run_dir / ck.MODEL_FILE)
    result["resume_max_diff"] = max(float((again[k] - saved[k]).abs().max()) for k in saved)
    with open(sys.argv[2], "w") as f:
        json.dump(result, f)
trainer.acc.wait_for_everyone()  # no rank tears the group down while rank 0 still writes its findings
trainer.acc.end_training()  # destroys the process group; left to interpreter exit, gloo can abort a rank
# C++ destructors at interpreter exit still abort a rank now and then ('terminate called without an active
# exception', ~1 run in 8 even with the teardown above); the findings are written, so leave at once
import os; os._exit(0)
'''


def _fsdp_config(tmp_path: Path):
    cfg = tiny_train_config(make_synthetic_dataset(tmp_path / "data", 2, 12, 32), tmp_path / "run", steps=6,
                            batch_size=4, warmup=1, lr=1e-2, log_every=1, eval_every=3, ckpt_every=3,
                            value_refresh_every=3, threads=1, fsdp=True)
    return cfg  # the default backbone, spatial-softmax keypoints included


def test_two_process_fsdp_shards_saves_full_and_resumes(tmp_path):
    r = run_two_process(tmp_path, WORKER, _fsdp_config(tmp_path))
    assert r["wrapped"] and r["blocks_wrapped"] and r["all_dtensor"] and r["still_sharded"]
    assert 0.45 < r["local_fraction"] < 0.6, r["local_fraction"]  # about half of every parameter per rank
    assert r["moved"] > 0 and len(r["losses"]) == 6
    assert r["saved_keys_match"] and r["saved_equals_gathered"] and r["policy_equals_gathered"]
    assert r["resumed_at"] == 3 and r["resume_max_diff"] == 0.0


def test_fsdp_option_plumbing(tmp_path, monkeypatch, caplog):
    """What can be checked in one process: the flag, the plugin, FSDP1 refused, and no sharding without a launcher."""
    from pivla.model.cms import CMSModel

    parsed = []

    def capture(cmd: TrainCommand) -> int:
        parsed.append(cmd.run)
        return 0

    monkeypatch.setattr("pivla.cli.train.train", capture)  # the real command line, without the training
    assert main(["train", "--fsdp"]) == 0 and parsed[0].fsdp
    for var in ("ACCELERATE_USE_FSDP", "FSDP_VERSION", "FSDP_CPU_RAM_EFFICIENT_LOADING"):
        monkeypatch.setenv(var, "")  # recorded, so that what Accelerate writes into the environment is undone
        monkeypatch.delenv(var)
    cfg = _fsdp_config(tmp_path)
    assert _fsdp_plugin(dataclasses.replace(cfg, fsdp=False)) is None
    plugin = _fsdp_plugin(cfg)
    assert plugin.fsdp_version == 2 and plugin.auto_wrap_policy is not None and not plugin.cpu_ram_efficient_loading
    assert _fsdp_blocks(CMSModel(cfg.model, 10)) == ["TransformerEncoderLayer"]
    monkeypatch.setenv("ACCELERATE_USE_FSDP", "true")  # `accelerate launch --use_fsdp` without --fsdp_version 2
    with pytest.raises(ValueError, match="--fsdp_version 2"):
        _fsdp_plugin(dataclasses.replace(cfg, fsdp=False))
    monkeypatch.setenv("ACCELERATE_USE_FSDP", "false")
    with caplog.at_level(logging.WARNING):
        assert not Trainer(cfg).fsdp
    assert "training without sharding" in caplog.text
