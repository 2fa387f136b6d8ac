"""Run directories and checkpoints: safetensors and JSON only (no pickle), every write atomic.

A run directory holds what a user deploys — ``model.safetensors``, ``config.json``, ``norm_stats.json``,
``tokenizer.json`` (and ``calibration.json`` once AURD thresholds are calibrated) — plus ``status.json``
and ``checkpoints/step_<N>/`` with the optimizer, scheduler and RNG state that ``--resume`` needs.
Tensors are always full (the trainer gathers FSDP shards first), so files do not depend on how a run was sharded.
"""

from __future__ import annotations

import shutil
from collections.abc import Callable
from pathlib import Path

import torch
from safetensors.torch import load_file, save_file

from pivla.config import from_dict
from pivla.io import atomic_dir, atomic_path, atomic_write_json, read_json
from pivla.training.config import TrainConfig

MODEL_FILE = "model.safetensors"
CONFIG_FILE = "config.json"
STATS_FILE = "norm_stats.json"
TOKENIZER_FILE = "tokenizer.json"
STATUS_FILE = "status.json"
CALIBRATION_FILE = "calibration.json"
AVERAGE_FILE = "average.safetensors"  # a checkpoint's weight average (--ema-decay)
RUN_ENSEMBLE_FILE = "run_ensemble.json"  # in a directory that ensembles several runs (``write_run_ensemble``)
COPIED_FROM_FILE = "copied_from.json"  # in a policy copied from another run (``copy_policy``)
DEPLOYED_FILES = (MODEL_FILE, CONFIG_FILE, STATS_FILE, TOKENIZER_FILE)  # what ``load_policy`` needs of a run


# backbone fields whose default changed, with the value every run written before they existed used
LEGACY_BACKBONE = {"grid_tokens": True}


def read_run_config(run_dir: Path) -> TrainConfig:
    """The ``TrainConfig`` of a run directory. Runs written before a default changed keep what they were
    trained with (``LEGACY_BACKBONE``), so old policies still load. Sections missing from an old file take
    their class defaults, not the recipe's (e.g. a full-size target encoder)."""
    data = read_json(Path(run_dir) / CONFIG_FILE)
    backbone = data.get("model", {}).get("backbone")
    if isinstance(backbone, dict):
        for key, value in LEGACY_BACKBONE.items():
            backbone.setdefault(key, value)
    return from_dict(TrainConfig, data)


def write_calibration(run_dir: str | Path, calibration: dict, stats: dict | None = None) -> None:
    """AURD's thresholds (``calibration.json``, read by ``load_policy``) and how they were found."""
    atomic_write_json(Path(run_dir) / CALIBRATION_FILE, calibration)
    if stats is not None:
        atomic_write_json(Path(run_dir) / "calibration_stats.json", stats)


def write_run_ensemble(runs: list[str | Path], out: str | Path, check: Callable[[Path], object] | None = None) -> Path:
    """A directory that ``load_policy`` reads as the ensemble of ``runs`` (``pivla ensemble-runs``): each run's
    deployed files copied to ``members/<i>/`` (so the directory moves and serves on its own) and
    ``run_ensemble.json`` naming them. Written atomically; an existing ``out`` is refused. ``check`` gets the
    complete directory before it takes ``out``'s place: an error it raises leaves nothing behind."""
    out = Path(out)
    if len(runs) < 2:
        raise ValueError(f"an ensemble needs at least two runs, got {len(runs)}")
    if out.exists():
        raise ValueError(f"{out} exists; choose a new directory")
    for run in runs:
        if (Path(run) / RUN_ENSEMBLE_FILE).exists():
            raise ValueError(f"{run} is an ensemble itself; name its members instead")
        _check_deployed(Path(run))
    with atomic_dir(out) as tmp:
        members = []
        for i, run in enumerate(runs):
            member = Path("members") / str(i)
            _copy_deployed(Path(run), tmp / member)
            members.append(str(member))
        sources = [str(Path(r).resolve()) for r in runs]
        atomic_write_json(tmp / RUN_ENSEMBLE_FILE, {"members": members, "sources": sources})
        if check is not None:
            check(tmp)
    return out


def _check_deployed(run: Path) -> None:
    missing = [f for f in DEPLOYED_FILES if not (run / f).is_file()]
    if missing:
        raise ValueError(f"{run}: not a trained run directory (missing {', '.join(missing)})")


def _copy_deployed(run: Path, dest: Path) -> None:
    """The files ``load_policy`` reads of one run, and its status, into ``dest``."""
    dest.mkdir(parents=True, exist_ok=True)
    for f in (*DEPLOYED_FILES, STATUS_FILE):
        if (run / f).is_file():
            shutil.copy2(run / f, dest / f)


def copy_policy(run: str | Path, out: str | Path) -> Path:
    """A copy of the policy of ``run`` (a trained run or an ensemble of runs) at ``out``: its deployed files,
    not its checkpoints, logs or AURD calibration, so that a study can calibrate the copy for its own tasks and
    leave the source as it was; ``copied_from.json`` names the source. Written atomically; an existing ``out`` is
    refused."""
    run, out = Path(run), Path(out)
    if out.exists():
        raise ValueError(f"{out} exists; choose a new directory")
    members = run_ensemble_members(run)
    for member in members or [run]:
        _check_deployed(member)
    with atomic_dir(out) as tmp:
        if members is None:
            _copy_deployed(run, tmp)
        else:
            for member in members:
                _copy_deployed(member, tmp / member.relative_to(run))
            shutil.copy2(run / RUN_ENSEMBLE_FILE, tmp / RUN_ENSEMBLE_FILE)
        atomic_write_json(tmp / COPIED_FROM_FILE, {"source": str(run.resolve())})
    return out


def copied_from(run_dir: str | Path) -> str | None:
    """The absolute path of the run a ``copy_policy`` copy was made from, or None for any other directory."""
    path = Path(run_dir) / COPIED_FROM_FILE
    return read_json(path)["source"] if path.exists() else None


def run_ensemble_members(run_dir: str | Path) -> list[Path] | None:
    """The member run directories of an ensemble directory, or None for a single run."""
    path = Path(run_dir) / RUN_ENSEMBLE_FILE
    if not path.exists():
        return None
    data = read_json(path)
    members = data.get("members") if isinstance(data, dict) else None
    if not isinstance(members, list) or len(members) < 2 or not all(isinstance(m, str) for m in members):
        raise ValueError(f"{path}: 'members' must list at least two run directories")
    return [Path(run_dir) / m for m in members]


def save_tensors(path: Path, tensors: dict[str, torch.Tensor], metadata: dict[str, str] | None = None) -> None:
    with atomic_path(path) as tmp:
        save_file({k: v.detach().contiguous().cpu() for k, v in tensors.items()}, tmp, metadata=metadata)


def load_tensors(path: Path) -> dict[str, torch.Tensor]:
    try:
        return load_file(str(path))
    except FileNotFoundError:
        raise FileNotFoundError(f"{path}: missing") from None
    except Exception as e:  # safetensors raises its own error types for truncated/corrupt files
        raise ValueError(f"{path}: corrupt or truncated safetensors file ({e})") from e


def optimizer_to_tensors(state: dict) -> tuple[dict[str, torch.Tensor], dict]:
    """Split an optimizer state_dict into tensors (for safetensors) and a JSON-able remainder."""
    tensors, scalars = {}, {}
    for idx, s in state["state"].items():
        for k, v in s.items():
            if isinstance(v, torch.Tensor):
                tensors[f"{idx}.{k}"] = v
            else:
                scalars[f"{idx}.{k}"] = v
    return tensors, {"param_groups": state["param_groups"], "scalars": scalars}


def optimizer_from_tensors(tensors: dict[str, torch.Tensor], meta: dict) -> dict:
    state: dict[int, dict] = {}
    for key, v in list(tensors.items()) + list(meta["scalars"].items()):
        idx, name = key.split(".", 1)
        state.setdefault(int(idx), {})[name] = v
    return {"state": state, "param_groups": meta["param_groups"]}


def save_checkpoint(run_dir: Path, step: int, model_state: dict[str, torch.Tensor], optimizer_state: dict,
                    train_state: dict, keep: int = 2, average: dict[str, torch.Tensor] | None = None) -> Path:
    """Write ``checkpoints/step_<N>`` completely under a temporary name, then rename it into place. The
    checkpoint's model file holds the live weights, which a resumed run continues from; ``average``, the
    weight average the run deploys, goes beside them."""
    ckpt_root = Path(run_dir) / "checkpoints"
    final = ckpt_root / f"step_{step:08d}"
    with atomic_dir(final, prefix=".tmp_") as tmp:
        save_tensors(tmp / MODEL_FILE, model_state)
        if average is not None:
            save_tensors(tmp / AVERAGE_FILE, average)
        opt_tensors, opt_meta = optimizer_to_tensors(optimizer_state)
        save_tensors(tmp / "optimizer.safetensors", opt_tensors)
        atomic_write_json(tmp / "optimizer.json", opt_meta)
        atomic_write_json(tmp / "train_state.json", {**train_state, "step": step})
    for old in sorted(p for p in ckpt_root.glob("step_*") if p.is_dir())[:-keep]:
        shutil.rmtree(old, ignore_errors=True)
    return final


def latest_checkpoint(run_dir: Path) -> Path | None:
    ckpts = sorted(p for p in (Path(run_dir) / "checkpoints").glob("step_*") if (p / "train_state.json").exists())
    return ckpts[-1] if ckpts else None


def load_checkpoint(ckpt: Path) -> tuple[dict[str, torch.Tensor], dict, dict]:
    model_state = load_tensors(ckpt / MODEL_FILE)
    opt_state = optimizer_from_tensors(load_tensors(ckpt / "optimizer.safetensors"), read_json(ckpt / "optimizer.json"))
    return model_state, opt_state, read_json(ckpt / "train_state.json")


def load_average(ckpt: Path) -> dict[str, torch.Tensor]:
    """A checkpoint's weight average; a run with ``--ema-decay`` resumed from a checkpoint without one is refused."""
    path = ckpt / AVERAGE_FILE
    if not path.exists():
        raise ValueError(f"{ckpt}: no weight average ({AVERAGE_FILE}) to resume --ema-decay from; "
                         "resume with the run's own --ema-decay or start a new run")
    return load_tensors(path)
