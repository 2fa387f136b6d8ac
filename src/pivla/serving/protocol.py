"""The wire protocol of ``pivla.serving``: openpi's, plus a few named methods.

Transport: one WebSocket connection per client (``ws://host:port``, no compression), binary frames of
msgpack with NumPy arrays encoded as openpi's ``msgpack_numpy`` does (:mod:`pivla.serving.msgpack_numpy`).
When the server has an API key, the opening request must carry ``Authorization: Api-Key <key>`` (else HTTP
401). ``GET /healthz`` answers 200 ``OK`` without a key, for load balancers. The server speaks plain
``ws://``; beyond a trusted network, put a TLS-terminating proxy in front and connect to ``wss://``.

1. On connect the server sends one binary frame, the **metadata** map:

   ``protocol`` ("pivla-serving/1"), ``pivla_version``; ``spec``: ``PolicySpec.to_dict()`` (camera keys
   and image size, proprio keys with lengths, chunk K, horizon H, action dim and space, latent dim, target
   cameras, whether the target latent reads the proprio); ``calibration``: AURD's thresholds (a dict, or None
   when the run was not calibrated);
   ``action_stats``: the action normalization (q01, q99, gripper_dim) that ``to_actions`` needs;
   ``target_encoder``: how a client computes AURD's observed latent (below); ``limits``:
   max_message_bytes, max_image_side, max_batch, idle_timeout_s; ``methods``: the request methods below.

2. Each **request** is one binary frame holding a map, answered in order by one binary frame:

   - an observation map (openpi's request): the policy's camera keys (HxWx3 uint8, any size up to
     ``max_image_side``, resized to the model's), its proprio keys (numbers, each of its declared length,
     finite) and ``instruction`` or openpi's ``prompt`` (a str; both may be given if they are equal); for a
     policy whose spec has ``action_prefix`` P > 0, optionally ``action_prefix``: the (n, D) physical actions,
     n <= P, the arm executes while the query is in flight. Other keys are ignored. Reply: the policy's
     ``infer`` output, ``actions`` (K, 7) physical and the rest (``actions_normalized``, ``u_act``,
     ``latents``, ``values``, ...), plus ``server_timing`` ``{"infer_ms": float}`` as openpi's server adds it.
   - ``{"method": "infer", "observation": obs, "outputs": [names]}``: the same, with only the named
     outputs (``outputs`` is optional). An AURD client needs ``CONTROL_OUTPUTS``: 5 kB for the recipe's
     model where all outputs take 63 kB (``discrete_probs`` alone is K x 7 x 256 floats).
   - ``{"method": "infer_batch", "observations": [obs, ...], "outputs": [names]}`` (at most
     ``max_batch``): the same outputs with a leading batch axis.
   - ``{"method": "encode", "observation": obs}``: ``{"latent": (d_z,)}``;
     ``{"method": "encode_batch", "observations": [...]}``: ``{"latents": (N, d_z)}``. Only the target
     encoder's cameras are needed, and the proprio keys when ``target_proprio`` (no instruction).
   - ``{"method": "target_encoder"}``: ``{"onnx": <graph bytes>, "sha256": <hex>}``.

   The key ``method`` is reserved: an observation never carries it.

3. **Errors**: a request that cannot be answered gets one *text* frame instead, the problem in words (a
   bad request) or the server's traceback (a failure while answering); the connection stays open for the
   next request. A message over ``max_message_bytes`` closes the connection (code 1009); so does
   ``idle_timeout_s`` without a request (code 1001, when it is not 0).

**The target encoder travels to the client.** AURD encodes every new observation but queries the policy
only when it replans, so encoding locally leaves only replans on the network. ``target_encoder`` in the
metadata is either ``{"runtime": "onnx", "sha256", "size_bytes", "cameras": [keys], "image_size",
"downsample", "input_shape", "latent_dim"}``: fetch the graph with the ``target_encoder`` method, check its
digest, and prepare an observation as :class:`pivla.model.onnx_encoder.ObservationEncoder` does (area-resize
each listed camera to ``image_size``, area-average by ``downsample``, scale to [-1, 1], CHW float32, batch 1); or
``{"runtime": "server"}`` when the policy's target encoder has no ONNX export (a DINOv2 or thumbnail target,
or onnxruntime missing on the server): the client then sends ``encode`` requests. The graph is not in the
metadata itself so that a client that never encodes (openpi's) does not download it on every connect.

**Several clients**: requests from all connections go to one inference worker thread, first come first
served; each is answered on its own (no batching across clients), so a client's outputs do not depend on
who else is connected.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np

from pivla.control.contract import ACTION_PREFIX, PolicySpec, action_prefix_of

PROTOCOL = "pivla-serving/1"
METHOD_KEY = "method"
METHODS = ("infer", "infer_batch", "encode", "encode_batch", "target_encoder")
INSTRUCTION_KEYS = ("instruction", "prompt")  # pivla's name and openpi's
TIMING_KEY = "server_timing"
# what executors, calibration and the evaluation read of a policy's outputs (``pivla.control``)
CONTROL_OUTPUTS = ("actions", "actions_normalized", "u_act", "latents", "values", "value_now")


class RequestError(ValueError):
    """A request the server cannot answer as sent; the text, sent back as an error frame, says why."""


def instruction_of(obs: Mapping[str, Any]) -> str:
    """The task text of an observation, under ``instruction`` or openpi's ``prompt``."""
    given = {k: obs[k] for k in INSTRUCTION_KEYS if k in obs}
    if not given:
        raise RequestError("observation is missing 'instruction' (or openpi's 'prompt'): the task as a str")
    for key, text in given.items():
        if not isinstance(text, str):
            raise RequestError(f"observation {key!r} must be a str, got {type(text).__name__}")
    if len(set(given.values())) > 1:
        raise RequestError("observation has both 'instruction' and 'prompt', and they differ")
    return next(iter(given.values()))


def check_image(obs: Mapping[str, Any], camera: str, max_side: int) -> np.ndarray:
    """A camera's picture as sent, once it is an HxWx3 uint8 array of a size the server accepts."""
    if camera not in obs:
        raise RequestError(f"observation is missing camera {camera!r}")
    im = obs[camera]
    if not isinstance(im, np.ndarray):
        raise RequestError(f"observation {camera!r} must be an array (msgpack-numpy), got {type(im).__name__}")
    if im.dtype != np.uint8 or im.ndim != 3 or im.shape[2] != 3:
        raise RequestError(f"observation {camera!r} must be an HxWx3 uint8 image, got {im.dtype} {im.shape}")
    if not (1 <= im.shape[0] <= max_side and 1 <= im.shape[1] <= max_side):
        raise RequestError(f"observation {camera!r} is {im.shape[1]}x{im.shape[0]} px; this server takes sides "
                           f"of 1 to {max_side} px")
    return im


def check_proprio(obs: Mapping[str, Any], key: str, length: int) -> np.ndarray:
    """A proprioceptive entry as a flat array of ``length`` finite numbers."""
    if key not in obs:
        raise RequestError(f"observation is missing proprio key {key!r} ({length} numbers)")
    try:
        arr = np.asarray(obs[key])
    except (ValueError, TypeError):
        arr = np.asarray(None)
    if arr.dtype.kind not in "biuf" or arr.ndim > 1 or arr.size != length:
        raise RequestError(f"observation {key!r} must be {length} numbers, got {arr.dtype} {arr.shape}")
    if not np.isfinite(arr.astype(np.float64)).all():
        raise RequestError(f"observation {key!r} contains NaN or inf")
    return arr.reshape(length)


def check_observation(obs: Any, spec: PolicySpec, max_image_side: int, cameras: int | None = None,
                      proprio: bool = True, text: bool | None = None) -> dict[str, Any]:
    """The observation the policy reads, with ``prompt`` renamed ``instruction``; ``cameras``: only the
    first so many (an encoding needs the target encoder's), ``proprio``: also the proprio keys, ``text``: also
    the instruction (default: with the proprio; an encoding whose latent reads the proprio needs no text)."""
    if not isinstance(obs, Mapping):
        raise RequestError(f"an observation is a map of key -> value, got {type(obs).__name__}")
    if METHOD_KEY in obs:
        raise RequestError(f"an observation cannot carry the reserved key {METHOD_KEY!r}")
    out: dict[str, Any] = {c: check_image(obs, c, max_image_side) for c in spec.cameras[:cameras]}
    if proprio:
        out.update({k: check_proprio(obs, k, n) for k, n in spec.proprio})
    if proprio if text is None else text:  # the instruction goes with the proprio unless told otherwise
        out["instruction"] = instruction_of(obs)
        try:
            prefix = action_prefix_of(obs, spec)
        except ValueError as e:
            raise RequestError(str(e)) from None
        if prefix is not None:
            out[ACTION_PREFIX] = prefix
    return out
