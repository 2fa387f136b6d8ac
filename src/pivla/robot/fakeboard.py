"""A pure-Python stand-in for the firmware, served on a pseudo-terminal, for fast unit tests.

It follows the same protocol, limits, e-stop and watchdog rules as ``firmware/src/pivla_arm.cpp`` (motion
is a plain rate limit rather than the firmware's trapezoid). The simavr board running the real ELF
(``pivla.robot.simboard``) remains the reference; tests that matter for the hardware run against that.
"""

from __future__ import annotations

import os
import select
import threading
import time
import tty

from pivla.robot import protocol as P


class FakeBoard:
    def __init__(self, watchdog_ms: int = 500) -> None:
        self._master, self._slave = os.openpty()
        tty.setraw(self._slave)
        self.port = os.ttyname(self._slave)
        self.config = P.BoardConfig(watchdog_ms, 600, 1500, 4000)
        lo, hi, home = P.PULSE_DEFAULT_LIMITS
        self.limits = [P.ChannelLimits(i, lo, hi, home) for i in range(P.N_CHANNELS)]
        self.pos = [float(home)] * P.N_CHANNELS
        self.target = [home] * P.N_CHANNELS
        self.speed = float(self.config.default_speed)
        self.flags = P.StateFlag(0)
        self.errors = 0
        self.min_seen = list(self.pos)
        self.max_seen = list(self.pos)
        self._decoder = P.FrameDecoder()
        self._start = time.monotonic()
        self._last_valid = self._start
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="fakeboard", daemon=True)
        self._thread.start()

    # --- firmware behaviour ----------------------------------------------------------------------
    def _state(self) -> bytes:
        moving = any(round(p) != t for p, t in zip(self.pos, self.target))
        flags = self.flags | (P.StateFlag.MOVING if moving else 0)
        uptime = int((time.monotonic() - self._start) * 1000)
        return P.pack_state(P.BoardState(flags, tuple(int(round(p)) for p in self.pos), tuple(self.target),
                                         uptime, self.errors))

    def _hold(self) -> None:
        self.target = [int(round(p)) for p in self.pos]
        self.pos = [float(t) for t in self.target]

    def _error(self, seq: int, code: P.ErrorCode, cmd: int) -> bytes:
        self.errors += 1
        return P.encode_frame(seq, P.Cmd.ERROR, bytes([code, cmd & 0xFF]))

    def _dispatch(self, f: P.Frame) -> tuple[bytes, bool]:
        cmd, n, pl = f.cmd, len(f.payload), f.payload
        ok = lambda payload: (P.encode_frame(f.seq, cmd | P.REPLY_FLAG, payload), True)  # noqa: E731
        expected = {P.Cmd.PING: 0, P.Cmd.SET_TARGETS: 2 + 2 * P.N_CHANNELS, P.Cmd.GET_STATE: 0, P.Cmd.HOME: 2,
                    P.Cmd.ESTOP: 0, P.Cmd.CLEAR_ESTOP: 0, P.Cmd.SET_CONFIG: 8, P.Cmd.GET_CONFIG: 0,
                    P.Cmd.SET_LIMITS: 7, P.Cmd.GET_LIMITS: 1}
        if cmd not in expected:
            return self._error(f.seq, P.ErrorCode.UNKNOWN_CMD, cmd), False
        if n != expected[cmd]:
            return self._error(f.seq, P.ErrorCode.LENGTH, cmd), False
        if cmd == P.Cmd.PING:
            return ok(bytes([P.PROTOCOL_VERSION, 1, 0, 0, P.N_CHANNELS, 0, 64, P.MAX_PAYLOAD]))
        if cmd in (P.Cmd.SET_TARGETS, P.Cmd.HOME):
            if self.flags & P.StateFlag.ESTOP:
                return self._error(f.seq, P.ErrorCode.ESTOP, cmd), False
            if cmd == P.Cmd.SET_TARGETS:
                speed, wanted = P.unpack_targets(pl)
                if any(not lim.min_us <= w <= lim.max_us for w, lim in zip(wanted, self.limits)):
                    return self._error(f.seq, P.ErrorCode.LIMIT, cmd), False
            else:
                speed, wanted = int.from_bytes(pl, "little"), tuple(lim.home_us for lim in self.limits)
            self.speed = float(min(speed or self.config.default_speed, self.config.max_speed))
            self.target = list(wanted)
            self.flags &= ~P.StateFlag.WATCHDOG
            return ok(self._state())
        if cmd == P.Cmd.GET_STATE:
            return ok(self._state())
        if cmd == P.Cmd.ESTOP:
            self._hold()
            self.flags |= P.StateFlag.ESTOP
            return ok(self._state())
        if cmd == P.Cmd.CLEAR_ESTOP:
            self._hold()
            self.flags &= ~(P.StateFlag.ESTOP | P.StateFlag.WATCHDOG)
            return ok(self._state())
        if cmd == P.Cmd.SET_CONFIG:
            c = P.unpack_config(pl)
            lo, hi = P.WATCHDOG_RANGE_MS
            if not (lo <= c.watchdog_ms <= hi and 0 < c.default_speed <= c.max_speed <= P.SPEED_CEILING_US_S
                    and c.accel >= 100):
                return self._error(f.seq, P.ErrorCode.PAYLOAD, cmd), False
            self.config = c
            return ok(P.pack_config(c))
        if cmd == P.Cmd.GET_CONFIG:
            return ok(P.pack_config(self.config))
        if cmd == P.Cmd.SET_LIMITS:
            lim = P.unpack_limits(pl)
            if (lim.channel >= P.N_CHANNELS or lim.min_us < P.PULSE_ABS_MIN_US or lim.max_us > P.PULSE_ABS_MAX_US
                    or lim.min_us + 20 > lim.max_us or not lim.min_us <= lim.home_us <= lim.max_us):
                return self._error(f.seq, P.ErrorCode.PAYLOAD, cmd), False
            now_us, tgt = round(self.pos[lim.channel]), self.target[lim.channel]
            if not (lim.min_us <= now_us <= lim.max_us and lim.min_us <= tgt <= lim.max_us):
                return self._error(f.seq, P.ErrorCode.STATE, cmd), False
            self.limits[lim.channel] = lim
            return ok(P.pack_limits(lim))
        if pl[0] >= P.N_CHANNELS:
            return self._error(f.seq, P.ErrorCode.PAYLOAD, cmd), False
        return ok(P.pack_limits(self.limits[pl[0]]))

    def _step(self, dt: float) -> None:
        for i in range(P.N_CHANNELS):
            err = self.target[i] - self.pos[i]
            step = max(-self.speed * dt, min(self.speed * dt, err))
            self.pos[i] += step
            self.min_seen[i] = min(self.min_seen[i], self.pos[i])
            self.max_seen[i] = max(self.max_seen[i], self.pos[i])

    def _run(self) -> None:
        last = time.monotonic()
        while not self._stop.is_set():
            ready, _, _ = select.select([self._master], [], [], 0.005)
            data = b""
            if ready:
                try:
                    data = os.read(self._master, 256)
                except OSError:
                    data = b""
            with self._lock:
                before = self._decoder.errors
                for frame in self._decoder.feed(data):
                    reply, valid = self._dispatch(frame)
                    if valid:
                        self._last_valid = time.monotonic()
                    os.write(self._master, reply)
                for _ in range(self._decoder.errors - before):
                    os.write(self._master, self._error(0, P.ErrorCode.CRC, 0))
                now = time.monotonic()
                if (not self.flags & (P.StateFlag.ESTOP | P.StateFlag.WATCHDOG)
                        and now - self._last_valid > self.config.watchdog_ms / 1000):
                    self._hold()
                    self.flags |= P.StateFlag.WATCHDOG
                self._step(now - last)
                last = now

    def pulses(self) -> tuple[float, ...]:
        with self._lock:
            return tuple(self.pos)

    def close(self) -> None:
        self._stop.set()
        self._thread.join(2)
        for fd in (self._master, self._slave):
            try:
                os.close(fd)
            except OSError:
                pass

    def __enter__(self) -> FakeBoard:
        return self

    def __exit__(self, *exc) -> None:
        self.close()
