"""The target encoder on ONNX Runtime, for AURD's per-step cost on a CPU.

AURD encodes every new observation with the target encoder (its U_pred, Eq. 13), so that encoding is most
of what AURD adds to a control step over a fixed horizon. At batch 1 the default CNN spends much of its
eager-PyTorch time dispatching small operators; on ONNX Runtime one encoding takes 0.5-0.7x as long,
and AURD's own time per step in the twin falls by ~0.6 ms (docs/experiments.md#target-encoder-on-onnx-runtime). Only
single-observation inference changes: training, calibration and the weights are PyTorch's.

The graph is exported from the loaded weights (``torch.onnx.export(dynamo=True)``, a few seconds), cached
in the run directory under a digest of those weights, and checked against PyTorch on every load: an
unreadable or disagreeing cache is exported again, and a fresh graph that disagrees is not used.
"""

from __future__ import annotations

import hashlib
import importlib.util
import logging
import math
import warnings
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F

from pivla.io import atomic_write_bytes
from pivla.model.onnx_encoder import OnnxEncoder

log = logging.getLogger(__name__)

ONNX_PREFIX = "target_encoder-"  # + 16 hex digits of a digest of the weights and image shape + ".onnx"
RUNTIMES = ("auto", "torch", "onnx")


def onnx_available() -> bool:
    """ONNX Runtime to run the graph, and onnx + onnxscript to export it (``torch.onnx.export(dynamo=True)``)."""
    return all(importlib.util.find_spec(m) is not None for m in ("onnxruntime", "onnx", "onnxscript"))


def weights_digest(module: torch.nn.Module) -> str:
    """SHA-256 over the module's state (names, shapes and bytes): which weights a cached graph belongs to."""
    h = hashlib.sha256()
    for name, t in sorted(module.state_dict().items()):
        h.update(name.encode())
        h.update(str(tuple(t.shape)).encode())
        h.update(t.detach().cpu().contiguous().numpy().tobytes())
    return h.hexdigest()


def export_onnx(module: torch.nn.Module, image_shape: tuple[int, int, int]) -> bytes:
    """(1, *image_shape) images, as ``module`` takes them -> (1, d_z) latents as an ONNX graph. Batch 1 is
    fixed: it is AURD's case, and ONNX Runtime plans a static graph better (0.85 against 1.03 ms with a
    dynamic batch axis)."""
    example = torch.rand(1, *image_shape)
    # the exporter's progress notes ("torchvision is not installed", optimiser passes) are not ours to show
    loggers = [logging.getLogger(name) for name in ("torch.onnx", "onnxscript", "onnx_ir")]
    levels = [lg.level for lg in loggers]
    for lg in loggers:
        lg.setLevel(logging.ERROR)
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            program = torch.onnx.export(module.eval(), (example,), dynamo=True, verbose=False,
                                        input_names=["images"], output_names=["latents"])
    finally:
        for lg, level in zip(loggers, levels):
            lg.setLevel(level)
    return program.model_proto.SerializeToString()


class TargetLatents(torch.nn.Module):
    """The exported part of a CNN target encoder: ``TargetEncoder.forward`` on images already cut to its
    cameras, area-averaged (``pivla.data.transforms.area_downsample``) and centred
    (``pivla.model.backbone.centre``) in NumPy before the graph, with the final 1 / sqrt(d_z) as the layer
    norm's scale. The graph then starts at the first convolution and ends at the layer norm (33 nodes instead
    of 36; in the twin's loop a graph like it encoded 0.01-0.07 ms faster,
    docs/experiments.md#the-encoding-path-in-the-control-loop).
    ``onnx_target_encoder`` checks the graph against this module; the tests check the whole ONNX path against
    the PyTorch ``TargetEncoder``."""

    def __init__(self, target: torch.nn.Module):
        super().__init__()
        self.target = target
        d_z = target.encoder.out_channels * target.cameras * target.grid**2
        self.register_buffer("scale", torch.full((d_z,), 1.0 / math.sqrt(d_z)), persistent=False)

    def forward(self, centred: torch.Tensor) -> torch.Tensor:
        """(1, cameras, 3, h, w) centred images -> (1, d_z) latents."""
        z = self.target.encoder.pooled(centred, centred=True, grid=self.target.grid).float()
        return F.layer_norm(z, z.shape[-1:], weight=self.scale)


def onnx_target_encoder(module: torch.nn.Module, image_shape: tuple[int, int, int], cache_dir: Path | None = None,
                        atol: float = 1e-5, rtol: float = 1e-3) -> OnnxEncoder | None:
    """The module on ONNX Runtime, or None (logged) when it cannot be exported or disagrees with PyTorch.

    ``cache_dir``: where ``target_encoder-<digest>.onnx`` is read from if these weights and this image shape
    were exported before, and written to (atomically, once the graph agrees with PyTorch) otherwise,
    replacing graphs of other weights; an unwritable directory only costs the export again on the next load.
    A cached graph that no longer agrees (say, the encoder's code changed) is exported again.
    """
    probe = torch.rand(1, *image_shape, generator=torch.Generator().manual_seed(0))
    with torch.no_grad():
        expected = module(probe).float().numpy()

    def error(encoder: OnnxEncoder) -> float | None:
        """Largest deviation from PyTorch on the probe, or None when within tolerance."""
        got = encoder(probe.numpy())
        if got.shape == expected.shape and np.allclose(got, expected, atol=atol, rtol=rtol):
            return None
        return float(np.abs(got - expected).max()) if got.shape == expected.shape else float("inf")

    path = None
    if cache_dir is not None:
        # the module's repr names its architecture and settings (say, a target encoder's downsampling)
        key = hashlib.sha256(f"{weights_digest(module)} {tuple(image_shape)} {module!r}".encode()).hexdigest()[:16]
        path = Path(cache_dir) / f"{ONNX_PREFIX}{key}.onnx"
    if path is not None and path.is_file():
        try:
            encoder = OnnxEncoder(path.read_bytes())
            if error(encoder) is None:
                return encoder
            log.info("target encoder: cached %s disagrees with PyTorch; exporting again", path)
        except Exception as e:  # noqa: BLE001 - ONNX Runtime raises its own types for a damaged file
            log.info("target encoder: cached %s unreadable (%s); exporting again", path, e)
    try:
        model_bytes = export_onnx(module, image_shape)
    except Exception as e:  # noqa: BLE001 - the exporter raises many types; PyTorch still works
        log.warning("target encoder: ONNX export failed (%s: %s); encoding with PyTorch", type(e).__name__, e)
        return None
    encoder = OnnxEncoder(model_bytes)
    err = error(encoder)
    if err is not None:
        log.warning("target encoder: ONNX graph disagrees with PyTorch (max error %.3g); encoding with PyTorch", err)
        return None
    if path is not None:
        try:
            atomic_write_bytes(path, model_bytes)
            for old in path.parent.glob(f"{ONNX_PREFIX}*.onnx"):
                if old != path:
                    old.unlink(missing_ok=True)
        except OSError as e:
            log.info("target encoder: could not cache %s (%s)", path, e)
    return encoder
