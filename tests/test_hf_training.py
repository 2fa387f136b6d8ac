"""End to end on the ``hf`` backbone: training with LoRA + DINOv2, checkpoint contents, resume, ``load_policy``,
and merging the adapters (``merge_run``) giving the same outputs as the adapters."""

from __future__ import annotations

import json
from dataclasses import replace

import numpy as np
import pytest
import torch

pytest.importorskip("transformers")
pytest.importorskip("peft")

from safetensors.torch import load_file  # noqa: E402

from pivla import load_policy  # noqa: E402
from pivla.bench.hf import make_tiny_dinov2, make_tiny_vlm  # noqa: E402
from pivla.data.read import read_dataset  # noqa: E402
from pivla.data.synthetic import make_synthetic_dataset  # noqa: E402
from pivla.model.config import BackboneConfig, ModelConfig, TargetEncoderConfig  # noqa: E402
from pivla.training.config import TrainConfig  # noqa: E402
from pivla.training.merge import MergeConfig, merge_run  # noqa: E402
from pivla.training.trainer import train  # noqa: E402


def test_train_resume_load_and_merge(tmp_path):
    vlm, dino = make_tiny_vlm(tmp_path / "vlm"), make_tiny_dinov2(tmp_path / "dino")
    data = make_synthetic_dataset(tmp_path / "data", 2, 12, 32)
    run, merged = tmp_path / "run", tmp_path / "merged"
    model = ModelConfig(image_size=32, max_text_len=24, backbone=BackboneConfig(name="hf", path=str(vlm), lora_rank=8),
                        target_encoder=TargetEncoderConfig(name="dinov2", path=str(dino)))
    cfg = TrainConfig(data=str(data), out=str(run), steps=2, batch_size=4, warmup=1, lr=1e-2, progress=False,
                      log_every=1, eval_every=100, ckpt_every=2, threads=2, seed=3, model=model)
    assert train(cfg) == run
    state = load_file(str(run / "model.safetensors"))
    assert not [k for k in state if k.startswith("target.") or ("backbone.vlm." in k and "lora_" not in k)]
    assert len([k for k in state if "lora_" in k]) == 2 * 4 * 2
    assert any(k.startswith("discrete_head.") for k in state) and "backbone.motor_readout.weight" in state
    train(replace(cfg, steps=4), resume=True)
    assert json.loads((run / "status.json").read_text())["step"] == 4
    state = load_file(str(run / "model.safetensors"))
    assert all(float(v.abs().max()) > 0 for k, v in state.items() if "lora_B" in k)  # adapters learned

    policy = load_policy(run, device="cpu")
    for k, v in state.items():  # what load_policy rebuilt is what was saved
        torch.testing.assert_close(policy.model.state_dict()[k], v, msg=k)
    ep = read_dataset(data)[0]
    obs = {k: v[5] for k, v in ep.obs.items()} | {"instruction": ep.instruction}
    a = policy.infer(obs)
    assert a["actions"].shape == (8, 7) and a["discrete_probs"].shape == (8, 7, 256)
    assert a["latents"].shape == (8, 32) and np.isfinite(a["actions"]).all()  # agent-view latent only

    assert merge_run(MergeConfig(policy=str(run), out=str(merged), device="cpu")) == merged
    base = load_file(str(vlm / "model.safetensors"))
    folded = load_file(str(merged / "backbone" / "model.safetensors"))
    assert not any("lora_" in k for k in folded)
    key = "language_model.model.layers.0.self_attn.q_proj.weight"  # the saved (legacy Llava) layout
    assert (folded[key] - base[key]).abs().max() > 1e-4  # the adapters really were folded in
    m_policy = load_policy(merged, device="cpu")
    assert m_policy.cfg.backbone.lora_rank == 0 and not any("lora_" in k for k in m_policy.model.state_dict())
    b = m_policy.infer(obs)
    for k in a:
        np.testing.assert_allclose(a[k], b[k], rtol=1e-4, atol=1e-5, err_msg=k)
    with pytest.raises(FileExistsError):
        merge_run(MergeConfig(policy=str(run), out=str(merged)))
    with pytest.raises(ValueError, match="no LoRA adapters"):
        merge_run(MergeConfig(policy=str(merged), out=str(tmp_path / "again")))
