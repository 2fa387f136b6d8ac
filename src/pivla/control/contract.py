"""The policy contract: what executors, the evaluation runner, the robot loop and a remote client may call.

A local :class:`pivla.policy.Policy` and a :class:`pivla.serving.RemotePolicy` both satisfy
:class:`ChunkPolicy`; executors depend on this protocol, never on a concrete class. Nothing here imports
torch, so the control layer runs on a robot laptop that has only NumPy.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any, Protocol, runtime_checkable

import numpy as np

from pivla.data.action_space import EE_DELTA, ActionSpace, pose_key

# An observation's actions in flight: (n, D) physical actions, n <= PolicySpec.action_prefix, that the arm executes
# from this observation's step on while the query is out; the chunk that answers it plans what follows them
ACTION_PREFIX = "action_prefix"

# Eq. 13's weight of U_act in U when nothing was calibrated (docs/method.md, "AURD")
DEFAULT_ETA = 0.7


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


@dataclass(frozen=True)
class PolicySpec:
    """What a policy reads and returns, enough for a client to build observations without its files.

    ``cameras``: image keys, each an (image_size, image_size, 3) uint8 picture (other sizes are resized);
    ``proprio``: proprioceptive keys with their lengths; an ``instruction`` string completes an observation.
    ``action_space``: what each of the D numbers of an action row means (the training data's).
    """

    cameras: tuple[str, ...]
    image_size: int
    proprio: tuple[tuple[str, int], ...]
    chunk: int  # K, actions per plan
    horizon: int  # H, AURD's nominal horizon and the value head's length
    action_space: ActionSpace = EE_DELTA
    latent_dim: int = 0
    target_cameras: int = 1  # leading cameras the target encoder reads (AURD's observed latent)
    target_proprio: bool = False  # the target latent reads the proprio keys too
    action_prefix: int = 0  # P: actions in flight an observation may carry under ACTION_PREFIX (0: none)
    extra: dict[str, Any] = field(default_factory=dict, hash=False, compare=False)

    @property
    def proprio_keys(self) -> tuple[str, ...]:
        return tuple(k for k, _ in self.proprio)

    @property
    def action_dim(self) -> int:
        return self.action_space.dim

    def present_pose(self, obs: Mapping[str, Any]) -> np.ndarray | None:
        """Where an arm on absolute targets is now, read from an observation: the first proprio key of the
        action's dimension (LeRobot's ``observation.state`` beside ``action``, both ``<joint>.pos``). None for a
        delta action space, which holds by commanding zero motion."""
        key = pose_key(self.proprio, self.action_space)
        return np.asarray(obs[key], np.float32).reshape(-1) if key is not None and key in obs else None

    def to_dict(self) -> dict[str, Any]:
        return {"cameras": list(self.cameras), "image_size": self.image_size,
                "proprio": [[k, n] for k, n in self.proprio], "chunk": self.chunk, "horizon": self.horizon,
                "action_dim": self.action_dim, "action_space": self.action_space.to_dict(),
                "latent_dim": self.latent_dim,
                "target_cameras": self.target_cameras, "target_proprio": self.target_proprio,
                "action_prefix": self.action_prefix, "extra": dict(self.extra)}

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> PolicySpec:
        return cls(cameras=tuple(d["cameras"]), image_size=int(d["image_size"]),
                   proprio=tuple((str(k), int(n)) for k, n in d["proprio"]), chunk=int(d["chunk"]),
                   horizon=int(d["horizon"]), action_space=_action_space(d.get("action_space")),
                   latent_dim=int(d.get("latent_dim", 0)),
                   target_cameras=int(d.get("target_cameras", 1)), target_proprio=bool(d.get("target_proprio", False)),
                   action_prefix=int(d.get("action_prefix", 0)), extra=dict(d.get("extra", {})))


def action_prefix_of(obs: Mapping[str, Any], spec: PolicySpec) -> np.ndarray | None:
    """An observation's actions in flight as an (n, D) float32 array (None when it carries none, or n = 0); a
    ValueError naming the problem for a policy that reads none, a wrong shape, more than P of them or NaN."""
    if ACTION_PREFIX not in obs:
        return None
    if spec.action_prefix == 0:
        raise ValueError(f"observation carries {ACTION_PREFIX!r}, and this policy was not trained to read actions "
                         "in flight (its action_prefix is 0)")
    try:
        arr = np.asarray(obs[ACTION_PREFIX], dtype=np.float64)
    except (TypeError, ValueError):
        raise ValueError(f"observation {ACTION_PREFIX!r} must be an (n, {spec.action_dim}) array of numbers") from None
    if arr.size == 0:
        return None
    if arr.ndim != 2 or arr.shape[1] != spec.action_dim:
        raise ValueError(f"observation {ACTION_PREFIX!r} must be (n, {spec.action_dim}) actions, got {arr.shape}")
    if len(arr) > spec.action_prefix:
        raise ValueError(f"observation {ACTION_PREFIX!r} holds {len(arr)} actions; this policy reads at most "
                         f"{spec.action_prefix}")
    if not np.isfinite(arr).all():
        raise ValueError(f"observation {ACTION_PREFIX!r} contains NaN or inf")
    return arr.astype(np.float32)


def _action_space(value: Any) -> ActionSpace:
    """A spec's action space; servers written before it existed sent a name for the twin's (or nothing)."""
    return ActionSpace.from_dict(value) if isinstance(value, Mapping) else EE_DELTA


@runtime_checkable
class ChunkPolicy(Protocol):
    """A chunking policy as the control loop sees it.

    ``infer(obs)`` returns at least: ``actions`` (K, D) physical, ``actions_normalized`` (K, D), ``u_act``
    (K,) (Eq. 13), ``latents`` (K, d_z) predicted next-observation latents, ``values`` (H,).
    ``encode(obs)`` is Enc(o), the target encoder's latent of one observation in the units of ``latents``.
    ``to_actions`` maps normalized actions to physical ones (temporal ensembling averages in normalized space).
    """

    spec: PolicySpec
    calibration: Calibration | None

    def infer(self, obs: Mapping[str, Any]) -> dict[str, np.ndarray]: ...

    def encode(self, obs: Mapping[str, Any]) -> np.ndarray: ...

    def to_actions(self, normalized: np.ndarray) -> np.ndarray: ...


@runtime_checkable
class BatchPolicy(ChunkPolicy, Protocol):
    """A policy that also answers in batches (calibration replays whole validation episodes)."""

    def infer_batch(self, obs_list: Sequence[Mapping[str, Any]]) -> dict[str, np.ndarray]: ...

    def encode_batch(self, obs_list: Sequence[Mapping[str, Any]]) -> np.ndarray: ...
