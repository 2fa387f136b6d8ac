"""How a policy's answer reaches the control loop: a latency model, and the links that deliver chunks.

A query sent at control step t delivers its chunk at step t + d. :class:`SimulatedLink` computes the answer
at once and holds it back for d steps, d drawn per query from a :class:`Latency` (seeded from the episode's
seed, so an episode depends on its seed and never on how fast this machine is). :class:`WallClockLink` runs
each query on a worker thread against the real policy (a ``RemotePolicy`` over a socket, or a local one) and
paces the loop at the env's control rate; an answer is available at the first control step that starts after
it came back. Both hand out :class:`Arrival` records; the loop cannot tell them apart.
"""

from __future__ import annotations

import math
import queue
import threading
import time
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np

REAL = "real"
LATENCY_SALT = 0x1A7E  # a stream of its own: latency draws never shift the env's or the policy's random numbers
LINK_ERRORS = (ConnectionError, TimeoutError)  # a lost or silent link; any other exception is a bug and is raised


@dataclass(frozen=True)
class Latency:
    """Policy latency: a lognormal of mean ``mean_ms`` and standard deviation ``jitter_ms`` (constant when the
    jitter is 0), or, with ``real``, whatever the wall clock measures."""

    mean_ms: float = 0.0
    jitter_ms: float = 0.0
    real: bool = False

    @property
    def zero(self) -> bool:
        return not self.real and self.mean_ms == 0.0

    def draw_ms(self, rng: np.random.Generator) -> float:
        """One query's latency in ms."""
        if self.jitter_ms == 0.0:
            return self.mean_ms
        sigma2 = math.log1p((self.jitter_ms / self.mean_ms) ** 2)
        return float(rng.lognormal(math.log(self.mean_ms) - sigma2 / 2, math.sqrt(sigma2)))

    def __str__(self) -> str:
        return REAL if self.real else f"{self.mean_ms:g}:{self.jitter_ms:g}"


def parse_latency(text: str, allow_real: bool = True) -> Latency:
    """``MEAN[:JITTER]`` in ms (``100``, ``100:20``) or ``real``; a ValueError names what is wrong."""
    spelled = str(text).strip()
    if allow_real and spelled == REAL:
        return Latency(real=True)
    expected = "expected MEAN[:JITTER] in milliseconds (e.g. 100 or 100:20)" + (" or 'real'" if allow_real else "")
    parts = spelled.split(":")
    if len(parts) > 2:
        raise ValueError(f"{text!r}: {expected}")
    try:
        mean, jitter = float(parts[0]), float(parts[1]) if len(parts) == 2 else 0.0
    except ValueError:
        raise ValueError(f"{text!r}: {expected}") from None
    if not (math.isfinite(mean) and math.isfinite(jitter)):
        raise ValueError(f"{text!r}: mean and jitter must be finite numbers of milliseconds")
    if mean < 0 or jitter < 0:
        raise ValueError(f"{text!r}: mean and jitter must be >= 0 ms")
    if jitter > 0 and mean == 0:
        raise ValueError(f"{text!r}: a jitter needs a mean above 0 ms (the latency is lognormal)")
    return Latency(mean, jitter)


def latency_rng(seed: int | None) -> np.random.Generator:
    """The latency draws of an episode (``pivla serve --delay-seed`` draws its delays from the same stream)."""
    return np.random.default_rng([int(seed or 0) & 0xFFFFFFFF, LATENCY_SALT])


def delay_steps(ms: float, hz: float) -> int:
    """Control steps until an answer ``ms`` after its query is usable: the first step starting at or after it."""
    return max(0, math.ceil(ms * hz / 1000.0 - 1e-9))


def control_hz(env: Any) -> float:
    """The env's control rate (the twin's ``render_fps``, LIBERO's ``control_hz``)."""
    unwrapped = getattr(env, "unwrapped", env)
    hz = getattr(unwrapped, "control_hz", None) or getattr(unwrapped, "metadata", {}).get("render_fps")
    if not hz:
        raise ValueError(f"{type(unwrapped).__name__} does not say its control rate "
                         f"(control_hz or metadata['render_fps'])")
    return float(hz)


@dataclass
class Arrival:
    """A query's answer: sent with the observation of step ``sent``, usable from step ``step``; ``output`` is
    None when the link failed (``error`` says how)."""

    id: int
    sent: int
    step: int
    output: Mapping[str, np.ndarray] | None
    error: str | None = None


@dataclass
class LinkStats:
    delays: list[int] = field(default_factory=list)  # control steps from send to arrival, per answered query
    failed: int = 0  # queries the link lost


class SimulatedLink:
    """Answers computed when sent, delivered ``delay_steps(latency.draw_ms(rng), hz)`` steps later."""

    def __init__(self, policy: Any, latency: Latency, hz: float, seed: int | None):
        self.policy, self.latency, self.hz = policy, latency, hz
        self.rng = latency_rng(seed)
        self.stats = LinkStats()
        self._next_id = 0
        self._in_flight: list[Arrival] = []

    def pace(self, step: int) -> None:
        """Simulated time needs no waiting."""

    def expected_delay_steps(self) -> int:
        """Control steps a query is expected in flight: the latency's mean at the control rate."""
        return delay_steps(self.latency.mean_ms, self.hz)

    def send(self, obs: Mapping[str, Any], step: int) -> int:
        qid, self._next_id = self._next_id, self._next_id + 1
        due = step + delay_steps(self.latency.draw_ms(self.rng), self.hz)
        try:
            arrival = Arrival(qid, step, due, self.policy.infer(obs))
        except LINK_ERRORS as e:
            arrival = Arrival(qid, step, due, None, f"{type(e).__name__}: {e}")
        self._in_flight.append(arrival)
        return qid

    def arrivals(self, step: int) -> list[Arrival]:
        due = [a for a in self._in_flight if a.step <= step]
        self._in_flight = [a for a in self._in_flight if a.step > step]
        for a in due:
            self._count(a)
        return due

    def wait(self, qid: int) -> Arrival:
        arrival = next(a for a in self._in_flight if a.id == qid)
        self._in_flight.remove(arrival)
        self._count(arrival)
        return arrival

    def _count(self, a: Arrival) -> None:
        if a.output is None:
            self.stats.failed += 1
        else:
            self.stats.delays.append(a.step - a.sent)

    def close(self) -> None:
        self._in_flight = []


class WallClockLink:
    """Real round trips on one worker thread, the loop paced at ``hz``: step s starts at t0 + s / hz, and an
    answer that came back at time a is usable from step ceil((a - t0) * hz). Nothing here knows the delay."""

    def __init__(self, policy: Any, hz: float):
        self.policy, self.period = policy, 1.0 / hz
        self.stats = LinkStats()
        self.t0: float | None = None
        self._next_id = 0
        self._requests: queue.Queue = queue.Queue()
        self._done: list[Arrival] = []
        self._bug: BaseException | None = None
        self._cond = threading.Condition()
        self._worker = threading.Thread(target=self._serve, name="pivla-link", daemon=True)
        self._worker.start()

    def pace(self, step: int) -> None:
        """Wait until control step ``step`` starts (at once when the loop is late)."""
        now = time.monotonic()
        if self.t0 is None:
            self.t0 = now - step * self.period
        wait = self.t0 + step * self.period - now
        if wait > 0:
            time.sleep(wait)

    def send(self, obs: Mapping[str, Any], step: int) -> int:
        qid, self._next_id = self._next_id, self._next_id + 1
        self._requests.put((qid, step, obs))
        return qid

    def expected_delay_steps(self) -> int:
        """Control steps a query is expected in flight: the mean of the round trips measured so far on this
        link, in steps (0 before the first answer)."""
        delays = self.stats.delays
        return max(0, math.ceil(sum(delays) / len(delays) - 1e-9)) if delays else 0

    def _serve(self) -> None:
        while (job := self._requests.get()) is not None:
            qid, sent, obs = job
            output, error = None, None
            try:
                output = self.policy.infer(obs)
            except LINK_ERRORS as e:
                error = f"{type(e).__name__}: {e}"
            except BaseException as e:  # noqa: BLE001 - handed to the control loop, which raises it
                self._bug = e
            came = time.monotonic()
            step = max(sent, math.ceil((came - self.t0) / self.period - 1e-9))
            with self._cond:
                self._done.append(Arrival(qid, sent, step, output, error))
                self._cond.notify_all()

    def _take(self, keep: Any) -> list[Arrival]:
        if self._bug is not None:
            raise self._bug
        taken = [a for a in self._done if keep(a)]
        self._done = [a for a in self._done if not keep(a)]
        for a in taken:
            if a.output is None:
                self.stats.failed += 1
            else:
                self.stats.delays.append(a.step - a.sent)
        return taken

    def arrivals(self, step: int) -> list[Arrival]:
        with self._cond:
            return self._take(lambda a: a.step <= step)

    def wait(self, qid: int) -> Arrival:
        with self._cond:
            self._cond.wait_for(lambda: self._bug is not None or any(a.id == qid for a in self._done))
            return self._take(lambda a: a.id == qid)[0]

    def close(self) -> None:
        self._requests.put(None)
        self._worker.join(timeout=5)


def make_link(policy: Any, latency: Latency, hz: float, seed: int | None) -> SimulatedLink | WallClockLink:
    return WallClockLink(policy, hz) if latency.real else SimulatedLink(policy, latency, hz, seed)
