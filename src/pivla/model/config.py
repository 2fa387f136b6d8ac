"""Configuration of the CMS model (paper Eqs. 3-7). One dataclass per component."""

from __future__ import annotations

from dataclasses import dataclass, field


@dataclass
class BackboneConfig:
    """Which backbone produces h_cog and h_mot. ``small``: CPU-friendly, trained from scratch;
    ``hf``: a local Hugging Face vision-language model with LoRA (see pivla.model.hf)."""

    name: str = "small"
    d_model: int = 128
    n_layers: int = 3
    n_heads: int = 4
    ff_mult: int = 2
    n_cog_tokens: int = 4
    vision_channels: tuple[int, ...] = (32, 64, 128, 128)
    # spatial-softmax keypoints per camera, read from CNN stage `keypoint_stage` (0 = off): explicit
    # image coordinates of learned features, which a policy needs to localise small objects quickly
    keypoints: int = 64
    keypoint_stage: int = -2  # which CNN stage the keypoints read (-2: 12x12 at 96 px, -3: 24x24)
    res_blocks: tuple[int, ...] = ()  # residual convolutions per CNN stage (empty = none)
    # one token per cell of the last CNN grid (True) or one pooled token per camera (False): with keypoints
    # carrying the coordinates, the pooled token cuts the transformer's sequence from ~100 tokens to ~30
    grid_tokens: bool = False
    dropout: float = 0.0
    # hf backbone
    path: str = ""
    lora_rank: int = 32
    lora_alpha: int = 16
    lora_dropout: float = 0.0
    lora_target_modules: tuple[str, ...] = ("q_proj", "k_proj", "v_proj", "o_proj")
    gradient_checkpointing: bool = False
    dtype: str = "auto"  # base weights: auto = bf16 on a bf16-capable GPU, else float32


@dataclass
class TargetEncoderConfig:
    """Frozen target encoder for L_SP and AURD's U_pred. ``ema``: exponential moving average of the
    policy's own vision encoder; ``frozen``: a frozen copy of it at initialisation; ``dinov2``: a local
    DINOv2 checkpoint (``path``); ``thumbnail``: the image average-pooled to ``grid`` x ``grid`` cells, no
    weights (cheap enough to run after every action: AURD's per-step overhead)."""

    name: str = "ema"
    ema_decay: float = 0.995
    path: str = ""
    grid: int = 12  # thumbnail cells per side
    # how many of the policy's cameras (leading ones; the agent view first) the latent describes. One by
    # default: AURD encodes every new observation, and the scene camera carries the task state.
    cameras: int = 1
    # ``ema``/``frozen`` only: the image is area-averaged by this factor per side before encoding. The
    # encoding then costs about 1/factor**2 of the policy's vision pass, which is AURD's per-step overhead.
    downsample: int = 1
    # ``ema``/``frozen`` only: the latent pools the output of the CNN's first ``stages`` stages (0: all). An
    # earlier stage has a fraction of the weights, and AURD's encoding in the control loop costs mostly
    # fetching them into a cache the simulator and renderer have just used.
    stages: int = 0


@dataclass
class ModelConfig:
    chunk: int = 8  # K, actions per chunk
    horizon: int = 5  # H_nominal, value entries and AURD's nominal horizon
    n_bins: int = 256  # B, discrete bins per action dimension
    action_dim: int = 7  # D
    cameras: tuple[str, ...] = ("agentview_rgb", "eye_in_hand_rgb")
    image_size: int = 96
    proprio_keys: tuple[str, ...] = ("ee_pos", "ee_ori", "gripper_states")
    proprio_dim: int = 8
    max_text_len: int = 16
    state_hidden: int = 256
    decoder_size: int = 24  # side of the inspection image decoded from predicted latents by g
    backbone: BackboneConfig = field(default_factory=BackboneConfig)
    target_encoder: TargetEncoderConfig = field(default_factory=TargetEncoderConfig)
