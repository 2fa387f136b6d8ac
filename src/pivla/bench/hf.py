"""CPU cost of CMS on the ``hf`` backbone, and the tiny random checkpoints it (and the tests) run on.

The tiny checkpoints (a Llava-style VLM with its tokenizer, a DINOv2) are built from configs with random
weights, so the whole ``hf`` path (loading, LoRA, training, merging) runs here without any download.
"""

from __future__ import annotations

import json
import statistics
import tempfile
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch

from pivla.io import atomic_dir
from pivla.model.cms import CMSModel
from pivla.model.config import BackboneConfig, ModelConfig, TargetEncoderConfig
from pivla.model.dinov2 import IMAGENET_MEAN, IMAGENET_STD
from pivla.model.hf.text import HFTextTokenizer

# the tiny tokenizer's words: OpenVLA's prompt and the instructions of the synthetic and tabletop tasks
TINY_WORDS = ("? : . , in what action should the robot take to out move the square left right up down pick place put "
              "open close a an on of and bowl plate drawer cup mug block red green blue").split()
TINY_VISION = ("siglip", "dinov2")


# -- tiny random checkpoints -------------------------------------------------------------------------------
def write_tiny_tokenizer(out: str | Path) -> None:
    """A small lower-casing word-level fast tokenizer (BOS added), saved into ``out`` with ``save_pretrained``."""
    from tokenizers import Tokenizer, models, normalizers, pre_tokenizers, processors
    from transformers import PreTrainedTokenizerFast

    specials = ["<unk>", "<s>", "</s>", "<pad>"]
    vocab = {w: i for i, w in enumerate(specials + sorted(set(TINY_WORDS)))}
    tk = Tokenizer(models.WordLevel(vocab, unk_token="<unk>"))
    tk.normalizer = normalizers.Lowercase()
    tk.pre_tokenizer = pre_tokenizers.Whitespace()
    tk.post_processor = processors.TemplateProcessing(single="<s> $A", special_tokens=[("<s>", 1)])
    tok = PreTrainedTokenizerFast(tokenizer_object=tk, unk_token="<unk>", bos_token="<s>", eos_token="</s>",
                                  pad_token="<pad>")
    tok.save_pretrained(str(out))


def make_tiny_vlm(out: str | Path, image_size: int = 32, hidden: int = 64, layers: int = 2, seed: int = 0,
                  vision: str = "siglip") -> Path:
    """A random Llava (``siglip`` or ``dinov2`` vision + Llama) with tokenizer and preprocessor config, for
    CPU tests, benchmarks and smoke runs of the ``hf`` path. Random weights: it learns, but knows nothing.
    ``out`` must not exist; it appears complete or not at all. The caller's torch RNG is left as it was."""
    from transformers import Dinov2Config, LlamaConfig, LlavaConfig, LlavaForConditionalGeneration, SiglipVisionConfig

    if vision not in TINY_VISION:
        raise ValueError(f"unknown tiny vision tower {vision!r}; choose one of {', '.join(TINY_VISION)}")
    out = _new_dir(out)
    with atomic_dir(out) as tmp:
        write_tiny_tokenizer(tmp)
        n_vocab = len(json.loads((tmp / "tokenizer.json").read_text())["model"]["vocab"])
        tower = dict(hidden_size=32, intermediate_size=64, num_hidden_layers=2, num_attention_heads=2,
                     image_size=image_size, patch_size=max(image_size // 4, 1))
        cfg = LlavaConfig(
            vision_config=SiglipVisionConfig(**tower) if vision == "siglip" else Dinov2Config(**tower),
            text_config=LlamaConfig(hidden_size=hidden, intermediate_size=2 * hidden, num_hidden_layers=layers,
                                    num_attention_heads=4, num_key_value_heads=2, vocab_size=n_vocab,
                                    max_position_embeddings=512),
            image_token_id=0, vision_feature_layer=-2 if vision == "dinov2" else -1,
            vision_feature_select_strategy="full" if vision == "siglip" else "default",
        )
        with torch.random.fork_rng(devices=[]):
            torch.manual_seed(seed)
            LlavaForConditionalGeneration(cfg).save_pretrained(str(tmp))
        pre = {"image_processor_type": "SiglipImageProcessor", "do_resize": True, "resample": 3,
               "size": {"height": image_size, "width": image_size}, "do_rescale": True, "rescale_factor": 1 / 255,
               "do_normalize": True, "image_mean": [0.5, 0.5, 0.5], "image_std": [0.5, 0.5, 0.5]}
        (tmp / "preprocessor_config.json").write_text(json.dumps(pre, indent=2))
    return out


def make_tiny_dinov2(out: str | Path, image_size: int = 32, hidden: int = 32, seed: int = 0) -> Path:
    """A random tiny DINOv2 with a preprocessor config in the official layout (resize the short side, centre
    crop, ImageNet normalisation). ``out`` must not exist; the caller's torch RNG is left as it was."""
    from transformers import Dinov2Config, Dinov2Model

    out = _new_dir(out)
    with atomic_dir(out) as tmp:
        cfg = Dinov2Config(hidden_size=hidden, num_hidden_layers=2, num_attention_heads=2,
                           intermediate_size=2 * hidden, patch_size=max(image_size // 4, 1), image_size=image_size)
        with torch.random.fork_rng(devices=[]):
            torch.manual_seed(seed)
            Dinov2Model(cfg).save_pretrained(str(tmp))
        pre = {"image_processor_type": "BitImageProcessor", "do_resize": True, "size": {"shortest_edge": image_size},
               "resample": 3, "do_center_crop": True, "crop_size": {"height": image_size, "width": image_size},
               "do_rescale": True, "rescale_factor": 1 / 255, "do_normalize": True,
               "image_mean": IMAGENET_MEAN, "image_std": IMAGENET_STD}
        (tmp / "preprocessor_config.json").write_text(json.dumps(pre, indent=2))
    return out


def _new_dir(out: str | Path) -> Path:
    out = Path(out)
    if out.exists():
        raise FileExistsError(f"{out} exists; a tiny checkpoint is written to a new directory")
    return out


# -- benchmark -------------------------------------------------------------------------------------------------
@dataclass
class HFBenchConfig:
    """What ``run_hf_bench`` times."""

    path: str = ""
    """Local Llava-style (or OpenVLA) checkpoint directory; empty: a tiny random Llava built for the run."""
    target_path: str = ""
    """Local DINOv2 checkpoint directory (the target encoder); empty: a tiny random DINOv2."""
    image_size: int = 32
    """Camera image side in pixels (also the tiny checkpoints' input size)."""
    batch: int = 1
    """Samples per forward pass."""
    repeats: int = 30
    """Timed runs per figure (after two warm-up runs); each figure is their median."""
    threads: int = 2
    """torch intra-op threads (0: torch's default)."""
    lora_rank: int = 32
    """LoRA rank on the language model (0: no adapters)."""


def run_hf_bench(cfg: HFBenchConfig) -> dict[str, Any]:
    """Forward (inference), target-encoder and train-step latency of CMS on the ``hf`` backbone.

    Returns medians in ms over ``cfg.repeats`` timed runs after two warm-up runs, with the settings and the
    model's parameter counts. A train step is a forward pass plus the backward pass of a loss touching
    every head (no optimizer step)."""
    for name in ("image_size", "batch", "repeats"):
        if getattr(cfg, name) < 1:
            raise ValueError(f"hf bench: {name} must be at least 1, got {getattr(cfg, name)}")
    if cfg.threads < 0 or cfg.lora_rank < 0:
        raise ValueError(f"hf bench: threads and lora_rank must be >= 0, got {cfg.threads} and {cfg.lora_rank}")
    if cfg.threads > 0:
        torch.set_num_threads(cfg.threads)
    with tempfile.TemporaryDirectory() as tmp:
        vlm = cfg.path or str(make_tiny_vlm(Path(tmp) / "vlm", image_size=cfg.image_size))
        dino = cfg.target_path or str(make_tiny_dinov2(Path(tmp) / "dino", image_size=cfg.image_size))
        text = HFTextTokenizer.from_pretrained(vlm, 32)
        model_cfg = ModelConfig(image_size=cfg.image_size, max_text_len=32,
                                backbone=BackboneConfig(name="hf", path=vlm, lora_rank=cfg.lora_rank),
                                target_encoder=TargetEncoderConfig(name="dinov2", path=dino))
        model = CMSModel(model_cfg, len(text.vocab))
        ids, mask = text.encode("put the bowl on the plate")
        b = cfg.batch
        batch = {"images": torch.rand(b, len(model_cfg.cameras), 3, cfg.image_size, cfg.image_size),
                 "text_ids": torch.from_numpy(ids).repeat(b, 1), "text_mask": torch.from_numpy(mask).repeat(b, 1),
                 "proprio": torch.randn(b, model_cfg.proprio_dim)}

        def infer() -> None:
            with torch.inference_mode():
                model(batch)

        def train_step() -> None:
            out = model(batch)
            (out.continuous.square().mean() + out.logits.float().logsumexp(-1).mean() + out.latents.square().mean()
             + out.values.square().mean()).backward()
            model.zero_grad(set_to_none=True)

        model.eval()
        infer_ms = _median_ms(infer, cfg.repeats)
        target_ms = _median_ms(lambda: model.target(batch["images"]), cfg.repeats)
        model.train()
        train_ms = _median_ms(train_step, cfg.repeats)
        counts = model.parameter_counts()
    return {"backbone": "hf", "vlm": cfg.path or "tiny-random-llava", "batch": b, "image_size": cfg.image_size,
            "threads": torch.get_num_threads(), "infer_ms": round(infer_ms, 2),
            "target_encoder_ms": round(target_ms, 2), "train_step_ms": round(train_ms, 2), "parameters": counts}


def _median_ms(fn: Callable[[], object], repeats: int) -> float:
    """Median wall time of ``fn`` in ms over ``repeats`` runs, after two warm-up runs (allocator, caches)."""
    for _ in range(2):
        fn()
    runs = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        runs.append((time.perf_counter() - t0) * 1e3)
    return statistics.median(runs)
