"""Reports as values, and the one renderer of their markdown and figures.

A report is a list of blocks: a string (a heading or a paragraph: one line), ``Lines`` (lines that follow one
another, such as a list or figure links) or a ``Table``; ``markdown`` puts one blank line between blocks. A
``Table`` keeps what a JSON report stores beside its cells (records, the paired comparisons behind its
differences). A ``Chart`` holds success curves with their 95% intervals; ``draw`` turns it into a PNG.
"""

from __future__ import annotations

import io
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from matplotlib.figure import Figure

from pivla.io import atomic_write_bytes


@dataclass(frozen=True)
class Lines:
    """Lines printed one under the other, without blank lines between them."""

    lines: tuple[str, ...]


@dataclass(frozen=True)
class Table:
    """A markdown table: its header and rows of cells (None: a blank cell), an optional ``## title`` and
    paragraph above it; ``key``, ``records`` and ``comparisons``: the table as a JSON report keeps it."""

    header: Sequence[str]
    rows: Sequence[Sequence[str | None]]
    title: str | None = None
    note: str | None = None
    key: str | None = None
    records: list = field(default_factory=list)
    comparisons: list = field(default_factory=list)


Block = str | Lines | Table


def _row(cells: Iterable[str | None]) -> str:
    return "|" + "|".join(" " if c is None else f" {c} " for c in cells) + "|"


def table_lines(table: Table) -> list[str]:
    lines = [f"## {table.title}", ""] if table.title else []
    if table.note:
        lines += [table.note, ""]
    return [*lines, _row(table.header), "|" + "---|" * len(table.header), *(_row(r) for r in table.rows)]


def block_lines(block: Block) -> list[str]:
    if isinstance(block, Table):
        return table_lines(block)
    if isinstance(block, Lines):
        return list(block.lines)
    return [block]


def markdown(blocks: Iterable[Block]) -> str:
    """The blocks one blank line apart (a block of no lines keeps its blank line), ending in a newline."""
    lines: list[str] = []
    for i, block in enumerate(blocks):
        if i:
            lines.append("")
        lines += block_lines(block)
    return "\n".join(lines) + "\n"


def write_markdown(path: Path, blocks: Iterable[Block]) -> str:
    text = markdown(blocks)
    atomic_write_bytes(path, text.encode())
    return text


# -- figures ----------------------------------------------------------------------------------------------
def new_figure(figsize: tuple[float, float], ncols: int = 1) -> tuple[Figure, Any]:
    """A figure and its axes outside pyplot: no global backend to select and no figure registry to close."""
    fig = Figure(figsize=figsize)
    return fig, fig.subplots(1, ncols)


def save_figure(fig: Figure, path: Path) -> None:
    """PNG, written atomically."""
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=110, bbox_inches="tight")
    atomic_write_bytes(path, buf.getvalue())


@dataclass(frozen=True)
class Curve:
    """Success rates (``ResultsStore.rate``'s dicts, None where not run) against x."""

    label: str
    xs: Sequence[float]
    rates: Sequence[dict | None]


@dataclass(frozen=True)
class Panel:
    """One axes of curves; ``legend``: None for none, else the legend's font size (0: matplotlib's)."""

    xlabel: str
    ylabel: str
    curves: Sequence[Curve]
    legend: float | None = None


@dataclass(frozen=True)
class Chart:
    """A figure of panels side by side, stored at ``path`` (relative to the report)."""

    path: str
    size: tuple[float, float]
    panels: Sequence[Panel]

    def measured(self) -> bool:
        """Whether any curve has a rate: a chart without one is not drawn."""
        return any(r is not None for p in self.panels for c in p.curves for r in c.rates)


def draw(chart: Chart, root: Path) -> None:
    """The chart as PNG under ``root``: success in % with Wilson 95% error bars, the points not run left out."""
    fig, axes = new_figure(chart.size, ncols=len(chart.panels))
    for ax, panel in zip(np.atleast_1d(axes), chart.panels):
        for curve in panel.curves:
            pts = [(x, r) for x, r in zip(curve.xs, curve.rates) if r is not None]
            if pts:
                ax.errorbar([x for x, _ in pts], [100 * r["rate"] for _, r in pts],
                            yerr=np.clip([[100 * (r["rate"] - r["ci95"][0]), 100 * (r["ci95"][1] - r["rate"])]
                                          for _, r in pts], 0, None).T,  # Wilson bounds can round past the rate
                            marker="o", capsize=3, label=curve.label)
        ax.set(xlabel=panel.xlabel, ylabel=panel.ylabel, ylim=(0, 102))
        if panel.legend is not None:
            if panel.legend:
                ax.legend(fontsize=panel.legend)
            else:
                ax.legend()
    save_figure(fig, root / chart.path)
