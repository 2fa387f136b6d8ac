"""Round-trip latency of the serial link (``pivla robot check --bench N``, ``pivla bench robot``)."""

from __future__ import annotations

import argparse
import statistics
import time

from pivla.robot.link import Board
from pivla.robot.simboard import SimBoard


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


def run_bench(args: argparse.Namespace) -> dict:
    """Flags: ``port`` (None: start a simavr board with the built firmware), ``n`` round trips."""
    port, n = getattr(args, "port", None), int(getattr(args, "n", 200))
    if port:
        board = Board.open(port)
        try:
            return {"port": port, **measure(board, n)}
        finally:
            board.close()
    with SimBoard() as sim:
        board = Board.open(sim.port)
        try:
            return {"port": f"simavr:{sim.port}", **measure(board, n)}
        finally:
            board.close()
