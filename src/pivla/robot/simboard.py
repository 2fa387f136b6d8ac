"""Runs the real firmware ELF on a simulated Uno (simavr) and watches the servo pulses it produces.

``firmware/build/simboard`` (built by ``make -C firmware sim``) prints the pseudo-terminal path of the
board's UART on its first line, then ``P <t_us> w0 .. w6`` lines with the pulse widths it measured on
the servo pins. ``SimBoard`` starts it, parses those lines in a thread, and keeps the latest widths and
the extremes ever seen, which is what the end-to-end tests check limits against.
"""

from __future__ import annotations

import collections
import logging
import os
import shutil
import subprocess
import threading
import time
from pathlib import Path

log = logging.getLogger(__name__)

DEBIAN_PACKAGES = ("gcc-avr", "avr-libc", "binutils-avr", "simavr", "libsimavr-dev", "arduino-core-avr")
ARDUINO_CORE = Path("/usr/share/arduino/hardware/arduino/avr/cores/arduino")
SIMAVR_HEADER = Path("/usr/include/simavr/sim_avr.h")


def firmware_dir() -> Path:
    """The repository's ``firmware/`` directory (override with $PIVLA_FIRMWARE_DIR)."""
    env = os.environ.get("PIVLA_FIRMWARE_DIR")
    if env:
        return Path(env)
    return Path(__file__).resolve().parents[3] / "firmware"


def missing_toolchain() -> list[str]:
    """What is missing to build the firmware and the harness (empty when everything is installed)."""
    missing = [tool for tool in ("make", "avr-gcc", "avr-objcopy", "avr-size", "gcc") if shutil.which(tool) is None]
    if not ARDUINO_CORE.is_dir():
        missing.append(f"Arduino core ({ARDUINO_CORE})")
    if not SIMAVR_HEADER.is_file():
        missing.append(f"simavr headers ({SIMAVR_HEADER})")
    return missing


def build(driver: str = "timer1") -> tuple[Path, Path]:
    """Builds (or brings up to date) the firmware ELF and the simavr harness; returns both paths."""
    missing = missing_toolchain()
    if missing:
        raise RuntimeError(f"cannot build the firmware, missing: {', '.join(missing)}; "
                           f"install the Debian packages: apt-get install -y {' '.join(DEBIAN_PACKAGES)}")
    fw = firmware_dir()
    for target in (["firmware", f"DRIVER={driver}"], ["sim"]):
        proc = subprocess.run(["make", "-C", str(fw), *target], capture_output=True, text=True)
        if proc.returncode != 0:
            raise RuntimeError(f"make {' '.join(target)} failed in {fw}:\n{proc.stdout[-2000:]}{proc.stderr[-2000:]}")
    return fw / "build" / driver / "pivla_arm.elf", fw / "build" / "simboard"


class SimBoard:
    """A simulated Uno running ``firmware``; use as a context manager. ``port`` is the pty to open."""

    def __init__(self, firmware: str | Path | None = None, realtime_factor: float = 1.0,
                 start_timeout_s: float = 10.0) -> None:
        if firmware is None:
            firmware, harness = build()
        else:
            firmware = Path(firmware)
            if not firmware.is_file():
                raise FileNotFoundError(f"firmware ELF not found: {firmware}")
            harness = firmware_dir() / "build" / "simboard"
            if not harness.is_file():
                _, harness = build()
        self.firmware = Path(firmware)
        self._proc = subprocess.Popen([str(harness), "-r", str(realtime_factor), str(firmware)],
                                      stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, bufsize=1)
        self._lock = threading.Lock()
        self._cond = threading.Condition(self._lock)
        self.pulses: tuple[float, ...] | None = None
        self.sim_time_us = 0
        self.min_seen: list[float] | None = None
        self.max_seen: list[float] | None = None
        self.history: collections.deque[tuple[int, tuple[float, ...]]] = collections.deque(maxlen=4096)
        self.crashed: str | None = None
        self.port = self._read_port(start_timeout_s)
        self._reader = threading.Thread(target=self._read_lines, name="simboard-reader", daemon=True)
        self._reader.start()
        self._stderr = threading.Thread(target=self._drain_stderr, name="simboard-stderr", daemon=True)
        self._stderr.start()

    def _read_port(self, timeout_s: float) -> str:
        result: list[str] = []
        reader = threading.Thread(target=lambda: result.append(self._proc.stdout.readline()), daemon=True)
        reader.start()
        reader.join(timeout_s)
        line = result[0].strip() if result else ""
        if not line.startswith("/dev/"):
            err = ""
            if self._proc.poll() is not None:
                err = self._proc.stderr.read()
            self.close()
            raise RuntimeError(f"simboard did not report a serial port (got {line!r}) {err.strip()}")
        return line

    def _read_lines(self) -> None:
        for line in self._proc.stdout:
            parts = line.split()
            if not parts:
                continue
            if parts[0] == "P" and len(parts) == 9:
                t_us = int(parts[1])
                widths = tuple(float(x) for x in parts[2:])
                with self._cond:
                    self.pulses = widths
                    self.sim_time_us = t_us
                    self.history.append((t_us, widths))
                    self.min_seen = (list(widths) if self.min_seen is None
                                     else [min(a, b) for a, b in zip(self.min_seen, widths)])
                    self.max_seen = (list(widths) if self.max_seen is None
                                     else [max(a, b) for a, b in zip(self.max_seen, widths)])
                    self._cond.notify_all()
            elif parts[0] == "X":
                with self._cond:
                    self.crashed = " ".join(parts[1:])
                    self._cond.notify_all()

    def _drain_stderr(self) -> None:
        for line in self._proc.stderr:
            log.debug("simavr: %s", line.rstrip())

    def reset_extremes(self) -> None:
        with self._cond:
            self.min_seen = self.max_seen = None

    def wait_for(self, predicate, timeout_s: float) -> tuple[float, ...]:
        """Blocks until ``predicate(widths)`` holds for the latest measured widths; returns them."""
        deadline = time.monotonic() + timeout_s
        with self._cond:
            while True:
                if self.crashed:
                    raise RuntimeError(f"simulated board stopped: {self.crashed}")
                if self.pulses is not None and predicate(self.pulses):
                    return self.pulses
                remaining = deadline - time.monotonic()
                if remaining <= 0:
                    raise TimeoutError(f"pulse widths never satisfied the condition; last {self.pulses}")
                self._cond.wait(remaining)

    def alive(self) -> bool:
        return self._proc.poll() is None

    def close(self) -> None:
        if self._proc.poll() is None:
            self._proc.terminate()
            try:
                self._proc.wait(3)
            except subprocess.TimeoutExpired:
                self._proc.kill()
                self._proc.wait()

    def __enter__(self) -> SimBoard:
        return self

    def __exit__(self, *exc) -> None:
        self.close()
