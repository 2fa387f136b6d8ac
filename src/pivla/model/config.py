"""Configuration of the CMS model (paper Eqs. 3-7). One dataclass per component; no torch import, so the
command line builds its help from these without loading the model."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal

# The proprioception of pivla's and LIBERO's observations (pivla.envs), each key with its length: what a policy
# reads unless told otherwise. ``joint_states`` is not among them: its length is the arm's number of joints.
PROPRIO_LENGTHS = {"ee_pos": 3, "ee_ori": 3, "gripper_states": 2}


@dataclass
class BackboneConfig:
    """Which backbone produces h_cog and h_mot. ``small``: CPU-friendly, trained from scratch;
    ``hf``: a local Hugging Face vision-language model with LoRA (pivla.model.hf)."""

    name: Literal["small", "hf"] = "small"
    """small: CNN + transformer trained from scratch; hf: a local VLM checkpoint with LoRA."""
    d_model: int = 128
    """Width of the small backbone's transformer."""
    n_layers: int = 3
    """Transformer layers of the small backbone."""
    n_heads: int = 4
    """Attention heads of the small backbone."""
    ff_mult: int = 2
    """Feed-forward width as a multiple of d_model."""
    n_cog_tokens: int = 4
    """Learned query tokens that become h_cog."""
    vision_channels: tuple[int, ...] = (32, 64, 128, 128)
    """Channels of the CNN stages (each halves the resolution)."""
    keypoints: int = 64
    """Spatial-softmax keypoints per camera (0: off): explicit image coordinates of learned features, which a
    policy needs to localise small objects quickly."""
    keypoint_stage: int = -2
    """CNN stage the keypoints read (-2: 12x12 at 96 px, -3: 24x24)."""
    res_blocks: tuple[int, ...] = ()
    """Residual convolutions per CNN stage (empty: none)."""
    film: bool = False
    """Scale and shift every CNN stage's channels by the instruction (FiLM, Perez et al. 2018), so the pictures are
    read for the object the words name before they are pooled into tokens and keypoints."""
    grid_tokens: bool = False
    """One token per cell of the last CNN grid instead of one pooled token per camera: with keypoints
    carrying the coordinates, pooled tokens cut the sequence from ~100 tokens to ~30."""
    dropout: float = 0.0
    """Dropout in the transformer."""
    path: str = ""
    """hf: local checkpoint directory (Llava-style or a converted OpenVLA)."""
    lora_rank: int = 32
    """hf: LoRA rank."""
    lora_alpha: int = 16
    """hf: LoRA alpha."""
    lora_dropout: float = 0.0
    """hf: LoRA dropout."""
    lora_target_modules: tuple[str, ...] = ("q_proj", "k_proj", "v_proj", "o_proj")
    """hf: module names LoRA adapts."""
    gradient_checkpointing: bool = False
    """hf: recompute activations in the backward pass (memory for time)."""
    dtype: str = "auto"
    """hf: dtype of the base weights (auto: bf16 on a bf16-capable GPU, else float32)."""


@dataclass
class TargetEncoderConfig:
    """The frozen target encoder of L_SP and of AURD's U_pred."""

    name: Literal["ema", "frozen", "dinov2", "thumbnail"] = "ema"
    """ema: moving average of the policy's vision encoder; frozen: a frozen copy at initialisation; dinov2: a
    local DINOv2 checkpoint (path); thumbnail: the picture pooled to grid x grid cells, no weights."""
    ema_decay: float = 0.995
    """ema: decay per training step."""
    path: str = ""
    """dinov2: local checkpoint directory."""
    grid: int = 12
    """thumbnail: cells per side."""
    cameras: int = 1
    """Leading cameras (the agent view first) the latent describes. One: AURD encodes every new observation,
    and the scene camera carries the task state."""
    downsample: int = 1
    """ema/frozen: area-average the picture by this factor per side before encoding. The encoding then costs
    about 1/factor**2 of the policy's vision pass, which is AURD's per-step overhead."""
    pool_grid: int = 1
    """ema/frozen: average the last feature map over a pool_grid x pool_grid partition instead of the whole
    picture (1), so that the latent keeps where things are (docs/experiments.md#aurd-does-not-see-a-displaced-object)."""  # noqa: E501 - tyro --help keeps its line breaks
    stages: int = 0
    """ema/frozen: the latent pools the output of the CNN's first stages (0: all). An earlier stage has a
    fraction of the weights, which AURD's encoding fetches into a cache the simulator has just used."""
    proprio: float = 0.0
    """Weight of the normalised proprioception appended to the pictures' latent (0: pictures only). The
    observation in z = Enc(o) holds the arm's state too: with it, U_pred sees the arm moved by something other
    than the chunk's own actions (docs/experiments.md#aurd-does-not-see-the-arm-pushed)."""


@dataclass
class ModelConfig:
    """The CMS model: chunk and horizon, inputs, heads (paper Eqs. 3-7). The defaults of the inputs and of D
    are the twin's layout; a training config leaves them empty, and training fills them from its dataset
    (``pivla.data.samples.resolve_inputs``), so a run's config.json holds the values the model was built with."""

    chunk: int = 8
    """K, actions per chunk."""
    horizon: int = 5
    """H, the value head's length and AURD's nominal horizon."""
    n_bins: int = 256
    """B, discrete bins per action dimension (Eq. 4)."""
    action_dim: int = 7
    """D, action dimensions: the training dataset's action space's (0 in a training config: taken from it)."""
    cameras: tuple[str, ...] = ("agentview_rgb", "eye_in_hand_rgb")
    """Image keys of an observation, the agent view first (empty in a training config: the dataset's)."""
    image_size: int = 96
    """Side in pixels of the square pictures the model reads (other sizes are resized)."""
    proprio_keys: tuple[str, ...] = tuple(PROPRIO_LENGTHS)
    """Proprioceptive keys, concatenated in this order (empty in a training config: the dataset's)."""
    proprio_dim: int = sum(PROPRIO_LENGTHS.values())
    """Length of the concatenated proprio vector, derived from the keys: the sum of their lengths in the
    training dataset (0 in a training config: training sums them; a value given must agree)."""
    relative_actions: bool = False
    """Absolute joint targets only: the heads predict each chunk's targets as offsets from the present pose (the
    proprio key of the action's dimension) at its first step, all but the gripper (openpi's delta actions); the
    policy adds the pose back, so what it exchanges stays absolute."""
    action_prefix: int = 0
    """P, actions in flight the model can be told (0: none). With a query in flight, the arm executes the actions
    the current plan still holds; told them, the model plans the chunk that follows them (training feeds the
    first d of each target chunk, d uniform in 0..P; asynchronous execution sends the planned actions of the
    steps the query is expected to spend in flight; docs/latency.md#actions-in-flight)."""
    max_text_len: int = 16
    """Instruction tokens kept."""
    state_hidden: int = 256
    """Hidden width of the state predictor (Eq. 6)."""
    decoder_size: int = 24
    """Side of the inspection image decoded from predicted latents by g."""
    backbone: BackboneConfig = field(default_factory=BackboneConfig)
    """Backbone (Eq. 3)."""
    target_encoder: TargetEncoderConfig = field(default_factory=TargetEncoderConfig)
    """Target encoder of L_SP and U_pred."""
