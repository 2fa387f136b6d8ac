"""The checkpoint's own tokenizer behind pivla's instruction-text interface (``encode``/``to_dict``/``vocab``)."""

from __future__ import annotations

import base64
import logging
import tempfile
from pathlib import Path

import numpy as np

from pivla.model.hf.common import check_local_dir

log = logging.getLogger(__name__)

# OpenVLA's prompt; the instruction is lower-cased and stripped of its final period, as OpenVLA does.
PROMPT = "In: What action should the robot take to {instruction}?\nOut:"


class HFTextTokenizer:
    """The checkpoint's own tokenizer behind pivla's text interface (``encode``/``to_dict``/``vocab``).

    ``to_dict`` embeds the tokenizer files, so a run directory stays self-contained even if the checkpoint
    directory moves (the backbone weights still come from ``backbone.path``)."""

    def __init__(self, tokenizer, max_len: int, path: str, files: dict[str, dict]):
        if tokenizer.pad_token is None:
            tokenizer.pad_token = tokenizer.unk_token or tokenizer.eos_token
        tokenizer.padding_side = "right"
        self.tokenizer = tokenizer
        self.max_len = int(max_len)
        self.path = path
        self.files = files
        self._warned = False

    @classmethod
    def from_pretrained(cls, path: str, max_len: int) -> HFTextTokenizer:
        from transformers import AutoTokenizer

        p = check_local_dir(path, "hf tokenizer")
        tok = AutoTokenizer.from_pretrained(str(p), local_files_only=True)
        return cls(tok, max_len, str(p.resolve()), _tokenizer_files(tok))

    @classmethod
    def from_dict(cls, d: dict) -> HFTextTokenizer:
        from transformers import AutoTokenizer

        files = d.get("files") or {}
        if not files:
            return cls.from_pretrained(d["path"], int(d["max_len"]))
        with tempfile.TemporaryDirectory() as tmp:
            for name, entry in files.items():
                data = base64.b64decode(entry["data"]) if entry["encoding"] == "base64" else entry["data"].encode()
                (Path(tmp) / name).write_bytes(data)
            tok = AutoTokenizer.from_pretrained(tmp, local_files_only=True)
        return cls(tok, int(d["max_len"]), d.get("path", ""), files)

    @property
    def vocab(self):
        return self.tokenizer  # len() is the vocabulary size

    def encode(self, text: str) -> tuple[np.ndarray, np.ndarray]:
        """Prompt-wrapped ids (max_len,) int64 and mask (max_len,) bool; right-padded, cut at max_len."""
        prompt = PROMPT.format(instruction=text.strip().lower().rstrip("."))
        enc = self.tokenizer(prompt, max_length=self.max_len, truncation=True, padding="max_length")
        ids = np.asarray(enc["input_ids"], np.int64)
        if not self._warned and len(self.tokenizer(prompt)["input_ids"]) > self.max_len:
            log.warning("instruction prompt longer than max_text_len=%d tokens is truncated; raise "
                        "--model.max-text-len (48-64 suits LIBERO with OpenVLA's prompt)", self.max_len)
            self._warned = True
        return ids, np.asarray(enc["attention_mask"], bool)

    def to_dict(self) -> dict:
        return {"kind": "hf", "path": self.path, "max_len": self.max_len, "files": self.files}


def _tokenizer_files(tok) -> dict[str, dict]:
    """The files ``save_pretrained`` writes for this tokenizer, as JSON-able text or base64."""
    out = {}
    with tempfile.TemporaryDirectory() as tmp:
        tok.save_pretrained(tmp)
        for f in sorted(Path(tmp).iterdir()):
            raw = f.read_bytes()
            try:
                out[f.name] = {"encoding": "utf-8", "data": raw.decode("utf-8")}
            except UnicodeDecodeError:
                out[f.name] = {"encoding": "base64", "data": base64.b64encode(raw).decode()}
    return out
