"""The benchmark suite: every model x every target, NNCG against onnxruntime and the hardware peak.

    python3 -m benchmarks.suite [--cpu 0] [--tune] [--targets ansi-c ssse3] [--models ball robot] [--runs 3]

writes benchmarks/RESULTS.md (the table, the machine's CPU, the date; sections other suites added, such as
benchmarks/real_suite.py's, are kept) and benchmarks/results.png (speed-up over onnxruntime and % of peak per
model and target, of every table in RESULTS.md). Models NNCG cannot compile yet are listed, not hidden.
With --runs N the whole suite is measured N times; each row shows the medians over the runs and the range
of the run's speed-ups.
"""

from __future__ import annotations

import argparse
import datetime
import platform
import re
import statistics
from collections import Counter
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

from nncg.backends import BACKENDS
from nncg.bench.benchmark import BenchResult, benchmark
from nncg.bench.peak import TARGET_ISA
from nncg.cli import positive_number
from nncg.errors import NncgError
from nncg.tune import tune

from .runs import merged_runs, runs_of

ROOT = Path(__file__).resolve().parent.parent
PAPER = ["ball", "pedestrian", "robot"]
MLPERF_TINY = ["resnet8", "dscnn", "mobilenet_v1_025", "autoencoder"]


def model_path(name: str) -> Path:
    folder = ROOT / "examples" if name in PAPER else ROOT / "benchmarks" / "models"
    return folder / f"{name}.onnx"


@dataclass(frozen=True)
class Row:
    model: str
    target: str
    result: BenchResult | None
    problem: str = ""  # why there is no result (an unsupported operator, ...)
    unroll: str = "auto"
    speedups: tuple[float, ...] = ()  # each run's speed-up, when the suite ran several times (result: medians)


def run_suite(
    models, targets, *, cpu=None, batches=15, min_batch_seconds=0.02, peaks=None, progress=print, tuned=False,
    path_of=None,
) -> list[Row]:  # fmt: skip
    """With `tuned`, each model is first tuned per layer for each target (nncg.tune, cached); `path_of` maps a
    model name to its file (default: model_path). A model that fails is a row with the reason, not an abort.
    Without `peaks` (fixed GFLOP/s per ISA) the peak kernel is timed in every batch (nncg.bench.benchmark)."""
    path_of = path_of or model_path
    rows = []
    for model in models:
        for target in targets:
            progress(f"{model} / {target} ...")
            level = "auto, tuned" if tuned else "auto"  # the defaults
            try:
                path = path_of(model)
                pipeline = tune(path, target, cpu=cpu, progress=lambda _: None) if tuned else None
                result = benchmark(
                    path, target, "auto", cpu=cpu, batches=batches, min_batch_seconds=min_batch_seconds,
                    peaks=peaks, pipeline=pipeline,
                )  # fmt: skip
                rows.append(Row(model, target, result, unroll=level))
            except Exception as exc:  # noqa: BLE001 - a C compiler or export failure on one model: report, go on
                rows.append(Row(model, target, None, problem_text(exc), unroll=level))
    return rows


def repeated(runs: int, measure: Callable[[], list], merge: Callable[[list], object], progress=print) -> list:
    """`measure` (the rows of one run of a suite) `runs` times, each row merged with its namesakes of
    the other runs (same models and targets in the same order)."""
    measured = []
    for run in range(runs):
        if runs > 1:
            progress(f"run {run + 1} of {runs}")
        measured.append(measure())
    return [merge(list(same)) for same in zip(*measured, strict=True)]


def merged_row(same: list[Row]) -> Row:
    """A model and target over several runs (runs.merged_runs): µs and speed-up the medians over the runs,
    `speedups` each run's."""
    return merged_runs(
        same, lambda row: row.result is not None, results=("result",),
        per_run={"speedups": lambda row: (row.result.speedup,)},
    )  # fmt: skip


def ratio_range(ratios: Sequence[float]) -> str:
    """The lowest and highest of a ratio's runs, as `1.46-1.58x`."""
    return f"{min(ratios):.2f}-{max(ratios):.2f}x"


def problem_text(exc: Exception) -> str:
    """Why a model has no result: what NNCG does not support, or how it failed."""
    if isinstance(exc, NncgError):
        return "not supported yet: " + short_problem(str(exc))
    return f"failed: {type(exc).__name__}: {first_line(exc)}"


def first_line(exc: Exception) -> str:
    return (str(exc).strip().splitlines() or [""])[0][:200]


def short_problem(message: str) -> str:
    """An unsupported-operators error as `Clip x27, AveragePool x1`; other errors' first line."""
    ops = re.findall(r"(\w+) \(node '", message.split("; NNCG supports")[0])
    if not ops:
        return message.splitlines()[0]
    return ", ".join(f"{op} x{n}" for op, n in Counter(ops).items())


def cpu_model() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def sampled_peaks(results: Sequence[BenchResult | None]) -> dict[str, float]:
    """Per ISA the median of the results' peaks (each the median of the peak kernel timed in its batches)."""
    by_isa: dict[str, list[float]] = {}
    for result in results:
        if result is not None and result.peak_gflops:
            by_isa.setdefault(result.peak_isa, []).append(result.peak_gflops)
    return {isa: statistics.median(gflops) for isa, gflops in sorted(by_isa.items())}


def peaks_text(peaks: dict) -> str:
    return ", ".join(f"{isa} {g:.1f} GFLOP/s" if g else f"{isa} n/a" for isa, g in peaks.items())


# How a suite's % of peak is measured, as its RESULTS.md section states it.
PEAK_NOTE = (
    "the peak kernel (nncg.bench.peak) timed on the same core in every batch beside NNCG and onnxruntime; "
    "% peak is the median of the per-batch ratios of NNCG's GFLOP/s to the peak's, so a slow spell of the "
    "machine moves neither"
)


def results_markdown(rows: list[Row], peaks: dict, cpu: int | None, date: str) -> str:
    lines = [
        "# Benchmark results",
        "",
        f"- CPU: {cpu_model()} ({'pinned to core ' + str(cpu) if cpu is not None else 'not pinned'})",
        f"- Date: {date}",
        f"- Peak: {PEAK_NOTE}; medians: {peaks_text(peaks)}",
        "- NNCG: the generated C at `gcc -O3` plus the target's flags, at the unroll level shown (tuned: per-layer",
        "  algorithm, block shapes and unroll budgets from `--tune`, timed on this core); onnxruntime:",
        "  batch 1, one intra-op thread, all graph optimisations; `ORT µs` with IOBinding, `ORT run µs` through",
        "  `InferenceSession.run`. Medians of 15 batches of >= 20 ms each, NNCG and onnxruntime interleaved.",
        f"- {SPEEDUP_COLUMN}.",
        "- GFLOP/s = 2 x MACs / NNCG µs; % peak of the ISA the target uses.",
        "  MACs are those of direct convolution, so GFLOP/s and % peak are effective rates: the 3x3 convs that",
        "  run as Winograd F(2x2,3x3) execute 2.25x fewer multiplies (plus the transforms' adds).",
        "- text + rodata go to flash; RAM is bss, which holds the static arena (arena B: activations placed by",
        "  the memory plan; activations B: all activation buffers without reuse); gen s / cc s: C generation and",
        "  compile time.",
        *runs_lines(runs_of(rows, "speedups")),
        "",
    ]
    return "\n".join(lines) + "\n" + results_table(rows)


SPEEDUP_COLUMN = (
    "speed-up: the median of the per-batch ratios ORT time / NNCG time (a batch times both within seconds, so a\n"
    "  slow spell of the machine cancels; it can differ from ORT µs / NNCG µs)"
)


def over_runs(runs: int) -> str:
    """What a threshold line's ratios are: `one run` or `medians of N runs`."""
    return f"medians of {runs} runs" if runs > 1 else "one run"


def runs_lines(runs: int, ratios: str = "speed-up", ranges: str = "range") -> list[str]:
    """The note on a table of several runs: what its figures and its range columns are."""
    if runs < 2:
        return []
    return [
        f"- Measured {runs} times (--runs {runs}, all models and targets each time): µs and {ratios} are the medians",
        f"  over the runs; {ranges}: the lowest and highest run's value.",
    ]


RESULT_COLUMNS = (
    "model", "target", "unroll", "NNCG µs", "ORT µs", "ORT run µs", "speed-up", "MACs", "GFLOP/s", "% peak",
    "max abs err", "max rel err", "text B", "rodata B", "bss B", "arena B", "activations B", "gen s", "cc s",
)  # fmt: skip


def results_table(rows: list[Row]) -> str:
    """The rows' table; with a range column after speed-up when they are medians of several runs."""
    if runs_of(rows, "speedups") < 2:
        return markdown_table(RESULT_COLUMNS, [result_cells(row) for row in rows])
    at = RESULT_COLUMNS.index("speed-up") + 1
    cells = [result_cells(row) for row in rows]
    cells = [[*c[:at], ratio_range(row.speedups), *c[at:]] if row.result else c for c, row in zip(cells, rows)]
    return markdown_table([*RESULT_COLUMNS[:at], "range", *RESULT_COLUMNS[at:]], cells)


def result_cells(row: Row) -> list[str]:
    r = row.result
    if r is None:
        return [row.model, row.target, row.unroll, row.problem]
    pct = f"{r.percent_of_peak:.1f} ({r.peak_isa})" if r.percent_of_peak is not None else "n/a"
    return [
        row.model, row.target, row.unroll, f"{r.nncg_us:.2f}", f"{r.ort_bound_us:.2f}", f"{r.ort_run_us:.2f}",
        f"{r.speedup:.2f}x", f"{r.macs:,}", f"{r.gflops:.2f}", pct, f"{r.max_abs_err:.1e}", f"{r.max_rel_err:.1e}",
        f"{r.sizes.text:,}", f"{r.sizes.rodata:,}", f"{r.sizes.bss:,}", f"{r.arena_bytes:,}",
        f"{r.activation_bytes:,}", f"{r.generate_seconds:.2f}", f"{r.compile_seconds:.2f}",
    ]  # fmt: skip


def markdown_table(columns, rows) -> str:
    """A Markdown table; a short row (the reason there are no figures) is padded with empty cells."""
    lines = ["| " + " | ".join(columns) + " |", "|" + "---|" * len(columns)]
    lines += ["| " + " | ".join([*row, *[""] * (len(columns) - len(row))]) + " |" for row in rows]
    return "\n".join(lines) + "\n"


@dataclass(frozen=True)
class Bar:
    table: str  # the heading above the bar's table in RESULTS.md: one panel pair per table
    model: str
    target: str
    speedup: float
    percent_of_peak: float


def write_chart(rows: list[Row], path: Path) -> None:
    draw_chart([Bar("", r.model, r.target, r.result.speedup, r.result.percent_of_peak or 0.0)
                for r in rows if r.result is not None], path)  # fmt: skip


def table_bars(markdown: str) -> list[Bar]:
    """The measured rows of every results table in `markdown` (RESULTS.md), so the chart shows all sections."""
    bars, columns, heading = [], None, ""
    for line in markdown.splitlines():
        cells = [cell.strip() for cell in line.strip().strip("|").split("|")]
        if line.startswith("#"):
            heading = line.lstrip("#").strip()
        if not line.startswith("|"):
            columns = None
        elif cells[:2] == ["model", "target"]:
            # Only tables of float speed-ups and % peak (not the int8 or memory suites' tables).
            columns = {name: i for i, name in enumerate(cells)} if {"speed-up", "% peak"} <= set(cells) else None
        elif columns and cells[columns["speed-up"]].endswith("x"):
            pct = cells[columns["% peak"]].split(" ")[0]
            bars.append(Bar(
                heading, cells[columns["model"]], cells[columns["target"]], float(cells[columns["speed-up"]][:-1]),
                0.0 if pct == "n/a" else float(pct),
            ))  # fmt: skip
    return bars


BAR_INCHES = 0.16  # width per bar: the widest table sets the figure's width


def draw_chart(bars: list[Bar], path: Path) -> None:
    """Per results table, two panels side by side: speed-up over onnxruntime and % of peak, the models along x
    with one bar per target (one colour per target across the figure)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import matplotlib.ticker

    tables = list(dict.fromkeys(bar.table for bar in bars)) or [""]
    targets = sorted({bar.target for bar in bars})
    colours = {t: plt.get_cmap("tab10")(i % 10) for i, t in enumerate(targets)}
    widest = max([sum(bar.table == table for bar in bars) for table in tables] + [8])
    fig, axes = plt.subplots(len(tables), 2, figsize=(2 * (BAR_INCHES * widest + 2), 3.4 * len(tables)), squeeze=False)
    for (left, right), table in zip(axes, tables):
        rows = [bar for bar in bars if bar.table == table]
        _grouped(left, rows, colours, "speedup", "speed-up vs onnxruntime")
        left.axhline(1.0, color="black", linewidth=0.8)
        left.set_yscale("log")  # 0.3x and 27x in one table: a ratio reads the same above and below 1
        speedups = [bar.speedup for bar in rows] + [1.0]
        left.set_ylim(min(speedups) / 1.3, max(speedups) * 1.3)  # room for a labelled tick above the tallest bar
        left.yaxis.set_major_locator(matplotlib.ticker.LogLocator(subs=(1.0, 2.0, 5.0)))
        left.yaxis.set_major_formatter(matplotlib.ticker.FuncFormatter(lambda value, _: f"{value:g}x"))
        left.yaxis.set_minor_formatter(matplotlib.ticker.NullFormatter())
        _grouped(right, rows, colours, "percent_of_peak", "% of ISA peak")
        left.set_title(table, fontsize=9, loc="left")
    handles = [plt.Rectangle((0, 0), 1, 1, color=colours[t]) for t in targets]
    if targets:
        fig.legend(handles, targets, loc="upper right", ncol=len(targets), fontsize=8)
    fig.suptitle("NNCG, batch 1, one core", x=0.01, ha="left")
    fig.tight_layout(rect=(0, 0, 1, 0.98))
    fig.savefig(path, dpi=100, metadata={"Software": None})
    plt.close(fig)


def _grouped(ax, rows: list[Bar], colours: dict, field: str, ylabel: str) -> None:
    """Bars of `field` grouped by model along x, one per target in the group."""
    models = list(dict.fromkeys(bar.model for bar in rows))
    x = 0.0
    ticks = []
    for model in models:
        group = [bar for bar in rows if bar.model == model]
        ticks.append(x + (len(group) - 1) / 2)
        for bar in group:
            ax.bar(x, getattr(bar, field), color=colours[bar.target], width=0.9)
            x += 1
        x += 1  # a gap between models
    ax.set_xticks(ticks, models, fontsize=7, rotation=60, ha="right")
    ax.set_ylabel(ylabel, fontsize=8)
    ax.tick_params(axis="y", labelsize=7)


SECTION = re.compile(r"<!-- (?P<name>[\w-]+):begin -->\n.*?<!-- (?P=name):end -->\n", re.DOTALL)


def marked_sections(document: str) -> str:
    """The sections other suites wrote into RESULTS.md (between begin/end markers), to keep on a rewrite."""
    return "".join("\n" + m.group(0) for m in SECTION.finditer(document))


def merge_section(document: str, name: str, section: str) -> str:
    """`document` with its section `name` replaced by `section`, or with `section` appended."""
    block = f"<!-- {name}:begin -->\n{section.rstrip()}\n<!-- {name}:end -->\n"
    for m in SECTION.finditer(document):
        if m.group("name") == name:
            return document[: m.start()] + block + document[m.end() :]
    return document.rstrip("\n") + "\n\n" + block


def write_section(out_dir: Path, name: str, section: str) -> Path:
    """out_dir/RESULTS.md with its section `name` replaced (or added), and the chart redrawn."""
    previous = out_dir / "RESULTS.md"
    document = previous.read_text() if previous.exists() else "# Benchmark results\n"
    return write_results(out_dir, merge_section(document, name, section))


def write_results(out_dir: Path, document: str) -> Path:
    """RESULTS.md and results.png (every table's measured rows) in `out_dir`."""
    out_dir.mkdir(parents=True, exist_ok=True)
    results = out_dir / "RESULTS.md"
    results.write_text(document)
    draw_chart(table_bars(document), out_dir / "results.png")
    return results


RUNS_HELP = "measure every model and target this many times; report the medians over the runs and their range"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--models", nargs="+", default=PAPER + MLPERF_TINY)
    # The targets this x86 host runs (neon is ARM code).
    parser.add_argument("--targets", nargs="+", default=sorted(t for t in BACKENDS if t in TARGET_ISA))
    parser.add_argument("--cpu", type=int, help="pin the measurements to this core")
    parser.add_argument("--out-dir", type=Path, default=ROOT / "benchmarks")
    parser.add_argument("--tune", action="store_true", help="tune every model per layer first (nncg-onnx --tune)")
    parser.add_argument("--runs", type=positive_number, default=1, help=RUNS_HELP)
    args = parser.parse_args(argv)

    def measure() -> list[Row]:
        return run_suite(args.models, args.targets, cpu=args.cpu, tuned=args.tune)

    rows = repeated(args.runs, measure, merged_row)
    peaks = sampled_peaks([row.result for row in rows])
    today = datetime.date.today().isoformat()
    previous = args.out_dir / "RESULTS.md"
    kept = marked_sections(previous.read_text()) if previous.exists() else ""  # e.g. benchmarks/real_suite.py's
    print(write_results(args.out_dir, results_markdown(rows, peaks, args.cpu, today) + kept).read_text())
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
