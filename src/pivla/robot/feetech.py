"""The Feetech STS bus (the SO-101's six STS3215 servos): packets, registers and a host bus over the SDK.

A packet is ``FF FF id len instr|error params checksum`` with ``len = len(params) + 2`` and checksum
``~(id + len + instr + sum(params)) & 0xFF``; registers are little-endian. The host side uses the vendor
SDK (``feetech-servo-sdk``, import ``scservo_sdk``) for framing and transactions, and keeps the bytes of
each transaction so that a failure can be named: which servo, and whether it stayed silent, answered with
a bad checksum, or the bus carried bytes that are no packet at all. The pure packet functions here are also
what the simulated bus (``pivla.robot.simbus``) speaks.
"""

from __future__ import annotations

import logging
import select
import threading
import time
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from enum import IntEnum
from typing import Self

log = logging.getLogger(__name__)

HEADER = b"\xff\xff"
BROADCAST_ID = 0xFE
MAX_PACKET_LEN = 250
STS3215_MODEL = 777
STS3215_RESOLUTION = 4096


class Instr(IntEnum):
    PING = 0x01
    READ = 0x02
    WRITE = 0x03
    SYNC_READ = 0x82
    SYNC_WRITE = 0x83


@dataclass(frozen=True)
class Register:
    """A control-table entry; ``sign_bit`` marks sign-magnitude values (the sign in that bit)."""

    name: str
    address: int
    size: int
    sign_bit: int | None = None

    def encode(self, value: int) -> int:
        if self.sign_bit is not None and value < 0:
            return -value | (1 << self.sign_bit)
        return value

    def decode(self, raw: int) -> int:
        if self.sign_bit is not None and raw & (1 << self.sign_bit):
            return -(raw & ~(1 << self.sign_bit))
        return raw


MODEL_NUMBER = Register("model_number", 3, 2)
ID = Register("id", 5, 1)
MIN_ANGLE_LIMIT = Register("min_angle_limit", 9, 2)
MAX_ANGLE_LIMIT = Register("max_angle_limit", 11, 2)
HOMING_OFFSET = Register("homing_offset", 31, 2, sign_bit=11)
MODE = Register("mode", 33, 1)
TORQUE_ENABLE = Register("torque_enable", 40, 1)
ACCELERATION = Register("acceleration", 41, 1)
GOAL_POSITION = Register("goal_position", 42, 2)
LOCK = Register("lock", 55, 1)
PRESENT_POSITION = Register("present_position", 56, 2)
PRESENT_SPEED = Register("present_speed", 58, 2, sign_bit=15)
PRESENT_LOAD = Register("present_load", 60, 2, sign_bit=10)
PRESENT_VOLTAGE = Register("present_voltage", 62, 1)
PRESENT_TEMPERATURE = Register("present_temperature", 63, 1)
MOVING = Register("moving", 66, 1)
PRESENT_CURRENT = Register("present_current", 69, 2)

# status-packet error bits, as the STS manual names them
ERROR_BITS = {1: "input voltage", 2: "angle sensor", 4: "overheat", 8: "overcurrent", 32: "overload"}


def checksum(body: bytes) -> int:
    """Checksum of ``id len instr params`` (everything between the header and the checksum byte)."""
    return ~sum(body) & 0xFF


def encode_packet(servo_id: int, code: int, params: bytes = b"") -> bytes:
    """An instruction (host) or status (servo, ``code`` = error byte) packet."""
    body = bytes([servo_id, len(params) + 2, code]) + bytes(params)
    return HEADER + body + bytes([checksum(body)])


@dataclass(frozen=True)
class Packet:
    servo_id: int
    code: int  # the instruction of a request, the error byte of a status packet
    params: bytes
    checksum_ok: bool
    raw: bytes
    garbage_before: int = 0  # bytes skipped as garbage just before this packet


class PacketReader:
    """Splits a byte stream into packets; bytes that start no packet are kept in ``garbage``.

    A packet with a wrong checksum is still returned (``checksum_ok`` False) so that its sender can be named.
    """

    def __init__(self) -> None:
        self._buf = bytearray()
        self.garbage = bytearray()
        self._skipped = 0

    def _skip(self, n: int) -> None:
        self.garbage += self._buf[:n]
        self._skipped += n
        del self._buf[:n]

    @property
    def pending(self) -> bytes:
        """Bytes of a packet not yet complete."""
        return bytes(self._buf)

    def feed(self, data: bytes) -> list[Packet]:
        self._buf += data
        out = []
        while True:
            start = self._buf.find(HEADER)
            if start < 0:  # keep a trailing 0xFF: it may be the first half of a header
                self._skip(len(self._buf) - (1 if self._buf.endswith(b"\xff") else 0))
                return out
            self._skip(start)
            if len(self._buf) < 4:
                return out
            servo_id, length = self._buf[2], self._buf[3]
            if servo_id == 0xFF or not 2 <= length <= MAX_PACKET_LEN:
                self._skip(1)
                continue
            if len(self._buf) < 4 + length:
                return out
            raw = bytes(self._buf[: 4 + length])
            del self._buf[: 4 + length]
            out.append(Packet(servo_id, raw[4], raw[5:-1], checksum(raw[2:-1]) == raw[-1], raw, self._skipped))
            self._skipped = 0


# ------------------------------------------------------------------------------------------------ errors
class BusError(RuntimeError):
    """A bus transaction failed; the message names the servo and what happened."""

    def __init__(self, message: str, servo_id: int | None = None, partial: Mapping[int, int] | None = None) -> None:
        super().__init__(message)
        self.servo_id = servo_id
        self.partial = dict(partial or {})  # values of the servos that did answer before the failure


class PortError(BusError):
    """The serial port cannot be opened or failed (the USB cable is out): the link is gone."""


class NoReply(BusError):
    """A servo did not answer within the reply timeout."""


class ChecksumError(BusError):
    """A servo's status packet arrived with a wrong checksum."""


class BusGarbage(BusError):
    """Bytes on the bus that belong to no packet (noise, a wrong baud rate, a second master)."""


class ServoFault(BusError):
    """A servo answered with error bits set (voltage, sensor, overheat, overcurrent, overload)."""


def _bits(error: int) -> str:
    return ", ".join(name for bit, name in ERROR_BITS.items() if error & bit) or f"error byte {error:#04x}"


def _hex(data: bytes, limit: int = 24) -> str:
    text = data[:limit].hex(" ")
    return text + (" ..." if len(data) > limit else "")


# ------------------------------------------------------------------------------------------------ host bus
@dataclass
class BusConfig:
    """The serial side of a Feetech bus."""

    port: str
    baudrate: int = 1_000_000
    reply_timeout_ms: float = 34.0
    """Added to a reply's wire time before it counts as missing (the SDK's budget for a 16 ms USB latency timer)."""
    retries: int = 0
    """Extra attempts of a transaction that expects replies before its failure is raised."""


def _sdk():
    try:
        import scservo_sdk
    except ModuleNotFoundError as exc:
        raise ModuleNotFoundError("the SO-101 needs feetech-servo-sdk: pip install 'pivla[so101]'") from exc
    return scservo_sdk


class FeetechBus:
    """Ping, register read/write, sync read/write and torque over the vendor SDK, one transaction at a time.

    ``lock`` serialises transactions (a watchdog thread shares the bus); ``last_reply`` is the monotonic
    time of the last transaction a servo answered, which is what proves the link alive.
    """

    def __init__(self, config: BusConfig, names: Mapping[int, str] | None = None) -> None:
        sdk = _sdk()
        self.config = config
        self.names = dict(names or {})
        self.lock = threading.RLock()
        self.last_reply = 0.0
        self.stale_bytes = 0
        self._sdk = sdk
        self._port = _make_port(sdk, config, self)
        self._ph = sdk.PacketHandler(0)  # protocol end 0: STS servos are little-endian
        try:
            ok = self._port.openPort()
        except (OSError, ValueError) as exc:  # pyserial's SerialException is an OSError
            raise PortError(f"cannot open serial port {config.port}: {exc}") from exc
        if not ok:
            raise PortError(f"cannot open serial port {config.port} at {config.baudrate} baud")

    def close(self) -> None:
        with self.lock:
            try:
                self._port.closePort()
            except OSError as exc:  # a port that already went away
                log.debug("closing %s: %s", self.config.port, exc)

    def __enter__(self) -> Self:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def servo(self, servo_id: int) -> str:
        name = self.names.get(servo_id)
        return f"servo {servo_id} ({name})" if name else f"servo {servo_id}"

    # --- transactions ----------------------------------------------------------------------------
    def _call(self, fn, *args):
        try:
            return fn(*args)
        except (OSError, ValueError) as exc:  # pyserial's SerialException is an OSError
            raise PortError(f"serial port {self.config.port} failed: {exc}") from exc
        finally:
            self._port.is_using = False  # the SDK leaves its busy flag set when a read raises

    def _drain(self) -> None:
        """Collects what is still arriving after a failure (the other servos' replies), so that it is neither
        taken for the next transaction's replies nor missing from the diagnosis."""
        fd = self._port.ser.fileno()
        deadline = time.monotonic() + self.config.reply_timeout_ms / 1000
        while time.monotonic() < deadline and select.select([fd], [], [], 0.002)[0]:
            self._port.rx += self._port.ser.read(max(1, self._port.ser.in_waiting))

    def _failure(self, servo_id: int, what: str, result: int, partial: Mapping[int, int]) -> BusError:
        """Names what went wrong from the bytes that came back during the transaction."""
        if result == self._sdk.COMM_TX_FAIL:
            return PortError(f"serial port {self.config.port}: could not send {what}", servo_id, partial)
        self._call(self._drain)
        reader = PacketReader()
        for p in reader.feed(bytes(self._port.rx)):
            if not p.checksum_ok:
                return ChecksumError(f"{self.servo(servo_id)}: reply to {what} failed its checksum "
                                     f"(got {p.raw[-1]:#04x}, expected {checksum(p.raw[2:-1]):#04x}): {_hex(p.raw)}",
                                     servo_id, partial)
        if reader.garbage:
            junk = bytes(reader.garbage) + reader.pending
            return BusGarbage(f"{self.servo(servo_id)}: {len(junk)} bytes of garbage on the bus instead of its "
                              f"reply to {what}: {_hex(junk)}", servo_id, partial)
        if reader.pending:
            return BusGarbage(f"{self.servo(servo_id)}: truncated reply to {what}: {_hex(reader.pending)}",
                              servo_id, partial)
        return NoReply(f"{self.servo(servo_id)} did not answer {what} within {self.config.reply_timeout_ms:.0f} ms",
                       servo_id, partial)

    def _check_clean(self, servo_id: int, what: str, expected: int, partial: Mapping[int, int]) -> None:
        """Bytes the SDK skipped on its way to the valid replies are a fault too (noise, a second master)."""
        waiting = self._call(lambda: self._port.ser.in_waiting)
        if waiting:
            self._call(self._port.readPort, waiting)
        if len(self._port.rx) == expected:
            return
        reader = PacketReader()
        packets = reader.feed(bytes(self._port.rx))
        noisy = next((p for p in packets if p.garbage_before), None)
        if reader.garbage:
            where = noisy.servo_id if noisy is not None else servo_id
            junk = bytes(reader.garbage) + reader.pending
            raise BusGarbage(f"{self.servo(where)}: {len(junk)} bytes of garbage on the bus before its reply to "
                             f"{what}: {_hex(junk)}", where, partial)
        extra = packets[-1] if packets else None
        who = self.servo(extra.servo_id) if extra is not None else "an unknown sender"
        raise BusGarbage(f"unexpected bytes after the replies to {what} (from {who}): "
                         f"{_hex(bytes(self._port.rx)[expected:])}", servo_id, partial)

    def _retrying(self, fn):
        with self.lock:
            for attempt in range(self.config.retries + 1):
                try:
                    out = fn()
                except PortError:
                    raise
                except BusError as exc:
                    if attempt == self.config.retries:
                        raise
                    log.warning("%s; retrying", exc)
                    continue
                self.last_reply = time.monotonic()
                return out

    def _status(self, servo_id: int, what: str, result: int, error: int, expected: int) -> None:
        if result != self._sdk.COMM_SUCCESS:
            raise self._failure(servo_id, what, result, {})
        self._check_clean(servo_id, what, expected, {})
        if error:
            raise ServoFault(f"{self.servo(servo_id)} reports a fault after {what}: {_bits(error)}", servo_id)

    def ping(self, servo_id: int) -> int:
        """The servo's model number (a ping, then a read of register 3)."""
        def go() -> int:
            model, result, error = self._call(self._ph.ping, self._port, servo_id)
            self._status(servo_id, "PING", result, error, 6 + MODEL_NUMBER.size)
            return model
        return self._retrying(go)

    def read(self, servo_id: int, reg: Register) -> int:
        def go() -> int:
            data, result, error = self._call(self._ph.readTxRx, self._port, servo_id, reg.address, reg.size)
            self._status(servo_id, f"READ {reg.name}", result, error, 6 + reg.size)
            return reg.decode(int.from_bytes(bytes(data), "little"))
        return self._retrying(go)

    def write(self, servo_id: int, reg: Register, value: int) -> None:
        """Writes one register and waits for the servo's acknowledgement."""
        data = list(reg.encode(int(value)).to_bytes(reg.size, "little"))

        def go() -> None:
            result, error = self._call(self._ph.writeTxRx, self._port, servo_id, reg.address, reg.size, data)
            self._status(servo_id, f"WRITE {reg.name}", result, error, 6)
        self._retrying(go)

    def sync_read(self, reg: Register, ids: Iterable[int]) -> dict[int, int]:
        """One register of several servos in one transaction (one request, one reply per servo in order).

        The SDK's GroupSyncRead does not say which servo failed and keeps the previous values of the servos
        after it, so the replies are collected here one by one with the SDK's own packet reader.
        """
        ids = list(ids)
        what = f"SYNC_READ {reg.name}"

        def go() -> dict[int, int]:
            result = self._call(self._ph.syncReadTx, self._port, reg.address, reg.size, ids, len(ids))
            if result != self._sdk.COMM_SUCCESS:
                raise self._failure(ids[0], what, result, {})
            out: dict[int, int] = {}
            errors: dict[int, int] = {}
            for sid in ids:
                data, result, error = self._call(self._ph.readRx, self._port, sid, reg.size)
                if result != self._sdk.COMM_SUCCESS:
                    raise self._failure(sid, what, result, out)
                if error:
                    errors[sid] = error
                out[sid] = reg.decode(int.from_bytes(bytes(data), "little"))
            self._check_clean(ids[-1], what, len(ids) * (6 + reg.size), out)
            if errors:
                sid, error = next(iter(errors.items()))
                raise ServoFault(f"{self.servo(sid)} reports a fault in {what}: {_bits(error)}", sid,
                                 {k: v for k, v in out.items() if k not in errors})
            return out
        return self._retrying(go)

    def sync_write(self, reg: Register, values: Mapping[int, int]) -> None:
        """One register of several servos in one broadcast packet; servos do not answer a sync write."""
        group = self._sdk.GroupSyncWrite(self._port, self._ph, reg.address, reg.size)
        for sid, value in values.items():
            group.addParam(sid, list(reg.encode(int(value)).to_bytes(reg.size, "little")))
        with self.lock:
            result = self._call(group.txPacket)
        if result != self._sdk.COMM_SUCCESS:
            raise PortError(f"serial port {self.config.port}: could not send SYNC_WRITE {reg.name} ({result})")

    def torque(self, ids: Iterable[int], on: bool) -> None:
        self.sync_write(TORQUE_ENABLE, {sid: int(on) for sid in ids})


def _make_port(sdk, config: BusConfig, bus: FeetechBus):
    """The SDK's port handler, keeping each transaction's received bytes, waiting on the file descriptor
    instead of spinning, and with the configured reply timeout."""

    class Port(sdk.PortHandler):
        def __init__(self) -> None:
            super().__init__(config.port)
            self.baudrate = config.baudrate
            self.rx = bytearray()

        def clearPort(self) -> None:  # called by the SDK before every request
            waiting = self.ser.in_waiting
            if waiting:  # a late reply to an earlier, failed transaction
                bus.stale_bytes += len(self.ser.read(waiting))
            self.rx.clear()
            self.ser.flush()

        def readPort(self, length: int) -> bytes:
            data = self.ser.read(length)
            if not data:
                remaining = self.packet_timeout - self.getTimeSinceStart()
                select.select([self.ser.fileno()], [], [], max(0.0, min(remaining, 1.0)) / 1000.0)
                data = self.ser.read(length)
            self.rx += data
            return data

        def setPacketTimeout(self, packet_length: int) -> None:
            self.packet_start_time = self.getCurrentTime()
            self.packet_timeout = self.tx_time_per_byte * packet_length + config.reply_timeout_ms

    return Port()
