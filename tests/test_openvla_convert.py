"""``convert_openvla`` (``pivla convert-openvla``) on a tiny random checkpoint written in OpenVLA's released
on-disk layout (timm / Prismatic key names, two shards and an index, config.json, preprocessor_config.json,
tokenizer).

The converted transformers towers and projector are checked against a reference written directly from the
timm-layout weights (a plain-torch timm ViT block and Prismatic's projector), and the ``hf`` backbone is
trained on the converted directory."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch
import torch.nn.functional as F

pytest.importorskip("transformers")
pytest.importorskip("peft")

from safetensors import safe_open  # noqa: E402
from safetensors.torch import save_file  # noqa: E402

from pivla import load_policy  # noqa: E402
from pivla.bench.hf import write_tiny_tokenizer  # noqa: E402
from pivla.data.read import read_dataset  # noqa: E402
from pivla.data.synthetic import make_synthetic_dataset  # noqa: E402
from pivla.model.config import BackboneConfig, ModelConfig  # noqa: E402
from pivla.model.hf.backbone import HFBackbone  # noqa: E402
from pivla.model.hf.text import HFTextTokenizer  # noqa: E402
from pivla.model.openvla import OpenVLAModel, convert_openvla  # noqa: E402
from pivla.training.config import TrainConfig  # noqa: E402
from pivla.training.merge import MergeConfig, merge_run  # noqa: E402
from pivla.training.trainer import train  # noqa: E402

SIZE, PATCH, HEADS, DEPTH = 32, 8, 16, 3  # 16 heads as in both timm definitions; 4 x 4 patches
D_DINO, D_SIG, MLP_SIG, LLM = 32, 48, 80, 64
DINO, SIG = "vision_backbone.featurizer.", "vision_backbone.fused_featurizer."
MEANS = [[0.485, 0.456, 0.406], [0.5, 0.5, 0.5]]
STDS = [[0.229, 0.224, 0.225], [0.5, 0.5, 0.5]]


# -- a tiny checkpoint in OpenVLA's released layout ---------------------------------------------------------
def released_weights(n_vocab: int) -> dict[str, torch.Tensor]:
    """Random tensors under the exact key names of openvla/openvla-7b's safetensors."""
    from transformers import LlamaConfig, LlamaForCausalLM

    g = torch.Generator().manual_seed(0)

    def r(*shape, scale=0.3):
        return torch.randn(*shape, generator=g) * scale

    def lin(out, inp):
        return torch.randn(out, inp, generator=g) / inp**0.5

    def tower(p, d, mlp, dino):
        sd = {p + "pos_embed": r(1, (SIZE // PATCH) ** 2, d), p + "patch_embed.proj.bias": r(d),
              p + "patch_embed.proj.weight": r(d, 3, PATCH, PATCH, scale=0.05), p + "norm.weight": 1 + r(d),
              p + "norm.bias": r(d)}
        if dino:
            sd |= {p + "cls_token": r(1, 1, d), p + "reg_token": r(1, 4, d)}
        for i in range(DEPTH):
            b = f"{p}blocks.{i}."
            sd |= {b + "norm1.weight": 1 + r(d), b + "norm1.bias": r(d), b + "attn.qkv.weight": lin(3 * d, d),
                   b + "attn.qkv.bias": r(3 * d), b + "attn.proj.weight": lin(d, d), b + "attn.proj.bias": r(d),
                   b + "norm2.weight": 1 + r(d), b + "norm2.bias": r(d), b + "mlp.fc1.weight": lin(mlp, d),
                   b + "mlp.fc1.bias": r(mlp), b + "mlp.fc2.weight": lin(d, mlp), b + "mlp.fc2.bias": r(d)}
            if dino:  # Prismatic renames timm's LayerScale gamma to scale_factor
                sd |= {b + "ls1.scale_factor": 0.5 + r(d), b + "ls2.scale_factor": 0.5 + r(d)}
        if not dino:  # SigLIP's MAP head (unused by OpenVLA, present in the checkpoint)
            a = p + "attn_pool."
            sd |= {a + "latent": r(1, 1, d), a + "q.weight": lin(d, d), a + "q.bias": r(d),
                   a + "kv.weight": lin(2 * d, d), a + "kv.bias": r(2 * d), a + "proj.weight": lin(d, d),
                   a + "proj.bias": r(d), a + "norm.weight": 1 + r(d), a + "norm.bias": r(d),
                   a + "mlp.fc1.weight": lin(mlp, d), a + "mlp.fc1.bias": r(mlp), a + "mlp.fc2.weight": lin(d, mlp),
                   a + "mlp.fc2.bias": r(d)}
        return sd

    v = D_DINO + D_SIG
    sd = tower(DINO, D_DINO, 4 * D_DINO, True) | tower(SIG, D_SIG, MLP_SIG, False)
    sd |= {"projector.fc1.weight": lin(4 * v, v), "projector.fc1.bias": r(4 * v),
           "projector.fc2.weight": lin(LLM, 4 * v), "projector.fc2.bias": r(LLM),
           "projector.fc3.weight": lin(LLM, LLM), "projector.fc3.bias": r(LLM)}
    torch.manual_seed(0)
    lm = LlamaForCausalLM(LlamaConfig(**text_config(n_vocab)))
    return sd | {"language_model." + k: v.clone() for k, v in lm.state_dict().items()}


def text_config(n_vocab: int) -> dict:
    return {"model_type": "llama", "hidden_size": LLM, "intermediate_size": 2 * LLM, "num_hidden_layers": 2,
            "num_attention_heads": 4, "num_key_value_heads": 2, "max_position_embeddings": 512, "vocab_size": n_vocab,
            "pad_token_id": 3}


def write_release(out, sd: dict[str, torch.Tensor], **config_overrides):
    """Two shards + index, config.json and preprocessor_config.json as OpenVLA releases them, and a tokenizer."""
    out.mkdir(parents=True)
    write_tiny_tokenizer(out)
    n_vocab = len(json.loads((out / "tokenizer.json").read_text())["model"]["vocab"])
    shards = {"model-00001-of-00002.safetensors": {k: v for k, v in sd.items() if not k.startswith("language_model.")},
              "model-00002-of-00002.safetensors": {k: v for k, v in sd.items() if k.startswith("language_model.")}}
    for name, part in shards.items():
        save_file(part, str(out / name), metadata={"format": "pt"})
    index = {"metadata": {"total_size": sum(v.numel() * v.element_size() for v in sd.values())},
             "weight_map": {k: name for name, part in shards.items() for k in part}}
    (out / "model.safetensors.index.json").write_text(json.dumps(index))
    config = {"model_type": "openvla", "architectures": ["OpenVLAForActionPrediction"],
              "auto_map": {"AutoConfig": "configuration_prismatic.OpenVLAConfig",
                           "AutoModelForVision2Seq": "modeling_prismatic.OpenVLAForActionPrediction"},
              "arch_specifier": "no-align+fused-gelu-mlp", "vision_backbone_id": "dinosiglip-vit-so-224px",
              "llm_backbone_id": "llama2-7b-pure", "hf_llm_id": "meta-llama/Llama-2-7b-hf",
              "timm_model_ids": ["vit_large_patch14_reg4_dinov2.lvd142m", "vit_so400m_patch14_siglip_224"],
              "timm_override_act_layers": [None, None], "image_sizes": [SIZE, SIZE], "use_fused_vision_backbone": True,
              "image_resize_strategy": "resize-naive", "n_action_bins": 256, "pad_token_id": 3,
              "pad_to_multiple_of": 64,
              "norm_stats": {"bridge_orig": {"action": {"q01": [0.0] * 7, "q99": [1.0] * 7}}},
              "text_config": text_config(n_vocab), "torch_dtype": "float32", "transformers_version": "4.40.1"}
    (out / "config.json").write_text(json.dumps(config | config_overrides))
    pre = {"auto_map": {"AutoImageProcessor": "processing_prismatic.PrismaticImageProcessor",
                        "AutoProcessor": "processing_prismatic.PrismaticProcessor"},
           "image_processor_type": "PrismaticImageProcessor", "image_resize_strategy": "resize-naive",
           "input_sizes": [[3, SIZE, SIZE], [3, SIZE, SIZE]], "interpolations": ["bicubic", "bicubic"],
           "means": MEANS, "stds": STDS, "processor_class": "PrismaticProcessor", "tvf_crop_params": [{}, {}],
           "use_fused_vision_backbone": True}
    (out / "preprocessor_config.json").write_text(json.dumps(pre))
    return out


@pytest.fixture(scope="module")
def release(tmp_path_factory):
    root = tmp_path_factory.mktemp("openvla")
    probe = root / "probe"
    probe.mkdir()
    write_tiny_tokenizer(probe)
    n_vocab = len(json.loads((probe / "tokenizer.json").read_text())["model"]["vocab"])
    sd = released_weights(n_vocab)
    src = write_release(root / "src", sd)
    return {"root": root, "sd": sd, "src": src, "converted": convert_openvla(src, root / "converted")}


# -- reference: timm's ViT and Prismatic's projector in plain torch -------------------------------------------
def ref_block(sd, b, x):
    """timm ``Block``: x + ls1 * attn(norm1(x)), then x + ls2 * mlp(norm2(x)) (layer scale 1 without ls)."""
    B, N, D = x.shape
    hd = D // HEADS

    def ln(t, n):
        return F.layer_norm(t, (D,), sd[b + n + ".weight"], sd[b + n + ".bias"], 1e-6)

    q, k, v = F.linear(ln(x, "norm1"), sd[b + "attn.qkv.weight"], sd[b + "attn.qkv.bias"]).reshape(
        B, N, 3, HEADS, hd).permute(2, 0, 3, 1, 4)
    a = ((q @ k.transpose(-2, -1)) * hd**-0.5).softmax(-1) @ v
    a = F.linear(a.transpose(1, 2).reshape(B, N, D), sd[b + "attn.proj.weight"], sd[b + "attn.proj.bias"])
    x = x + a * sd.get(b + "ls1.scale_factor", torch.ones(D))
    m = F.linear(F.gelu(F.linear(ln(x, "norm2"), sd[b + "mlp.fc1.weight"], sd[b + "mlp.fc1.bias"])),
                 sd[b + "mlp.fc2.weight"], sd[b + "mlp.fc2.bias"])
    return x + m * sd.get(b + "ls2.scale_factor", torch.ones(D))


def ref_tower(sd, p, px, blocks):
    """timm ``VisionTransformer`` up to ``blocks`` blocks, all tokens. Position embeddings cover patches only
    (DINOv2-reg4: ``no_embed_class``; SigLIP: no class token), then [cls, reg] tokens are prepended."""
    x = F.conv2d(px, sd[p + "patch_embed.proj.weight"], sd[p + "patch_embed.proj.bias"], stride=PATCH)
    x = x.flatten(2).transpose(1, 2) + sd[p + "pos_embed"]
    if p + "cls_token" in sd:
        b = len(x)
        x = torch.cat([sd[p + "cls_token"].expand(b, -1, -1), sd[p + "reg_token"].expand(b, -1, -1), x], dim=1)
    for i in range(blocks):
        x = ref_block(sd, f"{p}blocks.{i}.", x)
    return x


def ref_norm(sd, p, x):
    return F.layer_norm(x, x.shape[-1:], sd[p + "weight"], sd[p + "bias"], 1e-6)


def ref_pool(sd, p, x):
    """timm ``AttentionPoolLatent`` (SigLIP's MAP head), one latent query."""
    B, N, D = x.shape
    hd = D // HEADS
    q = F.linear(sd[p + "latent"].expand(B, -1, -1), sd[p + "q.weight"], sd[p + "q.bias"]).reshape(B, 1, HEADS, hd)
    k, v = F.linear(x, sd[p + "kv.weight"], sd[p + "kv.bias"]).reshape(B, N, 2, HEADS, hd).permute(2, 0, 3, 1, 4)
    o = ((q.transpose(1, 2) @ k.transpose(-2, -1)) * hd**-0.5).softmax(-1) @ v
    o = F.linear(o.transpose(1, 2).reshape(B, 1, D), sd[p + "proj.weight"], sd[p + "proj.bias"])
    m = F.linear(F.gelu(F.linear(ref_norm(sd, p + "norm.", o), sd[p + "mlp.fc1.weight"], sd[p + "mlp.fc1.bias"])),
                 sd[p + "mlp.fc2.weight"], sd[p + "mlp.fc2.bias"])
    return (o + m)[:, 0]


def ref_features(sd, px6):
    """Prismatic's fused backbone: ``get_intermediate_layers(n={len(blocks) - 2})`` of each tower (output of
    the second-to-last block, no final norm), class/register tokens dropped, concatenated channel-wise."""
    dino = ref_tower(sd, DINO, px6[:, :3], DEPTH - 1)[:, 5:]
    return torch.cat([dino, ref_tower(sd, SIG, px6[:, 3:], DEPTH - 1)], dim=2)


def ref_projector(sd, x):
    def fc(n, t):
        return F.linear(t, sd[f"projector.{n}.weight"], sd[f"projector.{n}.bias"])

    return fc("fc3", F.gelu(fc("fc2", F.gelu(fc("fc1", x)))))


# -- tests ----------------------------------------------------------------------------------------------------
def test_every_source_tensor_is_used_exactly_once(release):
    conv = release["converted"]
    meta = json.loads((conv / "pivla_openvla.json").read_text())
    assert sorted(meta["mapping"]) == sorted(release["sd"])  # nothing dropped, nothing invented
    targets = [t for ts in meta["mapping"].values() for t in ts]
    assert meta["created"] == ["dinov2/embeddings.mask_token"]
    written = set()
    for sub in ("", "dinov2/", "siglip/", "projector/"):
        for f in (conv / sub).glob("*.safetensors"):
            with safe_open(str(f), "pt") as h:
                written |= {sub + k for k in h.keys()}
    # every written tensor comes from the source, or is the one created tensor; targets are distinct except
    # SigLIP's pooling in_proj, built from timm's q and kv
    assert written == set(targets) | set(meta["created"])
    assert len(set(targets)) == len(targets) - 2
    assert meta["mapping"][DINO + "blocks.0.ls1.scale_factor"] == ["dinov2/encoder.layer.0.layer_scale1.lambda1"]
    assert not (conv / "modeling_prismatic.py").exists()
    assert "auto_map" not in json.loads((conv / "preprocessor_config.json").read_text())


def test_towers_and_projector_match_the_timm_reference(release):
    sd = release["sd"]
    model = OpenVLAModel.from_pretrained(release["converted"], torch.float32).eval()
    px = torch.randn(3, 6, SIZE, SIZE, generator=torch.Generator().manual_seed(1))
    with torch.no_grad():
        feats = model.vision_backbone(px)
        ref = ref_features(sd, px)
        assert feats.shape == ref.shape == (3, 16, D_DINO + D_SIG)
        torch.testing.assert_close(feats, ref, atol=1e-5, rtol=1e-5)
        torch.testing.assert_close(model.projector(feats), ref_projector(sd, ref), atol=1e-5, rtol=1e-5)
        # the parts OpenVLA does not use were converted too: last blocks, final norms, SigLIP's MAP head
        dino = model.vision_backbone.dinov2(pixel_values=px[:, :3]).last_hidden_state
        torch.testing.assert_close(dino, ref_norm(sd, DINO + "norm.", ref_tower(sd, DINO, px[:, :3], DEPTH)),
                                   atol=1e-5, rtol=1e-5)
        sig_final = ref_norm(sd, SIG + "norm.", ref_tower(sd, SIG, px[:, 3:], DEPTH))
        pooled = model.vision_backbone.siglip(pixel_values=px[:, 3:]).pooler_output
        torch.testing.assert_close(pooled, ref_pool(sd, SIG + "attn_pool.", sig_final), atol=1e-5, rtol=1e-5)
    lm = model.language_model.state_dict()
    for k, v in sd.items():
        if k.startswith("language_model."):
            assert torch.equal(lm[k.removeprefix("language_model.")], v), k


def test_large_parts_are_written_in_shards(release, tmp_path):
    """The 7B language model is written in several shards with an index (small shards here)."""
    conv = convert_openvla(release["src"], tmp_path / "sharded", max_shard_bytes=60_000)
    index = json.loads((conv / "model.safetensors.index.json").read_text())
    assert len(set(index["weight_map"].values())) > 2 and not (conv / "model.safetensors").exists()
    lm = OpenVLAModel.from_pretrained(conv, torch.float32).language_model.state_dict()
    for k, v in release["sd"].items():
        if k.startswith("language_model."):
            assert torch.equal(lm[k.removeprefix("language_model.")], v), k


def test_hf_backbone_runs_the_converted_model(release):
    """Pixels are normalised per tower (DINOv2 view first) and patches go through the projector."""
    path = release["converted"]
    text = HFTextTokenizer.from_pretrained(str(path), 24)
    cfg = ModelConfig(image_size=SIZE, max_text_len=24, backbone=BackboneConfig(
        name="hf", path=str(path), n_cog_tokens=2, lora_rank=4, gradient_checkpointing=True))
    backbone = HFBackbone(cfg).train()
    assert backbone.kind == "openvla" and backbone.parts.vision_size == SIZE
    images = torch.rand(2, 2, 3, SIZE, SIZE, generator=torch.Generator().manual_seed(2))
    px = torch.cat([(images[:, 0] - torch.tensor(m).view(1, 3, 1, 1)) / torch.tensor(s).view(1, 3, 1, 1)
                    for m, s in zip(MEANS, STDS)], dim=1)
    with torch.no_grad():
        emb = backbone.parts.image_embeddings(backbone.pixels(images[:, 0]))
    torch.testing.assert_close(emb, ref_projector(release["sd"], ref_features(release["sd"], px)), atol=1e-5, rtol=1e-5)
    ids, mask = zip(*(text.encode(s) for s in ["pick the red block", "open the drawer"]))
    batch = {"images": images, "text_ids": torch.from_numpy(np.stack(ids)),
             "text_mask": torch.from_numpy(np.stack(mask)), "proprio": torch.randn(2, 8)}
    h_cog, h_mot = backbone(batch)
    assert h_cog.shape == (2, 2, LLM) and h_mot.shape == (2, 8, LLM)
    (h_cog.square().mean() + h_mot.square().mean()).backward()
    lora = [n for n, p in backbone.named_parameters() if p.requires_grad and "lora_" in n]
    assert lora and all("language_model." in n for n in lora)
    trainable_vlm = [n for n, p in backbone.named_parameters() if p.requires_grad and n.startswith("vlm.")]
    assert all("lora_" in n for n in trainable_vlm)
    assert backbone.queries.grad.abs().sum() > 0


def test_train_and_merge_on_the_converted_checkpoint(release, tmp_path):
    conv = tmp_path / "conv"
    convert_openvla(release["src"], conv)
    data = make_synthetic_dataset(tmp_path / "data", 2, 12, SIZE)
    run, merged = tmp_path / "run", tmp_path / "merged"
    backbone = BackboneConfig(name="hf", path=str(conv), lora_rank=4)
    model = ModelConfig(image_size=SIZE, max_text_len=24, backbone=backbone)
    train(TrainConfig(data=str(data), out=str(run), batch_size=2, steps=2, warmup=1, lr=1e-2, progress=False,
                      log_every=1, eval_every=100, ckpt_every=2, threads=2, model=model))
    assert json.loads((run / "status.json").read_text())["step"] == 2
    policy = load_policy(run, device="cpu")
    ep = read_dataset(data)[0]
    obs = {k: v[5] for k, v in ep.obs.items()} | {"instruction": ep.instruction}
    a = policy.infer(obs)
    assert a["actions"].shape == (8, 7) and np.isfinite(a["actions"]).all()
    merge_run(MergeConfig(policy=str(run), out=str(merged), device="cpu"))
    assert (merged / "backbone" / "pivla_openvla.json").is_file()
    b = load_policy(merged, device="cpu").infer(obs)
    for k in a:
        np.testing.assert_allclose(a[k], b[k], rtol=1e-4, atol=1e-5, err_msg=k)


def test_incomplete_or_corrupt_sources_fail_clearly(release, tmp_path):
    sd, root = release["sd"], tmp_path
    with pytest.raises(FileExistsError):
        convert_openvla(release["src"], release["converted"])
    extra = sd | {SIG + "extra.weight": torch.zeros(2)}
    with pytest.raises(ValueError, match=r"unexpected \[vision_backbone\.fused_featurizer\.extra\.weight\]"):
        convert_openvla(write_release(root / "extra", extra), root / "out")
    dropped = {k: v for k, v in sd.items() if k != DINO + "blocks.1.ls2.scale_factor"}
    with pytest.raises(ValueError, match=r"missing \[vision_backbone\.featurizer\.blocks\.1\.ls2\.scale_factor\]"):
        convert_openvla(write_release(root / "dropped", dropped), root / "out")
    src = write_release(root / "shard", sd)
    (src / "model-00002-of-00002.safetensors").unlink()
    with pytest.raises(FileNotFoundError, match="model-00002-of-00002.safetensors"):
        convert_openvla(src, root / "out")
    src = write_release(root / "truncated", sd)
    f = src / "model-00001-of-00002.safetensors"
    f.write_bytes(f.read_bytes()[:-100])
    with pytest.raises(ValueError, match="not a readable safetensors file"):
        convert_openvla(src, root / "out")
    with pytest.raises(ValueError, match="fused DINOv2 \\+ SigLIP"):
        convert_openvla(write_release(root / "single", sd, use_fused_vision_backbone=False,
                                      timm_model_ids=["vit_so400m_patch14_siglip_224"]), root / "out")
    assert not (root / "out").exists() and not list(root.glob(".out.*"))  # nothing half-written is left
