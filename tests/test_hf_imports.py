"""The model layer's place in the package: it imports nothing above it (only ``pivla.io``, ``pivla.config``
and itself, function-local imports included), and the ``hf`` modules load without transformers or peft,
which are imported only where a checkpoint is read or LoRA applied."""

from __future__ import annotations

import ast
import subprocess
import sys
from pathlib import Path

import pivla

MODEL = Path(pivla.__file__).parent / "model"
BELOW_MODEL = ("pivla.io", "pivla.config", "pivla.model")


def pivla_imports(path: Path) -> list[tuple[str, int]]:
    """Every ``pivla`` module a file imports, anywhere in it, with its line."""
    found = []
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            found += [(alias.name, node.lineno) for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            assert node.level == 0, f"{path}:{node.lineno}: relative import"
            if node.module == "pivla":  # from pivla import config
                found += [(f"pivla.{alias.name}", node.lineno) for alias in node.names]
            else:
                found.append((node.module, node.lineno))
    return [(m, line) for m, line in found if m == "pivla" or m.startswith("pivla.")]


def test_model_layer_imports_nothing_above_it():
    files = sorted(MODEL.rglob("*.py"))
    assert MODEL / "hf" / "backbone.py" in files
    upward = [f"{f.relative_to(MODEL.parent)}:{line} imports {m}" for f in files for m, line in pivla_imports(f)
              if not any(m == b or m.startswith(b + ".") for b in BELOW_MODEL)]
    assert not upward, upward


def test_hf_modules_and_text_tokenizers_load_without_transformers():
    code = """
import sys
import pivla.data.text
assert "torch" not in sys.modules, "pivla.data.text pulled in torch"
import pivla.bench.hf, pivla.model.cms, pivla.model.dinov2, pivla.model.openvla, pivla.training.merge
from pivla.model.hf import backbone, common, lora, pixels, text, vlm
heavy = sorted(m for m in ("transformers", "peft") if m in sys.modules)
assert not heavy, f"imported at load time: {heavy}"
"""
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr[-2000:]
