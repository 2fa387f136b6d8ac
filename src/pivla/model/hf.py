"""The paper-scale backbone: a local Hugging Face vision-language model fine-tuned with LoRA.

The paper builds CMS on OpenVLA-7B. This backbone reads any Llava-style checkpoint that transformers loads
with ``AutoModelForImageTextToText`` (a vision tower, a projector and a decoder-only language model),
OpenVLA converted by ``pivla convert-openvla`` (plain transformers parts, see ``pivla.model.openvla``), and
OpenVLA's released layout (``model_type`` "openvla": a fused DINOv2 + SigLIP backbone, projector and
Llama-2) through the checkpoint's own code, always from a local directory (nothing is downloaded).

One forward pass, OpenVLA-OFT style: the language model reads
``[camera patches][prompt tokens][proprio token][N_cog cognitive queries][K x D action queries]``; the query
block attends to the whole prefix and, bidirectionally, to itself, so all K x D action positions are decoded
in parallel. ``h_cog`` is the final hidden state of the cognitive queries; ``h_mot[k]`` is a linear readout
of the D hidden states of chunk step k (OFT's action head input), feeding the same four heads as the small
backbone. Base weights stay frozen: only LoRA adapters on the language model, the queries, the proprio
projector and the readout train (plus the CMS heads).
"""

from __future__ import annotations

import base64
import json
import logging
import os
import shutil
import tempfile
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from pivla.io import atomic_dir
from pivla.model.config import ModelConfig

log = logging.getLogger(__name__)

# OpenVLA's prompt; the instruction is lower-cased and stripped of its final period, as OpenVLA does.
PROMPT = "In: What action should the robot take to {instruction}?\nOut:"
_RESAMPLE = {0: "nearest", 2: "bilinear", 3: "bicubic", "bilinear": "bilinear", "bicubic": "bicubic"}


def check_local_dir(path: str | os.PathLike, what: str) -> Path:
    """A local checkpoint directory with a config.json; a clear error otherwise (we never download)."""
    if not path:
        raise ValueError(f"{what}: no local checkpoint directory given")
    p = Path(path).expanduser()
    if not p.is_dir():
        raise FileNotFoundError(f"{what}: {p} is not a directory (give a local checkpoint; nothing is downloaded)")
    if not (p / "config.json").is_file():
        raise FileNotFoundError(f"{what}: {p} has no config.json (not a Hugging Face checkpoint directory)")
    return p


def resolve_dtype(name: str) -> torch.dtype:
    """``auto``: bf16 when a CUDA device with bf16 is present, else fp32 (CPU matmuls in bf16 are slow)."""
    if name == "auto":
        return torch.bfloat16 if torch.cuda.is_available() and torch.cuda.is_bf16_supported() else torch.float32
    table = {"float32": torch.float32, "fp32": torch.float32, "bfloat16": torch.bfloat16, "bf16": torch.bfloat16,
             "float16": torch.float16, "fp16": torch.float16}
    if name not in table:
        raise ValueError(f"unknown dtype {name!r}; choose auto, float32, bfloat16 or float16")
    return table[name]


# -- pixels ----------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class PixelSpec:
    """How a checkpoint wants its pixels: resize, optional centre crop, then one normalisation per stacked
    view (OpenVLA's fused backbone takes the same image twice, channel-stacked, normalised for each tower).
    Read from preprocessor_config.json because transformers 5 image processors need torchvision."""

    resize: int
    crop: int
    means: tuple[tuple[float, ...], ...]
    stds: tuple[tuple[float, ...], ...]
    mode: str = "bicubic"

    @classmethod
    def from_dir(cls, path: Path, image_size: int) -> "PixelSpec":
        """``image_size`` is the vision tower's input size (from config.json), used when the preprocessor
        config is absent or does not say."""
        f = path / "preprocessor_config.json"
        pc = json.loads(f.read_text()) if f.is_file() else {}
        if "means" in pc:  # Prismatic / OpenVLA
            sizes = [int(s[-1]) for s in pc.get("input_sizes", [[3, image_size, image_size]])]
            interp = (pc.get("interpolations") or ["bicubic"])[0]
            return cls(sizes[0], sizes[0], tuple(map(tuple, pc["means"])), tuple(map(tuple, pc["stds"])),
                       _RESAMPLE.get(interp, "bicubic"))
        size = pc.get("size", image_size)
        if isinstance(size, dict):
            size = size.get("shortest_edge") or size.get("height") or image_size
        crop = pc.get("crop_size", size) if pc.get("do_center_crop", False) else size
        if isinstance(crop, dict):
            crop = crop.get("height") or crop.get("shortest_edge") or size
        mean = tuple(pc.get("image_mean", (0.5, 0.5, 0.5)))
        std = tuple(pc.get("image_std", (0.5, 0.5, 0.5)))
        return cls(int(size), int(crop), (mean,), (std,), _RESAMPLE.get(pc.get("resample", 3), "bicubic"))

    @property
    def channels(self) -> int:
        return 3 * len(self.means)

    def __call__(self, images: torch.Tensor) -> torch.Tensor:
        """(N, 3, H, W) in [0, 1] -> (N, 3 * views, crop, crop), normalised."""
        if images.ndim != 4 or images.shape[1] != 3:
            raise ValueError(f"expected images (N, 3, H, W), got {tuple(images.shape)}")
        x = images.float()
        if x.shape[-1] != self.resize or x.shape[-2] != self.resize:
            smooth = self.mode in ("bilinear", "bicubic")
            x = F.interpolate(x, size=(self.resize, self.resize), mode=self.mode,
                              align_corners=False if smooth else None, antialias=smooth).clamp_(0.0, 1.0)
        if self.crop < self.resize:
            top = (self.resize - self.crop) // 2
            x = x[..., top : top + self.crop, top : top + self.crop]
        views = []
        for mean, std in zip(self.means, self.stds):
            m = torch.tensor(mean, device=x.device).view(1, 3, 1, 1)
            s = torch.tensor(std, device=x.device).view(1, 3, 1, 1)
            views.append((x - m) / s)
        return torch.cat(views, dim=1)


# -- tokenizer -------------------------------------------------------------------------------------------
class HFTextTokenizer:
    """The checkpoint's own tokenizer behind pivla's text interface (``encode``/``to_dict``/``vocab``).

    ``to_dict`` embeds the tokenizer files, so a run directory stays self-contained even if the checkpoint
    directory moves (the backbone weights still come from ``backbone.path``)."""

    def __init__(self, tokenizer, max_len: int, path: str, files: dict[str, dict]):
        if tokenizer.pad_token is None:
            tokenizer.pad_token = tokenizer.unk_token or tokenizer.eos_token
        tokenizer.padding_side = "right"
        self.tokenizer = tokenizer
        self.max_len = int(max_len)
        self.path = path
        self.files = files
        self._warned = False

    @classmethod
    def from_pretrained(cls, path: str, max_len: int) -> "HFTextTokenizer":
        from transformers import AutoTokenizer

        p = check_local_dir(path, "hf tokenizer")
        tok = AutoTokenizer.from_pretrained(str(p), local_files_only=True)
        return cls(tok, max_len, str(p.resolve()), _tokenizer_files(tok))

    @classmethod
    def from_dict(cls, d: dict) -> "HFTextTokenizer":
        from transformers import AutoTokenizer

        files = d.get("files") or {}
        if not files:
            return cls.from_pretrained(d["path"], int(d["max_len"]))
        with tempfile.TemporaryDirectory() as tmp:
            for name, entry in files.items():
                data = base64.b64decode(entry["data"]) if entry["encoding"] == "base64" else entry["data"].encode()
                (Path(tmp) / name).write_bytes(data)
            tok = AutoTokenizer.from_pretrained(tmp, local_files_only=True)
        return cls(tok, int(d["max_len"]), d.get("path", ""), files)

    @property
    def vocab(self):
        return self.tokenizer  # len() is the vocabulary size

    def encode(self, text: str) -> tuple[np.ndarray, np.ndarray]:
        """Prompt-wrapped ids (max_len,) int64 and mask (max_len,) bool; right-padded, cut at max_len."""
        prompt = PROMPT.format(instruction=text.strip().lower().rstrip("."))
        enc = self.tokenizer(prompt, max_length=self.max_len, truncation=True, padding="max_length")
        ids = np.asarray(enc["input_ids"], np.int64)
        if not self._warned and len(self.tokenizer(prompt)["input_ids"]) > self.max_len:
            log.warning("instruction prompt longer than max_text_len=%d tokens is truncated; raise "
                        "--model.max_text_len (48-64 suits LIBERO with OpenVLA's prompt)", self.max_len)
            self._warned = True
        return ids, np.asarray(enc["attention_mask"], bool)

    def to_dict(self) -> dict:
        return {"kind": "hf", "path": self.path, "max_len": self.max_len, "files": self.files}


def _tokenizer_files(tok) -> dict[str, dict]:
    """The files ``save_pretrained`` writes for this tokenizer, as JSON-able text or base64."""
    out = {}
    with tempfile.TemporaryDirectory() as tmp:
        tok.save_pretrained(tmp)
        for f in sorted(Path(tmp).iterdir()):
            raw = f.read_bytes()
            try:
                out[f.name] = {"encoding": "utf-8", "data": raw.decode("utf-8")}
            except UnicodeDecodeError:
                out[f.name] = {"encoding": "base64", "data": base64.b64encode(raw).decode()}
    return out


# -- loading the vision-language model ------------------------------------------------------------------------
def load_vlm(path: Path, dtype: torch.dtype) -> tuple[str, nn.Module]:
    """(kind, model): ``llava`` for anything AutoModelForImageTextToText reads with a vision tower and a
    projector, ``openvla`` for OpenVLA, converted (plain transformers parts) or in its released layout (its
    own modeling code, which needs ``timm``). Both OpenVLA forms expose the same parts."""
    import transformers

    from pivla.model.openvla import MARKER, OpenVLAModel

    if (path / MARKER).is_file():
        return "openvla", OpenVLAModel.from_pretrained(path, dtype)
    cfg = json.loads((path / "config.json").read_text())
    if cfg.get("model_type") in ("openvla", "prismatic"):
        from transformers.dynamic_module_utils import get_class_from_dynamic_module

        ref = (cfg.get("auto_map") or {}).get("AutoModelForVision2Seq")
        if not ref:
            raise ValueError(f"{path}: an OpenVLA config.json must name its model class in auto_map "
                             "(or convert the checkpoint with `pivla convert-openvla`)")
        cls = get_class_from_dynamic_module(ref, str(path), local_files_only=True)
        model = cls.from_pretrained(str(path), dtype=dtype, trust_remote_code=True, local_files_only=True,
                                    attn_implementation="sdpa")
        return "openvla", model
    model = transformers.AutoModelForImageTextToText.from_pretrained(str(path), dtype=dtype, local_files_only=True)
    inner = getattr(model, "model", model)
    for part in ("vision_tower", "multi_modal_projector", "language_model"):
        if not hasattr(inner, part):
            raise ValueError(f"{path}: {type(model).__name__} is not Llava-style (no {part}); "
                             "use a Llava-style checkpoint or OpenVLA's layout")
    return "llava", model


class _Parts:
    """Uniform access to the vision tower, projector, token embeddings and decoder of either layout."""

    def __init__(self, kind: str, model: nn.Module):
        self.kind = kind
        if kind == "openvla":
            self.tower, self.projector = model.vision_backbone, model.projector
            self.decoder = model.language_model.model
            self.layer, self.strategy = None, "full"
            sizes = getattr(model, "image_sizes", None) or model.config.image_sizes  # converted / remote code
            self.vision_size = int(sizes[0])
        else:
            inner = getattr(model, "model", model)
            self.tower, self.projector = inner.vision_tower, inner.multi_modal_projector
            lm = inner.language_model
            self.decoder = lm.model if hasattr(lm, "lm_head") else lm
            self.layer = model.config.vision_feature_layer
            self.strategy = model.config.vision_feature_select_strategy
            self.vision_size = int(model.config.vision_config.image_size)
        self.embed = model.get_input_embeddings()
        self.hidden = int(self.embed.weight.shape[1])

    def image_embeddings(self, pixels: torch.Tensor) -> torch.Tensor:
        return self.projector(vision_tokens(self.kind, self.tower, self.layer, self.strategy, pixels))


def vision_tokens(kind: str, tower: nn.Module, layer, strategy: str, pixels: torch.Tensor) -> torch.Tensor:
    """Vision features before the projector, (N, T, d_vision): Prismatic's backbone returns them directly;
    Llava selects ``vision_feature_layer`` (one or several, concatenated) and drops CLS for ``default``."""
    if kind == "openvla":
        return tower(pixels)
    out = tower(pixels, output_hidden_states=True)
    layers = [layer] if isinstance(layer, int) else list(layer)
    feats = [out.hidden_states[i] for i in layers]
    if strategy == "default":
        feats = [f[:, 1:] for f in feats]
    return torch.cat(feats, dim=-1)


class VisionPooler(nn.Module):
    """The VLM's own (frozen) vision tower as a target encoder: mean patch feature per camera."""

    def __init__(self, parts: _Parts, spec: PixelSpec):
        super().__init__()
        self.tower = parts.tower
        self.spec = spec
        self.kind, self.layer, self.strategy = parts.kind, parts.layer, parts.strategy

    def pooled(self, images: torch.Tensor) -> torch.Tensor:
        b, n = images.shape[:2]
        dtype = next(self.tower.parameters()).dtype
        px = self.spec(images.flatten(0, 1)).to(dtype)
        feats = vision_tokens(self.kind, self.tower, self.layer, self.strategy, px).float().mean(1)
        return feats.unflatten(0, (b, n)).flatten(1)

    def external_state_keys(self) -> set[str]:
        """Everything here is the checkpoint's frozen tower: rebuilt from disk, never saved."""
        return set(self.state_dict().keys())


def lora_target_names(model: nn.Module, targets: tuple[str, ...]) -> list[str]:
    """Full names of the language model's Linear layers whose last name component is in ``targets``
    (``all-linear``: every Linear of the language model except the output head)."""
    names = []
    for name, mod in model.named_modules():
        if not isinstance(mod, nn.Linear) or "language_model." not in name or name.endswith("lm_head"):
            continue
        if "all-linear" in targets or name.rsplit(".", 1)[-1] in targets:
            names.append(name)
    if not names:
        raise ValueError(f"no Linear layer named {list(targets)} in the language model")
    return names


def enable_activation_checkpointing(model: nn.Module, kwargs: dict | None) -> None:
    """``activation_checkpointing_enable`` (transformers >= 5.20) or its older name."""
    if hasattr(model, "activation_checkpointing_enable"):
        model.activation_checkpointing_enable(activation_checkpointing_kwargs=kwargs)
    else:
        model.gradient_checkpointing_enable(gradient_checkpointing_kwargs=kwargs)


class HFBackbone(nn.Module):
    """Backbone ``hf``: see the module docstring. ``cfg.backbone.path`` is a local checkpoint directory."""

    def __init__(self, cfg: ModelConfig):
        super().__init__()
        bc = cfg.backbone
        path = check_local_dir(bc.path, "backbone hf")
        kind, vlm = load_vlm(path, resolve_dtype(bc.dtype))
        vlm.requires_grad_(False)
        self.lora = bc.lora_rank > 0
        if self.lora:
            from peft import LoraConfig, get_peft_model

            lcfg = LoraConfig(r=bc.lora_rank, lora_alpha=bc.lora_alpha, lora_dropout=bc.lora_dropout,
                              target_modules=lora_target_names(vlm, tuple(bc.lora_target_modules)))
            vlm = get_peft_model(vlm, lcfg)
        self.vlm = vlm
        self.kind = kind
        if bc.gradient_checkpointing:
            enable_activation_checkpointing(self.base_model(), {"use_reentrant": False})
        self.parts = _Parts(kind, self.base_model())
        self.pixels = PixelSpec.from_dir(path, self.parts.vision_size)
        d = self.parts.hidden
        self.d_model = d
        self.n_cog, self.chunk, self.action_dim = bc.n_cog_tokens, cfg.chunk, cfg.action_dim
        emb_std = float(self.parts.embed.weight.float().std())
        self.queries = nn.Parameter(torch.randn(1, self.n_cog + cfg.chunk * cfg.action_dim, d) * emb_std)
        self.proprio_proj = nn.Sequential(nn.Linear(cfg.proprio_dim, d), nn.GELU(), nn.Linear(d, d))
        self.motor_readout = nn.Linear(cfg.action_dim * d, d)

    def base_model(self) -> nn.Module:
        """The transformers model (inside the peft wrapper when LoRA is on)."""
        return self.vlm.get_base_model() if self.lora else self.vlm

    @property
    def vision(self) -> VisionPooler:
        """The frozen vision tower, for the ``ema``/``frozen`` target encoders (``dinov2`` is the paper's)."""
        return VisionPooler(self.parts, self.pixels)

    def external_state_keys(self) -> set[str]:
        """Frozen checkpoint weights (rebuilt from ``backbone.path``): left out of run checkpoints."""
        trainable = {n for n, p in self.vlm.named_parameters() if p.requires_grad}
        return {f"vlm.{k}" for k in self.vlm.state_dict() if k not in trainable}

    def merge_lora(self) -> None:
        """Fold the adapters into the base weights (deployment); the backbone then has no LoRA."""
        if self.lora:
            self.vlm = self.vlm.merge_and_unload()
            self.lora = False
            self.parts = _Parts(self.kind, self.vlm)

    def _attention(self, valid: torch.Tensor, n_query: int, dtype: torch.dtype) -> tuple[torch.Tensor, torch.Tensor]:
        """Additive 4-D mask: causal over the prefix, the query block sees the valid prefix and itself
        (bidirectional); padded words are invisible. Position ids skip padding."""
        n = valid.shape[1]
        i = torch.arange(n, device=valid.device)
        causal = i.view(-1, 1) >= i.view(1, -1)
        in_query = i >= n - n_query
        allowed = (causal | (in_query.view(-1, 1) & in_query.view(1, -1))).unsqueeze(0) & valid.unsqueeze(1)
        allowed = allowed | torch.eye(n, dtype=torch.bool, device=valid.device).unsqueeze(0)
        mask = torch.zeros(allowed.shape, dtype=dtype, device=valid.device)
        mask.masked_fill_(~allowed, torch.finfo(dtype).min)
        position = (valid.long().cumsum(-1) - 1).clamp_min(0)
        return mask.unsqueeze(1), position

    def forward(self, batch: dict[str, torch.Tensor]) -> tuple[torch.Tensor, torch.Tensor]:
        images, ids, text_mask = batch["images"], batch["text_ids"], batch["text_mask"]
        b, n_cam = images.shape[:2]
        dtype = self.parts.embed.weight.dtype
        img = self.parts.image_embeddings(self.pixels(images.flatten(0, 1)).to(dtype))
        img = img.unflatten(0, (b, n_cam)).flatten(1, 2)
        text = self.parts.embed(ids)
        prop = self.proprio_proj(batch["proprio"].float()).unsqueeze(1).to(dtype)
        queries = self.queries.expand(b, -1, -1).to(dtype)
        x = torch.cat([img, text, prop, queries], dim=1)
        ones = lambda k: torch.ones(b, k, dtype=torch.bool, device=x.device)  # noqa: E731
        valid = torch.cat([ones(img.shape[1]), text_mask.bool(), ones(1 + queries.shape[1])], dim=1)
        mask, position = self._attention(valid, queries.shape[1], x.dtype)
        h = self.parts.decoder(inputs_embeds=x, attention_mask=mask, position_ids=position,
                               use_cache=False).last_hidden_state
        hq = h[:, -queries.shape[1] :].float()
        h_cog = hq[:, : self.n_cog]
        h_mot = self.motor_readout(hq[:, self.n_cog :].unflatten(1, (self.chunk, self.action_dim)).flatten(2))
        return h_cog, h_mot


# -- deployment: merge adapters --------------------------------------------------------------------------------
def merge_run(run_dir: str | Path, out_dir: str | Path, device: str = "auto") -> Path:
    """Write a deployable copy of an ``hf`` run with the LoRA adapters merged into the base weights.

    ``out_dir/backbone`` becomes a plain transformers checkpoint (merged weights, tokenizer, preprocessor);
    the new run's config points at it with ``lora_rank 0``, and its model.safetensors keeps only the
    queries, readout and CMS heads. The output appears atomically (written under a temporary name)."""
    from pivla import config as cfgmod
    from pivla.policy import load_policy
    from pivla.training import checkpoint as ck

    run_dir, out_dir = Path(run_dir), Path(out_dir)
    cfg = ck.read_run_config(run_dir)
    if cfg.model.backbone.name != "hf":
        raise ValueError(f"{run_dir}: backbone is {cfg.model.backbone.name!r}; only 'hf' runs have adapters")
    if cfg.model.backbone.lora_rank <= 0:
        raise ValueError(f"{run_dir}: no LoRA adapters to merge (lora_rank 0)")
    if out_dir.exists():
        raise FileExistsError(f"{out_dir} exists; choose a new directory")
    policy = load_policy(run_dir, device=device)
    model = policy.model
    backbone: HFBackbone = model.backbone
    src = Path(cfg.model.backbone.path)
    backbone.merge_lora()
    with atomic_dir(out_dir) as tmp:
        backbone.vlm.save_pretrained(str(tmp / "backbone"))
        policy.text.tokenizer.save_pretrained(str(tmp / "backbone"))
        for extra in ("preprocessor_config.json", "processor_config.json"):
            if (src / extra).is_file():
                shutil.copy2(src / extra, tmp / "backbone" / extra)
        new_cfg = replace(cfg, model=replace(cfg.model, backbone=replace(
            cfg.model.backbone, path=str((out_dir / "backbone").resolve()), lora_rank=0)))
        ck.save_tensors(tmp / ck.MODEL_FILE, model.state_dict_for_checkpoint(), metadata={"format": "pt", "merged_from": str(run_dir)})
        ck.atomic_write_json(tmp / ck.CONFIG_FILE, cfgmod.to_dict(new_cfg))
        for name in (ck.STATS_FILE, ck.TOKENIZER_FILE, ck.CALIBRATION_FILE, ck.STATUS_FILE, "split.json"):
            if (run_dir / name).is_file():
                shutil.copy2(run_dir / name, tmp / name)
    return out_dir


# -- tiny random checkpoints (tests, benchmarks, CPU smoke runs) ---------------------------------------------
TINY_WORDS = ("? : . , in what action should the robot take to out move the square left right up down pick place put "
              "open close a an on of and bowl plate drawer cup mug block red green blue").split()


def write_tiny_tokenizer(out: Path) -> None:
    """A small lower-casing word-level fast tokenizer (BOS added), saved with ``save_pretrained``."""
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
    CPU tests and smoke runs of the ``hf`` path. Random weights: it learns, but knows nothing."""
    from transformers import Dinov2Config, LlamaConfig, LlavaConfig, LlavaForConditionalGeneration, SiglipVisionConfig

    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    write_tiny_tokenizer(out)
    n_vocab = len(json.loads((out / "tokenizer.json").read_text())["model"]["vocab"])
    patch = max(image_size // 4, 1)
    tower = dict(hidden_size=32, intermediate_size=64, num_hidden_layers=2, num_attention_heads=2,
                 image_size=image_size, patch_size=patch)
    if vision not in ("siglip", "dinov2"):
        raise ValueError(f"unknown tiny vision tower {vision!r}; choose siglip or dinov2")
    cfg = LlavaConfig(
        vision_config=SiglipVisionConfig(**tower) if vision == "siglip" else Dinov2Config(**tower),
        text_config=LlamaConfig(hidden_size=hidden, intermediate_size=2 * hidden, num_hidden_layers=layers,
                                num_attention_heads=4, num_key_value_heads=2, vocab_size=n_vocab,
                                max_position_embeddings=512),
        image_token_id=0, vision_feature_layer=-2 if vision == "dinov2" else -1,
        vision_feature_select_strategy="full" if vision == "siglip" else "default",
    )
    torch.manual_seed(seed)
    LlavaForConditionalGeneration(cfg).save_pretrained(str(out))
    pre = {"image_processor_type": "SiglipImageProcessor", "do_resize": True, "resample": 3,
           "size": {"height": image_size, "width": image_size}, "do_rescale": True, "rescale_factor": 1 / 255,
           "do_normalize": True, "image_mean": [0.5, 0.5, 0.5], "image_std": [0.5, 0.5, 0.5]}
    (out / "preprocessor_config.json").write_text(json.dumps(pre, indent=2))
    return out


# -- benchmark ---------------------------------------------------------------------------------------------
def run_bench(args) -> dict:
    """Forward (inference) and train-step latency of CMS on the ``hf`` backbone.

    ``args``: ``path`` (VLM dir; empty = build the tiny random Llava in a temp dir), ``target_path``
    (DINOv2 dir; empty = tiny random), ``image_size``, ``batch``, ``repeats``, ``threads``, ``lora_rank``.
    Returns medians in ms over ``repeats`` timed runs after two warm-up runs."""
    import statistics
    import time

    from pivla.model.cms import CMSModel
    from pivla.model.config import BackboneConfig, TargetEncoderConfig
    from pivla.model.dinov2 import make_tiny_dinov2

    if args.threads > 0:
        torch.set_num_threads(args.threads)
    with tempfile.TemporaryDirectory() as tmp:
        vlm = args.path or str(make_tiny_vlm(Path(tmp) / "vlm", image_size=args.image_size))
        dino = args.target_path or str(make_tiny_dinov2(Path(tmp) / "dino", image_size=args.image_size))
        text = HFTextTokenizer.from_pretrained(vlm, 32)
        cfg = ModelConfig(image_size=args.image_size, max_text_len=32,
                          backbone=BackboneConfig(name="hf", path=vlm, lora_rank=args.lora_rank),
                          target_encoder=TargetEncoderConfig(name="dinov2", path=dino))
        model = CMSModel(cfg, len(text.vocab))
        ids, mask = text.encode("put the bowl on the plate")
        b = args.batch
        batch = {"images": torch.rand(b, len(cfg.cameras), 3, cfg.image_size, cfg.image_size),
                 "text_ids": torch.from_numpy(ids).repeat(b, 1), "text_mask": torch.from_numpy(mask).repeat(b, 1),
                 "proprio": torch.randn(b, cfg.proprio_dim)}

        def timed(fn) -> float:
            for _ in range(2):
                fn()
            runs = []
            for _ in range(args.repeats):
                t0 = time.perf_counter()
                fn()
                runs.append((time.perf_counter() - t0) * 1e3)
            return statistics.median(runs)

        def infer() -> None:
            with torch.inference_mode():
                model(batch)

        def train_step() -> None:
            out = model(batch)
            (out.continuous.square().mean() + out.logits.float().logsumexp(-1).mean() + out.latents.square().mean()
             + out.values.square().mean()).backward()
            model.zero_grad(set_to_none=True)

        model.eval()
        infer_ms = timed(infer)
        target_ms = timed(lambda: model.target(batch["images"]))
        model.train()
        train_ms = timed(train_step)
        counts = model.parameter_counts()
    return {"backbone": "hf", "vlm": args.path or "tiny-random-llava", "batch": b, "image_size": args.image_size,
            "threads": torch.get_num_threads(), "infer_ms": round(infer_ms, 2), "target_encoder_ms": round(target_ms, 2),
            "train_step_ms": round(train_ms, 2), "parameters": counts}
