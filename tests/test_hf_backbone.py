"""The ``hf`` backbone and ``dinov2`` target encoder on tiny random checkpoints built from configs."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest
import torch

pytest.importorskip("transformers")
pytest.importorskip("peft")

from pivla.bench.hf import HFBenchConfig, make_tiny_dinov2, make_tiny_vlm, run_hf_bench  # noqa: E402
from pivla.model.cms import CMSModel  # noqa: E402
from pivla.model.config import BackboneConfig, ModelConfig, TargetEncoderConfig  # noqa: E402
from pivla.model.dinov2 import Dinov2Encoder  # noqa: E402
from pivla.model.hf.backbone import HFBackbone  # noqa: E402
from pivla.model.hf.pixels import PixelSpec  # noqa: E402
from pivla.model.hf.text import HFTextTokenizer  # noqa: E402

SIZE = 32


@pytest.fixture(scope="module")
def dirs(tmp_path_factory):
    root = tmp_path_factory.mktemp("hf")
    return {"vlm": make_tiny_vlm(root / "vlm", image_size=SIZE),
            "dino": make_tiny_dinov2(root / "dino", image_size=SIZE)}


def model_cfg(dirs, target="dinov2", **backbone) -> ModelConfig:
    return ModelConfig(image_size=SIZE, max_text_len=24,
                       backbone=BackboneConfig(name="hf", path=str(dirs["vlm"]), n_cog_tokens=2, **backbone),
                       target_encoder=TargetEncoderConfig(name=target, path=str(dirs["dino"])))


def make_batch(text: HFTextTokenizer, b: int = 2, seed: int = 0) -> dict[str, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    ids, mask = zip(*(text.encode(s)
                      for s in ["move the square left", "pick the red block and put it on the plate"][:b]))
    return {"images": torch.rand(b, 2, 3, SIZE, SIZE, generator=g), "text_ids": torch.from_numpy(np.stack(ids)),
            "text_mask": torch.from_numpy(np.stack(mask)), "proprio": torch.randn(b, 8, generator=g)}


def test_forward_backward_and_only_adapters_and_heads_train(dirs):
    text = HFTextTokenizer.from_pretrained(str(dirs["vlm"]), 24)
    torch.manual_seed(0)
    model = CMSModel(model_cfg(dirs), len(text.vocab))
    out = model(make_batch(text))
    assert out.logits.shape == (2, 8, 7, 256) and out.continuous.shape == (2, 8, 7)
    assert out.h_cog.shape == (2, 2, 64) and out.h_mot.shape == (2, 8, 64)
    assert out.latents.shape == (2, 8, model.latent_dim) and model.latent_dim == 32  # CLS of the agent view
    (out.continuous.square().mean() + out.logits.logsumexp(-1).mean() + out.values.mean()).backward()
    trainable = {n for n, p in model.named_parameters() if p.requires_grad}
    base = [n for n in trainable if n.startswith("backbone.vlm.") and "lora_" not in n]
    assert not base, f"frozen base weights train: {base[:3]}"
    lora = [n for n in trainable if "lora_" in n]
    # default targets q/k/v/o on both layers of the language model only, A and B each
    assert len(lora) == 2 * 4 * 2 and all("language_model" in n for n in lora)
    assert not any(n.startswith("target.") for n in trainable)
    for name in ("backbone.queries", "backbone.motor_readout.weight", "backbone.proprio_proj.0.weight",
                 "discrete_head.proj.2.weight", "continuous_head.proj.2.weight"):
        assert name in trainable
        assert dict(model.named_parameters())[name].grad.abs().sum() > 0, name
    grads_b = [p.grad.abs().sum() for n, p in model.named_parameters() if "lora_B" in n]
    assert all(g > 0 for g in grads_b)  # B starts at zero, so only B gets gradient at step 0


def test_lora_rank_and_targets_are_configurable(dirs):
    text = HFTextTokenizer.from_pretrained(str(dirs["vlm"]), 24)
    model = HFBackbone(model_cfg(dirs, lora_rank=4, lora_target_modules=("all-linear",)))
    names = [n for n, _ in model.named_parameters() if "lora_A" in n]
    assert any("mlp.gate_proj" in n for n in names) and any("self_attn.q_proj" in n for n in names)
    assert all(p.shape[0] == 4 for n, p in model.named_parameters() if "lora_A" in n)
    assert not any("lm_head" in n or "vision_tower" in n for n in names)
    with pytest.raises(ValueError, match="no Linear layer"):
        HFBackbone(model_cfg(dirs, lora_target_modules=("no_such_proj",)))
    none = HFBackbone(model_cfg(dirs, lora_rank=0))
    assert not [n for n, p in none.named_parameters() if p.requires_grad and n.startswith("vlm.")]
    h_cog, h_mot = none(make_batch(text))
    assert torch.isfinite(h_cog).all() and torch.isfinite(h_mot).all()


def test_padding_does_not_change_outputs(dirs):
    """Padded word positions are masked out and do not shift positions: what sits there is irrelevant."""
    text = HFTextTokenizer.from_pretrained(str(dirs["vlm"]), 24)
    torch.manual_seed(0)
    backbone = HFBackbone(model_cfg(dirs)).eval()
    batch = make_batch(text, b=1)
    assert not batch["text_mask"].all()
    other = dict(batch, text_ids=batch["text_ids"].masked_fill(~batch["text_mask"], 5))
    with torch.no_grad():
        a, b = backbone(batch), backbone(other)
        changed = backbone(dict(batch, text_ids=batch["text_ids"].roll(1, dims=1)))
    torch.testing.assert_close(a[0], b[0])
    torch.testing.assert_close(a[1], b[1])
    assert (changed[1] - a[1]).abs().max() > 1e-4  # but the words do matter


def test_gradient_checkpointing_gives_the_same_gradients(dirs):
    text = HFTextTokenizer.from_pretrained(str(dirs["vlm"]), 24)
    batch = make_batch(text)
    grads = []
    for gc in (False, True):
        torch.manual_seed(0)
        backbone = HFBackbone(model_cfg(dirs, gradient_checkpointing=gc)).train()
        with torch.no_grad():  # non-zero B so that gradients flow through the adapters into A
            for n, p in backbone.named_parameters():
                if "lora_B" in n:
                    p.normal_(0, 0.1, generator=torch.Generator().manual_seed(1))
        h_cog, h_mot = backbone(batch)
        (h_cog.square().mean() + h_mot.square().mean()).backward()
        grads.append({n: p.grad.clone() for n, p in backbone.named_parameters() if p.requires_grad})
    assert grads[0].keys() == grads[1].keys()
    for n in grads[0]:
        torch.testing.assert_close(grads[0][n], grads[1][n], rtol=1e-4, atol=1e-6, msg=n)


def test_frozen_target_is_a_frozen_copy_of_the_vision_tower(dirs):
    text = HFTextTokenizer.from_pretrained(str(dirs["vlm"]), 24)
    model = CMSModel(model_cfg(dirs, target="frozen"), len(text.vocab))
    assert model.latent_dim == 32  # SigLIP hidden 32, agent-view camera (target_encoder.cameras = 1)
    tower = model.backbone.parts.tower
    copy = model.target.encoder.tower
    assert copy is not tower and all(not p.requires_grad for p in copy.parameters())
    assert all(k.startswith("target.encoder.") or k.startswith("backbone.vlm.") for k in model.external_state_keys())
    z = model.target(make_batch(text)["images"])
    assert z.shape == (2, 32) and torch.isfinite(z).all()


def test_tokenizer_round_trip_is_self_contained(dirs, tmp_path):
    src = tmp_path / "copy"
    shutil.copytree(dirs["vlm"], src)
    text = HFTextTokenizer.from_pretrained(str(src), 24)
    ids, mask = text.encode("Move the square left.")
    assert ids.dtype == np.int64 and ids.shape == (24,) and mask.dtype == bool and mask.sum() > 5
    assert ids[0] == text.tokenizer.bos_token_id and not mask[-1]
    data = json.loads(json.dumps(text.to_dict()))
    assert data["kind"] == "hf"
    shutil.rmtree(src)  # the run directory must not need the checkpoint's tokenizer files
    from pivla.data.text import load_text_tokenizer

    again = load_text_tokenizer(data)
    ids2, mask2 = again.encode("Move the square left.")
    np.testing.assert_array_equal(ids, ids2)
    np.testing.assert_array_equal(mask, mask2)
    assert len(again.vocab) == len(text.vocab)


def test_pixel_spec_reads_openvla_and_dinov2_layouts(tmp_path):
    # OpenVLA's preprocessor_config.json: two channel-stacked views (DINOv2 then SigLIP normalisation)
    (tmp_path / "preprocessor_config.json").write_text(json.dumps({
        "image_processor_type": "PrismaticImageProcessor", "image_resize_strategy": "resize-naive",
        "input_sizes": [[3, 224, 224], [3, 224, 224]], "interpolations": ["bicubic", "bicubic"],
        "means": [[0.485, 0.456, 0.406], [0.5, 0.5, 0.5]], "stds": [[0.229, 0.224, 0.225], [0.5, 0.5, 0.5]],
        "use_fused_vision_backbone": True}))
    spec = PixelSpec.from_dir(tmp_path, 224)
    x = torch.full((1, 3, 96, 96), 0.5)
    px = spec(x)
    assert px.shape == (1, 6, 224, 224)
    torch.testing.assert_close(px[0, 0, 0, 0], torch.tensor((0.5 - 0.485) / 0.229))
    torch.testing.assert_close(px[0, 3:], torch.zeros(3, 224, 224))
    # DINOv2's: resize the short side to 256, centre-crop 224
    (tmp_path / "preprocessor_config.json").write_text(json.dumps({
        "size": {"shortest_edge": 256}, "do_center_crop": True, "crop_size": {"height": 224, "width": 224},
        "image_mean": [0.485, 0.456, 0.406], "image_std": [0.229, 0.224, 0.225]}))
    spec = PixelSpec.from_dir(tmp_path, 224)
    assert (spec.resize, spec.crop, spec.channels) == (256, 224, 3)
    assert spec(torch.rand(2, 3, 64, 64)).shape == (2, 3, 224, 224)
    with pytest.raises(ValueError, match="expected images"):
        spec(torch.rand(2, 4, 64, 64))


def test_dinov2_encoder_is_frozen_cls_per_camera(dirs):
    from transformers import Dinov2Model

    enc = Dinov2Encoder(str(dirs["dino"]), SIZE)
    enc.train()
    assert not enc.model.training and all(not p.requires_grad for p in enc.parameters())
    images = torch.rand(3, 2, 3, SIZE, SIZE)
    z = enc.pooled(images)
    assert z.shape == (3, 64)
    ref = Dinov2Model.from_pretrained(str(dirs["dino"])).eval()
    mean = torch.tensor([0.485, 0.456, 0.406]).view(1, 3, 1, 1)
    std = torch.tensor([0.229, 0.224, 0.225]).view(1, 3, 1, 1)
    with torch.no_grad():  # the second camera's CLS token, pixels prepared by hand
        out = ref(pixel_values=(images[:, 1] - mean) / std)
    torch.testing.assert_close(z[:, 32:], out.last_hidden_state[:, 0])  # after DINOv2's final norm
    assert set(enc.external_state_keys()) == set(enc.state_dict())


def test_clear_errors_for_bad_checkpoint_dirs(dirs, tmp_path):
    with pytest.raises(FileNotFoundError, match="not a directory"):
        HFBackbone(model_cfg({"vlm": tmp_path / "missing", "dino": dirs["dino"]}))
    (tmp_path / "empty").mkdir()
    with pytest.raises(FileNotFoundError, match="no config.json"):
        Dinov2Encoder(str(tmp_path / "empty"), SIZE)
    with pytest.raises(ValueError, match="not a DINOv2"):
        Dinov2Encoder(str(dirs["vlm"]), SIZE)
    with pytest.raises(ValueError, match="no local checkpoint"):
        HFTextTokenizer.from_pretrained("", 16)
    (tmp_path / "openvla").mkdir()
    (tmp_path / "openvla" / "config.json").write_text(json.dumps({"model_type": "openvla"}))
    with pytest.raises(ValueError, match="auto_map"):
        HFBackbone(model_cfg({"vlm": tmp_path / "openvla", "dino": dirs["dino"]}))


def test_llava_with_a_dinov2_vision_tower(tmp_path):
    """Another Llava-style layout: DINOv2 tower, second-to-last layer, CLS dropped ('default' strategy)."""
    path = make_tiny_vlm(tmp_path / "vlm", image_size=SIZE, vision="dinov2")
    text = HFTextTokenizer.from_pretrained(str(path), 24)
    backbone = HFBackbone(model_cfg({"vlm": path, "dino": path}))
    assert type(backbone.parts.tower).__name__ == "Dinov2Model"
    batch = make_batch(text)
    with torch.no_grad():
        n_patch = backbone.parts.image_embeddings(backbone.pixels(batch["images"][:, 0])).shape[1]
    assert n_patch == (SIZE // (SIZE // 4)) ** 2  # 16 patches, CLS dropped
    h_cog, h_mot = backbone(batch)
    h_mot.square().mean().backward()
    assert h_cog.shape == (2, 2, 64) and backbone.queries.grad.abs().sum() > 0


def test_hf_bench_times_the_tiny_stack():
    out = run_hf_bench(HFBenchConfig(repeats=1, threads=0, lora_rank=4))
    assert out["vlm"] == "tiny-random-llava" and out["threads"] == torch.get_num_threads()
    assert all(out[k] > 0 for k in ("infer_ms", "target_encoder_ms", "train_step_ms"))
    counts = out["parameters"]
    assert 0 < counts["trainable"] < counts["total"]  # LoRA: the base weights stay frozen
    with pytest.raises(ValueError, match="repeats must be at least 1"):
        run_hf_bench(HFBenchConfig(repeats=0))


def test_tiny_checkpoints_go_to_new_directories_and_leave_the_rng_alone(tmp_path):
    state = torch.random.get_rng_state()
    a = make_tiny_dinov2(tmp_path / "a", seed=1)
    assert torch.equal(state, torch.random.get_rng_state())
    b = make_tiny_dinov2(tmp_path / "b", seed=1)
    assert (a / "model.safetensors").read_bytes() == (b / "model.safetensors").read_bytes()  # seeded
    with pytest.raises(FileExistsError, match="exists"):
        make_tiny_dinov2(a)
    with pytest.raises(ValueError, match="unknown tiny vision tower"):
        make_tiny_vlm(tmp_path / "c", vision="clip")
    assert not (tmp_path / "c").exists()
