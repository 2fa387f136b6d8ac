"""A trained CMS policy behind the smallest interface: ``infer(obs) -> dict`` (the ``ChunkPolicy`` contract).

``obs`` holds one time step under the dataset's observation key names plus ``instruction``. Inputs go
through the same pipeline as the training data (``pivla.data.transforms.input_pipeline``); outputs through
the steps below (Eq. 12 de-quantization, Eq. 13, head selection, un-normalization), outside the network, with
the statistics saved in the run.
"""

from __future__ import annotations

import dataclasses
import logging
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch

from pivla.control.contract import Calibration, PolicySpec, action_prefix_of
from pivla.control.math import action_uncertainty, dequantize
from pivla.data.normalize import ActionStats, NormStats
from pivla.data.text import WordTokenizer, load_text_tokenizer
from pivla.data.transforms import (
    compose,
    images_to_tensor,
    input_pipeline,
    proprio_steps,
    proprio_vector,
)
from pivla.model import encoder_runtime as er
from pivla.model.backbone import ConvEncoder
from pivla.model.cms import CMSModel, CMSOutput, proprio_latent
from pivla.model.device import select_device
from pivla.model.onnx_encoder import ObservationEncoder
from pivla.model.pixels import check_image, resize_images
from pivla.training import checkpoint as ck

log = logging.getLogger(__name__)

__all__ = ["Calibration", "Policy", "RunEnsemble", "load_policy"]


# -- output steps ----------------------------------------------------------------------------------------------
def head_outputs(out: CMSOutput, bin_centers: torch.Tensor) -> dict[str, np.ndarray]:
    """The model's heads as arrays: discrete probabilities, the continuous chunk clamped to the action range,
    its Eq. 12 de-quantization (computed on the model's device), latents and values."""
    probs = torch.softmax(out.logits.float(), dim=-1)
    return {
        "continuous_normalized": out.continuous.float().clamp(-1, 1).cpu().numpy(),
        "dequantized": dequantize(probs, bin_centers).cpu().numpy(),
        "discrete_probs": probs.cpu().numpy(),
        "latents": out.latents.float().cpu().numpy(),
        "values": out.values.float().cpu().numpy(),
        "value_now": out.value_now.float().cpu().numpy(),
    }


def select_heads(heads: Mapping[str, np.ndarray], action_head: str, gripper_head: str, both_heads: bool,
                 gripper: int | None) -> dict[str, np.ndarray]:
    """The executed chunk ``actions_normalized``: the arm from ``action_head``, the gripper (dimension
    ``gripper``, None for none) from ``gripper_head``; and ``u_act`` (Eq. 13), zero for a one-head policy."""
    cont, deq = heads["continuous_normalized"], heads["dequantized"]
    primary = (cont if action_head == "continuous" else deq).copy()
    if gripper is not None:
        primary[..., gripper] = (cont if gripper_head == "continuous" else deq)[..., gripper]
    u_act = action_uncertainty(cont, deq) if both_heads else np.zeros(cont.shape[:2])
    return {**heads, "actions_normalized": primary, "u_act": u_act}


def unnormalize_actions(outputs: Mapping[str, np.ndarray], stats: ActionStats) -> dict[str, np.ndarray]:
    """Physical ``actions`` from ``actions_normalized`` with the training set's statistics."""
    return {**outputs, "actions": stats.unnormalize(outputs["actions_normalized"])}


class Policy:
    """A local CMS policy (the ``ChunkPolicy`` and ``BatchPolicy`` contracts)."""

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
        if stats.space.dim != self.cfg.action_dim:
            raise ValueError(f"the statistics' actions are {stats.space.describe()}, the model's D is "
                             f"{self.cfg.action_dim}")
        self.spec = PolicySpec(
            cameras=tuple(self.cfg.cameras), image_size=self.cfg.image_size,
            proprio=_proprio_lengths(stats, self.cfg.proprio_keys),
            chunk=self.cfg.chunk, horizon=self.cfg.horizon, action_space=stats.space,
            latent_dim=model.latent_dim, target_cameras=model.target.cameras, target_proprio=model.target.proprio > 0,
            action_prefix=self.cfg.action_prefix)
        lengths = [n for _, n in self.spec.proprio]
        self._inputs = input_pipeline(self.cfg, stats.proprio, text, lengths)
        self._proprio = compose(proprio_steps(self.cfg, stats.proprio, lengths))
        # which head's actions are executed: the continuous one, unless the run trained only the discrete one
        self.action_head = action_head
        # U_act (Eq. 13) is the disagreement of two trained heads; a one-head ablation has none, and comparing
        # with the untrained head would feed AURD noise
        self.both_heads = both_heads
        # The twin's gripper (open -1 / closed +1) is a binary decision taken at a few
        # moments of an episode. The cross-entropy of the discrete head learns those moments; the SmoothL1 of
        # the continuous head can miss them (docs/experiments.md#gripper-from-the-discrete-head). So with two
        # trained heads the gripper follows Eq. 12 and the arm the continuous head.
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
        self._onnx_encoder, self._observation_encoder, self.encoder_runtime = None, None, "torch"
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
        self._observation_encoder = ObservationEncoder(self._onnx_encoder, self.cfg.cameras[: target.cameras],
                                                       self.cfg.image_size, target.downsample)
        self.encoder_runtime = "onnx"

    @property
    def target_graph(self) -> bytes | None:
        """The target encoder as the ONNX graph ``encode`` runs (None on PyTorch): what a server hands a
        client so that AURD's per-step encoding runs next to the robot."""
        return self._onnx_encoder.model_bytes if self._onnx_encoder is not None else None

    # -- inference -------------------------------------------------------------------------------------
    def model_inputs(self, obs_list: Sequence[Mapping[str, Any]]) -> dict[str, torch.Tensor]:
        """Observations through the input pipeline, batched as tensors on the policy's device."""
        samples = [self._inputs(obs) for obs in obs_list]
        inputs = {
            "images": images_to_tensor(np.stack([s["images"] for s in samples]), self.device),
            "text_ids": torch.from_numpy(np.stack([s["text_ids"] for s in samples])).to(self.device),
            "text_mask": torch.from_numpy(np.stack([s["text_mask"] for s in samples])).to(self.device),
            "proprio": torch.from_numpy(np.stack([s["proprio"] for s in samples])).to(self.device),
        }
        prefixes = [action_prefix_of(obs, self.spec) for obs in obs_list]
        if any(p is not None for p in prefixes):
            inputs.update({k: torch.from_numpy(v).to(self.device) for k, v in self._prefix_inputs(prefixes).items()})
        return inputs

    def _prefix_inputs(self, prefixes: Sequence[np.ndarray | None]) -> dict[str, np.ndarray]:
        """Each observation's actions in flight, normalised like the training targets, as the model's
        ``action_prefix`` (N, K, D) and ``prefix_mask`` (N, K)."""
        k, d = self.cfg.chunk, self.spec.action_dim
        actions, mask = np.zeros((len(prefixes), k, d), np.float32), np.zeros((len(prefixes), k), np.float32)
        for i, p in enumerate(prefixes):
            if p is not None:
                actions[i, : len(p)] = self.stats.action.normalize(p)
                mask[i, : len(p)] = 1
        return {"action_prefix": actions, "prefix_mask": mask}

    @torch.inference_mode()
    def infer_batch(self, obs_list: Sequence[Mapping[str, Any]]) -> dict[str, np.ndarray]:
        """Batched ``infer``: every output gains a leading batch dimension."""
        inputs = self.model_inputs(obs_list)
        heads = head_outputs(self.model(inputs), self.model.bin_centers)
        selected = select_heads(heads, self.action_head, self.gripper_head, self.both_heads,
                                self.spec.action_space.gripper)
        out = unnormalize_actions(selected, self.stats.action) if self.stats.target is None else \
            self._absolute(selected, obs_list)
        if not np.isfinite(out["actions"]).all():  # a finite input so far out of range that the network overflows
            raise ValueError("the policy computed non-finite actions from this observation (largest normalized "
                             f"proprio value {float(inputs['proprio'].abs().max()):.3g}; the training data's lie "
                             "within a few units)")
        return out

    def _absolute(self, outputs: Mapping[str, np.ndarray],
                  obs_list: Sequence[Mapping[str, Any]]) -> dict[str, np.ndarray]:
        """A relative policy's chunk as the absolute targets it exchanges: its offsets added to the present pose of
        each observation, within the training data's range; ``actions_normalized`` in the absolute statistics, so
        that ``to_actions`` (and temporal ensembling) read them as any policy's."""
        key, dim = self.stats.reference, self.spec.action_dim
        pose = np.stack([proprio_vector(obs, (key,), (dim,)) for obs in obs_list])
        normalized = self.stats.action.normalize(self.stats.to_absolute(outputs["actions_normalized"], pose))
        return {**outputs, "actions_normalized": normalized, "actions": self.stats.action.unnormalize(normalized)}

    def infer(self, obs: Mapping[str, Any]) -> dict[str, np.ndarray]:
        """One observation -> actions (K,D) un-normalised from the primary head (the gripper from
        ``gripper_head``), in the units of ``spec.action_space``; actions_normalized (K,D), continuous_normalized
        and dequantized (K,D) (both heads, normalized; Eq. 12 for the latter), u_act (K,) (Eq. 13; zero for a
        policy trained with one head), discrete_probs (K,D,256), latents (K,d_z) predicted next-observation
        latents, values (H,), value_now ()."""
        return {k: v[0] for k, v in self.infer_batch([obs]).items()}

    def _target_images(self, obs_list: Sequence[Mapping[str, Any]]) -> np.ndarray:
        """(N, n_target_cameras, S, S, 3) uint8: the leading cameras the target encoder reads, at the model's side."""
        cams = self.cfg.cameras[: self.model.target.cameras]
        return np.stack([np.stack([resize_images(check_image(obs[c], c), self.cfg.image_size) for c in cams])
                         for obs in obs_list])

    def encode_batch(self, obs_list: Sequence[Mapping[str, Any]]) -> np.ndarray:
        """Enc(o) for several observations: (N, d_z) target-encoder latents in the units of ``latents``."""
        if self._onnx_encoder is not None and len(obs_list) == 1:  # AURD's case; batches (calibration) stay in torch
            return self.encode(obs_list[0])[None]
        return self._encode_torch(obs_list)

    def _target_proprio(self, obs_list: Sequence[Mapping[str, Any]]) -> np.ndarray | None:
        """(N, P) normalised proprio when the target latent reads it, else None."""
        if self.model.target.proprio == 0:
            return None
        return np.stack([self._proprio(obs)["proprio"] for obs in obs_list])

    @torch.inference_mode()
    def _encode_torch(self, obs_list: Sequence[Mapping[str, Any]]) -> np.ndarray:
        proprio = self._target_proprio(obs_list)
        return self.model.target(images_to_tensor(self._target_images(obs_list), self.device),
                                 None if proprio is None else torch.from_numpy(proprio).to(self.device)
                                 ).float().cpu().numpy()

    def encode(self, obs: Mapping[str, Any]) -> np.ndarray:
        """Enc(o): the target encoder's latent of one observation (AURD's observed latent), on ONNX Runtime
        when it can (``pivla.model.onnx_encoder.ObservationEncoder``: the pictures' part), else in PyTorch."""
        if self._observation_encoder is None:
            return self._encode_torch([obs])[0]
        z = self._observation_encoder.encode(obs)
        proprio = self._target_proprio([obs])
        if proprio is None:
            return z
        return np.concatenate([z, proprio_latent(proprio[0], self.model.target.proprio)]).astype(np.float32)

    def to_actions(self, normalized: np.ndarray) -> np.ndarray:
        return self.stats.action.unnormalize(normalized)


class RunEnsemble:
    """Several trained runs of one recipe as one policy (the ``ChunkPolicy`` and ``BatchPolicy`` contracts).

    Training runs of the same recipe that differ only in their seed fail on different episodes; the average of
    their chunks fails on fewer (docs/experiments.md#an-ensemble-of-training-runs). Each output is the members'
    mean, in the first member's normalisation: the actions of both heads (a binary gripper's as a soft vote,
    thresholded once), the values; ``u_act`` is Eq. 13 on the averaged heads. AURD's latents and ``encode`` are the
    first member's (``lead``): with every member's side by side, AURD paused its way out of 10 `long` points on
    validation. There is no ``discrete_probs``: the members' bins differ.
    """

    def __init__(self, members: Sequence[Policy], run_dir: Path | None = None, calibration: Calibration | None = None):
        if len(members) < 2:
            raise ValueError(f"an ensemble needs at least two policies, got {len(members)}")
        lead = members[0]
        for i, m in enumerate(members[1:], 1):
            if dataclasses.replace(m.spec, latent_dim=0) != dataclasses.replace(lead.spec, latent_dim=0):
                raise ValueError(f"member {i} reads or returns other things than member 0: {m.spec} against "
                                 f"{lead.spec}")
            if (m.stats.target is None) != (lead.stats.target is None):
                raise ValueError(f"member {i} and member 0 differ in relative_actions")
        self.members, self.lead = list(members), lead
        self.run_dir, self.calibration = run_dir, calibration
        self.stats = lead.stats  # the normalisation of the ensemble's outputs (and of to_actions)
        self.both_heads = all(m.both_heads for m in members)
        self.gripper_head = lead.gripper_head
        self.spec = lead.spec

    @property
    def encoder_runtime(self) -> str:
        return self.lead.encoder_runtime

    def _mean(self, outs: Sequence[Mapping[str, np.ndarray]], key: str, head_space: bool) -> np.ndarray:
        """The members' ``key`` (normalised actions) averaged in the first member's normalisation: the heads'
        targets (``head_space``: the offsets of a relative policy) or the exchanged actions."""
        def space(stats: NormStats) -> ActionStats:
            return (stats.target or stats.action) if head_space else stats.action

        into = space(self.stats)
        return np.mean([into.renormalize(o[key], space(m.stats)) for o, m in zip(outs, self.members)], axis=0)

    def infer_batch(self, obs_list: Sequence[Mapping[str, Any]]) -> dict[str, np.ndarray]:
        outs = [m.infer_batch(obs_list) for m in self.members]
        cont = np.clip(self._mean(outs, "continuous_normalized", True), -1, 1)
        deq = np.clip(self._mean(outs, "dequantized", True), -1, 1)
        normalized = np.clip(self._mean(outs, "actions_normalized", False), -1, 1)
        return {
            "actions_normalized": normalized, "actions": self.stats.action.unnormalize(normalized),
            "continuous_normalized": cont, "dequantized": deq,
            "u_act": action_uncertainty(cont, deq) if self.both_heads else np.zeros(cont.shape[:2]),
            "latents": outs[0]["latents"],
            "values": np.mean([o["values"] for o in outs], axis=0),
            "value_now": np.mean([o["value_now"] for o in outs], axis=0),
        }

    def infer(self, obs: Mapping[str, Any]) -> dict[str, np.ndarray]:
        """``Policy.infer``'s outputs, averaged over the members (see the class), without ``discrete_probs``."""
        return {k: v[0] for k, v in self.infer_batch([obs]).items()}

    def encode_batch(self, obs_list: Sequence[Mapping[str, Any]]) -> np.ndarray:
        return self.lead.encode_batch(obs_list)

    def encode(self, obs: Mapping[str, Any]) -> np.ndarray:
        """The first member's Enc(o) (the units of ``latents``)."""
        return self.lead.encode(obs)

    def to_actions(self, normalized: np.ndarray) -> np.ndarray:
        return self.stats.action.unnormalize(normalized)


def load_policy(run_dir: str | Path, device: str = "auto", threads: int = 0, gripper_head: str | None = None,
                encoder_runtime: str = "auto") -> Policy | RunEnsemble:
    """Load a run directory written by ``pivla train`` (safetensors + JSON only), or an ensemble of runs written
    by ``pivla ensemble-runs``. ``gripper_head``: which head drives the gripper (default: the discrete one when both
    were trained, see ``Policy``); ``encoder_runtime``: where the target encoder runs (``auto``: ONNX Runtime on
    a CPU when possible, see ``Policy``)."""
    run_dir = Path(run_dir)
    if threads > 0:
        torch.set_num_threads(threads)
    calib = None
    if (run_dir / ck.CALIBRATION_FILE).exists():
        calib = Calibration(**ck.read_json(run_dir / ck.CALIBRATION_FILE))
    members = ck.run_ensemble_members(run_dir)
    if members is not None:
        return RunEnsemble([load_policy(m, device, 0, gripper_head, encoder_runtime) for m in members],
                              run_dir, calib)
    cfg = ck.read_run_config(run_dir)
    stats = NormStats.from_dict(ck.read_json(run_dir / ck.STATS_FILE))
    text = load_text_tokenizer(ck.read_json(run_dir / ck.TOKENIZER_FILE))
    dev = select_device(device)
    model = CMSModel(cfg.model, len(text.vocab))
    state = ck.load_tensors(run_dir / ck.MODEL_FILE)
    model.load_checkpoint_state(state, str(run_dir / ck.MODEL_FILE))
    head = "continuous" if cfg.loss.use_continuous else "discrete"
    both = cfg.loss.use_continuous and cfg.loss.use_discrete
    return Policy(model.to(dev), stats, text, run_dir, calib, dev, action_head=head, both_heads=both,
                  gripper_head=gripper_head, encoder_runtime=encoder_runtime)



def _proprio_lengths(stats: NormStats, keys: Sequence[str]) -> tuple[tuple[str, int], ...]:
    """Each proprio key with its length, as the training data had them (-1: unknown, in runs written before
    the layout was stored, except for a single key)."""
    if stats.proprio_layout is not None:
        return tuple((k, n) for k, n in stats.proprio_layout)
    if len(keys) == 1:
        return ((keys[0], len(stats.proprio.mean)),)
    return tuple((k, -1) for k in keys)
