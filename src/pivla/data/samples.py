"""From episodes to training samples: chunk targets with padding masks, next-observation targets,
episode-level splits and the advantage table of the RL term.

Everything random is drawn from generators seeded by (seed, step, rank), so a batch is a pure function of
the step: resuming a run replays exactly the batches an uninterrupted run would have seen.
"""

from __future__ import annotations

import dataclasses
import functools
import tempfile
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from pivla.data.action_space import EE_DELTA, ActionSpace, pose_key
from pivla.data.episode import DatasetError, DatasetLayout, Episode
from pivla.data.normalize import ActionStats, NormStats, StandardStats
from pivla.data.text import WordTokenizer
from pivla.data.transforms import NormalizeActions, input_pipeline, proprio_vector
from pivla.model.config import ModelConfig


def split_episodes(episodes: list[Episode], val_fraction: float, seed: int) -> tuple[list[int], list[int]]:
    """Episode-level split (never frames of one episode on both sides), stratified by instruction so
    every task is represented in validation when it has at least two episodes."""
    rng = np.random.default_rng(seed)
    by_task: dict[str, list[int]] = {}
    for i, ep in enumerate(episodes):
        by_task.setdefault(ep.instruction, []).append(i)
    train, val = [], []
    for idx in by_task.values():
        idx = list(rng.permutation(idx))
        n_val = round(len(idx) * val_fraction) if len(idx) > 1 else 0
        if val_fraction > 0 and len(idx) > 1:
            n_val = max(n_val, 1)
        val += idx[:n_val]
        train += idx[n_val:]
    return sorted(train), sorted(val)


def resolve_inputs(cfg: ModelConfig, layout: DatasetLayout, where: str) -> ModelConfig:
    """``cfg`` with what it leaves empty taken from the dataset at ``where`` (its cameras, proprio keys, and the
    lengths of proprio and actions), and what it names checked against the dataset, before any training."""
    space = layout.action_space
    if cfg.action_dim not in (0, space.dim):
        raise DatasetError(f"{where}: the dataset's actions are {space.describe()}, the model config's action_dim "
                           f"is {cfg.action_dim}")
    cameras = tuple(cfg.cameras) or layout.cameras
    keys = tuple(cfg.proprio_keys) or layout.proprio
    if not cameras:
        raise DatasetError(f"{where}: the dataset has no camera (no (T, H, W, 3) uint8 observation)")
    missing = [c for c in cameras if c not in layout.cameras]
    if missing:
        raise DatasetError(f"{where}: no camera(s) {missing} (the dataset has {list(layout.cameras)})")
    missing = [k for k in keys if k not in layout.vectors]
    if missing or not keys:
        raise DatasetError(f"{where}: no proprio key(s) {missing or 'chosen'} (the dataset's low-dim keys are "
                           f"{layout.vectors}); name them with --model.proprio-keys")
    proprio_dim = sum(layout.vectors[k] for k in keys)
    if cfg.proprio_dim not in (0, proprio_dim):
        raise DatasetError(f"{where}: proprio keys {list(keys)} give {proprio_dim} dims, the model config says "
                           f"{cfg.proprio_dim}")
    return dataclasses.replace(cfg, cameras=cameras, proprio_keys=keys, proprio_dim=proprio_dim,
                               action_dim=space.dim)


def fit_norm_stats(episodes: list[Episode], cfg: ModelConfig, space: ActionSpace = EE_DELTA) -> NormStats:
    """The training set's statistics, with the action space they normalise (and, for ``cfg.relative_actions``,
    the statistics of the chunk offsets the heads learn)."""
    actions = np.concatenate([ep.actions for ep in episodes])
    proprio = np.concatenate([proprio_vector(ep.obs, cfg.proprio_keys) for ep in episodes])
    if proprio.shape[-1] != cfg.proprio_dim:
        raise DatasetError(f"proprio keys {cfg.proprio_keys} give {proprio.shape[-1]} dims, "
                           f"config says {cfg.proprio_dim}")
    layout = [(k, int(np.asarray(episodes[0].obs[k]).shape[-1])) for k in cfg.proprio_keys]
    stats = NormStats(action=ActionStats.fit(actions, space, full_range=space.kind.absolute),
                      proprio=StandardStats.fit(proprio), proprio_layout=layout, action_space=space)
    if not cfg.relative_actions:
        return stats
    if not space.kind.absolute:
        raise DatasetError(f"relative actions are offsets from the present pose: the dataset's actions are "
                           f"{space.describe()}, not absolute targets")
    reference = pose_key(layout, space)
    if reference is None:
        raise DatasetError(f"relative actions need the present pose among the proprio keys: none of {layout} has the "
                           f"actions' {space.dim} dimensions")
    stats = dataclasses.replace(stats, reference=reference)
    offsets = [chunk_offsets(ep.actions, ep.obs[reference], cfg.chunk, stats.relative_dims()) for ep in episodes]
    return dataclasses.replace(stats, target=ActionStats.fit(np.concatenate([o[m] for o, m in offsets]), space))


def chunk_offsets(actions: np.ndarray, pose: np.ndarray, chunk: int, dims: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Every step's chunk of targets (T, K, D), ``dims`` as offsets from the pose at the chunk's first step (the
    rest as they are), past the episode's end repeating its last action; and which steps are inside it (T, K)."""
    T = len(actions)
    steps = np.arange(T)[:, None] + np.arange(chunk)[None]
    out = np.asarray(actions, np.float32)[np.minimum(steps, T - 1)]
    out[..., dims] -= np.asarray(pose, np.float32)[:, None, dims]
    return out, steps < T


@dataclass
class PreparedEpisode:
    images: np.ndarray  # (T, n_cam, S, S, 3) uint8
    proprio: np.ndarray  # (T, P) normalized
    actions: np.ndarray  # (T, D) normalized to [-1, 1]; a relative policy's: each step's chunk, (T, K, D)
    bins: np.ndarray  # int64, the shape of ``actions``
    rewards: np.ndarray
    dones: np.ndarray
    text_ids: np.ndarray
    text_mask: np.ndarray
    imitate: bool  # only successful episodes feed the imitation terms; failures teach the value head


def prepare_episode(ep: Episode, cfg: ModelConfig, stats: NormStats, text: WordTokenizer) -> PreparedEpisode:
    """An episode through the same input pipeline the policy applies at inference, plus the action targets."""
    try:
        lengths = None if stats.proprio_layout is None else [n for _, n in stats.proprio_layout]
        obs = input_pipeline(cfg, stats.proprio, text, lengths)({**ep.obs, "instruction": ep.instruction})
        if stats.target is None:
            targets = NormalizeActions(stats.action, cfg.n_bins)({"actions": ep.actions})
        else:
            offsets, _ = chunk_offsets(ep.actions, ep.obs[stats.reference], cfg.chunk, stats.relative_dims())
            targets = NormalizeActions(stats.target, cfg.n_bins)({"actions": offsets})
    except DatasetError as e:
        raise DatasetError(f"episode {ep.instruction!r}: {e}") from None
    return PreparedEpisode(
        images=obs["images"],
        proprio=obs["proprio"],
        actions=targets["actions"],
        bins=targets["bins"],
        rewards=ep.rewards.astype(np.float32),
        dones=ep.dones.astype(np.float32),
        text_ids=obs["text_ids"],
        text_mask=obs["text_mask"],
        imitate=bool(ep.success),
    )


def image_store(frames: int, cfg: ModelConfig, directory: Path | None = None) -> np.ndarray:
    """One uint8 array for the pictures of ``frames`` time steps, (frames, n_cam, S, S, 3): in memory, or with a
    ``directory`` in an unnamed file there that the OS pages in and out, for datasets larger than the RAM (the
    file is gone when the array is, even after a crash)."""
    shape = (frames, len(cfg.cameras), cfg.image_size, cfg.image_size, 3)
    if directory is None:
        return np.empty(shape, np.uint8)
    directory.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryFile(dir=directory) as f:
        return np.memmap(f, np.uint8, "w+", shape=shape)


def prepare_episodes(episodes: Iterable[Episode], lengths: Sequence[int], cfg: ModelConfig, stats: NormStats,
                     text: WordTokenizer, store: np.ndarray) -> list[PreparedEpisode]:
    """``prepare_episode`` for a stream of episodes, each one's pictures moved into ``store`` (``image_store``
    for ``sum(lengths)`` frames), so that no more than one episode is held twice. ``lengths`` are the episodes'
    step counts, read beforehand without pictures."""
    out: list[PreparedEpisode] = []
    start = 0
    for i, ep in enumerate(episodes):
        if i >= len(lengths):
            raise DatasetError(f"more than the {len(lengths)} episodes read before (the dataset was written meanwhile)")
        if len(ep.actions) != lengths[i]:
            raise DatasetError(f"episode {i} changed while it was read (the dataset was written meanwhile)")
        prepared = prepare_episode(ep, cfg, stats, text)
        view = store[start : start + lengths[i]]
        view[:] = prepared.images
        out.append(dataclasses.replace(prepared, images=view))
        start += lengths[i]
    if len(out) != len(lengths):
        raise DatasetError(f"{len(out)} episodes read where there were {len(lengths)} "
                           "(the dataset was written meanwhile)")
    return out


def gae(rewards: np.ndarray, values: np.ndarray, dones: np.ndarray, gamma: float, lam: float,
        bootstrap: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """Generalised advantage estimation over one episode (paper Eq. 11).

    delta_t = r_t + gamma * (1 - done_t) * V(s_{t+1}) - V(s_t);  A_t = delta_t + gamma * lam * (1 - done_t) * A_{t+1}.
    ``values`` holds V(s_t) for every step; V after the last step is ``bootstrap`` (0 for an episode that
    ended). Returns (advantages, lambda-returns = advantages + values).
    """
    T = len(rewards)
    adv = np.zeros(T, np.float32)
    next_value, next_adv = bootstrap, 0.0
    for t in range(T - 1, -1, -1):
        nonterminal = 1.0 - float(dones[t])
        delta = rewards[t] + gamma * nonterminal * next_value - values[t]
        next_adv = delta + gamma * lam * nonterminal * next_adv
        adv[t] = next_adv
        next_value = values[t]
    return adv, adv + values.astype(np.float32)


class ChunkDataset:
    """Samples (o_t, l, chunk a_{t:t+K}, next-observation targets, advantages, returns)."""

    def __init__(self, episodes: list[PreparedEpisode], cfg: ModelConfig, sp_steps: int):
        """``sp_steps``: chunk steps per sample whose next observation is an L_SP target (``LossConfig.sp_steps``)."""
        if not episodes:
            raise DatasetError("no episodes to train on")
        self.episodes = episodes
        self.cfg = cfg
        self.sp_steps = sp_steps
        self.index = np.array([(e, t) for e, ep in enumerate(episodes) for t in range(len(ep.actions))], np.int64)
        # RL tables, refreshed by the trainer from the value head; zeros until the first refresh
        self.advantages = [np.zeros(len(ep.actions), np.float32) for ep in episodes]
        self.returns = [np.zeros(len(ep.actions), np.float32) for ep in episodes]

    def __len__(self) -> int:
        return len(self.index)

    def set_values(self, values: list[np.ndarray], gamma: float, lam: float) -> None:
        """Recompute GAE advantages (normalised over the dataset) and lambda-returns from V(s_t) tables."""
        advs, rets = zip(*(gae(ep.rewards, v, ep.dones, gamma, lam) for ep, v in zip(self.episodes, values)))
        flat = np.concatenate(advs)
        mu, sd = flat.mean(), flat.std() + 1e-6
        self.advantages = [((a - mu) / sd).astype(np.float32) for a in advs]
        self.returns = list(rets)

    def observation(self, e: int, t: int) -> dict[str, np.ndarray]:
        ep = self.episodes[e]
        return {"images": ep.images[t], "proprio": ep.proprio[t], "text_ids": ep.text_ids, "text_mask": ep.text_mask}

    def _prefix(self, actions: np.ndarray, valid: np.ndarray, rng: np.random.Generator) -> dict[str, np.ndarray]:
        """With ``action_prefix`` P: the first d actions of the target chunk as the actions in flight, d uniform in
        0..P (0: the chunk as without latency), inside the episode; none without P (the random stream unchanged)."""
        p = self.cfg.action_prefix
        if p == 0:
            return {}
        mask = (np.arange(len(actions)) < rng.integers(0, p + 1)) & valid
        return {"action_prefix": np.where(mask[:, None], actions, 0.0).astype(np.float32),
                "prefix_mask": mask.astype(np.float32)}

    def sample(self, i: int, rng: np.random.Generator) -> dict[str, np.ndarray]:
        e, t = self.index[i]
        ep = self.episodes[e]
        T, K, H = len(ep.actions), self.cfg.chunk, self.cfg.horizon
        steps = np.arange(t, t + K)
        valid = steps < T
        idx = np.minimum(steps, T - 1)
        # values: state after k actions, k = 0..H; valid while t + k <= T - 1 (terminal state value is 0)
        vsteps = np.arange(t, t + H + 1)
        vvalid = vsteps < T
        ret = np.where(vvalid, self.returns[e][np.minimum(vsteps, T - 1)], 0.0).astype(np.float32)
        # next-observation targets for L_SP: a few random chunk steps k (1..K) with o_{t+k} inside the episode
        n_future = min(K, T - 1 - t)
        if n_future > 0:
            ks = rng.choice(np.arange(1, n_future + 1), size=self.sp_steps, replace=n_future < self.sp_steps)
            sp_mask = np.ones(self.sp_steps, np.float32)
        else:
            ks = np.ones(self.sp_steps, np.int64)
            sp_mask = np.zeros(self.sp_steps, np.float32)
        future = np.minimum(t + ks, T - 1)
        chunks = ep.actions.ndim == 3  # a relative policy's targets, one chunk per step
        actions = ep.actions[t] if chunks else ep.actions[idx]
        return {
            **self._prefix(actions, valid, rng),
            **self.observation(e, t),
            "actions": actions,
            "bins": ep.bins[t] if chunks else ep.bins[idx],
            "action_mask": valid.astype(np.float32),
            "imitate": np.float32(ep.imitate),
            "advantages": np.where(valid, self.advantages[e][idx], 0.0).astype(np.float32),
            "returns": ret,
            "value_mask": vvalid.astype(np.float32),
            "sp_index": (ks - 1).astype(np.int64),
            "sp_images": ep.images[future],
            "sp_proprio": ep.proprio[future],
            "sp_mask": sp_mask,
        }


def augment_shift(images: np.ndarray, rng: np.random.Generator, pad: int,
                  cameras: tuple[int, ...] | None = None) -> np.ndarray:
    """Random-shift augmentation (pad by replication, crop back), one shift per image; robust to camera jitter.
    ``images`` (B, cameras, H, W, C); ``cameras``: the indices shifted (None: all), the others left as they are."""
    if pad <= 0:
        return images
    if cameras is not None:
        out = images.copy()
        out[:, list(cameras)] = augment_shift(images[:, list(cameras)], rng, pad)
        return out
    *lead, H, W, C = images.shape
    flat = images.reshape(-1, H, W, C)
    padded = np.pad(flat, ((0, 0), (pad, pad), (pad, pad), (0, 0)), mode="edge")
    dx, dy = rng.integers(0, 2 * pad + 1, size=(2, len(flat)))
    out = np.stack([padded[i, dy[i] : dy[i] + H, dx[i] : dx[i] + W] for i in range(len(flat))])
    return out.reshape(*lead, H, W, C)


def augment_color(images: np.ndarray, rng: np.random.Generator, strength: float) -> np.ndarray:
    """Photometric augmentation per image: brightness, contrast and per-channel gain jitter, so that a
    policy trained in one scene is less tied to its exact colours and lighting (unseen environments)."""
    if strength <= 0:
        return images
    *lead, H, W, C = images.shape
    flat = images.reshape(-1, H, W, C).astype(np.float32)
    n = len(flat)
    bright = rng.uniform(-strength, strength, (n, 1, 1, 1)) * 255
    contrast = rng.uniform(1 - strength, 1 + strength, (n, 1, 1, 1))
    gain = rng.uniform(1 - strength / 2, 1 + strength / 2, (n, 1, 1, C))
    mean = flat.mean(axis=(1, 2, 3), keepdims=True)
    out = ((flat - mean) * contrast + mean) * gain + bright
    return np.clip(out, 0, 255).astype(np.uint8).reshape(*lead, H, W, C)


def collate(samples: list[dict[str, np.ndarray]]) -> dict[str, np.ndarray]:
    return {k: np.stack([s[k] for s in samples]) for k in samples[0]}


def epoch_batch_indices(n: int, batch: int, step: int, seed: int, rank: int = 0, world: int = 1) -> np.ndarray:
    """Indices of the batch a rank sees at ``step``: epoch-wise permutations seeded by (seed, epoch)."""
    start = step * batch * world + rank * batch
    out = np.empty(batch, np.int64)
    for j in range(batch):
        epoch, offset = divmod(start + j, n)
        out[j] = _permutation(n, seed, epoch)[offset]
    return out


def task_balanced_weights(tasks: Sequence[str], lengths: Sequence[int], balance: float) -> np.ndarray:
    """Sampling probability of every frame, episode by episode: proportional to ``n ** -balance``, n the frames of
    its episode's task. 0 draws frames uniformly (a task's share is its share of the frames); 1 draws every
    task equally often, so a task with short demonstrations is not drowned by the others in a multi-task
    policy (docs/experiments.md#equal-task-sampling)."""
    if not 0.0 <= balance <= 1.0:
        raise ValueError(f"task balance must be in [0, 1], got {balance}")
    frames: dict[str, int] = {}
    for task, n in zip(tasks, lengths, strict=True):
        frames[task] = frames.get(task, 0) + n
    w = np.concatenate([np.full(n, float(frames[task]) ** -balance) for task, n in zip(tasks, lengths)])
    return w / w.sum()


def weighted_batch_indices(cdf: np.ndarray, batch: int, step: int, seed: int, rank: int = 0) -> np.ndarray:
    """Indices of the batch a rank sees at ``step``, drawn with replacement from the distribution whose cumulative
    sum is ``cdf``, by a generator seeded by (seed, step, rank): a pure function of the step, as the epoch-wise
    permutations are."""
    u = np.random.default_rng([seed, step, rank, 1]).random(batch) * cdf[-1]
    return np.minimum(np.searchsorted(cdf, u, side="right"), len(cdf) - 1)


@functools.lru_cache(maxsize=4)
def _permutation(n: int, seed: int, epoch: int) -> np.ndarray:
    return np.random.default_rng([seed, epoch]).permutation(n)
