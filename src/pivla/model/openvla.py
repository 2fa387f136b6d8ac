"""OpenVLA's released checkpoint without timm or remote code: the converter and the model it produces.

``openvla/openvla-7b`` ships Prismatic's layout, read by its ``modeling_prismatic.py``, which builds both
vision towers with timm (and so needs torchvision, which pivla never installs):

- ``vision_backbone.featurizer.*``: timm ``vit_large_patch14_reg4_dinov2.lvd142m`` (DINOv2 ViT-L/14 with 4
  register tokens and layer scale; Prismatic renames timm's ``ls1.gamma`` to ``ls1.scale_factor``);
- ``vision_backbone.fused_featurizer.*``: timm ``vit_so400m_patch14_siglip_224`` (SigLIP So400m/14, no class
  token, attention-pooling head ``attn_pool``);
- ``projector.fc1/fc2/fc3``: Prismatic's fused GELU MLP projector;
- ``language_model.*``: ``LlamaForCausalLM`` (Llama-2-7B).

Prismatic feeds the same image to both towers, each normalised its own way (``means``/``stds`` in
preprocessor_config.json, stacked on the channel axis), takes each tower's patch tokens at the output of
its second-to-last block (timm ``get_intermediate_layers(n={len(blocks) - 2})``: no final norm, class and
register tokens dropped), concatenates them channel-wise and projects them.

:func:`convert_openvla` rewrites those weights as stock transformers checkpoints (see ``docs/backbones.md``
for the key table); :class:`OpenVLAModel` loads them and is what the ``hf`` backbone runs.
"""

from __future__ import annotations

import json
import os
import shutil
from collections import Counter
from collections.abc import Callable
from contextlib import ExitStack
from dataclasses import dataclass
from pathlib import Path

import torch
import torch.nn.functional as F
from safetensors import safe_open
from safetensors.torch import load_file, save_file
from torch import nn

from pivla.io import atomic_dir
from pivla.model.hf.common import check_local_dir
from pivla.model.hf.lora import enable_activation_checkpointing

MARKER = "pivla_openvla.json"
FORMAT = "pivla_openvla/1"
DINO_DIR, SIGLIP_DIR, PROJECTOR_DIR = "dinov2", "siglip", "projector"
# Both towers' features come from the output of their second-to-last block (Prismatic's choice).
FEATURE_LAYER = -2
# Head counts are not recoverable from weight shapes; they come from timm's model definitions.
DINO_HEADS = {"vit_large_patch14_reg4_dinov2.lvd142m": 16}
SIGLIP_HEADS = {"vit_so400m_patch14_siglip_224": 16, "vit_so400m_patch14_siglip_384": 16}
TOKENIZER_FILES = ("tokenizer.json", "tokenizer.model", "tokenizer_config.json", "special_tokens_map.json",
                   "added_tokens.json")
MAX_SHARD_BYTES = 5 * 2**30
_EPS = 1e-6  # timm ViTs use LayerNorm(eps=1e-6)


# -- the converted model -------------------------------------------------------------------------------------
class FusedProjector(nn.Module):
    """Prismatic's projector for fused backbones (``fused-gelu-mlp``): fc1, GELU, fc2, GELU, fc3."""

    def __init__(self, vision_dim: int, hidden_dim: int, llm_dim: int):
        super().__init__()
        self.fc1 = nn.Linear(vision_dim, hidden_dim)
        self.fc2 = nn.Linear(hidden_dim, llm_dim)
        self.fc3 = nn.Linear(llm_dim, llm_dim)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.fc3(F.gelu(self.fc2(F.gelu(self.fc1(x)))))


class FusedVisionBackbone(nn.Module):
    """(N, 6, H, W) pixels (DINOv2 view, then SigLIP view) -> (N, patches, d_dino + d_siglip): each tower's
    second-to-last block output without class/register tokens, concatenated channel-wise, as Prismatic's
    ``PrismaticVisionBackbone`` returns them."""

    def __init__(self, dinov2: nn.Module, siglip: nn.Module):
        super().__init__()
        self.dinov2, self.siglip = dinov2, siglip
        self.n_prefix = 1 + int(dinov2.config.num_register_tokens)

    def forward(self, pixels: torch.Tensor) -> torch.Tensor:
        dino_px, siglip_px = torch.split(pixels, [3, 3], dim=1)
        dino = self.dinov2(pixel_values=dino_px, output_hidden_states=True).hidden_states[FEATURE_LAYER]
        siglip = self.siglip(pixel_values=siglip_px, output_hidden_states=True).hidden_states[FEATURE_LAYER]
        return torch.cat([dino[:, self.n_prefix :], siglip], dim=2)


class OpenVLAModel(nn.Module):
    """A converted OpenVLA: ``vision_backbone``, ``projector`` and ``language_model`` under the names
    Prismatic's model uses, so the ``hf`` backbone drives it exactly like the remote-code model."""

    def __init__(self, language_model: nn.Module, vision_backbone: FusedVisionBackbone, projector: FusedProjector,
                 meta: dict):
        super().__init__()
        self.language_model, self.vision_backbone, self.projector = language_model, vision_backbone, projector
        self.meta = meta
        self.image_sizes = list(meta["image_sizes"])

    @classmethod
    def from_pretrained(cls, path: str | os.PathLike, dtype: torch.dtype) -> OpenVLAModel:
        from transformers import Dinov2WithRegistersModel, LlamaForCausalLM, SiglipVisionModel

        path = Path(path)
        meta = json.loads((path / MARKER).read_text())
        if meta.get("format") != FORMAT:
            raise ValueError(f"{path / MARKER}: format {meta.get('format')!r}, expected {FORMAT!r}")
        kw = dict(dtype=dtype, local_files_only=True)
        lm = LlamaForCausalLM.from_pretrained(str(path), **kw)
        towers = FusedVisionBackbone(Dinov2WithRegistersModel.from_pretrained(str(path / DINO_DIR), **kw),
                                     SiglipVisionModel.from_pretrained(str(path / SIGLIP_DIR), **kw))
        state = load_file(str(path / PROJECTOR_DIR / "model.safetensors"))
        (hidden, vision), llm = state["fc1.weight"].shape, state["fc3.weight"].shape[0]
        projector = FusedProjector(vision, hidden, llm)
        projector.load_state_dict(state)
        return cls(lm, towers, projector.to(dtype), meta)

    def save_pretrained(self, out: str | os.PathLike) -> None:
        """The layout :func:`convert_openvla` writes (used by ``pivla merge-lora``); tokenizer and
        preprocessor config are the caller's."""
        out = Path(out)
        self.language_model.save_pretrained(str(out))
        self.vision_backbone.dinov2.save_pretrained(str(out / DINO_DIR))
        self.vision_backbone.siglip.save_pretrained(str(out / SIGLIP_DIR))
        (out / PROJECTOR_DIR).mkdir(exist_ok=True)
        save_file({k: v.contiguous() for k, v in self.projector.state_dict().items()},
                  str(out / PROJECTOR_DIR / "model.safetensors"), metadata={"format": "pt"})
        (out / MARKER).write_text(json.dumps(self.meta, indent=1))

    def get_input_embeddings(self) -> nn.Module:
        return self.language_model.get_input_embeddings()

    def activation_checkpointing_enable(self, activation_checkpointing_kwargs: dict | None = None) -> None:
        """Only the language model: the frozen towers build no autograd graph."""
        enable_activation_checkpointing(self.language_model, activation_checkpointing_kwargs)


# -- the converter ----------------------------------------------------------------------------------------------
DINO, SIGLIP = "vision_backbone.featurizer.", "vision_backbone.fused_featurizer."
WB = ("weight", "bias")


@dataclass(frozen=True)
class _Rule:
    """``targets`` (names in one output part) computed from ``sources`` (OpenVLA keys) by ``fn``."""

    sources: tuple[str, ...]
    targets: tuple[str, ...]
    fn: Callable[..., tuple[torch.Tensor, ...]] = lambda *t: t


def _split_qkv(qkv: torch.Tensor) -> tuple[torch.Tensor, ...]:
    """timm's fused qkv rows are [q; k; v] (``reshape(B, N, 3, heads, head_dim)``)."""
    return tuple(t.clone() for t in qkv.chunk(3, dim=0))


def _cat_rows(*parts: torch.Tensor) -> tuple[torch.Tensor]:
    return (torch.cat(parts, dim=0),)


def _pos_with_zero_cls(pos: torch.Tensor) -> tuple[torch.Tensor]:
    """timm's DINOv2-with-registers pos_embed covers patches only (``no_embed_class``; DINOv2's class
    position is already folded into timm's cls_token); transformers adds a class row, which must be zero."""
    return (torch.cat([pos.new_zeros(1, 1, pos.shape[-1]), pos], dim=1),)


def _first(t: torch.Tensor) -> tuple[torch.Tensor]:
    return (t[0].clone(),)


def _renames(src: str, dst: str, pairs: tuple[tuple[str, str], ...]) -> list[_Rule]:
    """One-to-one renames ``src + a -> dst + b``, each pair expanded to ``.weight`` and ``.bias``."""
    return [_Rule((f"{src}{a}.{s}",), (f"{dst}{b}.{s}",)) for a, b in pairs for s in WB]


def _qkv(block: str, names: tuple[str, str, str]) -> list[_Rule]:
    return [_Rule((f"{block}attn.qkv.{s}",), tuple(f"{n}.{s}" for n in names), _split_qkv) for s in WB]


def _dinov2_rules(source: _Source, depth: int) -> list[_Rule]:
    """timm ``vit_*_reg4_dinov2`` -> transformers ``Dinov2WithRegistersModel`` (checkpoint names)."""
    p = DINO
    rules = [
        _Rule((p + "cls_token",), ("embeddings.cls_token",)),
        _Rule((p + "reg_token",), ("embeddings.register_tokens",)),
        _Rule((p + "pos_embed",), ("embeddings.position_embeddings",), _pos_with_zero_cls),
        # transformers' masked-image-modelling token: timm has none, and pivla never masks.
        _Rule((), ("embeddings.mask_token",), lambda: (torch.zeros_like(source.get(p + "cls_token")[0]),)),
        *_renames(p, "", (("patch_embed.proj", "embeddings.patch_embeddings.projection"), ("norm", "layernorm"))),
    ]
    for i in range(depth):
        b, h = f"{p}blocks.{i}.", f"encoder.layer.{i}."
        rules += _qkv(b, tuple(f"{h}attention.attention.{n}" for n in ("query", "key", "value")))
        rules += _renames(b, h, (("norm1", "norm1"), ("attn.proj", "attention.output.dense"), ("norm2", "norm2"),
                                 ("mlp.fc1", "mlp.fc1"), ("mlp.fc2", "mlp.fc2")))
        rules += [_Rule((f"{b}ls{j}.scale_factor",), (f"{h}layer_scale{j}.lambda1",)) for j in (1, 2)]
    return rules


def _siglip_rules(depth: int) -> list[_Rule]:
    """timm ``vit_so400m_patch14_siglip_*`` -> transformers ``SiglipVisionModel`` (checkpoint names)."""
    p, v = SIGLIP, "vision_model."
    rules = [
        _Rule((p + "pos_embed",), (v + "embeddings.position_embedding.weight",), _first),
        _Rule((p + "attn_pool.latent",), (v + "head.probe",)),
        # nn.MultiheadAttention's in_proj is [q; k; v]; timm's pool has q and a fused [k; v].
        *(_Rule((f"{p}attn_pool.q.{s}", f"{p}attn_pool.kv.{s}"), (f"{v}head.attention.in_proj_{s}",), _cat_rows)
          for s in WB),
        *_renames(p, v, (("patch_embed.proj", "embeddings.patch_embedding"), ("norm", "post_layernorm"),
                         ("attn_pool.proj", "head.attention.out_proj"), ("attn_pool.norm", "head.layernorm"),
                         ("attn_pool.mlp.fc1", "head.mlp.fc1"), ("attn_pool.mlp.fc2", "head.mlp.fc2"))),
    ]
    for i in range(depth):
        b, h = f"{p}blocks.{i}.", f"{v}encoder.layers.{i}."
        rules += _qkv(b, tuple(f"{h}self_attn.{n}_proj" for n in "qkv"))
        rules += _renames(b, h, (("norm1", "layer_norm1"), ("attn.proj", "self_attn.out_proj"),
                                 ("norm2", "layer_norm2"), ("mlp.fc1", "mlp.fc1"), ("mlp.fc2", "mlp.fc2")))
    return rules


class _Source:
    """OpenVLA's safetensors (an index and its shards, or one model.safetensors), opened lazily."""

    def __init__(self, path: Path, stack: ExitStack):
        index = path / "model.safetensors.index.json"
        if index.is_file():
            try:
                weight_map = json.loads(index.read_text())["weight_map"]
            except (json.JSONDecodeError, KeyError) as e:
                raise ValueError(f"{index}: not a safetensors index (no weight_map): {e}") from e
            files = sorted(set(weight_map.values()))
        elif (path / "model.safetensors").is_file():
            weight_map, files = None, ["model.safetensors"]
        else:
            raise FileNotFoundError(f"{path}: neither model.safetensors.index.json nor model.safetensors")
        missing = [f for f in files if not (path / f).is_file()]
        if missing:
            raise FileNotFoundError(f"{path}: shards named in {index.name} are missing: {missing}")
        self.files, self.where = {}, {}
        for f in files:
            try:
                self.files[f] = stack.enter_context(safe_open(str(path / f), "pt"))
            except Exception as e:  # safetensors raises its own error type for bad headers / truncation
                raise ValueError(f"{path / f}: not a readable safetensors file ({e})") from e
            self.where.update(dict.fromkeys(self.files[f].keys(), f))
        if weight_map is not None:
            wrong = [k for k, f in weight_map.items() if self.where.get(k) != f]
            unlisted = set(self.where) - set(weight_map)
            if wrong or unlisted:
                raise ValueError(f"{index} disagrees with its shards: {_names(wrong)} not where the index says, "
                                 f"{_names(unlisted)} not in the index")

    def keys(self) -> set[str]:
        return set(self.where)

    def get(self, key: str) -> torch.Tensor:
        return self.files[self.where[key]].get_tensor(key)

    def shape(self, key: str) -> tuple[int, ...]:
        return tuple(self.files[self.where[key]].get_slice(key).get_shape())


def _names(keys, limit: int = 12) -> str:
    keys = sorted(keys)
    more = f" (+{len(keys) - limit} more)" if len(keys) > limit else ""
    return "[" + ", ".join(keys[:limit]) + "]" + more if keys else "none"


def _depth(keys: set[str], prefix: str) -> int:
    blocks = {int(k[len(prefix) + 7 :].split(".", 1)[0]) for k in keys if k.startswith(prefix + "blocks.")}
    if not blocks:
        raise ValueError(f"no {prefix}blocks.* tensors: not OpenVLA's fused DINOv2 + SigLIP checkpoint")
    return max(blocks) + 1


def _read_openvla_config(src: Path) -> tuple[dict, dict]:
    """(config.json, preprocessor_config.json), checked to be the fused DINOv2 + SigLIP + Llama layout."""
    cfg = json.loads((src / "config.json").read_text())
    if cfg.get("model_type") not in ("openvla", "prismatic"):
        raise ValueError(f"{src}: model_type {cfg.get('model_type')!r} is not OpenVLA's ('openvla')")
    ids = list(cfg.get("timm_model_ids") or [])
    if not cfg.get("use_fused_vision_backbone") or len(ids) != 2:
        raise ValueError(f"{src}: only the fused DINOv2 + SigLIP backbone is supported, got timm_model_ids {ids}")
    if ids[0] not in DINO_HEADS or ids[1] not in SIGLIP_HEADS:
        raise ValueError(f"{src}: unsupported towers {ids}; supported: {sorted(DINO_HEADS)} + {sorted(SIGLIP_HEADS)}")
    if any(cfg.get("timm_override_act_layers") or []):
        raise ValueError(f"{src}: timm_override_act_layers {cfg['timm_override_act_layers']} are not supported")
    if "fused-gelu-mlp" not in cfg.get("arch_specifier", "fused-gelu-mlp"):
        raise ValueError(f"{src}: projector {cfg['arch_specifier']!r} is not the fused GELU MLP")
    sizes = cfg.get("image_sizes") or []
    if len(sizes) != 2 or sizes[0] != sizes[1]:
        raise ValueError(f"{src}: expected two equal image_sizes, got {sizes}")
    if (cfg.get("text_config") or {}).get("model_type", "llama") != "llama":
        raise ValueError(f"{src}: only a Llama language model is supported, got {cfg['text_config']['model_type']!r}")
    pre_file = src / "preprocessor_config.json"
    if not pre_file.is_file():
        raise FileNotFoundError(f"{src}: no preprocessor_config.json (the towers' means/stds)")
    pre = json.loads(pre_file.read_text())
    if len(pre.get("means") or []) != 2 or len(pre.get("stds") or []) != 2:
        raise ValueError(f"{pre_file}: expected two means/stds (DINOv2, SigLIP), got {pre.get('means')}")
    return cfg, pre


def _plan(source: _Source, lm_shapes: dict[str, tuple[int, ...]]) -> dict[str, list[_Rule]]:
    """Rules per output part ("" = the language model at the top level); every source key read exactly once,
    and an error naming every missing or unexpected source key."""
    keys = source.keys()
    parts = {
        "": [_Rule(("language_model." + k,), (k,)) for k in lm_shapes],
        DINO_DIR: _dinov2_rules(source, _depth(keys, DINO)),
        SIGLIP_DIR: _siglip_rules(_depth(keys, SIGLIP)),
        PROJECTOR_DIR: _renames("projector.", "", (("fc1", "fc1"), ("fc2", "fc2"), ("fc3", "fc3"))),
    }
    uses = Counter(k for rules in parts.values() for r in rules for k in r.sources)
    assert max(uses.values()) == 1, "a converter rule reads a source tensor twice"
    missing, unexpected = set(uses) - keys, keys - set(uses)
    if missing or unexpected:
        raise ValueError(f"not OpenVLA's released layout: missing {_names(missing)}; unexpected {_names(unexpected)}")
    wrong = [f"{k} {source.shape('language_model.' + k)} != {s}" for k, s in lm_shapes.items()
             if source.shape("language_model." + k) != s]
    if wrong:
        raise ValueError(f"language model shapes differ from text_config: {_names(wrong)}")
    return parts


def _tower_configs(source: _Source, cfg: dict, llm_dim: int) -> dict:
    """transformers configs of both towers, from the weights' shapes and the timm ids' head counts."""
    from transformers import Dinov2WithRegistersConfig, SiglipVisionConfig

    size = int(cfg["image_sizes"][0])
    common = {}
    for name, p in ((DINO_DIR, DINO), (SIGLIP_DIR, SIGLIP)):
        patch, n_pos = source.shape(p + "patch_embed.proj.weight")[-1], source.shape(p + "pos_embed")[1]
        if n_pos != (size // patch) ** 2:
            raise ValueError(f"{p}pos_embed has {n_pos} positions, but image size {size} / patch {patch} gives "
                             f"{(size // patch) ** 2}")
        common[name] = dict(hidden_size=source.shape(p + "pos_embed")[-1], num_hidden_layers=_depth(source.keys(), p),
                            image_size=size, patch_size=patch, layer_norm_eps=_EPS, hidden_act="gelu")
    d_dino, d_sig = common[DINO_DIR]["hidden_size"], common[SIGLIP_DIR]["hidden_size"]
    mlp = source.shape(DINO + "blocks.0.mlp.fc1.weight")[0]
    if mlp % d_dino:  # transformers sizes the DINOv2 MLP by an integer ratio
        raise ValueError(f"DINOv2 MLP width {mlp} is not a multiple of its width {d_dino}")
    fc1, fc3 = source.shape("projector.fc1.weight"), source.shape("projector.fc3.weight")
    if fc1[1] != d_dino + d_sig or fc3[0] != llm_dim:
        raise ValueError(f"projector {fc1} ... {fc3} does not map {d_dino} + {d_sig} vision channels to the "
                         f"language model's {llm_dim}")
    dino = Dinov2WithRegistersConfig(**common[DINO_DIR], num_attention_heads=DINO_HEADS[cfg["timm_model_ids"][0]],
                                     mlp_ratio=mlp // d_dino, num_register_tokens=source.shape(DINO + "reg_token")[1],
                                     qkv_bias=True, architectures=["Dinov2WithRegistersModel"])
    siglip = SiglipVisionConfig(**common[SIGLIP_DIR], num_attention_heads=SIGLIP_HEADS[cfg["timm_model_ids"][1]],
                                intermediate_size=source.shape(SIGLIP + "blocks.0.mlp.fc1.weight")[0],
                                vision_use_head=True, architectures=["SiglipVisionModel"])
    return {DINO_DIR: dino, SIGLIP_DIR: siglip}


class _ShardWriter:
    """Streams tensors into ``model.safetensors`` or, past ``max_bytes``, shards with an index, holding at most
    one shard in memory."""

    def __init__(self, out: Path, max_bytes: float):
        self.out, self.max_bytes = out, max_bytes
        self.done: list[tuple[Path, list[str]]] = []
        self.current: dict[str, torch.Tensor] = {}
        self.size = self.total = 0
        out.mkdir(parents=True, exist_ok=True)

    def add(self, name: str, t: torch.Tensor) -> None:
        self.current[name] = t.contiguous()
        self.size += t.numel() * t.element_size()
        if self.size >= self.max_bytes:
            self._flush()

    def _flush(self) -> None:
        if self.current:
            f = self.out / f".shard-{len(self.done)}"
            save_file(self.current, str(f), metadata={"format": "pt"})
            self.done.append((f, list(self.current)))
            self.total += self.size
        self.current, self.size = {}, 0

    def close(self) -> None:
        self._flush()
        if len(self.done) == 1:
            self.done[0][0].rename(self.out / "model.safetensors")
            return
        n, weight_map = len(self.done), {}
        for i, (f, keys) in enumerate(self.done, 1):
            name = f"model-{i:05d}-of-{n:05d}.safetensors"
            f.rename(self.out / name)
            weight_map.update(dict.fromkeys(keys, name))
        index = {"metadata": {"total_size": self.total}, "weight_map": weight_map}
        (self.out / "model.safetensors.index.json").write_text(json.dumps(index, indent=1))


def _write(tmp: Path, source: _Source, parts: dict[str, list[_Rule]], max_bytes: int) -> tuple[dict, list]:
    """Run the rules part by part; returns (source key -> output tensors, created tensors)."""
    mapping, created = {}, []
    for part, rules in parts.items():
        # the projector (~140 MB for OpenVLA) is always one file, which is what OpenVLAModel reads
        writer = _ShardWriter(tmp / part, max_bytes if part != PROJECTOR_DIR else float("inf"))
        for rule in rules:
            for name, t in zip(rule.targets, rule.fn(*(source.get(k) for k in rule.sources)), strict=True):
                writer.add(name, t)
            targets = [f"{part}/{t}" if part else t for t in rule.targets]
            mapping.update(dict.fromkeys(rule.sources, targets))
            created += [] if rule.sources else targets
        writer.close()
    return mapping, created


def _check_towers(path: Path) -> None:
    """Load both written towers with transformers: any key it misses, ignores or reshapes is an error."""
    from transformers import Dinov2WithRegistersModel, SiglipVisionModel

    for cls, sub in ((Dinov2WithRegistersModel, DINO_DIR), (SiglipVisionModel, SIGLIP_DIR)):
        _, info = cls.from_pretrained(str(path / sub), local_files_only=True, output_loading_info=True)
        bad = {k: v for k, v in info.items() if v}
        if bad:
            raise ValueError(f"converted {sub} tower does not load cleanly into {cls.__name__}: {bad}")


def convert_openvla(src: str | os.PathLike, out: str | os.PathLike, max_shard_bytes: int = MAX_SHARD_BYTES) -> Path:
    """Convert OpenVLA's released checkpoint (``src``) into a directory the ``hf`` backbone loads with plain
    transformers classes; returns ``out`` (written under a temporary name, then renamed).

    Output: ``config.json`` + ``model*.safetensors`` = ``LlamaForCausalLM`` (``language_model.*`` renamed,
    so the directory is also a complete causal-LM checkpoint), the tokenizer files copied verbatim,
    ``preprocessor_config.json`` without its ``auto_map``, ``dinov2/`` = ``Dinov2WithRegistersModel``,
    ``siglip/`` = ``SiglipVisionModel``, ``projector/`` = :class:`FusedProjector` and ``pivla_openvla.json``
    (format marker, image sizes, the source config.json, and every source key with the output tensors it
    became). Tensors keep their dtype (bf16 in the release); memory peaks at about one 5 GB output shard.

    Every source tensor is used exactly once; missing or unexpected source keys are an error naming them.
    Vision conversions: timm's fused ``attn.qkv`` rows split into q/k/v; DINOv2's ``pos_embed`` (patches only)
    gets a zero class row, since timm's ``cls_token`` already carries DINOv2's class position; Prismatic's
    ``ls{1,2}.scale_factor`` (timm ``gamma``) -> ``layer_scale{1,2}.lambda1``; SigLIP's ``pos_embed`` (1, P, D)
    -> an embedding table (P, D). The last blocks, final norms and SigLIP's ``attn_pool`` (-> the pooling
    ``head``), which OpenVLA never uses, are converted too, so nothing is lost. One tensor is created:
    DINOv2's ``mask_token`` (zeros), which transformers has and timm lacks; it only acts on masked inputs.

    Assumptions (the real 7B weights were not available here; the mapping is tested against a timm-layout
    reference on tiny random weights in the released key layout):
    - both towers have 16 heads (timm's ViT-L and So400m definitions; head counts are not in the weights);
    - activations are exact GELU: timm 0.9 (OpenVLA pins 0.9.10-0.9.16) builds SigLIP with ``nn.GELU``, not
      big_vision's tanh approximation, so ``hidden_act`` is ``gelu`` in both towers; LayerNorm eps 1e-6;
    - the Llama config is ``LlamaConfig(**text_config)`` with transformers' defaults for absent fields, as
      OpenVLA's own configuration code builds it (so e.g. rms_norm_eps is whatever that gives).
    """
    from transformers import LlamaConfig, LlamaForCausalLM

    src, out = check_local_dir(src, "convert-openvla").resolve(), Path(out)
    if out.exists():
        raise FileExistsError(f"{out} exists; choose a new directory")
    cfg, pre = _read_openvla_config(src)
    tokenizer_files = [f for f in TOKENIZER_FILES if (src / f).is_file()]
    if "tokenizer_config.json" not in tokenizer_files:
        raise FileNotFoundError(f"{src}: no tokenizer_config.json (the tokenizer is copied from the checkpoint)")
    text_cfg = LlamaConfig(**{k: v for k, v in cfg.get("text_config", {}).items() if k != "model_type"},
                           architectures=["LlamaForCausalLM"])
    with torch.device("meta"):
        lm_shapes = {k: tuple(v.shape) for k, v in LlamaForCausalLM(text_cfg).state_dict().items()}
    with ExitStack() as stack:
        source = _Source(src, stack)
        try:
            parts = _plan(source, lm_shapes)
            towers = _tower_configs(source, cfg, text_cfg.hidden_size)
        except ValueError as e:
            raise ValueError(f"{src}: {e}") from e
        with atomic_dir(out) as tmp:
            text_cfg.save_pretrained(str(tmp))
            for sub, tower_cfg in towers.items():
                tower_cfg.save_pretrained(str(tmp / sub))
            mapping, created = _write(tmp, source, parts, max_shard_bytes)
            _check_towers(tmp)
            for f in tokenizer_files:
                shutil.copy2(src / f, tmp / f)
            pre.pop("auto_map", None)  # no remote processor code travels with the converted checkpoint
            (tmp / "preprocessor_config.json").write_text(json.dumps(pre, indent=2))
            meta = {"format": FORMAT, "image_sizes": cfg["image_sizes"], "source": str(src), "openvla_config": cfg,
                    "created": created, "mapping": mapping}
            (tmp / MARKER).write_text(json.dumps(meta, indent=1))
    return out
