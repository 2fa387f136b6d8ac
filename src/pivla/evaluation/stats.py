"""Statistics for success rates measured on shared episodes.

Every executor of a benchmark condition meets the same episodes (same seeds), so two executors' outcomes
are *paired*: episode i gives a 2x2 table cell (both succeed, only A, only B, neither). The right tests use
that pairing: McNemar's exact test on the discordant pairs, and a confidence interval for the difference
that accounts for the correlation between the two success rates (Newcombe 1998, "Improved confidence
intervals for the difference between binomial proportions based on paired data", Stat. Med. 17:2635-2650,
method 10: Wilson score limits of each rate combined with the estimated correlation). An unpaired interval
(two independent Wilson intervals) is needlessly wide when the executors succeed on mostly the same episodes.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

Z95 = 1.959963984540054  # the standard normal's 97.5% quantile


def wilson_interval(successes: int, n: int, z: float = Z95) -> tuple[float, float]:
    """Wilson score interval for a binomial proportion (95% by default); (0, 1) when ``n`` is 0."""
    if n < 0 or not 0 <= successes <= max(n, 0):
        raise ValueError(f"wilson_interval: need 0 <= successes <= n, got successes={successes}, n={n}")
    if n == 0:
        return 0.0, 1.0
    p = successes / n
    denom = 1 + z * z / n
    centre = (p + z * z / (2 * n)) / denom
    half = z * np.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / denom
    return float(max(0.0, centre - half)), float(min(1.0, centre + half))


def mcnemar_exact(b: int, c: int) -> float:
    """Two-sided exact McNemar p-value for ``b`` pairs where only A succeeded and ``c`` where only B did.

    Under "A and B are equally good" each discordant pair is a fair coin, so the p-value is twice the
    binomial(b + c, 1/2) tail of the rarer kind, capped at 1 (1 when there are no discordant pairs).
    Computed with exact integers, so it stays right for thousands of pairs."""
    if b < 0 or c < 0:
        raise ValueError(f"mcnemar_exact: counts must be >= 0, got b={b}, c={c}")
    n = b + c
    if n == 0:
        return 1.0
    tail = sum(math.comb(n, i) for i in range(min(b, c) + 1))
    return min(1.0, 2 * tail / 2**n)


def _outcomes(a: Sequence[bool] | np.ndarray, b: Sequence[bool] | np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Two equally long 1-D success vectors (bool, or 0/1) as bool arrays."""
    arrays = []
    for name, x in (("a", a), ("b", b)):
        arr = np.asarray(x)
        if arr.ndim != 1:
            raise ValueError(f"{name}: expected a 1-D sequence of episode successes, got shape {arr.shape}")
        if arr.dtype != bool and not np.isin(arr, (0, 1)).all():
            raise ValueError(f"{name}: episode successes must be booleans or 0/1")
        arrays.append(arr.astype(bool))
    if len(arrays[0]) != len(arrays[1]):
        raise ValueError(f"paired outcomes need the same episodes: {len(arrays[0])} against {len(arrays[1])}")
    if len(arrays[0]) == 0:
        raise ValueError("no paired episodes to compare")
    return arrays[0], arrays[1]


def newcombe_paired_interval(both: int, a_only: int, b_only: int, neither: int,
                             z: float = Z95) -> tuple[float, float]:
    """Newcombe's method 10 interval for p_A - p_B from a paired 2x2 table (module docstring).

    With a = both, b = a_only, c = b_only, d = neither, n = a + b + c + d, p_A = (a + b) / n,
    p_B = (a + c) / n, Wilson limits (l_A, u_A) and (l_B, u_B), and the correlation estimate
    phi = (ad - bc) / sqrt((a+b)(c+d)(a+c)(b+d)), whose positive numerator is reduced by n/2 (down to 0), and
    phi = 0 when a margin is empty:

        lower = (p_A - p_B) - sqrt((p_A - l_A)^2 - 2 phi (p_A - l_A)(u_B - p_B) + (u_B - p_B)^2)
        upper = (p_A - p_B) + sqrt((u_A - p_A)^2 - 2 phi (u_A - p_A)(p_B - l_B) + (p_B - l_B)^2)
    """
    if min(both, a_only, b_only, neither) < 0:
        raise ValueError(f"table counts must be >= 0, got {(both, a_only, b_only, neither)}")
    n = both + a_only + b_only + neither
    if n == 0:
        raise ValueError("no paired episodes to compare")
    sa, sb = both + a_only, both + b_only
    pa, pb = sa / n, sb / n
    la, ua = wilson_interval(sa, n, z)
    lb, ub = wilson_interval(sb, n, z)
    margins = sa * (n - sa) * sb * (n - sb)
    cross = both * neither - a_only * b_only
    if margins == 0:
        phi = 0.0
    elif cross > n / 2:
        phi = (cross - n / 2) / math.sqrt(margins)
    elif cross >= 0:
        phi = 0.0
    else:
        phi = cross / math.sqrt(margins)
    delta = math.sqrt(max(0.0, (pa - la) ** 2 - 2 * phi * (pa - la) * (ub - pb) + (ub - pb) ** 2))
    eps = math.sqrt(max(0.0, (ua - pa) ** 2 - 2 * phi * (ua - pa) * (pb - lb) + (pb - lb) ** 2))
    diff = pa - pb
    return max(-1.0, diff - delta), min(1.0, diff + eps)


def paired_difference(a: Sequence[bool] | np.ndarray, b: Sequence[bool] | np.ndarray,
                      z: float = Z95) -> tuple[float, float, float]:
    """(p_A - p_B, lower, upper): the episode-paired difference in success with Newcombe's method 10 interval
    (95% by default); ``a[i]`` and ``b[i]`` are the two executors' outcomes on episode i."""
    a, b = _outcomes(a, b)
    both, a_only, b_only = int(np.sum(a & b)), int(np.sum(a & ~b)), int(np.sum(~a & b))
    lo, hi = newcombe_paired_interval(both, a_only, b_only, len(a) - both - a_only - b_only, z)
    return (a_only - b_only) / len(a), lo, hi


def compare(a: Sequence[bool] | np.ndarray, b: Sequence[bool] | np.ndarray) -> dict:
    """Executor A against B on the same episodes: ``n``, ``successes_a``, ``successes_b``, ``only_a`` (episodes
    only A solved; McNemar's b), ``only_b`` (only B; McNemar's c), ``diff`` (p_A - p_B), ``ci95`` (Newcombe's
    paired interval) and ``p_mcnemar``."""
    a, b = _outcomes(a, b)
    only_a, only_b = int(np.sum(a & ~b)), int(np.sum(~a & b))
    diff, lo, hi = paired_difference(a, b)
    return {"n": len(a), "successes_a": int(a.sum()), "successes_b": int(b.sum()), "only_a": only_a,
            "only_b": only_b, "diff": diff, "ci95": [lo, hi], "p_mcnemar": mcnemar_exact(only_a, only_b)}


def percent_interval(lo: float, hi: float, signed: bool = False) -> str:
    """An interval of proportions in percent, ``[lo, hi]`` to one decimal; ``signed`` for differences."""
    spec = "+.1f" if signed else ".1f"
    return f"[{100 * lo:{spec}}, {100 * hi:{spec}}]"


def format_difference(cmp: dict, with_p: bool = True) -> str:
    """A paired comparison (``compare``) in points with its 95% interval, and McNemar's p unless ``with_p`` is
    off: the one spelling every report uses."""
    text = f"{100 * cmp['diff']:+.1f} {percent_interval(*cmp['ci95'], signed=True)}"
    return f"{text} (p {cmp['p_mcnemar']:.2g})" if with_p else text


def paired_rows(rows_a: list[dict], rows_b: list[dict]) -> list[tuple[dict, dict]]:
    """Two evaluations' episode rows (``episodes.jsonl``) paired on (task index, episode), in that order;
    raises unless both ran exactly the same episodes with the same seeds."""
    a = {(r["task_index"], r["episode"]): r for r in rows_a}
    b = {(r["task_index"], r["episode"]): r for r in rows_b}
    if a.keys() != b.keys():
        missing = sorted(a.keys() ^ b.keys())[:5]
        raise ValueError(f"the two evaluations did not run the same episodes (e.g. task, episode {missing})")
    keys = sorted(a)
    seeds_differ = [k for k in keys if a[k]["seed"] != b[k]["seed"]]
    if seeds_differ:
        raise ValueError(f"the two evaluations ran other seeds for the same episodes (e.g. {seeds_differ[:5]})")
    return [(a[k], b[k]) for k in keys]


def paired_successes(rows_a: list[dict], rows_b: list[dict]) -> tuple[np.ndarray, np.ndarray]:
    """Success vectors of two evaluations' episode rows, aligned by ``paired_rows``."""
    pairs = paired_rows(rows_a, rows_b)
    return (np.array([bool(ra["success"]) for ra, _ in pairs]), np.array([bool(rb["success"]) for _, rb in pairs]))
