"""What serving costs: a policy query over loopback against the same query in-process, and AURD's closed
loop on the twin with a ``RemotePolicy`` against a local policy.

The server runs in its own process (as deployed) with the default configuration's untrained policy, built
from the same seed as the in-process one, so both sides compute the same outputs (checked). Rounds alternate
local and remote so that machine noise hits both alike; figures are medians over rounds.

- *round trip*: p50 / p99 of ``infer`` at batch 1, and per request the part that is not the server's own
  compute (``transport``: serialisation, WebSocket framing, loopback, the worker hand-off, and the wake-up
  of the waiting client, which on a machine busy with other jobs can wait for the scheduler's next tick);
  also an ``encode`` request answered on the server, whose compute is ~0.1 ms;
- *closed loop*: whole ``pick_place`` episodes under AURD with its thresholds lifted (it completes every
  nominal horizon, so both sides make the same queries); control ms per step as ``run_episode`` times it.
  AURD's per-step encoding runs on the client in both cases; only replans cross the network.
"""

from __future__ import annotations

import multiprocessing as mp
import socket
import time
import urllib.request
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch

from pivla.bench.policy import default_policy, random_obs
from pivla.control.executors import make_executor
from pivla.control.runner import run_episode
from pivla.envs import make_env
from pivla.envs.rollout import episode_seed
from pivla.serving.client import RemotePolicy
from pivla.serving.msgpack_numpy import packb
from pivla.serving.server import ServeConfig, serve


@dataclass
class ServeBenchConfig:
    """What ``run_serve_bench`` measures."""

    requests: int = 200
    """Timed queries per side and round."""
    warmup: int = 20
    """Untimed queries per side and round first."""
    rounds: int = 3
    """Alternating local / remote rounds."""
    loop_episodes: int = 2
    """Twin episodes per side and round (0: skip the closed loop)."""
    loop_max_steps: int = 80
    """Control steps per episode at most."""
    threads: int = 1
    """Torch intra-op threads, in-process and in the server. One: on a busy 2-core machine two threads per
    process oversubscribe the cores, and a batch-1 query took 5-15x as long."""
    seed: int = 0
    """Weights of the untrained policy, observations and episode seeds."""
    startup_timeout: float = 180.0
    """Seconds for the server process to answer /healthz."""


def _default_policy(cfg: ServeBenchConfig) -> Any:
    torch.manual_seed(cfg.seed)
    return default_policy(None)


def _serve_default(cfg: ServeBenchConfig, port: int) -> None:
    """Server process: the same untrained policy as the in-process side, on loopback."""
    torch.set_num_threads(cfg.threads)
    serve(ServeConfig(port=port, threads=cfg.threads), policy=_default_policy(cfg))


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _wait_healthy(port: int, proc: mp.process.BaseProcess, timeout: float) -> None:
    deadline = time.monotonic() + timeout
    while True:
        try:
            with urllib.request.urlopen(f"http://127.0.0.1:{port}/healthz", timeout=5) as r:
                if r.status == 200:
                    return
        except OSError:
            pass
        if not proc.is_alive():
            raise RuntimeError(f"benchmark server exited with code {proc.exitcode} before answering /healthz")
        if time.monotonic() > deadline:
            raise TimeoutError(f"benchmark server did not answer /healthz within {timeout} s")
        time.sleep(0.2)


def _percentiles(times_s: list[float]) -> tuple[float, float]:
    ms = np.asarray(times_s) * 1e3
    return float(np.percentile(ms, 50)), float(np.percentile(ms, 99))


def _round_trips(local: Any, remote: RemotePolicy, observations: list[dict], cfg: ServeBenchConfig) -> dict:
    rounds: dict[str, list] = {"local_p50": [], "local_p99": [], "remote_p50": [], "remote_p99": [],
                               "transport_p50": [], "server_p50": []}
    for _ in range(cfg.rounds):
        for side, policy in (("local", local), ("remote", remote)):
            times, transport, server = [], [], []
            for i in range(cfg.warmup + cfg.requests):
                obs = observations[i % len(observations)]
                t0 = time.perf_counter()
                policy.infer(obs)
                dt = time.perf_counter() - t0
                if i >= cfg.warmup:
                    times.append(dt)
                    if side == "remote":
                        server.append(remote.last_server_ms / 1e3)
                        transport.append(dt - remote.last_server_ms / 1e3)
            p50, p99 = _percentiles(times)
            rounds[f"{side}_p50"].append(p50)
            rounds[f"{side}_p99"].append(p99)
            if side == "remote":
                rounds["transport_p50"].append(_percentiles(transport)[0])
                rounds["server_p50"].append(_percentiles(server)[0])
    med = {k: round(float(np.median(v)), 3) for k, v in rounds.items()}
    overhead = [r - lo for r, lo in zip(rounds["remote_p50"], rounds["local_p50"])]
    return {
        "infer_ms_p50_local": med["local_p50"], "infer_ms_p99_local": med["local_p99"],
        "infer_ms_p50_remote": med["remote_p50"], "infer_ms_p99_remote": med["remote_p99"],
        "overhead_ms_p50": round(float(np.median(overhead)), 3),
        "overhead_ms_p50_rounds": [round(x, 3) for x in overhead],
        "transport_ms_p50": med["transport_p50"], "server_infer_ms_p50": med["server_p50"],
    }


def _encode_round_trips(local: Any, url: str, observations: list[dict], cfg: ServeBenchConfig) -> dict:
    """An ``encode`` request answered on the server (~0.1 ms of compute) against the same encoding
    in-process: the round trip's own cost when the server has next to nothing to do."""
    remote_ms, local_ms = [], []
    with RemotePolicy(url, local_encoder=False) as remote:
        for _ in range(cfg.rounds):
            for policy, out in ((local, local_ms), (remote, remote_ms)):
                times = []
                for i in range(cfg.warmup + cfg.requests):
                    t0 = time.perf_counter()
                    policy.encode(observations[i % len(observations)])
                    times.append(time.perf_counter() - t0)
                out.append(_percentiles(times[cfg.warmup:])[0])
    return {"encode_ms_p50_local": round(float(np.median(local_ms)), 3),
            "encode_ms_p50_remote": round(float(np.median(remote_ms)), 3)}


def _closed_loop(local: Any, remote: RemotePolicy, cfg: ServeBenchConfig) -> dict:
    spec = remote.spec
    env = make_env("tabletop", "pick_place", 0, image_size=spec.image_size, cameras=tuple(spec.cameras))
    per_step: dict[str, list[float]] = {"local": [], "remote": []}
    actions: dict[str, list[np.ndarray]] = {"local": [], "remote": []}
    for r in range(cfg.rounds):
        for side, policy in (("local", local), ("remote", remote)):
            times = []
            for e in range(cfg.loop_episodes):
                ex = make_executor("aurd", tau_low=1e9, tau_high=1e9, v_thresh=-1e9)
                res = run_episode(env, policy, ex, seed=episode_seed(cfg.seed, e), max_steps=cfg.loop_max_steps,
                                  keep_episode=r == 0)
                times += res.step_times
                if r == 0:
                    actions[side].append(res.episode.actions)
            per_step[side].append(float(np.mean(times)) * 1e3)
    env.close()
    same = all(np.array_equal(a, b) for a, b in zip(actions["local"], actions["remote"]))
    local_ms, remote_ms = float(np.median(per_step["local"])), float(np.median(per_step["remote"]))
    return {
        "loop_control_ms_local": round(local_ms, 3), "loop_control_ms_remote": round(remote_ms, 3),
        "loop_remote_overhead_ms": round(remote_ms - local_ms, 3),
        "loop_control_ms_rounds": {k: [round(x, 3) for x in v] for k, v in per_step.items()},
        "loop_same_actions": same, "loop_steps_per_round": sum(len(a) for a in actions["local"]),
    }


def run_serve_bench(cfg: ServeBenchConfig) -> dict:
    """Loopback round trip against in-process, and the AURD closed loop remote against local (JSON-able)."""
    torch.set_num_threads(cfg.threads)
    local = _default_policy(cfg)
    port = _free_port()
    proc = mp.get_context("spawn").Process(target=_serve_default, args=(cfg, port), daemon=True)
    proc.start()
    try:
        _wait_healthy(port, proc, cfg.startup_timeout)
        with RemotePolicy(f"ws://127.0.0.1:{port}") as remote:
            rng = np.random.default_rng(cfg.seed)
            observations = [random_obs(local, rng) for _ in range(8)]
            first_local, first_remote = local.infer(observations[0]), remote.infer(observations[0])
            result: dict[str, Any] = {
                "same_outputs": all(np.array_equal(first_local[k], v) for k, v in first_remote.items()),
                "request_bytes": len(packb(remote.wire_observation(observations[0]))),
                "reply_bytes": len(packb(first_remote)),  # the outputs RemotePolicy fetches by default
                "reply_bytes_all_outputs": len(packb(first_local)),
                **_round_trips(local, remote, observations, cfg),
                **_encode_round_trips(local, f"ws://127.0.0.1:{port}", observations, cfg),
                "image_size": remote.spec.image_size, "cameras": len(remote.spec.cameras),
                "threads": cfg.threads, "requests": cfg.requests, "rounds": cfg.rounds,
                "target_encoder": remote.encoder_runtime,
            }
            if cfg.loop_episodes > 0:
                result.update(_closed_loop(local, remote, cfg))
    finally:
        proc.terminate()
        proc.join(30)
        if proc.is_alive():
            proc.kill()
            proc.join()
    return result
