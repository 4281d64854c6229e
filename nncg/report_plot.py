"""The plots of --report (nncg/report.py), drawn with matplotlib's Agg renderer into PNG bytes that are
the same for the same data: no pyplot state, no timestamp, no software tag, DejaVu Sans (shipped with
matplotlib), math text off (a `$` draws as itself). Labels are layer indices and the layers' C names
(identifiers NNCG made), never a model's own text."""

from __future__ import annotations

import io
from collections.abc import Sequence

import matplotlib
from matplotlib.figure import Figure

STYLE = {"font.family": "DejaVu Sans", "font.size": 9, "text.parse_math": False}
DPI = 100
KIB = 1024


def memory_timeline(spans: Sequence, layers: int, arena_bytes: int) -> bytes:
    """Top: each arena buffer as a bar over the layers it is live in (x: layer index, y: its bytes
    offset..offset+size). Bottom: the bytes live at each layer against the arena size.
    `spans` are report.BufferSpan."""
    with matplotlib.rc_context(STYLE):
        fig = Figure(figsize=(10, 6.5), dpi=DPI, layout="constrained")
        placed, live = fig.subplots(2, 1, sharex=True, height_ratios=(3, 1))
        colours = matplotlib.colormaps["tab20"]
        for i, span in enumerate(spans):
            placed.broken_barh(
                [(span.first - 0.45, span.last - span.first + 0.9)],
                (span.offset / KIB, span.size / KIB),
                facecolors=colours(i % 20),
                edgecolors="black",
                linewidth=0.5,
            )
        placed.set_ylabel("arena offset (KiB)")
        placed.set_title("Arena buffers: offset and lifetime")
        placed.set_ylim(0, max(arena_bytes, 1) / KIB)
        occupancy = [sum(s.size for s in spans if s.first <= i <= s.last) / KIB for i in range(layers)]
        live.bar(range(layers), occupancy, color="#4c72b0", width=0.8)
        live.axhline(arena_bytes / KIB, color="#c44e52", linewidth=1, label="arena size")
        live.legend(loc="upper right")
        live.set_ylabel("live (KiB)")
        live.set_xlabel("layer index")
        live.set_xlim(-0.6, max(layers, 1) - 0.4)
        return _png(fig)


def layer_times(names: Sequence[str], micros: Sequence[float]) -> bytes:
    """--profile: one horizontal bar of µs per layer, first layer on top."""
    with matplotlib.rc_context(STYLE):
        fig = Figure(figsize=(10, 1.2 + 0.22 * len(names)), dpi=DPI, layout="constrained")
        axes = fig.subplots()
        positions = range(len(names))
        axes.barh(positions, micros, color="#4c72b0")
        axes.set_yticks(positions, [f"{i} {name}" for i, name in enumerate(names)])
        axes.invert_yaxis()
        axes.set_xlabel("µs per inference")
        axes.set_title("Time per layer (--profile)")
        return _png(fig)


def runtimes(labels: Sequence[str], micros: Sequence[float]) -> bytes:
    """--benchmark: median µs per inference of NNCG and onnxruntime side by side."""
    with matplotlib.rc_context(STYLE):
        fig = Figure(figsize=(7, 2.4), dpi=DPI, layout="constrained")
        axes = fig.subplots()
        positions = range(len(labels))
        bars = axes.barh(positions, micros, color=["#55a868"] + ["#8172b2"] * (len(labels) - 1))
        axes.bar_label(bars, [f"{us:.1f} µs" for us in micros], padding=3)
        axes.set_yticks(positions, labels)
        axes.invert_yaxis()
        axes.set_xlabel("median µs per inference")
        axes.set_xlim(0, max(micros, default=1) * 1.25)
        axes.set_title("NNCG vs onnxruntime (--benchmark)")
        return _png(fig)


def _png(fig: Figure) -> bytes:
    out = io.BytesIO()
    fig.savefig(out, format="png", metadata={"Software": None})
    return out.getvalue()
