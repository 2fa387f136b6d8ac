"""Serve a pivla policy over WebSockets with openpi's protocol (``pivla.serving.protocol`` describes it).

``serve(ServeConfig(policy="runs/pp"))`` loads the run and answers until SIGINT / SIGTERM. openpi's own
client (``openpi_client.websocket_client_policy.WebsocketClientPolicy``) works against it unchanged, and
:class:`pivla.serving.client.RemotePolicy` makes the served policy a ``ChunkPolicy`` for pivla's executors,
with AURD's per-step target encoding on the client (the graph is handed out by the ``target_encoder`` method).

Built on ``websockets``' asyncio server: one event loop does all network I/O (handshakes, the ``/healthz``
check, pings, many idle connections, clients that vanish or go silent) and never runs the model, and one inference
worker thread answers the requests of all connections first come, first served (see the protocol). A
thread per connection (the sync server) would need a lock around the model anyway, and would keep a thread
per idle client; the loop also keeps answering health checks while a long inference runs.

What a client sends is checked before it reaches the model: the message size by the WebSocket layer (a
larger message closes that connection), then every array header while decoding (dtype, shape, data
length), then each observation against the policy's spec (keys, image dtype, shape and size, proprio
lengths, NaN / inf, the instruction). Each problem is answered with a text frame naming it and the
connection stays usable; nothing a client sends stops the server or delays other clients beyond its own
queued requests.
"""

from __future__ import annotations

import asyncio
import copy
import dataclasses
import hashlib
import hmac
import http
import ipaddress
import logging
import signal
import threading
import time
import traceback
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any
from urllib.parse import urlsplit

import numpy as np
from websockets.asyncio.server import ServerConnection
from websockets.asyncio.server import serve as ws_serve
from websockets.exceptions import ConnectionClosed, ConnectionClosedOK
from websockets.frames import CloseCode
from websockets.http11 import Request, Response

import pivla
from pivla.control.contract import PolicySpec
from pivla.control.latency import Latency, latency_rng, parse_latency
from pivla.model import encoder_runtime as er
from pivla.model.backbone import ConvEncoder
from pivla.model.config import PROPRIO_LENGTHS
from pivla.model.onnx_encoder import ObservationEncoder
from pivla.policy import load_policy
from pivla.serving import protocol as P
from pivla.serving.msgpack_numpy import DecodeError, packb, unpackb

log = logging.getLogger(__name__)


@dataclasses.dataclass
class ServeConfig:
    """How to serve one policy."""

    policy: str = ""
    """Run directory written by `pivla train`."""
    host: str = "127.0.0.1"
    """Interface to bind; anything but loopback needs an API key."""
    port: int = 8000
    """TCP port (openpi's default)."""
    api_key_file: str = ""
    """File holding the API key clients send as "Authorization: Api-Key <key>"."""
    max_message_bytes: int = 16 * 2**20
    """Larger requests close their connection (WebSocket code 1009)."""
    max_image_side: int = 1024
    """Largest accepted camera picture side, px (pictures are resized to the model's)."""
    max_batch: int = 64
    """Observations per infer_batch / encode_batch request."""
    max_connections: int = 64
    """Open connections; more are answered HTTP 503."""
    idle_timeout_s: float = 600.0
    """A connection that sends nothing for this long is closed (code 1001), so clients that forget to close
    do not use up max_connections; 0 keeps idle connections open. RemotePolicy reconnects transparently."""
    device: str = "cpu"
    """Where the policy runs: cpu, cuda, auto."""
    threads: int = 0
    """Torch intra-op threads (0: torch's default)."""
    encoder_runtime: str = "auto"
    """The server's own target encoding (encode requests): auto, torch, onnx."""
    delay_ms: str = "0"
    """Answer each policy query (infer, infer_batch) no earlier than this long after it arrived: MEAN[:JITTER] ms,
    lognormal, to try asynchronous execution against a slower model or network (docs/latency.md)."""
    delay_seed: int = 0
    """Seed of the delays; each connection draws its own sequence from it, one delay per query, in order (the
    stream ``pivla eval --latency-ms`` draws an episode's latencies from when given the episode's seed)."""


def is_loopback(host: str) -> bool:
    """True when ``host`` is reachable only from this machine."""
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False  # a host name other than localhost may resolve to any interface


def read_api_key(path: str) -> str | None:
    """The key in ``path`` (surrounding whitespace removed), None when no file is configured."""
    if not path:
        return None
    try:
        key = Path(path).read_text().strip()
    except OSError as e:
        raise ValueError(f"api_key_file {path}: cannot read it ({e.strerror})") from None
    if not key or any(c.isspace() for c in key):
        raise ValueError(f"api_key_file {path}: must hold one key without spaces")
    return key


def spec_of(policy: Any) -> PolicySpec:
    """``policy.spec``, with the proprio lengths a run written before they were stored leaves unknown (-1)
    taken from pivla's observation convention (``PROPRIO_LENGTHS``; one other key, such as ``joint_states``,
    whose length is the arm's, gets the rest of proprio_dim)."""
    spec = policy.spec
    if all(n > 0 for _, n in spec.proprio):
        return spec
    keys, total = spec.proprio_keys, len(policy.stats.proprio.mean)
    known = {k: PROPRIO_LENGTHS[k] for k in keys if k in PROPRIO_LENGTHS}
    unknown = [k for k in keys if k not in known]
    rest = total - sum(known.values())
    if len(unknown) > 1 or (not unknown and rest != 0) or (unknown and rest < 1):
        raise ValueError(f"cannot tell the lengths of the proprio keys {list(keys)} ({total} numbers in all) of a "
                         f"run that did not record them (known lengths: {PROPRIO_LENGTHS})")
    lengths = {**known, **{k: rest for k in unknown}}
    return dataclasses.replace(spec, proprio=tuple((k, lengths[k]) for k in keys))


def _probe_observations(spec: PolicySpec, n: int = 2) -> list[dict]:
    rng = np.random.default_rng(0)
    return [{c: rng.integers(0, 256, (spec.image_size, spec.image_size, 3), dtype=np.uint8)
             for c in spec.cameras[: spec.target_cameras]} for _ in range(n)]


def target_encoder_graph(policy: Any, spec: PolicySpec) -> tuple[bytes, int] | None:
    """The policy's target encoder as an ONNX graph that :class:`ObservationEncoder` runs, with its
    downsampling factor, or None (logged) when it has none: only the small backbone's CNN is exported.

    The graph the policy encodes with is handed out, else (a policy on a GPU) one is exported; either way a
    client's encoding of probe observations must agree with ``policy.encode`` before it is."""
    policy = getattr(policy, "lead", policy)  # an ensemble of runs encodes with its first member's encoder
    target = policy.model.target
    if target.proprio > 0:
        log.info("the target latent reads the proprio too: clients encode on the server")
        return None
    if not isinstance(target.encoder, ConvEncoder):
        log.info("target encoder %s has no ONNX export: clients encode on the server", type(target.encoder).__name__)
        return None
    if not er.onnx_available():
        log.info("onnxruntime / onnx / onnxscript missing: clients encode on the server")
        return None
    cameras = spec.cameras[: spec.target_cameras]
    probes = _probe_observations(spec)
    expected = [policy.encode(o) for o in probes]

    def agrees(graph: bytes) -> bool:
        try:
            local = ObservationEncoder(graph, cameras, spec.image_size, target.downsample)
            return all(np.allclose(local.encode(o), e, atol=1e-4, rtol=1e-3) for o, e in zip(probes, expected))
        except Exception as e:  # noqa: BLE001 - ONNX Runtime raises its own types for a graph it cannot run
            log.info("target encoder graph unusable (%s)", e)
            return False

    graph = policy.target_graph  # the graph the policy itself encodes with (None: it runs on PyTorch)
    if graph is not None and agrees(graph):
        return graph, target.downsample
    module = target if policy.device.type == "cpu" else copy.deepcopy(target).cpu()
    side = spec.image_size // target.downsample
    try:
        graph = er.export_onnx(er.TargetLatents(module), (spec.target_cameras, 3, side, side))
    except Exception as e:  # noqa: BLE001 - the exporter raises many types; encode requests still work
        log.warning("target encoder: ONNX export failed (%s: %s); clients encode on the server", type(e).__name__, e)
        return None
    if not agrees(graph):
        log.warning("target encoder: the exported graph disagrees with the policy; clients encode on the server")
        return None
    return graph, target.downsample


class PolicyService:
    """Everything a request needs apart from the network: metadata, decoding, checks, the policy call and
    the encoded reply. ``answer`` runs on the inference worker thread only."""

    def __init__(self, policy: Any, cfg: ServeConfig):
        self.policy, self.cfg = policy, cfg
        self.spec = spec_of(policy)
        found = target_encoder_graph(policy, self.spec)
        self.graph = found[0] if found else None
        if found:
            graph, downsample = found
            side = self.spec.image_size // downsample
            target = {"runtime": "onnx", "sha256": hashlib.sha256(graph).hexdigest(), "size_bytes": len(graph),
                      "cameras": list(self.spec.cameras[: self.spec.target_cameras]),
                      "image_size": self.spec.image_size, "downsample": downsample,
                      "input_shape": [1, self.spec.target_cameras, 3, side, side], "latent_dim": self.spec.latent_dim}
        else:
            target = {"runtime": "server"}
        calibration = getattr(policy, "calibration", None)
        self.metadata = {
            "protocol": P.PROTOCOL, "pivla_version": pivla.__version__, "spec": self.spec.to_dict(),
            "calibration": dataclasses.asdict(calibration) if calibration is not None else None,
            "action_stats": dataclasses.asdict(policy.stats.action), "target_encoder": target,
            "limits": {"max_message_bytes": cfg.max_message_bytes, "max_image_side": cfg.max_image_side,
                       "max_batch": cfg.max_batch, "idle_timeout_s": cfg.idle_timeout_s},
            "methods": list(P.METHODS),
        }
        self.metadata_frame = packb(self.metadata)

    def answer(self, message: bytes | str) -> tuple[bytes | str, bool]:
        """The reply frame to one request (binary msgpack, or a text frame saying what went wrong), and whether
        it answered a policy query (infer, infer_batch: what ``--delay-ms`` holds back)."""
        try:
            if isinstance(message, str):
                raise P.RequestError("requests are binary msgpack frames, got a text frame")
            request = unpackb(message)
            reply = packb(self._dispatch(request))
            method = request.get(P.METHOD_KEY, "infer") if isinstance(request, dict) else None
            return reply, method in ("infer", "infer_batch")
        except (P.RequestError, DecodeError) as e:
            log.info("bad request: %s", e)
            return f"bad request: {e}", False
        except Exception:  # noqa: BLE001 - the client gets the traceback and the server goes on
            log.exception("request failed")
            return traceback.format_exc(), False

    def _observations(self, request: dict, **checks: Any) -> list[dict]:
        items = request.get("observations")
        if not isinstance(items, list) or not 1 <= len(items) <= self.cfg.max_batch:
            raise P.RequestError(f"'observations' must be a list of 1 to {self.cfg.max_batch} observations")
        return [P.check_observation(o, self.spec, self.cfg.max_image_side, **checks) for o in items]

    @staticmethod
    def _select(outputs: dict, request: dict) -> dict:
        """The outputs a method call names in ``outputs`` (all when it names none)."""
        names = request.get("outputs") if P.METHOD_KEY in request else None
        if names is None:
            return outputs
        if not isinstance(names, list) or not all(isinstance(n, str) for n in names):
            raise P.RequestError("'outputs' must be a list of output names")
        unknown = sorted(set(names) - set(outputs))
        if unknown:
            raise P.RequestError(f"unknown outputs {unknown}; this policy returns {sorted(outputs)}")
        return {n: outputs[n] for n in names}

    def _dispatch(self, request: Any) -> dict:
        if not isinstance(request, dict):
            raise P.RequestError(f"a request is a map (an observation or a method call), got {type(request).__name__}")
        method = request.get(P.METHOD_KEY, "infer")
        encode_only = {"cameras": self.spec.target_cameras, "proprio": self.spec.target_proprio, "text": False}
        t0 = time.perf_counter()
        if method == "infer":
            obs = request.get("observation") if P.METHOD_KEY in request else request
            reply: dict = self._infer(self.policy.infer, P.check_observation(obs, self.spec, self.cfg.max_image_side))
            reply = self._select(reply, request)
        elif method == "infer_batch":
            reply = self._select(self._infer(self.policy.infer_batch, self._observations(request)), request)
        elif method == "encode":
            obs = P.check_observation(request.get("observation"), self.spec, self.cfg.max_image_side, **encode_only)
            return {"latent": self.policy.encode(obs)}
        elif method == "encode_batch":
            return {"latents": self.policy.encode_batch(self._observations(request, **encode_only))}
        elif method == "target_encoder":
            if self.graph is None:
                raise P.RequestError("this policy's target encoder has no ONNX graph; send 'encode' requests")
            return {"onnx": self.graph, "sha256": self.metadata["target_encoder"]["sha256"]}
        else:
            raise P.RequestError(f"unknown method {method!r}; methods: {list(P.METHODS)}")
        reply[P.TIMING_KEY] = {"infer_ms": (time.perf_counter() - t0) * 1e3}
        return reply

    @staticmethod
    def _infer(fn: Any, observations: Any) -> dict:
        """The policy's answer; a ValueError is the policy refusing this input (a value its input pipeline
        rejects, or one so far out of range that the actions come out non-finite), which the client is told."""
        try:
            return fn(observations)
        except ValueError as e:
            raise P.RequestError(str(e)) from e


class _Server:
    """The asyncio side: handshake checks, one handler per connection, the inference worker."""

    def __init__(self, service: PolicyService, cfg: ServeConfig, api_key: str | None, delay: Latency):
        self.service, self.cfg, self.delay = service, cfg, delay
        self.expected_auth = f"Api-Key {api_key}".encode() if api_key else None
        self.worker = ThreadPoolExecutor(max_workers=1, thread_name_prefix="pivla-infer")
        self.server: Any = None

    def process_request(self, connection: ServerConnection, request: Request) -> Response | None:
        if urlsplit(request.path).path == "/healthz":
            return connection.respond(http.HTTPStatus.OK, "OK\n")
        if self.expected_auth is not None:
            given = request.headers.get("Authorization", "").encode()
            if not hmac.compare_digest(given, self.expected_auth):
                log.info("refused %s: missing or wrong API key", connection.remote_address)
                return connection.respond(http.HTTPStatus.UNAUTHORIZED,
                                          "missing or wrong API key: send the header 'Authorization: Api-Key <key>'\n")
        if len(self.server.connections) >= self.cfg.max_connections:
            return connection.respond(http.HTTPStatus.SERVICE_UNAVAILABLE,
                                      f"server busy: {self.cfg.max_connections} connections open\n")
        return None

    async def handler(self, ws: ServerConnection) -> None:
        loop = asyncio.get_running_loop()
        peer = ws.remote_address
        log.info("client %s connected", peer)
        idle = self.cfg.idle_timeout_s or None
        delays = latency_rng(self.cfg.delay_seed)  # per connection: its delays do not depend on other clients
        try:
            await ws.send(self.service.metadata_frame)
            while True:
                try:
                    message = await asyncio.wait_for(ws.recv(), idle)
                except TimeoutError:
                    log.info("client %s idle for %g s: closing", peer, idle)
                    await ws.close(CloseCode.GOING_AWAY, f"idle for {idle:g} s")
                    return
                received = loop.time()
                reply, query = await loop.run_in_executor(self.worker, self.service.answer, message)
                if query and not self.delay.zero:  # held here, not on the worker: other clients are not delayed
                    await asyncio.sleep(max(0.0, received + self.delay.draw_ms(delays) / 1e3 - loop.time()))
                await ws.send(reply)
        except ConnectionClosedOK:
            log.info("client %s disconnected", peer)
        except ConnectionClosed as e:
            log.info("client %s gone (%s)", peer, e)

    async def run(self) -> None:
        stop = asyncio.Event()
        loop = asyncio.get_running_loop()
        if threading.current_thread() is threading.main_thread():
            for sig in (signal.SIGINT, signal.SIGTERM):
                loop.add_signal_handler(sig, stop.set)
        try:
            async with ws_serve(self.handler, self.cfg.host, self.cfg.port, process_request=self.process_request,
                                compression=None, max_size=self.cfg.max_message_bytes) as server:
                self.server = server
                log.info("serving %s on ws://%s:%d (protocol %s, target encoder: %s)", self.cfg.policy or "a policy",
                         self.cfg.host, self.cfg.port, P.PROTOCOL, self.service.metadata["target_encoder"]["runtime"])
                if not self.delay.zero:
                    log.info("policy answers held back %s ms (mean:jitter, seed %d)", self.delay, self.cfg.delay_seed)
                await stop.wait()
                log.info("shutting down")
        finally:
            self.worker.shutdown(wait=True, cancel_futures=True)


def serve(cfg: ServeConfig, policy: Any = None) -> None:
    """Serve ``cfg.policy`` (or an already loaded ``policy``) until SIGINT / SIGTERM.

    Refuses, before loading anything, to bind a non-loopback host without an API key: the policy drives a
    robot, and anyone who reaches the port could query it."""
    if not cfg.idle_timeout_s >= 0:
        raise ValueError(f"ServeConfig.idle_timeout_s: {cfg.idle_timeout_s} (seconds >= 0; 0 keeps idle connections)")
    try:
        delay = parse_latency(cfg.delay_ms, allow_real=False)
    except ValueError as e:
        raise ValueError(f"--delay-ms {e}") from None
    api_key = read_api_key(cfg.api_key_file)
    if api_key is None and not is_loopback(cfg.host):
        raise ValueError(f"refusing to serve on {cfg.host!r} without an API key: anyone who can reach the port "
                         "could query the policy. Give an API key file (api_key_file, --api-key-file; clients send "
                         "'Authorization: Api-Key <key>') "
                         "or bind 127.0.0.1")
    if policy is None:
        if not cfg.policy:
            raise ValueError("ServeConfig.policy: give the run directory to serve")
        policy = load_policy(cfg.policy, device=cfg.device, threads=cfg.threads, encoder_runtime=cfg.encoder_runtime)
    asyncio.run(_Server(PolicyService(policy, cfg), cfg, api_key, delay).run())
