"""Where episodes run: this machine's processes (each caller's own loop), or the actors of a Ray cluster.

Ray is imported only when the ray backend runs (``pip install pivla[ray]``). Each actor calls ``setup`` once
(it builds envs and loads the policy) and then runs one job at a time. Results are keyed by job index and
come back in job order, so the output depends neither on the number of actors nor on the node a job ran
on: an actor lost mid-job (its process killed, its node gone) is replaced, the job runs again on another
actor, and only the copy that finished counts. docs/cluster.md runs it on a multi-node cluster.
"""

from __future__ import annotations

import contextlib
import logging
import os
import socket
from collections import Counter, deque
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from typing import Any, Literal

from tqdm import tqdm

log = logging.getLogger(__name__)

FAULT_ENV = "PIVLA_RAY_FAULT"
"""Fault injection for tests: a file path; the first actor to create that file exits (as if killed) after its
job ran and before the result is returned, the case where a lost episode could be counted twice."""
JOB_ATTEMPTS = 3  # actors lost on one job before the run gives up: a job that kills every actor is a bug


@dataclass
class BackendConfig:
    """Where episodes run (results are the same either way)."""

    backend: Literal["local", "ray"] = "local"
    """local: processes on this machine (--workers); ray: --workers Ray actors, each holding its env and
    policy, on the cluster of --ray-address (docs/cluster.md)."""
    ray_address: str | None = None
    """HOST:PORT of a running Ray cluster (``ray start --head``); default: start Ray on this machine with
    --workers CPUs and no dashboard."""
    ray_worker_cpus: int = 1
    """CPUs each Ray actor reserves (its torch threads)."""


def import_ray() -> Any:
    """Ray, or a one-line error saying how to install it."""
    try:
        import ray
    except ImportError:
        raise ValueError("--backend ray needs Ray: pip install 'pivla[ray]' (or pip install ray==2.60.0)") from None
    return ray


def check_reachable(address: str, timeout: float = 5.0) -> None:
    """Fail fast on a HOST:PORT nothing listens on: ``ray.init`` would wait for it forever."""
    host, _, port = address.rpartition(":")
    if not host or not port.isdigit():
        raise ValueError(f"--ray-address {address!r}: give HOST:PORT of the head node (ray start --head --port PORT)")
    try:
        socket.create_connection((host, int(port)), timeout=timeout).close()
    except OSError as e:
        raise ConnectionError(f"--ray-address {address}: no Ray cluster answers there ({e}); start one with "
                              "`ray start --head --port PORT` or give the head's address") from None


def check_backend(cfg: BackendConfig) -> None:
    """Bad backend settings as one-line errors, before a run writes anything."""
    if cfg.backend == "ray":
        import_ray()
        if cfg.ray_address:
            check_reachable(cfg.ray_address)
    if cfg.ray_worker_cpus < 1:
        raise ValueError(f"--ray-worker-cpus {cfg.ray_worker_cpus}: must be >= 1")


def _fault_once() -> None:
    path = os.environ.get(FAULT_ENV)
    if not path:
        return
    try:
        os.close(os.open(path, os.O_CREAT | os.O_EXCL | os.O_WRONLY))
    except FileExistsError:
        return
    os._exit(1)


class _Worker:
    """One Ray actor: ``setup(*setup_args)`` once in its process, then ``run(job)`` per job."""

    def __init__(self, run: Callable[[Any], Any], setup: Callable[..., None] | None, setup_args: tuple) -> None:
        self._run = run
        if setup is not None:
            setup(*setup_args)

    def run(self, job: Any) -> Any:
        result = self._run(job)
        _fault_once()
        return result


@contextlib.contextmanager
def ray_session(cfg: BackendConfig, num_cpus: int | None = None) -> Iterator[Any]:
    """Ray, joined at ``--ray-address`` or started on this machine with ``num_cpus`` (and shut down after); a
    Ray the caller initialised is used as it is."""
    ray = import_ray()
    started = not ray.is_initialized()
    if started:
        if cfg.ray_address:
            check_reachable(cfg.ray_address)
            ray.init(address=cfg.ray_address, log_to_driver=False)
        else:
            ray.init(num_cpus=num_cpus, include_dashboard=False, log_to_driver=False)
    try:
        yield ray
    finally:
        if started:
            ray.shutdown()


def ray_map(run: Callable[[Any], Any], jobs: Sequence[Any], cfg: BackendConfig, *, workers: int,
            setup: Callable[..., None] | None = None, setup_args: tuple = (), desc: str | None = None) -> Iterator[Any]:
    """``run(job)`` for every job on Ray actors, yielded in job order. ``run`` and ``setup`` must be module-level
    functions (actors import them by name). Ray is started on this machine when no address is given and shut
    down at the end; a cluster joined, or a Ray already initialised by the caller, is left running."""
    if not jobs:
        return
    with ray_session(cfg, num_cpus=min(os.cpu_count() or 1, workers * cfg.ray_worker_cpus)) as ray:
        actors: list[Any] = []
        progress = tqdm(total=len(jobs), desc=desc, unit="ep", disable=desc is None, leave=False)
        try:
            cpus = int(ray.cluster_resources().get("CPU", 0))
            n = max(1, min(workers, len(jobs), cpus // cfg.ray_worker_cpus))  # more would wait for CPUs forever
            remote = ray.remote(num_cpus=cfg.ray_worker_cpus, scheduling_strategy="SPREAD")(_Worker)

            def spawn() -> Any:
                actor = remote.remote(run, setup, setup_args)
                actors.append(actor)
                return actor

            queue, running, finished, lost, next_out = deque(range(len(jobs))), {}, {}, Counter(), 0

            def submit(actor: Any) -> None:
                if queue:
                    i = queue.popleft()
                    running[actor.run.remote(jobs[i])] = (actor, i)

            for _ in range(n):
                submit(spawn())
            while next_out < len(jobs):
                if next_out in finished:
                    yield finished.pop(next_out)
                    next_out += 1
                    progress.update()
                    continue
                [ref], _ = ray.wait(list(running), num_returns=1)
                actor, i = running.pop(ref)
                try:
                    finished[i] = ray.get(ref)
                except ray.exceptions.RayActorError as e:
                    lost[i] += 1
                    if lost[i] >= JOB_ATTEMPTS:
                        raise RuntimeError(f"job {i}: {lost[i]} Ray workers were lost running it; last: {e}") from e
                    log.warning("a Ray worker was lost during job %d; it runs again on a new worker", i)
                    queue.appendleft(i)
                    actor = spawn()
                submit(actor)
        finally:
            progress.close()
            for actor in actors:
                ray.kill(actor)
