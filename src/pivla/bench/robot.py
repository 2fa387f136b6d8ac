"""Round-trip latency of the serial link to the arm's board (``pivla bench robot``, ``pivla robot check --bench N``)."""

from __future__ import annotations

import statistics
import time
from dataclasses import dataclass

from pivla.robot.link import Board
from pivla.robot.simboard import SimBoard


@dataclass
class RobotBenchConfig:
    """Which board to time."""

    port: str | None = None
    """Serial port of the board (default: start the firmware on a simulated Uno)."""
    n: int = 200
    """Round trips of each kind."""


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
        lat.sort()
        results[f"{name}_ms_median"] = round(statistics.median(lat), 3)
        results[f"{name}_ms_p90"] = round(lat[int(0.9 * (len(lat) - 1))], 3)
    results["resends"] = board.link.resends
    results["n"] = n
    return results


def run_robot_bench(cfg: RobotBenchConfig) -> dict:
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
