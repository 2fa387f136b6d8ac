"""``RemotePolicy``: a policy served by ``pivla.serving.server`` (or any server of its protocol) as a
``ChunkPolicy``, so pivla's executors, the evaluation loop and the arm drive it like a local one.

``infer`` is one round trip; ``encode`` (AURD's per-step observed latent) runs here on ONNX Runtime with the
server's target-encoder graph, fetched once (a reconnection checks that the server still has the same one),
so an AURD control step crosses the network only when it replans. A dropped connection is reopened on the
next call (the request is sent again: inference has no side effects) and must come back to the same policy;
when it cannot, the call raises
``ConnectionError`` naming the server and the cause.

No PyTorch and no MuJoCo here: NumPy, msgpack, websockets, OpenCV and ONNX Runtime.
"""

from __future__ import annotations

import dataclasses
import hashlib
import threading
import time
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np
from websockets.exceptions import ConnectionClosed, InvalidHandshake, InvalidStatus, InvalidURI
from websockets.frames import CloseCode
from websockets.sync.client import ClientConnection, connect

from pivla.control.contract import ACTION_PREFIX, Calibration, PolicySpec
from pivla.data.normalize import ActionStats
from pivla.model.onnx_encoder import ObservationEncoder
from pivla.model.pixels import resize_images
from pivla.serving import protocol as P
from pivla.serving.msgpack_numpy import packb, unpackb


class ServerError(RuntimeError):
    """The server answered a request with an error frame (its text: the problem or a traceback)."""


class ServerRefused(ConnectionError):
    """The server is reachable but will not serve this client: a wrong API key, another protocol, or (after a
    reconnect) another policy. Not retried."""


def _same_policy(a: Mapping[str, Any], b: Mapping[str, Any]) -> bool:
    """Two metadata maps describe the same served policy (what the client relies on after a reconnect)."""
    keys = ("spec", "action_stats")
    return (all(a.get(k) == b.get(k) for k in keys)
            and a["target_encoder"].get("sha256") == b["target_encoder"].get("sha256"))


class RemotePolicy:
    """A served policy behind ``ChunkPolicy`` / ``BatchPolicy``.

    ``url``: ``ws://host:port`` (``host:port`` means ``ws://``); ``api_key``: sent as
    ``Authorization: Api-Key <key>``; ``timeout``: seconds to wait for a reply (a reply that does not come
    closes the connection: it would arrive out of order); ``retries``: reconnection attempts per call.
    ``local_encoder=False`` sends ``encode`` requests instead of running the graph here. ``outputs``: which
    of the policy's outputs ``infer`` fetches (default: what the executors and calibration read, 5 kB a
    reply instead of 63 kB for the recipe's model; None: all of them).

    Not thread-safe beyond one call at a time (calls are serialised by a lock): one connection answers in
    order. Output arrays are read-only views of the reply.
    """

    def __init__(self, url: str, api_key: str | None = None, timeout: float = 30.0, retries: int = 2,
                 local_encoder: bool = True, outputs: Sequence[str] | None = P.CONTROL_OUTPUTS):
        self.url = url if "://" in url else f"ws://{url}"
        self.api_key, self.timeout, self.retries = api_key, timeout, retries
        self.outputs = list(outputs) if outputs is not None else None
        self._lock = threading.Lock()
        self._ws: ClientConnection | None = None
        self.reconnects = 0
        self.last_server_ms: float | None = None  # the server's own time for the last infer (server_timing)
        self.metadata = self._open()
        self.spec = PolicySpec.from_dict(self.metadata["spec"])
        fields = {f.name for f in dataclasses.fields(Calibration)}
        calib = self.metadata.get("calibration")
        self.calibration: Calibration | None = (
            Calibration(**{k: v for k, v in calib.items() if k in fields}) if calib is not None else None)
        self.action_stats = ActionStats(**self.metadata["action_stats"])
        self._encoder = self._local_encoder() if local_encoder else None
        # where encode runs, as ``Policy.encoder_runtime`` says it for a local policy
        self.encoder_runtime = "onnx" if self._encoder is not None else "server"

    # -- ChunkPolicy ---------------------------------------------------------------------------------
    def infer(self, obs: Mapping[str, Any]) -> dict[str, np.ndarray]:
        """One observation -> the served policy's outputs (``actions`` (K, 7) physical, ...)."""
        return self._outputs(self._call({P.METHOD_KEY: "infer", "observation": self.wire_observation(obs),
                                         "outputs": self.outputs}))

    def infer_batch(self, obs_list: Sequence[Mapping[str, Any]]) -> dict[str, np.ndarray]:
        """Several observations in one request (at most the server's ``max_batch``)."""
        return self._outputs(self._call({P.METHOD_KEY: "infer_batch", "outputs": self.outputs,
                                         "observations": [self.wire_observation(o) for o in obs_list]}))

    def encode(self, obs: Mapping[str, Any]) -> np.ndarray:
        """Enc(o), (d_z,): on this machine when the server handed out its graph, else one round trip."""
        if self._encoder is not None:
            return self._encoder.encode(obs)
        return self._call({P.METHOD_KEY: "encode", "observation": self.wire_observation(obs, encode=True)})["latent"]

    def encode_batch(self, obs_list: Sequence[Mapping[str, Any]]) -> np.ndarray:
        """(N, d_z) latents."""
        if self._encoder is not None:
            return np.stack([self._encoder.encode(o) for o in obs_list])
        return self._call({P.METHOD_KEY: "encode_batch",
                           "observations": [self.wire_observation(o, encode=True) for o in obs_list]})["latents"]

    def to_actions(self, normalized: np.ndarray) -> np.ndarray:
        """Normalized actions -> physical ones, with the served run's statistics."""
        return self.action_stats.unnormalize(normalized)

    def close(self) -> None:
        with self._lock:
            self._drop()

    def __enter__(self) -> RemotePolicy:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # -- wire ----------------------------------------------------------------------------------------
    def wire_observation(self, obs: Mapping[str, Any], encode: bool = False) -> dict[str, Any]:
        """What is sent for ``obs``: the keys the server reads (for an encoding, the target encoder's cameras)
        and nothing else, pictures already resized to the model's side (as the server would: a camera's
        640x480 frame crosses the network as an 80x80 one). Anything malformed goes as it is, for the server
        to name the problem."""
        cameras = self.spec.cameras[: self.spec.target_cameras] if encode else self.spec.cameras
        wire = {c: self._model_picture(obs[c]) for c in cameras if c in obs}
        keys = () if encode else (*P.INSTRUCTION_KEYS, ACTION_PREFIX)
        if self.spec.target_proprio or not encode:
            keys = (*self.spec.proprio_keys, *keys)
        wire.update({k: obs[k] for k in keys if k in obs})
        return wire

    def _model_picture(self, image: Any) -> Any:
        if (isinstance(image, np.ndarray) and image.dtype == np.uint8 and image.ndim == 3 and image.shape[-1] == 3
                and min(image.shape[:2]) > 0):
            return resize_images(image, self.spec.image_size)
        return image

    def _outputs(self, reply: dict) -> dict[str, np.ndarray]:
        timing = reply.pop(P.TIMING_KEY, None)
        self.last_server_ms = timing.get("infer_ms") if isinstance(timing, dict) else None
        return reply

    def _open(self) -> dict:
        """A new connection and the server's metadata."""
        headers = {"Authorization": f"Api-Key {self.api_key}"} if self.api_key else None
        try:
            ws = connect(self.url, additional_headers=headers, compression=None, max_size=None,
                         open_timeout=self.timeout, legacy=True)
        except InvalidStatus as e:
            body = e.response.body.decode(errors="replace").strip() if e.response.body else ""
            raise ServerRefused(f"pivla server at {self.url} refused the connection: HTTP "
                                f"{e.response.status_code} {body}") from None
        except InvalidURI as e:
            raise ValueError(f"not a WebSocket URL: {self.url!r} ({e})") from None
        except InvalidHandshake as e:
            raise ServerRefused(f"{self.url} is no WebSocket server ({e})") from None
        except OSError as e:  # refused, unreachable, timed out
            raise ConnectionError(f"pivla server at {self.url} unreachable ({e})") from None
        try:
            frame = ws.recv(timeout=self.timeout)
        except (ConnectionClosed, TimeoutError) as e:
            ws.close()
            raise ConnectionError(f"pivla server at {self.url} sent no metadata ({e})") from None
        try:
            metadata = unpackb(frame) if isinstance(frame, bytes) else None
        except ValueError:
            metadata = None
        if not isinstance(metadata, dict) or metadata.get("protocol") != P.PROTOCOL:
            ws.close()
            raise ServerRefused(f"{self.url} does not speak {P.PROTOCOL} (its first frame: {str(frame)[:200]!r})")
        self._ws = ws
        return metadata

    def _drop(self) -> None:
        if self._ws is not None:
            self._ws.close()
            self._ws = None

    def _reconnect(self) -> None:
        metadata = self._open()
        if not _same_policy(metadata, self.metadata):
            self._drop()
            raise ServerRefused(f"pivla server at {self.url} now serves a different policy (spec, action "
                                "normalization or target encoder changed); make a new RemotePolicy")
        self.reconnects += 1

    def _call(self, request: dict) -> dict:
        """One request, one reply; a dropped connection is reopened up to ``retries`` times."""
        frame = packb(request)
        with self._lock:
            failure: Exception | None = None
            for attempt in range(self.retries + 1):
                if self._ws is None:
                    if attempt:
                        time.sleep(min(0.1 * 2 ** attempt, 2.0))
                    try:
                        self._reconnect()
                    except ServerRefused:
                        raise
                    except ConnectionError as e:
                        failure = e
                        continue
                try:
                    self._ws.send(frame)
                    reply = self._ws.recv(timeout=self.timeout)
                except TimeoutError:
                    self._drop()
                    raise TimeoutError(f"pivla server at {self.url}: no reply within {self.timeout} s") from None
                except (ConnectionClosed, OSError) as e:
                    self._drop()
                    if (isinstance(e, ConnectionClosed) and e.rcvd is not None
                            and e.rcvd.code == CloseCode.MESSAGE_TOO_BIG):
                        raise ValueError(f"request of {len(frame)} bytes is larger than the server accepts "
                                         f"({self.metadata['limits']['max_message_bytes']})") from None
                    failure = e
                    continue
                if isinstance(reply, str):
                    raise ServerError(f"pivla server at {self.url}: {reply}")
                return unpackb(reply)
        raise ConnectionError(f"pivla server at {self.url}: connection lost, {self.retries} reconnection "
                              f"attempt(s) failed (last: {failure})")

    def _local_encoder(self) -> ObservationEncoder | None:
        info = self.metadata["target_encoder"]
        if info.get("runtime") != "onnx":
            return None
        reply = self._call({P.METHOD_KEY: "target_encoder"})
        graph = reply["onnx"]
        if hashlib.sha256(graph).hexdigest() != info["sha256"]:
            raise ConnectionError(f"pivla server at {self.url}: target encoder graph does not match its digest")
        return ObservationEncoder(graph, info["cameras"], info["image_size"], info["downsample"])


def open_policy(target: str, api_key: str | None = None, **local: Any) -> Any:
    """A ``ChunkPolicy`` from a run directory (loaded here, with ``local`` options of ``load_policy``) or from
    ``ws://HOST:PORT`` (a served policy: ``RemotePolicy``); executors, evaluation and the arm take either."""
    if target.startswith(("ws://", "wss://")):
        return RemotePolicy(target, api_key=api_key)
    from pivla.policy import load_policy  # torch: only where the policy runs locally

    return load_policy(target, **local)
