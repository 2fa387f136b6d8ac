"""Training loop for the CMS model with the unified objective.

One code path for CPU, one GPU and several GPUs or nodes: Accelerate wraps the model (DDP when launched
with ``torchrun`` or ``accelerate launch``; FSDP2 with ``--fsdp true`` or ``accelerate launch --use_fsdp``)
and handles mixed precision. Batches are a pure function of (seed, step, rank), so ``--resume`` replays
exactly what an uninterrupted run would have done. Checkpoints always hold full tensors, so a run trained
under FSDP loads and resumes like any other.
"""

from __future__ import annotations

import contextlib
import dataclasses
import logging
import math
import os
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import torch
from accelerate import Accelerator
from accelerate.state import PartialState
from accelerate.utils import (
    DistributedType,
    FullyShardedDataParallelPlugin,
    broadcast_object_list,
    parse_flag_from_env,
)
from torch import nn
from torch.distributed.tensor import DTensor, distribute_tensor
from torch.utils.tensorboard import SummaryWriter
from tqdm import tqdm

from pivla import config as cfgmod
from pivla.data.episode import DatasetError, DatasetLayout, Episode
from pivla.data.normalize import NormStats
from pivla.data.read import dataset_layout, iter_dataset
from pivla.data.samples import (
    ChunkDataset,
    augment_color,
    augment_shift,
    collate,
    epoch_batch_indices,
    fit_norm_stats,
    image_store,
    prepare_episodes,
    resolve_inputs,
    split_episodes,
    task_balanced_weights,
    weighted_batch_indices,
)
from pivla.data.text import build_text_tokenizer, load_text_tokenizer
from pivla.data.transforms import batch_to_tensors
from pivla.model.cms import CMSModel
from pivla.training import checkpoint as ck
from pivla.training.average import WeightAverage
from pivla.training.config import TrainConfig
from pivla.training.losses import unified_loss

log = logging.getLogger(__name__)


def lr_lambda(step: int, cfg: TrainConfig) -> float:
    """Linear warm-up, then cosine decay to ``min_lr_ratio`` of the peak."""
    warmup = cfg.warmup_steps
    if step < warmup:
        return (step + 1) / max(warmup, 1)
    progress = min(1.0, (step - warmup) / max(cfg.steps - warmup, 1))
    return cfg.min_lr_ratio + (1 - cfg.min_lr_ratio) * 0.5 * (1 + math.cos(math.pi * progress))


def _fsdp_plugin(cfg: TrainConfig):
    """FSDP2 from ``--fsdp true`` or from ``accelerate launch --use_fsdp`` (the plugin reads the other FSDP_*
    settings from the environment). FSDP1 is refused: it replaces parameters by flat shards, and the trainer
    calls the unwrapped model (loss terms, validation, the EMA target) outside the wrapper."""
    if not (cfg.fsdp or parse_flag_from_env("ACCELERATE_USE_FSDP")):
        return None
    version = 2 if cfg.fsdp else int(os.environ.get("FSDP_VERSION", "1"))  # Accelerate's default is 1
    if version != 2:
        raise ValueError(f"FSDP version {version} is not supported: launch with --fsdp_version 2 or pass --fsdp true")
    # transformer blocks become their own FSDP units (names filled in by the Trainer), unless the launcher chose
    policy = None if "FSDP_AUTO_WRAP_POLICY" in os.environ else "transformer_based_wrap"
    # Every rank builds the whole model from local files, so rank-0-only loading (on by default in
    # `accelerate launch`) saves nothing, and its loader assumes a transformers model (it fails on CMSModel).
    return FullyShardedDataParallelPlugin(fsdp_version=2, auto_wrap_policy=policy, cpu_ram_efficient_loading=False)


def _accelerator(cfg: TrainConfig):
    use_cpu = cfg.device == "cpu" or (cfg.device == "auto" and not torch.cuda.is_available())
    mp = cfg.mixed_precision
    if mp == "auto":
        mp = "bf16" if (not use_cpu and torch.cuda.is_bf16_supported()) else "no"
    plugin = _fsdp_plugin(cfg)
    acc = Accelerator(cpu=use_cpu, mixed_precision=mp, fsdp_plugin=plugin)
    if plugin is not None and acc.distributed_type == DistributedType.MULTI_CPU:
        # Accelerate enables FSDP only on accelerator backends and would silently run DDP here, but torch's
        # fully_shard works with gloo: switch the shared state exactly as AcceleratorState does on GPUs.
        if mp != "no":
            plugin.set_mixed_precision(mp)
        acc.state.fsdp_plugin = plugin
        acc.state.distributed_type = PartialState._shared_state["distributed_type"] = DistributedType.FSDP
    if plugin is not None and acc.distributed_type != DistributedType.FSDP:
        log.warning("FSDP requested, but Accelerate runs %s (a single process?): training without sharding",
                    acc.distributed_type)
    return acc


def _fsdp_blocks(model: nn.Module) -> list[str]:
    """Classes that get their own FSDP unit, so that only one block's weights are gathered at a time: what
    Hugging Face models declare in ``_no_split_modules``, and the small backbone's transformer layers."""
    present = {type(m).__name__ for m in model.modules()}
    names = {n for m in model.modules() for n in getattr(m, "_no_split_modules", None) or ()}
    names |= {type(m).__name__ for m in model.modules() if isinstance(m, nn.TransformerEncoderLayer)}
    return sorted(names & present)


def _shard_like(value, param: torch.Tensor):
    """This rank's part of a full tensor shaped like an FSDP-sharded parameter, laid out like it (no traffic)."""
    if isinstance(param, DTensor) and torch.is_tensor(value) and value.shape == param.shape:
        return distribute_tensor(value.to(param.device), param.device_mesh, param.placements, src_data_rank=None)
    return value


def _full(tensors: dict) -> dict:
    """Gather FSDP shards (DTensors) into full CPU tensors; a collective, so every rank calls it in the same order."""
    return {k: v.full_tensor().cpu() if isinstance(v, DTensor) else v for k, v in tensors.items()}


def training_episodes(cfg: TrainConfig, obs_keys: tuple[str, ...] | None = None) -> Iterator[Episode]:
    """The episodes of ``--data`` then of each ``--extra-data``, one at a time, with only ``obs_keys`` when given."""
    if not cfg.data:
        raise DatasetError("no dataset given (--data DIR)")
    for root in (cfg.data, *cfg.extra_data):
        yield from iter_dataset(root, obs_keys)


def training_layout(cfg: TrainConfig, stats: NormStats | None = None) -> DatasetLayout:
    """The layout of ``--data``, after refusing any ``--extra-data`` (or, with a resumed run's ``stats``, any
    dataset) whose actions are not the policy's, by name, before anything is loaded."""
    if not cfg.data:
        raise DatasetError("no dataset given (--data DIR)")
    layout = dataset_layout(cfg.data)
    if stats is not None:
        stats.space.check_same(layout.action_space, f"--data {cfg.data}")
    for root in cfg.extra_data:
        layout.action_space.check_same(dataset_layout(root).action_space, f"--extra-data {root}")
    return layout


def images_on_disk(cfg: TrainConfig, frames: int, local_processes: int = 1) -> bool:
    """``cfg.image_store``, with auto choosing disk when the pictures would fill more than a third of the RAM
    (each of the machine's ``local_processes`` training processes holds its own copy)."""
    if cfg.image_store != "auto":
        return cfg.image_store == "disk"
    size = frames * len(cfg.model.cameras) * cfg.model.image_size ** 2 * 3 * local_processes
    return size > os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES") / 3


def shifted_cameras(cfg: TrainConfig) -> tuple[int, ...] | None:
    """The indices of ``cfg.augment_shift_cameras`` among the model's cameras (None: all), refused at once when
    one is not a camera the model reads."""
    if not cfg.augment_shift_cameras:
        return None
    unknown = [c for c in cfg.augment_shift_cameras if c not in cfg.model.cameras]
    if unknown:
        raise ValueError(f"--augment-shift-cameras {' '.join(unknown)}: not among the model's cameras "
                         f"{', '.join(cfg.model.cameras)}")
    return tuple(cfg.model.cameras.index(c) for c in cfg.augment_shift_cameras)


class Trainer:
    """Holds the state of one run; ``run()`` trains to ``cfg.steps`` and returns the run directory."""

    def __init__(self, cfg: TrainConfig, resume: bool = False):
        self.run_dir = Path(cfg.out)
        resumed = resume and (self.run_dir / ck.STATS_FILE).exists()
        stats = NormStats.from_dict(ck.read_json(self.run_dir / ck.STATS_FILE)) if resumed else None
        # the model's cameras, proprioception and action dimension: the dataset's unless the config names them
        layout = training_layout(cfg, stats)
        cfg = self.cfg = dataclasses.replace(cfg, model=resolve_inputs(cfg.model, layout, cfg.data))
        self.shift_cameras = shifted_cameras(cfg)
        if cfg.threads > 0:
            torch.set_num_threads(cfg.threads)
        self.acc = _accelerator(cfg)
        self.device = self.acc.device
        torch.manual_seed(cfg.seed)
        # Split, statistics and vocabulary from the episodes without their pictures; the pictures are then
        # streamed into one store, so that a dataset is never held twice (it may not fit even once).
        episodes = list(training_episodes(cfg, tuple(cfg.model.proprio_keys)))
        train_idx, val_idx = split_episodes(episodes, cfg.val_fraction, cfg.seed)
        train_eps = [episodes[i] for i in train_idx]
        if stats is not None:
            self.stats = stats
            self.text = load_text_tokenizer(ck.read_json(self.run_dir / ck.TOKENIZER_FILE))
        else:
            self.stats = fit_norm_stats(train_eps, cfg.model, layout.action_space)
            self.text = build_text_tokenizer(cfg.model.backbone.name, [ep.instruction for ep in train_eps],
                                             cfg.model.max_text_len, cfg.model.backbone.path)
        # frames drawn by task weight (None: the epoch-wise permutations, every frame once per epoch); computed
        # before any picture is loaded, so a bad --task-balance is refused at once
        self.train_cdf = None if cfg.task_balance == 0 else np.cumsum(task_balanced_weights(
            [ep.instruction for ep in train_eps], [len(ep.actions) for ep in train_eps], cfg.task_balance))
        lengths = [len(ep.actions) for ep in episodes]
        local = int(os.environ.get("LOCAL_WORLD_SIZE", "1"))  # processes on this machine (torchrun, accelerate launch)
        on_disk = images_on_disk(cfg, sum(lengths), local)
        store = image_store(sum(lengths), cfg.model, self.run_dir if on_disk else None)
        log.info("%d frames of pictures, %.1f GB, held %s", sum(lengths), store.nbytes / 1e9,
                 "in a file the OS pages in" if on_disk else "in memory")
        keys = (*cfg.model.cameras, *cfg.model.proprio_keys)
        prepared = prepare_episodes(training_episodes(cfg, keys), lengths, cfg.model, self.stats, self.text, store)
        self.train_set = ChunkDataset([prepared[i] for i in train_idx], cfg.model, cfg.loss.sp_steps)
        self.val_set = ChunkDataset([prepared[i] for i in val_idx], cfg.model, cfg.loss.sp_steps) if val_idx else None
        self.split = {"train_episodes": [int(i) for i in train_idx], "val_episodes": [int(i) for i in val_idx]}
        self.model = CMSModel(cfg.model, len(self.text.vocab)).to(self.device)
        self.fsdp = self.acc.distributed_type == DistributedType.FSDP
        if self.fsdp:
            self._configure_fsdp()
        if self.fsdp and cfg.ema_decay:
            raise ValueError("--ema-decay is not supported with FSDP: each rank holds only a shard of the weights")
        self.average = WeightAverage(self.model, cfg.ema_decay) if cfg.ema_decay else None
        params = [p for p in self.model.parameters() if p.requires_grad]
        # the fused kernel updates all parameters in one pass (3 against 15 ms a step on 2 CPU cores); FSDP's
        # sharded parameters keep the default per-tensor loop, the one its tests cover
        fused = not self.fsdp and self.device.type in ("cpu", "cuda")
        self.optimizer = torch.optim.AdamW(params, lr=cfg.lr, weight_decay=cfg.weight_decay, fused=fused)
        self.scheduler = torch.optim.lr_scheduler.LambdaLR(self.optimizer, lambda s: lr_lambda(s, cfg))
        self.step = 0
        self.history: list[dict] = []
        self._values: list[np.ndarray] = []  # V(s_t) table behind the current GAE advantages
        self.started = time.time()
        optimizer_state = self._resume() if resume else None
        self.ddp_model, self.optimizer = self.acc.prepare(self.model, self.optimizer)
        if optimizer_state is not None:  # after prepare: under FSDP the optimizer now holds sharded parameters
            self._load_optimizer_state(optimizer_state)
        self.writer = None

    def _configure_fsdp(self) -> None:
        """Refuse what fully_shard cannot shard; transformer blocks become units unless the launcher named classes."""
        scalars = [n for n, p in self.model.named_parameters() if p.dim() == 0]
        if scalars:
            raise ValueError(f"FSDP cannot shard 0-d parameters {scalars}: give them shape (1,)")
        plugin = self.acc.state.fsdp_plugin
        if plugin.transformer_cls_names_to_wrap is None:
            plugin.transformer_cls_names_to_wrap = _fsdp_blocks(self.model)

    # -- state ---------------------------------------------------------------------------------------
    def _resume(self) -> dict | None:
        """Restore everything but the optimizer (before ``prepare``, into the whole model); returns the
        optimizer state, which is loaded after ``prepare``."""
        ckpt = ck.latest_checkpoint(self.run_dir)
        if ckpt is None:
            log.warning("--resume: no checkpoint in %s, starting from scratch", self.run_dir)
            return None
        model_state, opt_state, train_state = ck.load_checkpoint(ckpt)
        self.model.load_checkpoint_state(model_state, str(ckpt))
        if self.average is not None:
            self.average.load(ck.load_average(ckpt), int(train_state.get("average_updates", 0)), str(ckpt))
        self.scheduler.load_state_dict(train_state["scheduler"])
        self.step = int(train_state["step"])
        self.history = train_state.get("history", [])
        torch.set_rng_state(torch.tensor(train_state["torch_rng"], dtype=torch.uint8))
        if "values" in train_state:
            self._set_values([np.asarray(v, np.float32) for v in train_state["values"]])
        log.info("resumed from %s at step %d", ckpt, self.step)
        return opt_state

    def _load_optimizer_state(self, state: dict) -> None:
        """Checkpoints hold full tensors; under FSDP each rank keeps its shard of the moments."""
        if self.fsdp:
            params = [p for group in self.optimizer.param_groups for p in group["params"]]
            state = {**state, "state": {i: {k: _shard_like(v, params[i]) for k, v in s.items()}
                                        for i, s in state["state"].items()}}
        self.optimizer.load_state_dict(state)

    def _save(self, final: bool = False) -> None:
        """Under FSDP every rank takes part (the shards are gathered), and rank 0 writes the same files as DDP."""
        if not (self.fsdp or self.acc.is_main_process):
            return
        state = _full(self.model.state_dict_for_checkpoint())
        opt_state = self.optimizer.state_dict()
        opt_state = {**opt_state, "state": {i: _full(s) for i, s in opt_state["state"].items()}}
        if not self.acc.is_main_process:
            return
        train_state = {
            "scheduler": self.scheduler.state_dict(),
            "torch_rng": torch.get_rng_state().tolist(),
            "history": self.history[-200:],
        }
        if self._values:
            train_state["values"] = [v.tolist() for v in self._values]
        average = None
        if self.average is not None:
            train_state["average_updates"] = self.average.updates
            average = self.average.shadow
        ck.save_checkpoint(self.run_dir, self.step, state, opt_state, train_state, self.cfg.keep_checkpoints,
                           average=average)
        self.write_run_files(state if self.average is None else self.average.averaged(state))
        self._write_status(done=final)

    def write_run_files(self, state: dict[str, torch.Tensor]) -> None:
        """The deployable part of the run directory (what ``load_policy`` reads)."""
        ck.save_tensors(self.run_dir / ck.MODEL_FILE, state, metadata={"format": "pt", "step": str(self.step)})
        ck.atomic_write_json(self.run_dir / ck.CONFIG_FILE, cfgmod.to_dict(self.cfg))
        ck.atomic_write_json(self.run_dir / ck.STATS_FILE, self.stats.to_dict())
        ck.atomic_write_json(self.run_dir / ck.TOKENIZER_FILE, self.text.to_dict())
        ck.atomic_write_json(self.run_dir / "split.json", self.split)

    def _write_status(self, done: bool) -> None:
        ck.atomic_write_json(self.run_dir / ck.STATUS_FILE, {
            "step": self.step, "steps": self.cfg.steps, "done": done,
            "elapsed_s": round(time.time() - self.started, 1),
            "last": self.history[-1] if self.history else {},
            "train_samples": len(self.train_set), "val_samples": len(self.val_set) if self.val_set else 0,
        })

    # -- batches ---------------------------------------------------------------------------------------
    def _batch(self, dataset: ChunkDataset, step: int, rank: int, world: int, augment: bool,
               seed_offset: int = 0) -> dict[str, torch.Tensor]:
        cfg = self.cfg
        if dataset is self.train_set and self.train_cdf is not None:
            idx = weighted_batch_indices(self.train_cdf, cfg.batch_size, step, cfg.seed, rank)
        else:
            idx = epoch_batch_indices(len(dataset), cfg.batch_size, step, cfg.seed + seed_offset, rank, world)
        rng = np.random.default_rng([cfg.seed + seed_offset, step, rank])
        batch = collate([dataset.sample(int(i), rng) for i in idx])
        if augment:
            shifted = augment_shift(batch["images"], rng, cfg.augment_pad, self.shift_cameras)
            batch["images"] = augment_color(shifted, rng, cfg.augment_color)
        return batch_to_tensors(batch, self.device)

    # -- value refresh for the RL term -------------------------------------------------------------------
    @torch.no_grad()
    def _state_values(self, dataset: ChunkDataset, batch: int = 64) -> list[np.ndarray]:
        """V(s_t) of every training frame: one forward pass over the whole dataset, in batches of 64 frames (on 2
        CPU cores a 256-frame batch's activations leave the cache and cost 1.5x a frame)."""
        self.model.eval()
        values = []
        for e, ep in enumerate(dataset.episodes):
            out = []
            for s in range(0, len(ep.actions), batch):
                ts = range(s, min(s + batch, len(ep.actions)))
                b = batch_to_tensors(collate([dataset.observation(e, t) for t in ts]), self.device)
                with self.acc.autocast():
                    out.append(self.model(b).value_now.float().cpu().numpy())
            values.append(np.concatenate(out))
        self.model.train()
        return values

    def _refresh_values(self) -> None:
        """New GAE advantages from the current critic. At step 0 the value head is untrained, its values small
        and nearly equal everywhere: zeros stand in for them and spare a pass over the whole dataset (~35 s of
        the demo's training)."""
        if self.step == 0:
            self._set_values([np.zeros(len(ep.actions), np.float32) for ep in self.train_set.episodes])
        else:
            self._set_values(self._state_values(self.train_set))

    def _set_values(self, values: list[np.ndarray]) -> None:
        self._values = values
        self.train_set.set_values(values, self.cfg.loss.gamma, self.cfg.loss.gae_lambda)

    # -- loop ----------------------------------------------------------------------------------------------
    def train_step(self) -> dict[str, float]:
        cfg, acc = self.cfg, self.acc
        rank, world = acc.process_index, acc.num_processes
        logs_sum: dict[str, float] = {}
        for micro in range(cfg.grad_accum):
            batch = self._batch(self.train_set, self.step * cfg.grad_accum + micro, rank, world, augment=True)
            sync = micro == cfg.grad_accum - 1
            ctx = acc.no_sync(self.ddp_model) if not sync else contextlib.nullcontext()
            with ctx, acc.autocast():
                out = self.ddp_model(batch, aux_on_trunk=cfg.loss.aux_on_trunk)
                loss, logs = unified_loss(self.model, out, batch, cfg.loss)
                if not torch.isfinite(loss):
                    raise FloatingPointError(f"non-finite loss at step {self.step}: "
                                             f"{ {k: float(v) for k, v in logs.items()} }")
                acc.backward(loss / cfg.grad_accum)
            for k, v in logs.items():
                logs_sum[k] = logs_sum.get(k, 0.0) + float(v) / cfg.grad_accum
        if cfg.grad_clip > 0:
            logs_sum["grad_norm"] = float(acc.clip_grad_norm_(self.model.parameters(), cfg.grad_clip))
        self.optimizer.step()
        self.scheduler.step()
        self.optimizer.zero_grad(set_to_none=True)
        self.model.update_target()
        if self.average is not None:
            self.average.update(self.model)
        self.step += 1
        logs_sum["lr"] = self.scheduler.get_last_lr()[0]
        return logs_sum

    @torch.no_grad()
    def validate(self, n_batches: int = 4) -> dict[str, float]:
        if self.val_set is None:
            return {}
        self.model.eval()
        sums: dict[str, float] = {}
        for i in range(n_batches):
            batch = self._batch(self.val_set, i, 0, 1, augment=False, seed_offset=10_000)
            with self.acc.autocast():
                _, logs = unified_loss(self.model, self.model(batch), batch, self.cfg.loss)
            for k, v in logs.items():
                sums[k] = sums.get(k, 0.0) + float(v) / n_batches
        self.model.train()
        return sums

    def _save_due(self, since: float) -> bool:
        """Whether ``ckpt_minutes`` have passed since ``since`` (checked at log steps). Rank 0's clock decides
        for every rank: under FSDP all of them take part in a save."""
        cfg = self.cfg
        if cfg.ckpt_minutes <= 0 or self.step % cfg.log_every:
            return False
        due = [time.monotonic() - since >= cfg.ckpt_minutes * 60]
        if self.acc.num_processes > 1:
            broadcast_object_list(due)
        return bool(due[0])

    def run(self) -> Path:
        cfg, acc = self.cfg, self.acc
        if acc.is_main_process:
            self.run_dir.mkdir(parents=True, exist_ok=True)
            self.writer = SummaryWriter(str(self.run_dir / "tb"))
        self.model.train()
        bar = tqdm(total=cfg.steps, initial=self.step, desc="train", disable=not (cfg.progress and acc.is_main_process),
                   mininterval=2.0, dynamic_ncols=True)
        t0, s0 = time.time(), self.step
        saved = time.monotonic()
        while self.step < cfg.steps:
            if cfg.loss.use_rl and cfg.loss.alpha > 0 and self.step % cfg.every(cfg.value_refresh_every) == 0:
                self._refresh_values()
            logs = self.train_step()
            bar.update(1)
            if self.step % cfg.log_every == 0 or self.step == cfg.steps:
                rate = ((self.step - s0) * cfg.batch_size * cfg.grad_accum * acc.num_processes
                        / max(time.time() - t0, 1e-9))
                logs["samples_per_s"] = rate
                self.history.append({"step": self.step, **{k: round(v, 5) for k, v in logs.items()}})
                bar.set_postfix(loss=f"{logs['total']:.3f}", il=f"{logs['il']:.3f}")
                if self.writer:
                    for k, v in logs.items():
                        self.writer.add_scalar(f"train/{k}", v, self.step)
            if self.step % cfg.every(cfg.eval_every) == 0 or self.step == cfg.steps:
                val = self.validate()
                if val and self.writer:
                    for k, v in val.items():
                        self.writer.add_scalar(f"val/{k}", v, self.step)
                    self.history.append({"step": self.step, **{f"val_{k}": round(v, 5) for k, v in val.items()}})
            if self.step % cfg.every(cfg.ckpt_every) == 0 or self.step == cfg.steps or self._save_due(saved):
                self._save(final=self.step == cfg.steps)
                saved = time.monotonic()
        bar.close()
        if self.writer:
            self.writer.close()
        acc.wait_for_everyone()
        return self.run_dir


def train(cfg: TrainConfig, resume: bool = False) -> Path:
    """Train (or resume) a run; returns its directory."""
    os.makedirs(cfg.out, exist_ok=True)
    trainer = Trainer(cfg, resume=resume)
    run_dir = trainer.run()
    # Tear the process group down explicitly: left to interpreter exit, gloo can abort a rank (SIGABRT).
    trainer.acc.end_training()
    return run_dir
