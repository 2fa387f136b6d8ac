"""A word-level instruction tokenizer built from the training data.

No pretrained tokenizer can be downloaded at run time, and the default backbone learns its word embeddings
from scratch, so a vocabulary of the words in the training instructions is all it needs. Words never seen
in training map to ``<unk>``; the vocabulary is saved as JSON beside the checkpoint.
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field

import numpy as np

from pivla.model.hf.text import HFTextTokenizer

PAD, UNK = "<pad>", "<unk>"


def words(text: str) -> list[str]:
    return re.findall(r"[a-z0-9]+", text.lower())


@dataclass
class WordTokenizer:
    vocab: list[str] = field(default_factory=lambda: [PAD, UNK])
    max_len: int = 16

    @classmethod
    def build(cls, instructions: list[str], max_len: int = 16) -> WordTokenizer:
        seen = sorted({w for text in instructions for w in words(text)})
        return cls(vocab=[PAD, UNK, *seen], max_len=max_len)

    def __post_init__(self) -> None:
        self._index = {w: i for i, w in enumerate(self.vocab)}

    def encode(self, text: str) -> tuple[np.ndarray, np.ndarray]:
        """Token ids (max_len,) int64 and a validity mask (max_len,) bool; long instructions are cut."""
        ids = [self._index.get(w, 1) for w in words(text)][: self.max_len] or [1]
        out = np.zeros(self.max_len, np.int64)
        out[: len(ids)] = ids
        mask = np.zeros(self.max_len, bool)
        mask[: len(ids)] = True
        return out, mask

    def to_dict(self) -> dict:
        return {"vocab": self.vocab, "max_len": self.max_len}

    @classmethod
    def from_dict(cls, d: dict) -> WordTokenizer:
        return cls(vocab=list(d["vocab"]), max_len=int(d["max_len"]))


def build_text_tokenizer(backbone: str, instructions: list[str], max_len: int, path: str = ""):
    """The instruction tokenizer a backbone needs: words from the data for ``small``; the checkpoint's own
    tokenizer (loaded from the local directory) for ``hf``. Both expose ``encode``/``to_dict``/``vocab``."""
    if backbone == "hf":
        return HFTextTokenizer.from_pretrained(path, max_len)
    return WordTokenizer.build(instructions, max_len)


def load_text_tokenizer(data: dict):
    """Inverse of ``tokenizer.to_dict()`` for either kind (``kind`` key; word tokenizers omit it)."""
    if data.get("kind") == "hf":
        return HFTextTokenizer.from_dict(data)
    return WordTokenizer.from_dict(data)
