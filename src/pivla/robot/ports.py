"""Which serial port is the arm's: the one that disappears when its USB cable is unplugged (LeRobot's way)."""

from __future__ import annotations

import time
from collections.abc import Callable


class PortNotFound(RuntimeError):
    """Unplugging removed no port, or more than one."""


def list_ports() -> list[str]:
    """Serial ports with a device behind them (USB adapters, ACM boards), sorted."""
    from serial.tools import list_ports as lp

    return sorted(p.device for p in lp.comports())


def find_port(wait: Callable[[str], object] = input, settle_s: float = 0.5) -> str:
    """Lists the ports, asks for the cable to be unplugged (``wait`` shows the prompt and returns once done),
    lists them again and returns the one that went away."""
    before = list_ports()
    if not before:
        raise PortNotFound("no serial ports found; plug in the arm's USB cable first")
    wait(f"ports now: {', '.join(before)}\nunplug the arm's USB cable and press Enter")
    time.sleep(settle_s)  # the kernel removes the device node shortly after the cable is out
    gone = sorted(set(before) - set(list_ports()))
    if len(gone) == 1:
        return gone[0]
    if not gone:
        raise PortNotFound("no port went away; was the cable of the arm's board unplugged?")
    raise PortNotFound(f"several ports went away ({', '.join(gone)}); unplug only the arm's cable")
