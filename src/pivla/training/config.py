"""Training configuration: the unified loss's weights and the training run, with the validated recipe as the
default and named presets for other settings.

Importing this module imports no torch, so the command line can show ``pivla train --help`` instantly.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Literal

from pivla.model.config import BackboneConfig, ModelConfig, TargetEncoderConfig

# the model inputs a training run takes from its dataset unless they are named (pivla.data.samples.resolve_inputs)
FROM_DATASET = {"cameras": (), "proprio_keys": (), "proprio_dim": 0, "action_dim": 0}


@dataclass
class LossConfig:
    """Weights and switches of the unified objective (paper Eqs. 8-11)."""

    alpha: float = 0.1
    """Weight of L_RL (Eq. 8)."""
    beta: float = 0.05
    """Weight of L_SP (Eq. 8)."""
    lam: float = 1.0
    """Weight of SmoothL1 inside L_IL (Eq. 9)."""
    gamma: float = 0.99
    """GAE discount."""
    gae_lambda: float = 0.95
    """GAE lambda."""
    critic_coef: float = 1.0
    """Critic regression inside L_RL (the paper omits it; an actor-critic needs it)."""
    use_discrete: bool = True
    """Train the discrete head (ablations switch one head off)."""
    use_continuous: bool = True
    """Train the continuous head."""
    use_rl: bool = True
    """Add the actor-critic term."""
    actor_positive_only: bool = False
    """The actor term (Eq. 10) weighs only actions with positive advantages; negative ones count zero
    (docs/experiments.md#the-three-suite-policys-training-length)."""
    use_sp: bool = True
    """Add the latent state-prediction term."""
    use_recon: bool = True
    """Train the inspection decoder g on predicted latents."""
    aux_on_trunk: bool = True
    """L_RL and L_SP train the shared backbone with the action heads (Eq. 8). Off: imitation alone shapes the
    backbone; the critic and the state predictor learn on stop-gradient features, so the value and the
    predicted latents AURD reads are still trained, and the actor term, which acts only through the
    continuous head, is dropped (docs/experiments.md#auxiliary-terms-on-stop-gradient-features)."""
    sp_steps: int = 1
    """Chunk steps per sample whose next observation is encoded for L_SP. One, not two: the same expected
    loss and 1.04-1.12x faster training at equal validation success (docs/experiments.md#one-state-prediction-step)."""


@dataclass
class TrainConfig:
    """One training run. The defaults are the recipe ``pivla demo`` validated on the twin: 4000 steps of
    batch 32 at 80 px, the target encoder reading the agent view downsampled 4x."""

    data: str = ""
    """Dataset directory: LIBERO-layout HDF5 files or a LeRobot v3 dataset."""
    out: str = "runs/default"
    """Run directory to write (model, config, statistics, checkpoints)."""
    extra_data: tuple[str, ...] = ()
    """More dataset directories, e.g. recorded policy rollouts for the RL and value terms."""
    steps: int = 4000
    """Optimizer steps. At 1800 x 64 the policy had not learned to localise objects; with 90 demos per task
    4000 scored as well as 5000 (docs/experiments.md#training-length)."""
    batch_size: int = 32
    """Samples per step and process."""
    grad_accum: int = 1
    """Gradient accumulation steps."""
    lr: float = 3e-4
    """Peak learning rate (AdamW)."""
    weight_decay: float = 0.01
    """AdamW weight decay."""
    warmup: int = 200
    """Linear warm-up steps, at most a tenth of the run."""
    min_lr_ratio: float = 0.05
    """Cosine decay ends at this fraction of the peak learning rate."""
    grad_clip: float = 1.0
    """Gradient-norm clip."""
    seed: int = 0
    """Seed of initialisation, batches, augmentation and the validation split."""
    task_balance: float = 0.0
    """How evenly the tasks (told apart by instruction) are drawn: 0, every frame equally often; 1, every task
    equally often, whatever the length and number of its demonstrations; between, a frame's weight is its task's
    frame count to the power -task_balance (docs/experiments.md#equal-task-sampling)."""
    ema_decay: float = 0.0
    """Deploy an exponential moving average of the weights with this decay (0: the last weights). Checkpoints
    keep the live weights too, so ``--resume`` continues both (docs/experiments.md#a-weight-average)."""
    val_fraction: float = 0.05
    """Share of episodes held out for validation loss (per task, whole episodes)."""
    augment_pad: int = 4
    """Random-shift augmentation in pixels."""
    augment_shift_cameras: tuple[str, ...] = ()
    """The cameras (dataset keys) the random shift moves; empty: every camera. A wrist camera rides with the
    gripper and sees where the grasp will land, so shifting it teaches nothing about jitter and blurs that
    (docs/experiments.md#shift-augmentation-and-near-misses)."""
    augment_color: float = 0.2
    """Photometric jitter strength (0: off)."""
    log_every: int = 25
    """Steps between log lines."""
    eval_every: int = 0
    """Steps between validation losses (0: five times per run)."""
    ckpt_every: int = 0
    """Steps between checkpoints (0: five times per run)."""
    ckpt_minutes: float = 10.0
    """Also a checkpoint once this many minutes have passed since the last one (0: off), checked at log steps:
    a training killed on a slow machine (a fifth of a LIBERO run is half an hour on 2 cores) loses at most
    about this much. Resuming from any checkpoint trains the same weights."""
    keep_checkpoints: int = 2
    """Checkpoints kept on disk."""
    value_refresh_every: int = 0
    """Steps between refreshes of the GAE table from the value head (0: five times per run)."""
    mixed_precision: str = "auto"
    """auto: bf16 on a GPU that supports it, else none; or no | fp16 | bf16."""
    device: str = "auto"
    """auto | cpu | cuda."""
    threads: int = 0
    """Torch intra-op threads on a CPU (0: all cores)."""
    fsdp: bool = False
    """Shard parameters, gradients and optimizer state across processes (FSDP2) instead of DDP."""
    progress: bool = True
    """Show a progress bar."""
    image_store: Literal["auto", "memory", "disk"] = "auto"
    """Where the training pictures are held: in memory, or in a file in the run directory that the OS pages in
    (for datasets larger than the RAM); auto chooses disk when they would fill more than a third of the RAM."""
    model: ModelConfig = field(default_factory=lambda: ModelConfig(
        image_size=80, target_encoder=TargetEncoderConfig(downsample=4), **FROM_DATASET))
    """The CMS model; its cameras, proprio keys and dimensions are the dataset's unless named."""
    loss: LossConfig = field(default_factory=LossConfig)
    """The unified objective."""

    def every(self, value: int) -> int:
        """An interval setting, 0 meaning five times per run."""
        return value if value > 0 else max(self.steps // 5, 1)

    @property
    def warmup_steps(self) -> int:
        return min(self.warmup, self.steps // 10)


def check_target_divides(model: ModelConfig) -> None:
    """Refuse an image size the target encoder's downsampling does not divide (before anything is collected)."""
    factor = model.target_encoder.downsample
    if model.image_size % factor:
        raise ValueError(f"image size {model.image_size} px is not a multiple of the target encoder's downsampling "
                         f"({factor}x)")


def with_twin_inputs(model: ModelConfig) -> ModelConfig:
    """``model`` on the twin's cameras, proprioception and actions (``ModelConfig``'s defaults): a model built
    without a dataset to take them from."""
    twin = ModelConfig()
    return dataclasses.replace(model, **{name: getattr(twin, name) for name in FROM_DATASET})


def libero_preset() -> TrainConfig:
    """LIBERO: both cameras at 128 px, proprio without the wrapping roll angle (end effector + gripper); the
    twin's other-suites recipe on top: the weight average deployed and the wrist view left unshifted
    (docs/experiments.md#libero-spatial-with-the-twins-weight-average-and-an-unshifted-wrist)."""
    base = TrainConfig()
    model = dataclasses.replace(base.model, image_size=128, proprio_keys=("ee_pos", "gripper_states"))
    return dataclasses.replace(base, model=model, ema_decay=0.999, augment_shift_cameras=model.cameras[:1])


def paper_preset() -> TrainConfig:
    """The paper's scale: an OpenVLA-style VLM with LoRA 32 and a DINOv2 target (local checkpoints given with
    ``--model.backbone.path`` and ``--model.target-encoder.path``), at OpenVLA-OFT's optimiser settings."""
    base = TrainConfig()
    model = dataclasses.replace(
        base.model, image_size=224,
        backbone=BackboneConfig(name="hf", lora_rank=32, lora_alpha=16, gradient_checkpointing=True),
        target_encoder=TargetEncoderConfig(name="dinov2"))
    return dataclasses.replace(base, model=model, lr=5e-5, batch_size=8, grad_accum=4, steps=50_000, warmup=1000)


def so101_preset() -> TrainConfig:
    """The SO-101 (its twin's demonstrations or a LeRobot recording): 80-px cameras read for the cube the
    instruction names (FiLM), joint targets learnt as offsets from the present pose, 8000 steps
    (docs/experiments.md#film-on-the-instruction)."""
    base = TrainConfig()
    model = dataclasses.replace(base.model, image_size=80, relative_actions=True,
                                backbone=dataclasses.replace(base.model.backbone, film=True))
    return dataclasses.replace(base, model=model, steps=8000)


PresetName = Literal["default", "libero", "paper", "so101"]
PRESETS: dict[str, Callable[[], TrainConfig]] = {"default": TrainConfig, "libero": libero_preset,
                                                 "paper": paper_preset, "so101": so101_preset}
