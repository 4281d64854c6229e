"""The memory suite: each model at every --memory setting, latency against the arena it needs (issue 18).

    python3 -m benchmarks.memory_suite [--models robot ...] [--targets ssse3 avx2] [--cpu 0] [--batches 15] [--int8]
                                       [--runs 3]

For the paper's models and the MLPerf-Tiny-shaped ones, per x86 target, the three settings (speed, balanced,
min) and onnxruntime (one thread) are timed in one interleaved run (nncg.bench.benchmark_variants), so each
setting's latency ratio to speed's is measured side by side. Next to it: the arena (NAME_ARENA_BYTES), the
layer-by-layer bound and all activations side by side (nncg.compiler.memory_figures), the plan and the error
against onnxruntime. With --int8, each model also quantised as the int8 suite quantises it (rows "NAME int8",
its errors against onnxruntime on the QDQ model). --runs N measures all of it N times and reports the medians
over the runs and the ratios' ranges. Writes the "memory" section of benchmarks/RESULTS.md and prints it.
"""

from __future__ import annotations

import argparse
import datetime
import shlex
import statistics
import sys
from dataclasses import dataclass
from pathlib import Path

from nncg.bench.benchmark import BenchResult, Timing, benchmark_variants, paired_ratio
from nncg.cli import positive_number
from nncg.lowering.band_plan import MEMORY_MODES
from nncg.safe_text import markdown_text

from .int8_suite import quantized_model
from .runs import merged_runs, runs_of
from .suite import (
    MLPERF_TINY,
    PAPER,
    PEAK_NOTE,
    ROOT,
    RUNS_HELP,
    cpu_model,
    model_path,
    over_runs,
    peaks_text,
    problem_text,
    ratio_range,
    repeated,
    runs_lines,
    sampled_peaks,
    write_section,
)

SECTION = "memory"
INT8 = " int8"  # a model name's suffix: the QDQ model of the int8 suite
# Issue 18's arena targets at --memory min (float32, bytes).
MIN_TARGETS = {"robot": 48_000, "mobilenet_v1_025": 73_728, "resnet8": 65_536, "pedestrian": 16_384}
PLAN_LIMIT = 400  # characters of a plan shown in a cell
# A second build of speed, timed in the same run: its ratio to speed's is the noise floor of the others.
CONTROL = "speed again"
SETTINGS = {**{mode: mode for mode in MEMORY_MODES}, CONTROL: "speed"}  # row name: --memory


@dataclass(frozen=True)
class MemoryRow:
    model: str
    target: str
    setting: str
    result: BenchResult | None
    speed: BenchResult | None  # the same model and target at --memory speed, timed in the same run
    problem: str = ""
    # Each run's latency relative to speed's: the median of the per-batch ratios of the same interleaved run.
    ratios: tuple[float, ...] = ()

    @property
    def ratio(self) -> float:
        """The median over the runs of the latency relative to speed's."""
        return statistics.median(self.ratios)

    @property
    def arena_cut(self) -> float:
        """How many times smaller the arena is than speed's."""
        return self.speed.arena_bytes / self.result.arena_bytes


def suite_model(name: str):
    """The file of a model of the suite, or for NAME int8 the int8 suite's QDQ model of NAME."""
    return quantized_model(name.removesuffix(INT8)) if name.endswith(INT8) else model_path(name)


def run_memory_suite(
    models, targets, *, cpu=None, batches=15, min_batch_seconds=0.02, peaks=None, progress=print, path_of=None,
) -> list[MemoryRow]:  # fmt: skip
    """A row per model, target and setting; a model that fails is one row per setting with the reason.
    Without `peaks` (fixed GFLOP/s per ISA) the peak kernel is timed in every batch (nncg.bench.benchmark)."""
    path_of = path_of or suite_model
    variants = {row: {"memory": memory} for row, memory in SETTINGS.items()}
    timing = Timing(batches, min_batch_seconds, cpu=cpu, peaks=peaks)
    rows = []
    for model in models:
        for target in targets:
            progress(f"{model} / {target} ...")
            try:
                results = benchmark_variants(path_of(model), target, variants, timing=timing)
            except Exception as exc:  # noqa: BLE001 - one model's failure is a row, not an abort
                rows += [MemoryRow(model, target, s, None, None, problem_text(exc)) for s in SETTINGS]
                continue
            speed = results["speed"]
            for s in SETTINGS:
                ratio = paired_ratio(results[s].batch_us, speed.batch_us)
                rows.append(MemoryRow(model, target, s, results[s], speed, ratios=(ratio,)))
    return rows


def merged_memory_row(same: list[MemoryRow]) -> MemoryRow:
    """A model, target and setting over several runs (runs.merged_runs): µs the medians over the runs, the
    ratios each run's."""
    return merged_runs(
        same,
        lambda row: row.result is not None,
        results=("result", "speed"),
        per_run={"ratios": lambda row: row.ratios},
    )


HEADER = (
    "| model | target | memory | NNCG µs | x speed | ORT µs | arena B | arena cut | layer bound B | activations B "
    "| max abs err | max rel err | plan |"
)


def memory_table(rows: list[MemoryRow]) -> str:
    """The rows' table; with an x speed range column when they are medians of several runs."""
    ranges = runs_of(rows, "ratios") > 1
    header = HEADER.replace(" x speed |", " x speed | x speed range |") if ranges else HEADER
    separators = header.count(" | ")
    lines = [header, "|" + "---|" * separators + "---|"]
    for row in rows:
        head = f"| {row.model} | {row.target} | {row.setting} |"
        r = row.result
        if r is None:
            lines.append(f"{head} {markdown_text(row.problem, PLAN_LIMIT)} |" + " |" * (separators - 3))
            continue
        ratio = f"{row.ratio:.2f}x" + (f" | {ratio_range(row.ratios)}" if ranges else "")
        lines.append(
            f"{head} {r.nncg_us:.2f} | {ratio} | {r.ort_bound_us:.2f} | {r.arena_bytes:,} "
            f"| {row.arena_cut:.2f}x | {r.layer_bound_bytes:,} | {r.all_activation_bytes:,} | {r.max_abs_err:.1e} "
            f"| {r.max_rel_err:.1e} | {markdown_text(r.plan, PLAN_LIMIT)} |"
        )
    return "\n".join(lines) + "\n"


def target_lines(rows: list[MemoryRow]) -> list[str]:
    """Issue 18's targets against the measurements: balanced within 1.3x of speed with >= 2x less arena,
    and min's arena under the figure the issue names (a model without one: its arena only)."""
    lines = []
    for row in rows:
        if row.result is None or row.setting in ("speed", CONTROL):
            continue
        what = f"{row.model} / {row.target} / {row.setting}: {row.ratio:.2f}x speed's latency, "
        what += f"{row.arena_cut:.2f}x less arena"
        if row.setting == "balanced":
            met = row.ratio <= 1.3 and row.arena_cut >= 2
            lines.append(f"- {what} ({'meets' if met else 'misses'} <= 1.3x and >= 2x)")
        elif row.model in MIN_TARGETS:
            goal = MIN_TARGETS[row.model]
            met = row.result.arena_bytes <= goal
            lines.append(f"- {what}; arena {row.result.arena_bytes:,} B ({'meets' if met else 'misses'} <= {goal:,} B)")
        else:
            lines.append(f"- {what}; arena {row.result.arena_bytes:,} B")
    return lines


def section_markdown(
    rows: list[MemoryRow], peaks: dict, cpu: int | None, date: str, batches: int, command: str, note: str = ""
):
    lines = [
        "## Memory settings (issue 18)",
        "",
        f"- CPU: {cpu_model()} ({'pinned to core ' + str(cpu) if cpu is not None else 'not pinned'}); date: {date}",
        f"- Peak: {PEAK_NOTE}; medians: {peaks_text(peaks)}",
        f"- Command: `{command}`",
        *([f"- {note}"] if note else []),
        "- The settings and onnxruntime are timed in turn within each batch, so the ratios are steadier than",
        "  the absolute µs; the speed again rows show how much two builds of the same C differ.",
        "- NNCG untuned defaults (unroll auto) at `--memory speed|balanced|min`; NNCG µs: the median of",
        f"  {batches} batches of >= 20 ms each; x speed: the median of the per-batch ratios of this setting's time",
        "  to speed's, same run (a slow spell of the machine slows both and cancels); ORT µs: onnxruntime",
        "  (one thread, IOBinding), timed in the same run: one figure for all the settings.",
        *runs_lines(runs_of(rows, "ratios"), "x speed", "x speed range"),
        "- arena B: NAME_ARENA_BYTES; arena cut: speed's arena over this one; layer bound B: the most one layer",
        "  computed whole needs; activations B: every activation side by side, no reuse. Both leave scratch",
        "  buffers (Winograd's) out, which the arena holds: speed's arena can exceed them.",
        "- errors: against onnxruntime on the same fixed-seed inputs; plan: the layers run in bands of rows.",
        f"- {CONTROL}: speed built a second time and timed in the same run, the same C: its x speed is the noise",
        "  of the others' ratios (balanced and min print the same C as speed where their plan is speed's).",
        "",
        memory_table(rows),
        f"Against issue 18's targets ({over_runs(runs_of(rows, 'ratios'))}):",
        "",
        *target_lines(rows),
        "",
    ]
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--models", nargs="+", default=PAPER + MLPERF_TINY)
    parser.add_argument("--targets", nargs="+", default=["ssse3", "avx2"], help="x86 targets (default: ssse3 avx2)")
    parser.add_argument("--cpu", type=int, help="pin the measurements to this core")
    parser.add_argument(
        "--batches", type=positive_number, default=15, help="timed batches per model and target (median)"
    )
    parser.add_argument("--note", default="", help="a line for the section, e.g. the machine's load")
    parser.add_argument("--runs", type=positive_number, default=1, help=RUNS_HELP)
    parser.add_argument("--int8", action="store_true", help="each model quantised too (the int8 suite's QDQ model)")
    parser.add_argument("--out-dir", type=Path, default=ROOT / "benchmarks")
    args = parser.parse_args(argv)
    models = [*args.models, *(name + INT8 for name in args.models if args.int8)]
    rows = repeated(args.runs, lambda: run_memory_suite(models, args.targets, cpu=args.cpu, batches=args.batches),
                    merged_memory_row)  # fmt: skip
    peaks = sampled_peaks([result for row in rows for result in (row.result, row.speed)])
    command = shlex.join(["python3", "-m", "benchmarks.memory_suite", *argv])
    date = datetime.date.today().isoformat()
    section = section_markdown(rows, peaks, args.cpu, date, args.batches, command, args.note)
    write_section(args.out_dir, SECTION, section)
    print(section)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
