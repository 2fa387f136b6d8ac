"""Loading a local vision-language model and reaching its parts the same way whatever its layout."""

from __future__ import annotations

import json
from pathlib import Path

import torch
from torch import nn

from pivla.model.hf.pixels import PixelSpec
from pivla.model.openvla import MARKER, OpenVLAModel


def resolve_dtype(name: str) -> torch.dtype:
    """``auto``: bf16 when a CUDA device with bf16 is present, else fp32 (CPU matmuls in bf16 are slow)."""
    if name == "auto":
        return torch.bfloat16 if torch.cuda.is_available() and torch.cuda.is_bf16_supported() else torch.float32
    table = {"float32": torch.float32, "fp32": torch.float32, "bfloat16": torch.bfloat16, "bf16": torch.bfloat16,
             "float16": torch.float16, "fp16": torch.float16}
    if name not in table:
        raise ValueError(f"unknown dtype {name!r}; choose auto, float32, bfloat16 or float16")
    return table[name]


def load_vlm(path: Path, dtype: torch.dtype) -> tuple[str, nn.Module]:
    """(kind, model): ``llava`` for anything AutoModelForImageTextToText reads with a vision tower and a
    projector, ``openvla`` for OpenVLA, converted (plain transformers parts) or in its released layout (its
    own modeling code, which needs ``timm``). Both OpenVLA forms expose the same parts."""
    import transformers

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


class VLMParts:
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

    def __init__(self, parts: VLMParts, spec: PixelSpec):
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
