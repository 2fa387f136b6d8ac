"""A simulated Feetech bus: STS3215 servos behind a pseudo-terminal, for tests and benchmarks without an arm.

A thread serves the pty's master end and speaks the STS protocol (``pivla.robot.feetech``): ping, read,
write, sync read and sync write on each servo's control table. Servos move toward their goal at a bounded
speed while their torque is on, apply their homing offset and clamp goals to their angle limits as the real
ones do, and ignore requests whose checksum is wrong. Replies are paced to the bus's bit rate (10 bits a
byte on the wire, request and replies in turn, no return delay), so a round trip costs what the wire
would; a USB adapter's latency is not modelled.

Faults are injected on purpose: a servo that does not answer (``mute``), one whose replies carry a wrong
checksum (``corrupt``), one that reports error bits (``error_bits``), bytes that are no packet before the
next replies (``inject_garbage``), and the link going away altogether (``unplug``). Every byte received
is kept (``received``) so tests can check what reached the bus.
"""

from __future__ import annotations

import os
import select
import threading
import time
import tty
from dataclasses import dataclass
from typing import Self

from pivla.robot import feetech as F

WRITABLE = {reg.address + k for reg in (F.ID, F.MIN_ANGLE_LIMIT, F.MAX_ANGLE_LIMIT, F.HOMING_OFFSET, F.MODE,
                                         F.TORQUE_ENABLE, F.ACCELERATION, F.GOAL_POSITION, F.LOCK)
            for k in range(reg.size)}  # the bytes a host may write; the rest of the table is read-only


@dataclass
class SimBusConfig:
    """Servos on the simulated bus and how they behave."""

    ids: tuple[int, ...] = (1, 2, 3, 4, 5, 6)
    baudrate: int = 1_000_000
    """Replies are paced to this bit rate (0: as fast as the host reads)."""
    speed_ticks_s: float = 3000.0
    """How fast a servo turns toward its goal (an STS3215 at 7.4 V turns about 3000 ticks/s unloaded)."""
    start_ticks: int = 2048
    """Where every servo starts (present position, no homing offset)."""


class SimServo:
    """One STS3215's control table and shaft. ``raw`` is the shaft angle in ticks before the homing offset."""

    def __init__(self, servo_id: int, raw: float) -> None:
        self.regs = bytearray(128)
        self.raw = float(raw)
        self.muted = False
        self.corrupt = False
        self.error_bits = 0
        self._put(F.MODEL_NUMBER, F.STS3215_MODEL)
        self._put(F.ID, servo_id)
        self._put(F.MAX_ANGLE_LIMIT, F.STS3215_RESOLUTION - 1)
        self._put(F.LOCK, 1)
        self._put(F.GOAL_POSITION, round(raw))

    def _put(self, reg: F.Register, value: int) -> None:
        self.regs[reg.address : reg.address + reg.size] = reg.encode(value).to_bytes(reg.size, "little")

    def get(self, reg: F.Register) -> int:
        return reg.decode(int.from_bytes(self.regs[reg.address : reg.address + reg.size], "little"))

    @property
    def servo_id(self) -> int:
        return self.regs[F.ID.address]

    @property
    def present(self) -> int:
        return round(self.raw - self.get(F.HOMING_OFFSET)) % F.STS3215_RESOLUTION

    def _target_raw(self) -> float:
        return self.get(F.GOAL_POSITION) + self.get(F.HOMING_OFFSET)

    def read(self, address: int, size: int) -> bytes:
        moving = self.get(F.TORQUE_ENABLE) and abs(self._target_raw() - self.raw) > 1
        self._put(F.PRESENT_POSITION, self.present)
        self.regs[F.MOVING.address] = int(bool(moving))
        self.regs[F.PRESENT_VOLTAGE.address] = 74
        self.regs[F.PRESENT_TEMPERATURE.address] = 30
        return bytes(self.regs[address : address + size])

    def write(self, address: int, data: bytes) -> None:
        for i, byte in enumerate(data):
            if address + i in WRITABLE:
                self.regs[address + i] = byte
        if address <= F.GOAL_POSITION.address < address + len(data):  # the servo clamps to its angle limits
            lo, hi = self.get(F.MIN_ANGLE_LIMIT), self.get(F.MAX_ANGLE_LIMIT)
            if lo < hi:
                self._put(F.GOAL_POSITION, min(max(self.get(F.GOAL_POSITION), lo), hi))

    def step(self, dt: float, speed: float) -> None:
        if self.get(F.TORQUE_ENABLE):
            err = self._target_raw() - self.raw
            self.raw += max(-speed * dt, min(speed * dt, err))


class SimBus:
    """Serves ``config.ids`` servos on a pty; ``port`` is the path a host opens."""

    def __init__(self, config: SimBusConfig | None = None) -> None:
        self.config = config or SimBusConfig()
        self._master, self._slave = os.openpty()
        tty.setraw(self._slave)
        self.port = os.ttyname(self._slave)
        self.servos = {sid: SimServo(sid, self.config.start_ticks) for sid in self.config.ids}
        self.received = bytearray()
        self.goal_writes: list[tuple[int, int]] = []  # (servo id, goal) for every goal that reached a servo
        self.bad_requests = 0
        self._garbage = b""
        self._reader = F.PacketReader()
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._unplug = threading.Event()
        self._unplugged = False
        self._wire_free = 0.0  # when the wire is next idle (requests and replies take turns on it)
        self._thread = threading.Thread(target=self._run, name="simbus", daemon=True)
        self._thread.start()

    # --- fault injection -------------------------------------------------------------------------
    def mute(self, servo_id: int, muted: bool = True) -> None:
        """The servo neither answers nor obeys (its cable is out)."""
        with self._lock:
            self.servos[servo_id].muted = muted

    def corrupt(self, servo_id: int, corrupt: bool = True) -> None:
        """The servo's replies carry a wrong checksum."""
        with self._lock:
            self.servos[servo_id].corrupt = corrupt

    def error_bits(self, servo_id: int, bits: int) -> None:
        """The servo reports these error bits in its status packets (e.g. 4: overheat)."""
        with self._lock:
            self.servos[servo_id].error_bits = bits

    def inject_garbage(self, data: bytes = b"\x00\x13\x37\xaa\x55") -> None:
        """These bytes go out on the bus just before the next reply."""
        with self._lock:
            self._garbage += data

    def unplug(self) -> None:
        """The link goes away: the pty's master end closes, so the host's reads and writes fail."""
        self._unplug.set()
        self._thread.join(2)

    # --- inspection ------------------------------------------------------------------------------
    def positions(self) -> dict[int, int]:
        """Present position of every servo (ticks)."""
        with self._lock:
            return {sid: s.present for sid, s in self.servos.items()}

    def set_position(self, servo_id: int, ticks: int) -> None:
        """Moves a shaft by hand (as with torque off) to ``ticks`` of present position."""
        with self._lock:
            s = self.servos[servo_id]
            s.raw = float(ticks + s.get(F.HOMING_OFFSET))
            if not s.get(F.TORQUE_ENABLE):
                s._put(F.GOAL_POSITION, ticks)

    def register(self, servo_id: int, reg: F.Register) -> int:
        with self._lock:
            return self.servos[servo_id].get(reg)

    def set_register(self, servo_id: int, reg: F.Register, value: int) -> None:
        with self._lock:
            self.servos[servo_id]._put(reg, value)

    # --- protocol --------------------------------------------------------------------------------
    def _reply(self, servo: SimServo, params: bytes = b"") -> bytes:
        packet = F.encode_packet(servo.servo_id, servo.error_bits, params)
        if servo.corrupt:
            packet = packet[:-1] + bytes([packet[-1] ^ 0x5A])
        return packet

    def _by_id(self, servo_id: int) -> SimServo | None:
        for s in self.servos.values():
            if s.servo_id == servo_id and not s.muted:
                return s
        return None

    def _dispatch(self, p: F.Packet) -> list[bytes]:
        """The replies to one request, in the order the servos send them."""
        if not p.checksum_ok:
            self.bad_requests += 1
            return []
        instr, params = p.code, p.params
        if p.servo_id == F.BROADCAST_ID:
            if instr == F.Instr.SYNC_WRITE and len(params) >= 2:
                address, size = params[0], params[1]
                for at in range(2, len(params) - size, size + 1):
                    servo = self._by_id(params[at])
                    if servo is not None:
                        self._write(servo, address, params[at + 1 : at + 1 + size])
                return []
            if instr == F.Instr.SYNC_READ and len(params) >= 2:
                address, size = params[0], params[1]
                servos = [self._by_id(sid) for sid in params[2:]]
                return [self._reply(s, s.read(address, size)) for s in servos if s is not None]
            if instr == F.Instr.WRITE and params:
                for s in self.servos.values():
                    if not s.muted:
                        self._write(s, params[0], params[1:])
            return []
        servo = self._by_id(p.servo_id)
        if servo is None:
            return []
        if instr == F.Instr.PING:
            return [self._reply(servo)]
        if instr == F.Instr.READ and len(params) == 2:
            return [self._reply(servo, servo.read(params[0], params[1]))]
        if instr == F.Instr.WRITE and params:
            self._write(servo, params[0], params[1:])
            return [self._reply(servo)]
        return []

    def _write(self, servo: SimServo, address: int, data: bytes) -> None:
        servo.write(address, data)
        if address <= F.GOAL_POSITION.address < address + len(data):
            self.goal_writes.append((servo.servo_id, servo.get(F.GOAL_POSITION)))

    def _byte_s(self) -> float:
        return 10.0 / self.config.baudrate if self.config.baudrate else 0.0

    def _run(self) -> None:
        last = time.monotonic()
        while not self._stop.is_set():
            if self._unplug.is_set():  # closed by this thread, so no other thread selects on a reused fd
                with self._lock:
                    self._unplugged = True
                    os.close(self._master)
                return
            ready, _, _ = select.select([self._master], [], [], 0.002)
            data = os.read(self._master, 512) if ready else b""
            now = time.monotonic()
            with self._lock:
                self.received += data
                for s in self.servos.values():
                    s.step(now - last, self.config.speed_ticks_s)
                last = now
                replies = []
                for packet in self._reader.feed(data):
                    replies += self._dispatch(packet)
            if data:
                self._wire_free = max(now, self._wire_free) + len(data) * self._byte_s()
            if replies:
                self._send(replies)

    def _send(self, replies: list[bytes]) -> None:
        """Writes each reply when the wire would have carried it (after the requests and earlier replies)."""
        byte_s = self._byte_s()
        due = self._wire_free
        for i, reply in enumerate(replies):
            with self._lock:
                if i == 0 and self._garbage:
                    reply, self._garbage = self._garbage + reply, b""
            due += len(reply) * byte_s
            wait = due - time.monotonic()
            if wait > 0:
                time.sleep(wait)
            os.write(self._master, reply)
        self._wire_free = due

    def close(self) -> None:
        self._stop.set()
        self._thread.join(2)
        fds = [self._slave] if self._unplugged else [self._master, self._slave]
        for fd in fds:
            try:
                os.close(fd)
            except OSError:
                pass

    def __enter__(self) -> Self:
        return self

    def __exit__(self, *exc) -> None:
        self.close()
