"""The Cognitive-Motor Synergy model: one forward pass gives discrete and continuous action chunks,
predicted latents of the next observations and values (paper Eqs. 3-7)."""

from __future__ import annotations

import copy
import math
from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import nn

from pivla.model.backbone import build_backbone
from pivla.model.config import ModelConfig
from pivla.model.dinov2 import Dinov2Encoder
from pivla.model.tokenizer import bin_centers


@dataclass
class CMSOutput:
    logits: torch.Tensor  # (B, K, D, n_bins) discrete head, Eq. 4
    continuous: torch.Tensor  # (B, K, D) continuous head, Eq. 5 (normalized action space)
    latents: torch.Tensor  # (B, K, d_z) predicted next-observation latents, Eq. 6
    values: torch.Tensor  # (B, H) V[k] = expected return after executing k+1 actions, Eq. 7
    value_now: torch.Tensor  # (B,) value of the current state, the GAE baseline
    h_cog: torch.Tensor
    h_mot: torch.Tensor


class DiscreteHead(nn.Module):
    """Eq. 4, f_d(h_mot): each motor token -> D x B logits. Shared across chunk steps, so its cost is
    K small matmuls rather than one huge flat projection."""

    def __init__(self, d: int, action_dim: int, n_bins: int):
        super().__init__()
        self.action_dim, self.n_bins = action_dim, n_bins
        self.proj = nn.Sequential(nn.Linear(d, d), nn.GELU(), nn.Linear(d, action_dim * n_bins))

    def forward(self, h_mot: torch.Tensor) -> torch.Tensor:
        return self.proj(h_mot).unflatten(-1, (self.action_dim, self.n_bins))


class ContinuousHead(nn.Module):
    """Eq. 5, f_c(h_mot): each motor token -> D continuous actions (normalized space)."""

    def __init__(self, d: int, action_dim: int):
        super().__init__()
        self.proj = nn.Sequential(nn.Linear(d, d), nn.GELU(), nn.Linear(d, action_dim))

    def forward(self, h_mot: torch.Tensor) -> torch.Tensor:
        return self.proj(h_mot)


class ValueHead(nn.Module):
    """Eq. 7, f_v(h_cog): H+1 values; index 0 is the current state (the GAE baseline), index k the state
    after executing k actions of the chunk."""

    def __init__(self, d: int, horizon: int):
        super().__init__()
        self.proj = nn.Sequential(nn.Linear(d, d), nn.GELU(), nn.Linear(d, horizon + 1))

    def forward(self, h_cog: torch.Tensor) -> torch.Tensor:
        return self.proj(h_cog.mean(1))


class StatePredictor(nn.Module):
    """Eq. 6 generalised to the chunk, f_s(h_cog, A_c): one latent per chunk step.

    Step k sees the pooled cognitive readout, the k-th action and the cumulative action up to k, plus a
    step embedding. The actions enter detached: L_SP must shape the representation, not bend the actions
    towards whatever makes the future easy to predict.
    """

    def __init__(self, d: int, action_dim: int, chunk: int, latent_dim: int, hidden: int):
        super().__init__()
        self.step_emb = nn.Parameter(torch.randn(chunk, d) * 0.02)
        self.net = nn.Sequential(
            nn.Linear(d + 2 * action_dim, hidden), nn.GELU(), nn.Linear(hidden, hidden), nn.GELU(),
            nn.Linear(hidden, latent_dim),
        )

    def forward(self, h_cog: torch.Tensor, actions: torch.Tensor) -> torch.Tensor:
        a = actions.detach()
        ctx = h_cog.mean(1, keepdim=True) + self.step_emb  # (B, K, d)
        return self.net(torch.cat([ctx, a, a.cumsum(1)], dim=-1))


class LatentDecoder(nn.Module):
    """g(z_hat): predicted latent -> low-resolution RGB image, for looking at what the model expects.
    Trained on stop-gradient latents, so it never influences the policy."""

    def __init__(self, latent_dim: int, size: int):
        super().__init__()
        self.base = max(size // 4, 1)
        self.fc = nn.Linear(latent_dim, 64 * self.base * self.base)
        self.up = nn.Sequential(
            nn.ConvTranspose2d(64, 32, 4, stride=2, padding=1), nn.GELU(),
            nn.ConvTranspose2d(32, 3, 4, stride=2, padding=1),
        )
        self.size = size

    def forward(self, z: torch.Tensor) -> torch.Tensor:
        x = self.fc(z.detach()).unflatten(-1, (64, self.base, self.base))
        lead = x.shape[:-3]
        img = torch.sigmoid(self.up(x.flatten(0, -4)))
        img = F.interpolate(img, size=(self.size, self.size), mode="bilinear", align_corners=False)
        return img.unflatten(0, lead)


def proprio_latent(proprio, weight: float):
    """The proprio part of z = Enc(o): ``weight`` x the normalised proprio / sqrt(P), so that at weight 1 an L2
    distance is an RMS error per feature in the training set's standard deviations, as the pictures' part is
    per feature. NumPy or torch arrays alike (a policy appends it to the ONNX graph's picture latents)."""
    return proprio * (weight / math.sqrt(proprio.shape[-1]))


class TargetEncoder(nn.Module):
    """z = Enc(o): the frozen target of L_SP and the observed latent of AURD's U_pred.

    Latents leave in *policy units*: layer-normalised (scale-free, so eta mixes comparable quantities) and
    divided by sqrt(d_z), so that an L2 distance between two latents is an RMS error per feature.
    """

    def __init__(self, encoder: nn.Module, kind: str, ema_decay: float, cameras: int = 1, downsample: int = 1,
                 grid: int = 1, proprio: float = 0.0):
        super().__init__()
        if downsample < 1 or grid < 1:
            raise ValueError(f"target encoder downsample and grid must be >= 1, got {downsample} and {grid}")
        if not (math.isfinite(proprio) and proprio >= 0):
            raise ValueError(f"target encoder proprio weight must be >= 0, got {proprio}")
        self.encoder = encoder
        self.kind = kind
        self.ema_decay = ema_decay
        self.cameras = cameras
        self.downsample = downsample
        self.grid = grid
        self.proprio = float(proprio)
        self.encoder.requires_grad_(False)

    def extra_repr(self) -> str:
        return (f"kind={self.kind!r}, cameras={self.cameras}, downsample={self.downsample}, grid={self.grid}, "
                f"proprio={self.proprio}")

    @torch.no_grad()
    def forward(self, images: torch.Tensor, proprio: torch.Tensor | None = None) -> torch.Tensor:
        """(..., n_cam, 3, H, W) images in [0, 1] (and, when the latent reads it, (..., P) normalised proprio)
        -> (..., d_z) latents: the pictures' (``picture_latents``), then ``proprio`` x proprio / sqrt(P), an RMS
        per feature like the pictures' part."""
        z = self.picture_latents(images)
        if self.proprio == 0:
            return z
        if proprio is None or proprio.shape[:-1] != z.shape[:-1]:
            raise ValueError(f"this target latent reads the proprio too: give (..., P) for images "
                             f"{tuple(images.shape)}, got {None if proprio is None else tuple(proprio.shape)}")
        return torch.cat([z, proprio_latent(proprio.float(), self.proprio)], dim=-1)

    @torch.no_grad()
    def picture_latents(self, images: torch.Tensor) -> torch.Tensor:
        """(..., n_cam, 3, H, W) images in [0, 1] -> (..., d_pic) latents of the first ``cameras`` cameras,
        area-averaged ``downsample`` times per side first."""
        images = images[..., : self.cameras, :, :, :]
        if self.downsample > 1:
            images = F.avg_pool2d(images.flatten(0, -4), self.downsample).unflatten(0, images.shape[:-3])
        lead = images.shape[:-4]
        flat = images.flatten(0, len(lead) - 1) if len(lead) > 1 else images
        z = self.encoder.pooled(flat, grid=self.grid) if self.grid > 1 else self.encoder.pooled(flat)
        z = F.layer_norm(z.float(), z.shape[-1:]) / math.sqrt(z.shape[-1])
        return z.unflatten(0, lead) if len(lead) > 1 else z

    @torch.no_grad()
    def update(self, online: nn.Module) -> None:
        """EMA step towards the policy's online vision encoder (no-op for frozen encoders), parameter by name:
        a truncated target (``TargetEncoderConfig.stages``) follows the stages it kept."""
        if self.kind != "ema":
            return
        online_params = dict(online.named_parameters())
        for name, p_t in self.encoder.named_parameters():
            p_t.lerp_(online_params[name].detach().to(p_t.dtype), 1.0 - self.ema_decay)


class Thumbnail(nn.Module):
    """The image average-pooled to ``grid`` x ``grid`` cells: a weight-free encoder whose latent is a
    low-resolution picture of the scene, so that L_SP predicts coarse next frames and AURD's observed latent
    costs a pooling instead of a CNN pass. The target's layer norm removes overall brightness and contrast."""

    def __init__(self, grid: int):
        super().__init__()
        if grid < 1:
            raise ValueError(f"thumbnail grid must be >= 1, got {grid}")
        self.grid = grid

    def pooled(self, images: torch.Tensor) -> torch.Tensor:
        """(B, n_cam, 3, H, W) -> (B, n_cam * 3 * grid * grid)."""
        return F.adaptive_avg_pool2d(images.flatten(0, 1), self.grid).reshape(images.shape[0], -1)


def build_target_encoder(cfg: ModelConfig, backbone: nn.Module) -> TargetEncoder:
    tc = cfg.target_encoder
    for key, default in (("downsample", 1), ("stages", 0), ("pool_grid", 1)):
        if getattr(tc, key) != default and tc.name not in ("ema", "frozen"):
            raise ValueError(f"target encoder {key} {getattr(tc, key)}: only the 'ema' and 'frozen' encoders "
                             f"take it, not {tc.name!r} (set it to {default})")
    if tc.name in ("ema", "frozen"):
        if not hasattr(backbone, "vision"):
            raise ValueError(f"target encoder {tc.name!r} needs a backbone with a 'vision' encoder; use dinov2")
        if cfg.image_size % tc.downsample:
            raise ValueError(f"target encoder downsample {tc.downsample} must divide image_size {cfg.image_size}")
        encoder = copy.deepcopy(backbone.vision)
        if tc.stages:
            encoder.truncate(tc.stages)
        return TargetEncoder(encoder, tc.name, tc.ema_decay, tc.cameras, tc.downsample, tc.pool_grid, tc.proprio)
    if tc.name == "dinov2":
        return TargetEncoder(Dinov2Encoder(tc.path, cfg.image_size), "frozen", tc.ema_decay, tc.cameras,
                             proprio=tc.proprio)
    if tc.name == "thumbnail":
        return TargetEncoder(Thumbnail(tc.grid), "frozen", tc.ema_decay, tc.cameras, proprio=tc.proprio)
    raise ValueError(f"unknown target encoder {tc.name!r}; choose 'ema', 'frozen', 'dinov2' or 'thumbnail'")


def check_action_prefix(cfg: ModelConfig) -> None:
    """A ValueError naming what cannot read actions in flight: more than K - 1 of them, another backbone than the
    small one, or relative actions (offsets from a pose the actions in flight have already moved away from)."""
    p = cfg.action_prefix
    if p == 0:
        return
    if not 0 < p < cfg.chunk:
        raise ValueError(f"action_prefix must be 0 to K - 1 = {cfg.chunk - 1} actions, got {p}")
    if cfg.backbone.name != "small":
        raise ValueError(f"action_prefix: only the small backbone reads actions in flight, not {cfg.backbone.name!r}")
    if cfg.relative_actions:
        raise ValueError("action_prefix does not combine with relative_actions")


class CMSModel(nn.Module):
    """Backbone + the four heads of Eqs. 4-7 + the decoder g + the target encoder."""

    def __init__(self, cfg: ModelConfig, vocab_size: int):
        super().__init__()
        unset = [name for name in ("cameras", "proprio_keys", "proprio_dim", "action_dim") if not getattr(cfg, name)]
        if unset:
            raise ValueError(f"model config leaves {unset} to the dataset: fill them from one first "
                             "(pivla.data.samples.resolve_inputs)")
        check_action_prefix(cfg)
        self.cfg = cfg
        self.backbone = build_backbone(cfg, vocab_size)
        d = self.backbone.d_model
        self.target = build_target_encoder(cfg, self.backbone)
        with torch.no_grad():
            probe = torch.zeros(1, len(cfg.cameras), 3, cfg.image_size, cfg.image_size)
            self.latent_dim = int(self.target(probe, torch.zeros(1, cfg.proprio_dim)).shape[-1])
        self.discrete_head = DiscreteHead(d, cfg.action_dim, cfg.n_bins)
        self.continuous_head = ContinuousHead(d, cfg.action_dim)
        self.value_head = ValueHead(d, cfg.horizon)
        self.state_predictor = StatePredictor(d, cfg.action_dim, cfg.chunk, self.latent_dim, cfg.state_hidden)
        self.decoder = LatentDecoder(self.latent_dim, cfg.decoder_size)
        # per-dimension log std of the actor's Gaussian around the continuous head (L_RL). It starts at 1
        # (the width of the normalized action range): with a narrow Gaussian the actor's gradient on the
        # mean, residual / sigma^2 times a unit-variance advantage, swamps imitation while advantages are
        # still noise (measured: the SmoothL1 term did not fall in 500 steps with sigma = 0.1).
        self.log_sigma = nn.Parameter(torch.zeros(cfg.action_dim))
        self.register_buffer("bin_centers", torch.from_numpy(bin_centers(cfg.n_bins)), persistent=False)

    def forward(self, batch: dict[str, torch.Tensor], aux_on_trunk: bool = True) -> CMSOutput:
        """``aux_on_trunk=False`` gives the value head and the state predictor stop-gradient features: their losses
        then train those heads only, and the shared trunk learns from the action heads alone."""
        h_cog, h_mot = self.backbone(batch)
        continuous = self.continuous_head(h_mot)
        aux = h_cog if aux_on_trunk else h_cog.detach()
        v = self.value_head(aux)
        return CMSOutput(
            logits=self.discrete_head(h_mot),
            continuous=continuous,
            latents=self.state_predictor(aux, continuous),
            values=v[:, 1:],
            value_now=v[:, 0],
            h_cog=h_cog,
            h_mot=h_mot,
        )

    def external_state_keys(self) -> set[str]:
        """State-dict keys of frozen pretrained weights that are rebuilt from a local checkpoint directory
        (``backbone.path``, the DINOv2 path): run checkpoints leave them out, so a 7B run stores only
        adapters and heads. Parts declare them with their own ``external_state_keys()``."""
        keys: set[str] = set()
        for prefix, module in (("backbone.", self.backbone), ("target.encoder.", self.target.encoder)):
            declare = getattr(module, "external_state_keys", None)
            if declare is not None:
                keys |= {prefix + k for k in declare()}
        return keys

    def state_dict_for_checkpoint(self) -> dict[str, torch.Tensor]:
        """The state dict minus ``external_state_keys()``: what model.safetensors holds."""
        external = self.external_state_keys()
        return {k: v for k, v in self.state_dict().items() if k not in external}

    def load_checkpoint_state(self, state: dict[str, torch.Tensor], source: str = "checkpoint") -> None:
        """Inverse of ``state_dict_for_checkpoint``: every other key must match exactly."""
        try:
            missing, unexpected = self.load_state_dict(state, strict=False)
        except RuntimeError as e:  # shape mismatches: a checkpoint from another config or version
            raise ValueError(f"{source}: does not match the model built from config.json ({e})") from None
        external = self.external_state_keys()
        missing = [k for k in missing if k not in external]
        if missing or unexpected:
            raise ValueError(f"{source}: does not match the model built from config.json "
                             f"(missing {missing[:5]}, unexpected {unexpected[:5]})")

    def update_target(self) -> None:
        if hasattr(self.backbone, "vision"):
            self.target.update(self.backbone.vision)

    def parameter_counts(self) -> dict[str, int]:
        parts = {
            "backbone": self.backbone, "discrete_head": self.discrete_head, "continuous_head": self.continuous_head,
            "value_head": self.value_head, "state_predictor": self.state_predictor, "decoder": self.decoder,
            "target_encoder": self.target,
        }
        counts = {k: sum(p.numel() for p in m.parameters()) for k, m in parts.items()}
        counts["trainable"] = sum(p.numel() for p in self.parameters() if p.requires_grad)
        counts["total"] = sum(p.numel() for p in self.parameters())
        return counts
