"""Two processes (``torchrun``, gloo on CPU) train the tiny ``hf`` stack; afterwards every rank must hold
bit-identical parameters, and the adapters must have moved (so the check is not vacuous)."""

from __future__ import annotations

import pytest

pytest.importorskip("transformers")
pytest.importorskip("peft")

from pivla.bench.hf import make_tiny_dinov2, make_tiny_vlm  # noqa: E402
from pivla.data.synthetic import make_synthetic_dataset  # noqa: E402
from pivla.model.config import BackboneConfig, ModelConfig, TargetEncoderConfig  # noqa: E402
from pivla.training.trainer import TrainConfig  # noqa: E402
from tests.conftest import run_two_process  # noqa: E402

WORKER = '''
import json, sys
import torch, torch.distributed as dist
from pivla import config as cfgmod
from pivla.training.trainer import Trainer, TrainConfig

trainer = Trainer(cfgmod.from_dict(TrainConfig, json.load(open(sys.argv[1]))))
trainer.run()
flat = torch.cat([p.detach().float().flatten() for p in trainer.model.parameters()])
lora_b = torch.cat([p.detach().flatten() for n, p in trainer.model.named_parameters() if "lora_B" in n])
gathered = [torch.zeros_like(flat) for _ in range(dist.get_world_size())]
dist.all_gather(gathered, flat)
if dist.get_rank() == 0:
    with open(sys.argv[2], "w") as f:
        json.dump({"world": dist.get_world_size(), "max_diff": max(float((g - flat).abs().max()) for g in gathered),
                   "lora_b_abs": float(lora_b.abs().sum())}, f)
trainer.acc.wait_for_everyone()  # no rank tears the group down while rank 0 still writes its findings
trainer.acc.end_training()  # destroys the process group; left to interpreter exit, gloo can abort a rank
# C++ destructors at interpreter exit still abort a rank now and then ('terminate called without an active
# exception', ~1 run in 8 even with the teardown above); the findings are written, so leave at once
import os; os._exit(0)
'''


def test_two_process_training_keeps_ranks_identical(tmp_path):
    cfg = TrainConfig(
        data=str(make_synthetic_dataset(tmp_path / "data", 2, 12, 32)), out=str(tmp_path / "run"), steps=3,
        batch_size=2, warmup=1, lr=1e-2, threads=1, progress=False, log_every=1, eval_every=100, ckpt_every=100,
        model=ModelConfig(image_size=32, max_text_len=24,
                          backbone=BackboneConfig(name="hf", path=str(make_tiny_vlm(tmp_path / "vlm")), lora_rank=8),
                          target_encoder=TargetEncoderConfig(name="dinov2",
                                                             path=str(make_tiny_dinov2(tmp_path / "dino")))))
    result = run_two_process(tmp_path, WORKER, cfg)
    assert result["world"] == 2
    assert result["max_diff"] == 0.0
    assert result["lora_b_abs"] > 0
    assert (tmp_path / "run" / "model.safetensors").is_file()
