"""The target encoder's exported graph on ONNX Runtime, and AURD's observed latent of one observation with it.

AURD encodes every new observation (U_pred, Eq. 13); on a CPU the small CNN runs 0.5-0.7x as long on ONNX
Runtime as in eager PyTorch (docs/experiments.md#target-encoder-on-onnx-runtime). Nothing here imports
torch: a local policy (``pivla.policy``) and a robot laptop holding a served policy's graph
(``pivla.serving.RemotePolicy``) run the same code, so their latents agree bit for bit. Exporting the graph
needs torch and lives in ``pivla.model.encoder_runtime``.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from pivla.model.pixels import area_downsample, centre, check_image, resize_images


class OnnxEncoder:
    """A callable: float32 (1, *image_shape) array -> float32 (1, d_z) array, on ONNX Runtime's CPU provider.

    One thread that does not spin between calls: between two encodings the control loop steps the simulator
    and renders, and a spinning thread would take a core from it; at batch 1 a second thread's wake-up costs
    more than it saves. Input and output stay bound to two preallocated arrays (I/O binding), which saves
    ONNX Runtime's per-call conversion of the feed and allocation of the result.
    """

    def __init__(self, model_bytes: bytes):
        import onnxruntime as ort  # optional: a robot laptop that does not encode needs none

        self.model_bytes = model_bytes
        opts = ort.SessionOptions()
        opts.intra_op_num_threads = 1
        opts.inter_op_num_threads = 1
        opts.add_session_config_entry("session.intra_op.allow_spinning", "0")
        opts.log_severity_level = 3
        self.session = ort.InferenceSession(model_bytes, opts, providers=["CPUExecutionProvider"])
        (inp,), (out,) = self.session.get_inputs(), self.session.get_outputs()
        if not all(isinstance(d, int) for d in (*inp.shape, *out.shape)):
            raise ValueError(f"target encoder graph must have static shapes, got {inp.shape} -> {out.shape}")
        self._in = np.zeros(inp.shape, np.float32)
        self._out = np.zeros(out.shape, np.float32)
        self._binding = self.session.io_binding()
        self._binding.bind_cpu_input(inp.name, self._in)
        self._binding.bind_output(out.name, "cpu", 0, np.float32, self._out.shape, self._out.ctypes.data)

    @property
    def input_shape(self) -> tuple[int, ...]:
        return self._in.shape

    @property
    def inputs(self) -> np.ndarray:
        """The bound input array: a caller that prepares its images in place here, then calls ``run``, saves
        a copy (``Policy.encode``)."""
        return self._in

    def run(self) -> np.ndarray:
        """Latents of what ``inputs`` holds now."""
        self.session.run_with_iobinding(self._binding)
        return self._out.copy()

    def __call__(self, images: np.ndarray) -> np.ndarray:
        if images.shape != self._in.shape:
            raise ValueError(f"target encoder graph takes images of shape {self._in.shape}, got {images.shape}")
        np.copyto(self._in, images)
        return self.run()


class ObservationEncoder:
    """Enc(o) of one observation: each of the target encoder's cameras resized to the model's side,
    area-averaged ``downsample`` times per side and centred straight into the graph's bound input (the
    copies and temporaries of a batch path cost as much again as the graph itself;
    docs/experiments.md#encoding-into-the-graph-input)."""

    def __init__(self, graph: OnnxEncoder | bytes, cameras: Sequence[str], image_size: int, downsample: int):
        if downsample < 1 or image_size % downsample:
            raise ValueError(f"downsample {downsample} must be >= 1 and divide the image size {image_size}")
        self.graph = graph if isinstance(graph, OnnxEncoder) else OnnxEncoder(graph)
        self.cameras, self.image_size, self.downsample = tuple(cameras), int(image_size), int(downsample)
        side = self.image_size // self.downsample
        expected = (1, len(self.cameras), 3, side, side)
        if self.graph.input_shape != expected:
            raise ValueError(f"target encoder graph takes {self.graph.input_shape}, but {len(self.cameras)} "
                             f"camera(s) at {self.image_size} px downsampled {self.downsample}x give {expected}")

    def encode(self, obs: Mapping[str, Any]) -> np.ndarray:
        """(d_z,) float32 latent of ``obs``'s target cameras."""
        images = self.graph.inputs[0]
        for camera, dst in zip(self.cameras, images):
            if camera not in obs:
                raise ValueError(f"observation is missing camera {camera!r} "
                                 f"(the target encoder reads {list(self.cameras)})")
            area_downsample(resize_images(check_image(obs[camera], camera), self.image_size), self.downsample, out=dst)
        centre(images, inplace=True)
        return self.graph.run()[0]
