"""Round-trip latency of the serial link to an arm (``pivla bench robot``, ``pivla robot check --bench N``):
the pivla arm's board (real, or its firmware under simavr) or the SO-101's servo bus (real, or simulated)."""

from __future__ import annotations

import statistics
import time
from dataclasses import dataclass
from typing import Literal

from pivla.robot.link import Board
from pivla.robot.simboard import SimBoard


@dataclass
class RobotBenchConfig:
    """Which arm to time."""

    port: str | None = None
    """Serial port of the arm (default: a simulated one: the firmware on a simulated Uno, or a simulated
    SO-101 bus at 1 Mbit/s)."""
    n: int = 200
    """Round trips of each kind."""
    robot: Literal["pivla-arm", "so101"] = "pivla-arm"
    """The pivla arm's board, or an SO-101's servo bus."""
    calibration: str | None = None
    """SO-101 on a real port: its LeRobot calibration file (every goal passes its limits)."""


def _summary(name: str, lat_ms: list[float]) -> dict:
    lat = sorted(lat_ms)
    return {f"{name}_ms_median": round(statistics.median(lat), 3),
            f"{name}_ms_p90": round(lat[int(0.9 * (len(lat) - 1))], 3)}


def measure(board: Board, n: int) -> dict:
    """``n`` GET_STATE and ``n`` SET_TARGETS round trips (holding position); latencies in ms."""
    st = board.state()
    results = {}
    for name, call in (("state", board.state), ("set_targets", lambda: board.set_targets(st.targets_us))):
        lat = []
        for _ in range(n):
            t0 = time.perf_counter()
            call()
            lat.append((time.perf_counter() - t0) * 1000)
        results.update(_summary(name, lat))
    results["resends"] = board.link.resends
    results["n"] = n
    return results


def measure_so101(arm, n: int) -> dict:
    """``n`` control steps of an SO-101 holding where it is: a sync read of the six present positions, then
    a sync write of the six goals (through the arm's guard); latencies in ms."""
    arm.enable()
    read, write, both = [], [], []
    for _ in range(n):
        t0 = time.perf_counter()
        q = arm.read()
        t1 = time.perf_counter()
        arm.command(q)
        t2 = time.perf_counter()
        read.append((t1 - t0) * 1000)
        write.append((t2 - t1) * 1000)
        both.append((t2 - t0) * 1000)
    return {**_summary("sync_read", read), **_summary("sync_write", write), **_summary("round_trip", both),
            "stale_bytes": arm.bus.stale_bytes, "n": n}


def _so101_bench(cfg: RobotBenchConfig) -> dict:
    from pivla.robot.feetech import BusConfig
    from pivla.robot.simbus import SimBus
    from pivla.robot.so101 import SO101, SO101Calibration, SO101Config

    config = SO101Config(watchdog_s=0.0)
    if cfg.port:
        if not cfg.calibration:
            raise ValueError("timing a real SO-101 needs its calibration file (--calibration)")
        with SO101.open(BusConfig(cfg.port), SO101Calibration.load(cfg.calibration), config) as arm:
            return {"port": cfg.port, **measure_so101(arm, cfg.n)}
    with SimBus() as sim, SO101.open(BusConfig(sim.port), SO101Calibration.full_range("sim"), config) as arm:
        return {"port": f"simulated bus at {sim.config.baudrate} bit/s:{sim.port}", **measure_so101(arm, cfg.n)}


def run_robot_bench(cfg: RobotBenchConfig) -> dict:
    if cfg.robot == "so101":
        return _so101_bench(cfg)
    if cfg.port:
        board = Board.open(cfg.port)
        try:
            return {"port": cfg.port, **measure(board, cfg.n)}
        finally:
            board.close()
    with SimBoard() as sim:
        board = Board.open(sim.port)
        try:
            return {"port": f"simavr:{sim.port}", **measure(board, cfg.n)}
        finally:
            board.close()
