"""A trained CMS policy behind the smallest interface: ``infer(obs) -> dict``.

``obs`` holds one time step under the dataset's observation key names plus ``instruction``. Inputs are
normalised and outputs un-normalised here, outside the network, with the statistics saved in the run.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from pivla.control.math import DEFAULT_ETA, action_uncertainty
from pivla.data.dataset import proprio_vector, resize_images
from pivla.data.normalize import NormStats
from pivla.data.text import WordTokenizer, load_text_tokenizer
from pivla.data.transforms import area_downsample, images_to_tensor
from pivla.model import encoder_runtime as er
from pivla.model.backbone import ConvEncoder, centre
from pivla.model.cms import CMSModel
from pivla.training import checkpoint as ck

log = logging.getLogger(__name__)


@dataclass
class Calibration:
    """Executor thresholds calibrated on validation data (never on test episodes): AURD's, and the same
    percentiles of U_act alone for AdaHorizon (None in files written before they existed)."""

    tau_low: float
    tau_high: float
    v_thresh: float
    eta: float = DEFAULT_ETA
    source: str = ""
    act_low: float | None = None  # P(tau_low_pct) of U_act: AdaHorizon extends below it
    act_high: float | None = None  # P(tau_high_pct) of U_act: AdaHorizon replans above it
    pred_baseline: str = "none"  # how U_pred was measured when calibrating; AURD uses the same by default


def select_device(device: str = "auto") -> torch.device:
    if device == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    return torch.device(device)


class Policy:
    def __init__(self, model: CMSModel, stats: NormStats, text: WordTokenizer, run_dir: Path | None = None,
                 calibration: Calibration | None = None, device: torch.device | None = None,
                 action_head: str = "continuous", both_heads: bool = True, gripper_head: str | None = None,
                 encoder_runtime: str = "auto"):
        if gripper_head not in (None, "continuous", "discrete"):
            raise ValueError(f"gripper_head must be 'continuous' or 'discrete', got {gripper_head!r}")
        if gripper_head not in (None, action_head) and not both_heads:
            raise ValueError(f"gripper_head {gripper_head!r}: this policy trained only its {action_head} head")
        self.model = model.eval()
        self.cfg = model.cfg
        self.stats = stats
        self.text = text
        self.run_dir = run_dir
        self.calibration = calibration
        self.device = device or next(model.parameters()).device
        self.bin_centers = model.bin_centers.cpu().numpy()
        self.chunk, self.horizon = self.cfg.chunk, self.cfg.horizon
        # which head's actions are executed: the continuous one, unless the run trained only the discrete one
        self.action_head = action_head
        # U_act (Eq. 13) is the disagreement of two trained heads; a one-head ablation has none, and comparing
        # with the untrained head would feed AURD noise
        self.both_heads = both_heads
        # The gripper (the last action dimension, open -1 / closed +1) is a binary decision taken at a few
        # moments of an episode. The cross-entropy of the discrete head learns those moments; the SmoothL1 of
        # the continuous head can miss them (a policy whose discrete head gave P(open) = 0.95 kept its
        # continuous gripper at +1, set the object down and never let go; docs/results.md, session 6).
        # So with two trained heads the gripper follows Eq. 12 and the arm the continuous head.
        self.gripper_head = gripper_head or ("discrete" if both_heads else action_head)
        # AURD encodes every new observation: on a CPU the default target encoder runs on ONNX Runtime
        # ("auto"), where one encoding takes 0.5-0.7x as long (pivla.model.encoder_runtime); "torch" forces PyTorch
        self.set_encoder_runtime(encoder_runtime)

    def set_encoder_runtime(self, runtime: str) -> None:
        """Where ``encode`` runs the target encoder: "torch", "onnx" (an error if impossible) or "auto" (ONNX
        Runtime when on a CPU with the small backbone's CNN and onnxruntime installed). The runtime in use
        is ``encoder_runtime``."""
        if runtime not in er.RUNTIMES:
            raise ValueError(f"encoder_runtime must be one of {er.RUNTIMES}, got {runtime!r}")
        self._onnx_encoder, self.encoder_runtime = None, "torch"
        if runtime == "torch":
            return
        target = self.model.target
        reason = None
        if self.device.type != "cpu":
            reason = f"the policy runs on {self.device.type}"
        elif not isinstance(target.encoder, ConvEncoder):
            reason = f"only the small backbone's CNN is exported, not {type(target.encoder).__name__}"
        elif not er.onnx_available():
            reason = "onnxruntime, onnx or onnxscript is not installed"
        if reason is None:
            side = self.cfg.image_size // target.downsample
            self._onnx_encoder = er.onnx_target_encoder(er.TargetLatents(target), (target.cameras, 3, side, side),
                                                        self.run_dir)
            reason = None if self._onnx_encoder is not None else "export or check failed (logged above)"
        if reason is not None:
            if runtime == "onnx":
                raise RuntimeError(f"encoder_runtime 'onnx': {reason}")
            log.debug("target encoder on PyTorch: %s", reason)
            return
        self.encoder_runtime = "onnx"

    # -- transforms ------------------------------------------------------------------------------------
    def _check_obs(self, obs: dict) -> None:
        for key in (*self.cfg.cameras, *self.cfg.proprio_keys, "instruction"):
            if key not in obs:
                raise KeyError(f"observation is missing {key!r} (policy needs {list(self.cfg.cameras)} + "
                               f"{list(self.cfg.proprio_keys)} + 'instruction')")
        for key in self.cfg.proprio_keys:
            if not np.all(np.isfinite(np.asarray(obs[key], dtype=np.float64))):
                raise ValueError(f"observation {key!r} contains NaN or inf")

    def _image(self, obs: dict, camera: str) -> np.ndarray:
        """(S, S, 3) uint8 picture of one camera, resized to the model's."""
        im = np.asarray(obs[camera])
        if im.ndim != 3 or im.shape[-1] != 3 or im.dtype != np.uint8:
            raise ValueError(f"observation {camera!r} must be an HxWx3 uint8 image, got {im.shape} {im.dtype}")
        return resize_images(im, self.cfg.image_size)

    def _images(self, obs_list: list[dict], cameras: int | None = None) -> np.ndarray:
        """(N, n_cam, S, S, 3) uint8 of the first ``cameras`` cameras (default all), resized to the model's."""
        return np.stack([np.stack([self._image(obs, c) for c in self.cfg.cameras[:cameras]]) for obs in obs_list])

    def model_inputs(self, obs_list: list[dict]) -> dict[str, torch.Tensor]:
        for obs in obs_list:
            self._check_obs(obs)
        ids, masks = zip(*(self.text.encode(str(o["instruction"])) for o in obs_list))
        proprio = np.stack([self.stats.proprio.normalize(proprio_vector(o, self.cfg.proprio_keys)) for o in obs_list])
        return {
            "images": images_to_tensor(self._images(obs_list), self.device),
            "text_ids": torch.from_numpy(np.stack(ids)).to(self.device),
            "text_mask": torch.from_numpy(np.stack(masks)).to(self.device),
            "proprio": torch.from_numpy(proprio.astype(np.float32)).to(self.device),
        }

    # -- inference -------------------------------------------------------------------------------------
    @torch.inference_mode()
    def infer_batch(self, obs_list: list[dict]) -> dict[str, np.ndarray]:
        """Batched ``infer``: every output gains a leading batch dimension."""
        out = self.model(self.model_inputs(obs_list))
        probs = torch.softmax(out.logits.float(), dim=-1)
        cont = out.continuous.float().clamp(-1, 1).cpu().numpy()
        deq = (probs @ self.model.bin_centers).cpu().numpy()  # Eq. 12
        primary = (cont if self.action_head == "continuous" else deq).copy()
        primary[..., -1] = (cont if self.gripper_head == "continuous" else deq)[..., -1]
        return {
            "actions": self.stats.action.unnormalize(primary),
            "actions_normalized": primary,
            "continuous_normalized": cont,
            "dequantized": deq,
            "u_act": action_uncertainty(cont, deq) if self.both_heads else np.zeros(cont.shape[:2]),
            "discrete_probs": probs.cpu().numpy(),
            "latents": out.latents.float().cpu().numpy(),
            "values": out.values.float().cpu().numpy(),
            "value_now": out.value_now.float().cpu().numpy(),
        }

    def infer(self, obs: dict) -> dict[str, np.ndarray]:
        """One observation -> actions (K,7) un-normalised from the primary head (the gripper from
        ``gripper_head``), actions_normalized (K,7),
        continuous_normalized and dequantized (K,7) (both heads, normalized; Eq. 12 for the latter), u_act (K,)
        (Eq. 13; zero for a policy trained with one head),
        discrete_probs (K,7,256), latents (K,d_z) predicted next-observation latents, values (H,),
        value_now ()."""
        return {k: v[0] for k, v in self.infer_batch([obs]).items()}

    def encode_batch(self, obs_list: list[dict]) -> np.ndarray:
        """Enc(o) for several observations: (N, d_z) target-encoder latents in the units of ``latents``."""
        if self._onnx_encoder is not None and len(obs_list) == 1:  # AURD's case; batches (calibration) stay in torch
            return self.encode(obs_list[0])[None]
        return self._encode_torch(obs_list)

    @torch.inference_mode()
    def _encode_torch(self, obs_list: list[dict]) -> np.ndarray:
        target = self.model.target
        return target(images_to_tensor(self._images(obs_list, target.cameras), self.device)).float().cpu().numpy()

    def encode(self, obs: dict) -> np.ndarray:
        """Enc(o): the target encoder's latent of one observation (AURD's observed latent).

        On ONNX Runtime each camera's picture is area-averaged and centred straight into the graph's bound
        input: AURD encodes every new observation, and the copies and temporaries of the batch path cost
        as much again as the graph itself (docs/results.md, session 19)."""
        if self._onnx_encoder is None:
            return self._encode_torch([obs])[0]
        target, images = self.model.target, self._onnx_encoder.inputs[0]
        for camera, dst in zip(self.cfg.cameras[: target.cameras], images):
            area_downsample(self._image(obs, camera), target.downsample, out=dst)
        centre(images, inplace=True)
        return self._onnx_encoder.run()[0]

    def to_actions(self, normalized: np.ndarray) -> np.ndarray:
        return self.stats.action.unnormalize(normalized)


def load_policy(run_dir: str | Path, device: str = "auto", threads: int = 0, gripper_head: str | None = None,
                encoder_runtime: str = "auto") -> Policy:
    """Load a run directory written by ``pivla train`` (safetensors + JSON only). ``gripper_head``: which head
    drives the gripper (default: the discrete one when both were trained, see ``Policy``); ``encoder_runtime``:
    where the target encoder runs (``auto``: ONNX Runtime on a CPU when possible, see ``Policy``)."""
    run_dir = Path(run_dir)
    if threads > 0:
        torch.set_num_threads(threads)
    cfg = ck.read_run_config(run_dir)
    stats = NormStats.from_dict(ck.read_json(run_dir / ck.STATS_FILE))
    text = load_text_tokenizer(ck.read_json(run_dir / ck.TOKENIZER_FILE))
    dev = select_device(device)
    model = CMSModel(cfg.model, len(text.vocab))
    state = ck.load_tensors(run_dir / ck.MODEL_FILE)
    model.load_checkpoint_state(state, str(run_dir / ck.MODEL_FILE))
    calib = None
    if (run_dir / ck.CALIBRATION_FILE).exists():
        calib = Calibration(**ck.read_json(run_dir / ck.CALIBRATION_FILE))
    head = "continuous" if cfg.loss.use_continuous else "discrete"
    both = cfg.loss.use_continuous and cfg.loss.use_discrete
    return Policy(model.to(dev), stats, text, run_dir, calib, dev, action_head=head, both_heads=both,
                  gripper_head=gripper_head, encoder_runtime=encoder_runtime)
