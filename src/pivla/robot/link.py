"""The host end of the serial link: framing, timeouts, retries and a bound on bytes in flight.

The Uno's receive buffer holds 64 bytes; frames sent faster than the firmware reads them are silently
lost. ``SerialLink`` therefore never has more than ``max_in_flight_bytes`` of unanswered requests on the
wire. Every command of the protocol is idempotent (absolute targets, not deltas), so a request whose
reply is lost or corrupted is simply sent again with a new sequence number. A link that stops answering
raises ``LinkLost``; the firmware's watchdog then holds the arm still on its own.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass

from pivla.robot import protocol as P

log = logging.getLogger(__name__)

# Transport-level errors: the frame was damaged on the way, so resending is the right answer.
RETRYABLE = {P.ErrorCode.CRC, P.ErrorCode.LENGTH, P.ErrorCode.TIMEOUT}


class LinkError(RuntimeError):
    """Base class for link failures."""


class LinkLost(LinkError):
    """The board stopped answering or the port went away. The arm is (or will be) held by the watchdog."""


class BoardError(LinkError):
    """The board understood a request and refused it (limits, e-stop, bad payload)."""

    def __init__(self, code: int, cmd: int) -> None:
        self.code = code
        self.cmd = cmd
        name = P.ErrorCode(code).name if code in P.ErrorCode._value2member_map_ else str(code)
        cname = P.Cmd(cmd).name if cmd in P.Cmd._value2member_map_ else hex(cmd)
        super().__init__(f"board refused {cname}: {name}")


@dataclass
class LinkConfig:
    """Serial settings. ``connect_timeout_s`` covers the Uno's auto-reset on open (bootloader ~1-2 s)."""

    port: str
    baudrate: int = 115200
    reply_timeout_s: float = 0.15
    retries: int = 3
    max_in_flight_bytes: int = 48
    connect_timeout_s: float = 4.0


class SerialLink:
    def __init__(self, config: LinkConfig, serial_port=None) -> None:
        """Opens ``config.port`` with pyserial (or uses ``serial_port``, any object with read/write)."""
        self.config = config
        if config.max_in_flight_bytes < P.MAX_FRAME or config.max_in_flight_bytes > 63:
            raise ValueError(f"max_in_flight_bytes must be in [{P.MAX_FRAME}, 63] to fit the 64-byte RX buffer")
        if serial_port is None:
            import serial

            try:
                serial_port = serial.Serial(config.port, config.baudrate, timeout=0.01, write_timeout=1.0)
            except (serial.SerialException, OSError) as exc:
                raise LinkLost(f"cannot open serial port {config.port}: {exc}") from exc
        self._port = serial_port
        self._decoder = P.FrameDecoder()
        self._seq = 0
        self._in_flight: dict[int, tuple[int, int, float]] = {}
        self._replies: dict[int, P.Frame] = {}
        self.alive = True
        self.latencies_s: list[float] = []
        self.resends = 0

    def close(self) -> None:
        self.alive = False
        try:
            self._port.close()
        except OSError:
            pass

    def __enter__(self) -> SerialLink:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    # --- low level -------------------------------------------------------------------------------
    def _io(self, fn, *args):
        if not self.alive:
            raise LinkLost(f"link to {self.config.port} is closed")
        try:
            return fn(*args)
        except (OSError, ValueError) as exc:
            self.alive = False
            raise LinkLost(f"serial port {self.config.port} failed: {exc}") from exc
        except Exception as exc:  # pyserial's SerialException/SerialTimeoutException
            if type(exc).__module__.startswith("serial"):
                self.alive = False
                raise LinkLost(f"serial port {self.config.port} failed: {exc}") from exc
            raise

    def _pump(self, wait_s: float) -> None:
        """Reads whatever arrives within ``wait_s`` and files replies by sequence number."""
        deadline = time.monotonic() + wait_s
        while True:
            waiting = self._io(lambda: self._port.in_waiting)
            data = self._io(self._port.read, max(1, waiting))
            if data:
                now = time.monotonic()
                for frame in self._decoder.feed(data):
                    sent = self._in_flight.pop(frame.seq, None)
                    if sent is None:
                        log.debug("dropping stale reply seq=%d cmd=%#x", frame.seq, frame.cmd)
                        continue
                    self.latencies_s.append(now - sent[2])
                    self._replies[frame.seq] = frame
            if self._replies or time.monotonic() >= deadline:
                return

    def _in_flight_bytes(self) -> int:
        return sum(n for _, n, _ in self._in_flight.values())

    def send(self, cmd: int, payload: bytes = b"") -> int:
        """Writes one request once the in-flight budget allows it; returns its sequence number."""
        frame = P.encode_frame(self._seq, cmd, payload)
        while self._in_flight and self._in_flight_bytes() + len(frame) > self.config.max_in_flight_bytes:
            self._pump(0.005)
            self._expire()
        seq = self._seq
        self._seq = (self._seq + 1) & 0xFF
        self._replies.pop(seq, None)
        self._io(self._port.write, frame)
        self._in_flight[seq] = (cmd, len(frame), time.monotonic())
        return seq

    def _expire(self) -> None:
        now = time.monotonic()
        for seq, (_, _, sent) in list(self._in_flight.items()):
            if now - sent > self.config.reply_timeout_s:
                del self._in_flight[seq]

    def wait(self, seq: int, timeout_s: float | None = None) -> P.Frame | None:
        """The reply to ``seq``, or None on timeout."""
        deadline = time.monotonic() + (self.config.reply_timeout_s if timeout_s is None else timeout_s)
        while seq not in self._replies:
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                self._in_flight.pop(seq, None)
                return None
            self._pump(min(remaining, 0.02))
        return self._replies.pop(seq)

    # --- requests --------------------------------------------------------------------------------
    def request(self, cmd: int, payload: bytes = b"", expect_len: int | None = None) -> bytes:
        """Sends ``cmd`` until a matching reply arrives; returns its payload.

        Raises BoardError when the board refuses, LinkLost after ``retries`` unanswered attempts.
        """
        last = "no reply"
        for attempt in range(self.config.retries + 1):
            if attempt:
                self.resends += 1
            seq = self.send(cmd, payload)
            reply = self.wait(seq)
            if reply is None:
                last = f"no reply within {self.config.reply_timeout_s * 1000:.0f} ms"
                continue
            if reply.cmd == P.Cmd.ERROR:
                if len(reply.payload) != 2:
                    last = "malformed error reply"
                    continue
                code, bad_cmd = reply.payload
                if code in RETRYABLE:
                    last = f"board reported {P.ErrorCode(code).name}"
                    continue
                raise BoardError(code, bad_cmd)
            if reply.cmd != cmd | P.REPLY_FLAG:
                last = f"reply command {reply.cmd:#x} does not answer {cmd:#x}"
                continue
            if expect_len is not None and len(reply.payload) != expect_len:
                last = f"reply has {len(reply.payload)} bytes, expected {expect_len}"
                continue
            return reply.payload
        self.alive = False
        raise LinkLost(f"board on {self.config.port} did not answer {P.Cmd(cmd).name} "
                       f"after {self.config.retries + 1} attempts ({last})")


class Board:
    """Typed commands of the firmware over a ``SerialLink``."""

    def __init__(self, link: SerialLink) -> None:
        self.link = link

    @classmethod
    def open(cls, port: str, **kwargs) -> Board:
        """Opens ``port`` and waits (pinging) until the firmware answers, e.g. after the Uno's reset."""
        config = LinkConfig(port=port, **kwargs)
        link = SerialLink(config)
        board = cls(link)
        deadline = time.monotonic() + config.connect_timeout_s
        while True:
            try:
                seq = link.send(P.Cmd.PING)
                reply = link.wait(seq, 0.25)
                if reply is not None and reply.cmd == P.Cmd.PING | P.REPLY_FLAG:
                    return board
            except LinkLost:
                link.close()
                raise
            if time.monotonic() > deadline:
                link.close()
                raise LinkLost(f"no pivla firmware answered on {port} within {config.connect_timeout_s:.1f} s")

    def close(self) -> None:
        self.link.close()

    def ping(self) -> P.BoardInfo:
        info = P.unpack_info(self.link.request(P.Cmd.PING, expect_len=8))
        if info.protocol != P.PROTOCOL_VERSION or info.channels != P.N_CHANNELS:
            raise P.ProtocolError(f"board speaks protocol {info.protocol} with {info.channels} channels; "
                                  f"this host needs protocol {P.PROTOCOL_VERSION} with {P.N_CHANNELS}")
        return info

    def state(self) -> P.BoardState:
        return P.unpack_state(self.link.request(P.Cmd.GET_STATE, expect_len=P.STATE_SIZE))

    def set_targets(self, pulses_us, speed_us_s: int = 0) -> P.BoardState:
        return P.unpack_state(self.link.request(P.Cmd.SET_TARGETS, P.pack_targets(pulses_us, speed_us_s),
                                                expect_len=P.STATE_SIZE))

    def home(self, speed_us_s: int = 0) -> P.BoardState:
        return P.unpack_state(self.link.request(P.Cmd.HOME, int(speed_us_s).to_bytes(2, "little"),
                                                expect_len=P.STATE_SIZE))

    def estop(self) -> P.BoardState:
        return P.unpack_state(self.link.request(P.Cmd.ESTOP, expect_len=P.STATE_SIZE))

    def clear_estop(self) -> P.BoardState:
        return P.unpack_state(self.link.request(P.Cmd.CLEAR_ESTOP, expect_len=P.STATE_SIZE))

    def config(self) -> P.BoardConfig:
        return P.unpack_config(self.link.request(P.Cmd.GET_CONFIG, expect_len=8))

    def set_config(self, cfg: P.BoardConfig) -> P.BoardConfig:
        return P.unpack_config(self.link.request(P.Cmd.SET_CONFIG, P.pack_config(cfg), expect_len=8))

    def limits(self, channel: int) -> P.ChannelLimits:
        return P.unpack_limits(self.link.request(P.Cmd.GET_LIMITS, bytes([channel]), expect_len=7))

    def set_limits(self, lim: P.ChannelLimits) -> P.ChannelLimits:
        return P.unpack_limits(self.link.request(P.Cmd.SET_LIMITS, P.pack_limits(lim), expect_len=7))

    def wait_idle(self, timeout_s: float = 10.0, poll_s: float = 0.02) -> P.BoardState:
        """Polls until no channel is moving (which also keeps the watchdog fed)."""
        deadline = time.monotonic() + timeout_s
        while True:
            st = self.state()
            if not st.moving:
                return st
            if time.monotonic() > deadline:
                raise LinkError(f"arm still moving after {timeout_s:.1f} s: {st.pulses_us} -> {st.targets_us}")
            time.sleep(poll_s)
