"""A deployable copy of an ``hf`` run with its LoRA adapters folded into the backbone's base weights.

A merged backbone runs without peft and without the adapters' extra matmuls; the run it belongs to then loads
like any other (``lora_rank 0``). Works on the run's files alone: its config, tokenizer and weights.
"""

from __future__ import annotations

import shutil
from dataclasses import dataclass, replace
from pathlib import Path

from pivla import config as cfgmod
from pivla.io import atomic_dir, atomic_write_json, read_json
from pivla.model.cms import CMSModel
from pivla.model.device import select_device
from pivla.model.hf.backbone import HFBackbone
from pivla.model.hf.text import HFTextTokenizer
from pivla.training import checkpoint as ck

# run files carried over unchanged (the weights and config are rewritten)
_COPIED = (ck.STATS_FILE, ck.TOKENIZER_FILE, ck.CALIBRATION_FILE, ck.STATUS_FILE, "split.json")
# the checkpoint's pixel preprocessing, which save_pretrained of model and tokenizer does not write
_PREPROCESSOR_FILES = ("preprocessor_config.json", "processor_config.json")


@dataclass
class MergeConfig:
    """What to merge and where to."""

    policy: str
    """Run directory trained with the hf backbone and LoRA."""
    out: str
    """New run directory to write (must not exist)."""
    device: str = "auto"
    """Where to merge: auto (cuda when present, else cpu), cpu or cuda[:N]."""


def merge_run(cfg: MergeConfig) -> Path:
    """Write ``cfg.out``: the run ``cfg.policy`` with its LoRA adapters merged into the base weights.

    ``out/backbone`` becomes a plain transformers checkpoint (merged weights, tokenizer, preprocessor config);
    the new run's config points at it with ``lora_rank 0``, and its model.safetensors keeps only the queries,
    readout and CMS heads. The output appears atomically (written under a temporary name)."""
    if not cfg.policy or not cfg.out:
        raise ValueError("merge: give both the run directory to merge and the new directory to write")
    run_dir, out_dir = Path(cfg.policy), Path(cfg.out)
    if not (run_dir / ck.CONFIG_FILE).is_file():
        raise FileNotFoundError(f"{run_dir}: not a pivla run directory (no {ck.CONFIG_FILE})")
    train_cfg = ck.read_run_config(run_dir)
    bc = train_cfg.model.backbone
    if bc.name != "hf":
        raise ValueError(f"{run_dir}: backbone is {bc.name!r}; only 'hf' runs have adapters")
    if bc.lora_rank <= 0:
        raise ValueError(f"{run_dir}: no LoRA adapters to merge (lora_rank 0)")
    if out_dir.exists():
        raise FileExistsError(f"{out_dir} exists; choose a new directory")
    text_data = read_json(run_dir / ck.TOKENIZER_FILE)
    if text_data.get("kind") != "hf":
        raise ValueError(f"{run_dir / ck.TOKENIZER_FILE}: not a checkpoint tokenizer (kind {text_data.get('kind')!r})")
    text = HFTextTokenizer.from_dict(text_data)
    model = CMSModel(train_cfg.model, len(text.vocab))
    model.load_checkpoint_state(ck.load_tensors(run_dir / ck.MODEL_FILE), str(run_dir / ck.MODEL_FILE))
    model.to(select_device(cfg.device))
    backbone: HFBackbone = model.backbone
    backbone.merge_lora()
    src = Path(bc.path)
    with atomic_dir(out_dir) as tmp:
        backbone.vlm.save_pretrained(str(tmp / "backbone"))
        text.tokenizer.save_pretrained(str(tmp / "backbone"))
        for name in _PREPROCESSOR_FILES:
            if (src / name).is_file():
                shutil.copy2(src / name, tmp / "backbone" / name)
        merged_backbone = replace(bc, path=str((out_dir / "backbone").resolve()), lora_rank=0)
        new_cfg = replace(train_cfg, model=replace(train_cfg.model, backbone=merged_backbone))
        ck.save_tensors(tmp / ck.MODEL_FILE, model.state_dict_for_checkpoint(),
                        metadata={"format": "pt", "merged_from": str(run_dir)})
        atomic_write_json(tmp / ck.CONFIG_FILE, cfgmod.to_dict(new_cfg))
        for name in _COPIED:
            if (run_dir / name).is_file():
                shutil.copy2(run_dir / name, tmp / name)
    return out_dir
