"""The int8 benchmark: MLPerf Tiny models in int8, NNCG's int8 C against onnxruntime and NNCG's float C.

The MLPerf-Tiny-shaped models quantised by nncg.quantize, and the MLPerf Tiny reference models (mlperf_*,
benchmarks/mlperf_tiny.py) as TFLite's full-integer converter quantises them and tf2onnx converts that, NNCG's
int8 C against onnxruntime running the same QDQ model and against NNCG's own float C, per x86 target; and the
models' Cortex-M4 builds, int8 next to float.

    python3 -m benchmarks.int8_suite [--models dscnn ...] [--targets ansi-c ssse3 avx2 avx512 avx512vnni] [--cpu 0]
                                     [--batches 15] [--runs 3] [--no-cortex-m4] [--reduce-range]

Each model is quantised with nncg.quantize's defaults (uint8 activations, per-channel int8 weights; 7-bit
weights with --reduce-range) on seeded standard-normal calibration inputs; the mlperf_* ones by TFLite (int8
activations and per-channel weights, the same number of seeded standard-normal inputs as representative
dataset, float input and output; --reduce-range does not apply to them; needs TensorFlow and tf2onnx).
Per target, the int8 C, the float C and onnxruntime on the QDQ model (batch 1, one thread, all graph
optimisations) are timed interleaved, medians as benchmarks/suite.py times (nncg.bench), ratios the medians
of the per-batch ratios; --runs N measures all of it N times and reports the medians over the runs and the
ratios' ranges. Errors are in quantisation steps of each output against that onnxruntime session, on seeded
inputs. The Cortex-M4 builds (tests/cross_helpers.py: arm-none-eabi-gcc -Os, run in qemu-system-arm) give
flash and RAM from arm-none-eabi-size and the stack's deepest use. Writes the "int8" section of benchmarks/RESULTS.md.
"""

from __future__ import annotations

import argparse
import datetime
import shlex
import shutil
import statistics
import sys
import tempfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import onnx

import nncg
from nncg.bench.benchmark import interleaved_samples, paired_ratio, pinned
from nncg.bench.harness import CompiledHarness
from nncg.bench.onnxruntime_timer import OnnxruntimeTimer
from nncg.bench.peak import TARGET_ISA
from nncg.cli import positive_number
from nncg.compiler import CompiledModel
from nncg.host_cpu import host_targets
from nncg.ir.kinds import BufferRole
from nncg.quant_steps import Comparison, compare_steps
from nncg.verify import build_model, find_c_compiler, random_inputs, reference_session

from . import mlperf_tiny
from .real_models import ensure, ensure_int8
from .runs import merged_runs, runs_of
from .suite import (
    MLPERF_TINY,
    ROOT,
    RUNS_HELP,
    cpu_model,
    first_line,
    markdown_table,
    model_path,
    over_runs,
    ratio_range,
    repeated,
    runs_lines,
    write_section,
)

SECTION = "int8"
CALIBRATION_SAMPLES = 16
CALIBRATION_SEED = 1234  # not the timed input's seed (0): the error inputs are not the calibration's
ERROR_INPUTS = 8  # seeded inputs 1..8 for the error figures


MODELS = [*MLPERF_TINY, *mlperf_tiny.MODELS]


def float_path(name: str) -> Path:
    """The float model: an MLPerf-Tiny-shaped one, or an MLPerf Tiny reference model's tf2onnx conversion."""
    return ensure(name, None) if name in mlperf_tiny.MODELS else model_path(name)


def quantized_model(name: str, reduce_range: bool = False) -> onnx.ModelProto:
    """The QDQ model nncg.quantize writes from the float model and seeded standard-normal calibration inputs;
    for an MLPerf Tiny reference model, tf2onnx's conversion of TFLite's full-integer model."""
    if name in mlperf_tiny.MODELS:
        return onnx.load(ensure_int8(name))
    model = onnx.load(model_path(name))
    shape = [d.dim_value for d in model.graph.input[0].type.tensor_type.shape.dim]
    samples = np.random.default_rng(CALIBRATION_SEED).standard_normal((CALIBRATION_SAMPLES, *shape), np.float32)
    return nncg.quantize(model, samples, reduce_range=reduce_range)


@dataclass(frozen=True)
class Build:
    """What one compiled model costs: section sizes of its object (host or Cortex-M4), arena and weights."""

    text: int
    rodata: int
    bss: int
    arena: int
    weights: int


@dataclass(frozen=True)
class Int8Row:
    model: str
    target: str
    int8_us: float = 0.0
    float_us: float = 0.0
    ort_us: float = 0.0  # onnxruntime on the QDQ model, IOBinding
    vs_ort: tuple[float, ...] = ()  # each run's ORT int8 over int8: the median of the per-batch ratios
    vs_float: tuple[float, ...] = ()  # each run's float over int8, the same way
    errors: Comparison | None = None
    int8: Build | None = None
    float: Build | None = None
    problem: str = ""  # why there is no measurement


def weight_bytes(compiled: CompiledModel) -> int:
    """The constant buffers' bytes at their element type (int8 weights, int32 biases, float constants)."""
    return sum(b.size * b.dtype.bytes for b in compiled.record.program.role(BufferRole.CONSTANT))


def build_of(compiled: CompiledModel, harness: CompiledHarness) -> Build:
    s = harness.sizes
    return Build(s.text, s.rodata, s.bss, compiled.arena_bytes, weight_bytes(compiled))


def error_steps(qdq: onnx.ModelProto, int8: CompiledModel, cc: str, workdir: Path) -> Comparison:
    """NNCG's int8 C against onnxruntime's reference session on ERROR_INPUTS seeded inputs."""
    program = build_model(int8, workdir, cc=cc)
    names = [spec.name for spec in int8.inputs]
    feeds = [random_inputs(int8.inputs, seed) for seed in range(1, ERROR_INPUTS + 1)]
    reference = reference_session(qdq)
    runs = ((program.run(inputs), reference.run(None, dict(zip(names, inputs)))) for inputs in feeds)
    return compare_steps(qdq, runs)


def measure(name: str, qdq: onnx.ModelProto, target: str, *, cpu, batches: int, min_batch_seconds: float) -> Int8Row:
    """The int8 C, the float C and onnxruntime on the QDQ model, timed in turn on the same input."""
    cc = find_c_compiler(None)
    int8 = nncg.compile(qdq, target=target)
    floats = nncg.compile(float_path(name), target=target)
    inputs = random_inputs(int8.inputs, seed=0)
    with pinned(cpu), tempfile.TemporaryDirectory(prefix="nncg-int8-bench-") as tmp:
        harnesses = [CompiledHarness(c, Path(tmp, kind), cc, inputs) for c, kind in ((int8, "int8"), (floats, "float"))]
        try:
            ort = OnnxruntimeTimer(qdq, [p.name for p in int8.inputs], inputs)
            timers = {"int8": harnesses[0].run, "float": harnesses[1].run, "ort": ort.run_bound}
            samples = interleaved_samples(timers, batches, min_batch_seconds)
        finally:
            for harness in harnesses:
                harness.close()
        errors = error_steps(qdq, int8, cc, Path(tmp, "errors"))
    us = {key: statistics.median(seconds) * 1e6 for key, seconds in samples.items()}
    return Int8Row(
        name, target, us["int8"], us["float"], us["ort"], (paired_ratio(samples["ort"], samples["int8"]),),
        (paired_ratio(samples["float"], samples["int8"]),), errors, build_of(int8, harnesses[0]),
        build_of(floats, harnesses[1]),
    )  # fmt: skip


def run_int8_suite(
    models: dict[str, onnx.ModelProto], targets, *, cpu=None, batches=15, min_batch_seconds=0.02, progress=print
) -> list[Int8Row]:
    """One row per model (name: QDQ model) and target; a model that fails is a row with the reason."""
    rows = []
    for name, qdq in models.items():
        for target in targets:
            progress(f"{name} / {target} ...")
            try:
                rows.append(measure(name, qdq, target, cpu=cpu, batches=batches, min_batch_seconds=min_batch_seconds))
            except Exception as exc:  # noqa: BLE001 - a compile or C compiler failure on one model: report, go on
                rows.append(Int8Row(name, target, problem=f"failed: {type(exc).__name__}: {first_line(exc)}"))
    return rows


def merged_int8_row(same: list[Int8Row]) -> Int8Row:
    """A model and target over several runs (runs.merged_runs): µs the medians over the runs, the ratios each
    run's. Errors and sizes are the first run's (the same C on the same inputs)."""
    return merged_runs(
        same, lambda row: row.errors is not None, medians=("int8_us", "float_us", "ort_us"),
        per_run={"vs_ort": lambda row: row.vs_ort, "vs_float": lambda row: row.vs_float},
    )  # fmt: skip


def ratio_cell(ratios: tuple[float, ...]) -> str:
    """The median over the runs of a paired ratio."""
    return f"{statistics.median(ratios):.2f}x"


INT8_COLUMNS = (
    "model", "target", "int8 µs", "ORT int8 µs", "vs ORT int8", "float µs", "int8 vs float", "max steps", "identical",
    "arena B int8 / float", "weights B int8 / float", "text B", "rodata B",
)  # fmt: skip
RANGE_COLUMNS = {"vs ORT int8": "vs ORT range", "int8 vs float": "vs float range"}  # after the ratio, several runs


def int8_table(rows: list[Int8Row]) -> str:
    ranges = runs_of(rows, "vs_ort") > 1
    columns = [name for c in INT8_COLUMNS for name in (c, RANGE_COLUMNS.get(c) if ranges else None) if name]
    return markdown_table(columns, [int8_cells(row, ranges) for row in rows])


def int8_cells(row: Int8Row, ranges: bool = False) -> list[str]:
    """The row's cells; `ranges`: each ratio followed by its range over the runs."""
    if row.errors is None:
        return [row.model, row.target, row.problem]
    i, f = row.int8, row.float
    vs_ort = [ratio_cell(row.vs_ort), *([ratio_range(row.vs_ort)] if ranges else [])]
    vs_float = [ratio_cell(row.vs_float), *([ratio_range(row.vs_float)] if ranges else [])]
    return [
        row.model, row.target, f"{row.int8_us:.2f}", f"{row.ort_us:.2f}", *vs_ort, f"{row.float_us:.2f}", *vs_float,
        f"{row.errors.max_steps:g}", f"{100 * row.errors.identical:.1f} % of {row.errors.elements}",
        f"{i.arena:,} / {f.arena:,}", f"{i.weights:,} / {f.weights:,}", f"{i.text:,}", f"{i.rodata:,}",
    ]  # fmt: skip


def cross_helpers():
    """tests/cross_helpers.py: the bare-metal Cortex-M4 build and QEMU run the cross tests use (as
    scripts/cross_matrix.py does), or None when its toolchain is not installed."""
    if str(ROOT / "tests") not in sys.path:
        sys.path.append(str(ROOT / "tests"))
    import cross_helpers as helpers

    return None if any(shutil.which(tool) is None for tool in helpers.CORTEX_M4_TOOLS) else helpers


def cortex_m4_row(helpers, float_model: Path, qdq: onnx.ModelProto) -> dict[str, object]:
    """Flash and RAM of the float and the int8 build (ansi-c) run on the emulated Cortex-M4, and the int8
    run's outputs against onnxruntime on the QDQ model."""
    sizes, errors = {}, None
    for kind, model in (("float", float_model), ("int8", qdq)):
        compiled = nncg.compile(model)
        inputs = random_inputs(compiled.inputs, seed=0)
        with tempfile.TemporaryDirectory(prefix="nncg-cortex-m4-") as tmp:
            result = helpers.run_cortex_m4(compiled, inputs, Path(tmp))
        sizes[kind] = helpers.size_row(result, compiled.arena_bytes)
        if kind == "int8":
            reference = OnnxruntimeTimer(qdq, [p.name for p in compiled.inputs], inputs).outputs()
            errors = compare_steps(qdq, [(result.outputs, reference)])
    f, i = sizes["float"], sizes["int8"]
    return {
        "flash B float / int8": f"{f['flash']:,} / {i['flash']:,}",
        "int8 / float flash": f"{i['flash'] / f['flash']:.2f}",
        "RAM B float / int8": f"{f['RAM']:,} / {i['RAM']:,}",
        "int8 / float RAM": f"{i['RAM'] / f['RAM']:.2f}",
        "arena B float / int8": f"{f['arena']:,} / {i['arena']:,}",
        "stack B float / int8": f"{f['stack']:,} / {i['stack']:,}",
        "int8 vs ORT": str(errors),
    }


def cortex_m4_rows(helpers, models: dict[str, onnx.ModelProto]) -> dict[str, dict[str, object]]:
    rows = {}
    for name, qdq in models.items():
        try:
            rows[name] = cortex_m4_row(helpers, float_path(name), qdq)
        except Exception as exc:  # noqa: BLE001 - a build or QEMU failure on one model: report, go on
            rows[name] = {"problem": f"failed: {type(exc).__name__}: {first_line(exc)}"}
    return rows


def cortex_m4_table(rows: dict[str, dict[str, object]]) -> str:
    columns = list(max(rows.values(), key=len))  # a failed model's row has only its problem
    cells = [[name, *(str(row.get(c, "")) for c in columns)] if "problem" not in row else [name, row["problem"]]
             for name, row in rows.items()]  # fmt: skip
    return markdown_table(["model", *columns], cells)


SSSE3_VS_FLOAT = 1.8  # issue 16's speed targets, one core, batch 1
BEST_VS_ORT = 1.5


def speed_targets(rows: list[Int8Row]) -> str:
    """Issue 16's speed targets against the measured ratios (over several runs their medians), per model
    (reported, never asserted)."""
    measured = [r for r in rows if r.errors is not None]
    ssse3 = {r.model: statistics.median(r.vs_float) for r in measured if r.target == "ssse3"}
    best: dict[str, float] = {}
    for r in measured:
        best[r.model] = max(best.get(r.model, 0.0), statistics.median(r.vs_ort))
    runs = over_runs(runs_of(measured, "vs_ort"))
    return (
        f"- Issue 16's targets ({runs}): ssse3 int8 >= {SSSE3_VS_FLOAT}x NNCG's ssse3 float: "
        f"{_met(ssse3, SSSE3_VS_FLOAT)}; "
        f"best x86 target >= {BEST_VS_ORT}x onnxruntime int8: {_met(best, BEST_VS_ORT)}."
    )


def _met(ratios: dict[str, float], target: float) -> str:
    if not ratios:
        return "not measured"
    shown = ", ".join(f"{model} {value:.2f}x" for model, value in ratios.items())
    return f"{shown} (met on {sum(v >= target for v in ratios.values())} of {len(ratios)})"


def section_markdown(
    rows: list[Int8Row],
    m4_rows: dict,
    cpu: int | None,
    date: str,
    command: str,
    note: str = "",
    reduce_range: bool = False,
) -> str:
    lines = [
        "## int8: MLPerf-Tiny-shaped models quantised by nncg.quantize"
        + (" with reduce_range (7-bit weights)" if reduce_range else "")
        + ", and the MLPerf Tiny reference models (TFLite full-integer)",
        "",
        f"- CPU: {cpu_model()} ({'pinned to core ' + str(cpu) if cpu is not None else 'not pinned'}); date: {date}",
        f"- Command: `{command}`",
        *([f"- {note}"] if note else []),
        "- Models: nncg.quantize's defaults (uint8 activations, per-channel int8 weights"
        + (", here 7-bit: reduce_range=True)" if reduce_range else ")")
        + f" on {CALIBRATION_SAMPLES}",
        f"  standard-normal calibration inputs (seed {CALIBRATION_SEED}); mlperf_*: the MLPerf Tiny reference",
        "  models (benchmarks/mlperf_tiny.py) quantised by TFLite's full-integer converter on as many seeded",
        "  inputs, converted by tf2onnx from_tflite. int8 µs: NNCG's int8 C; ORT int8 µs:",
        "  onnxruntime on the same QDQ model (batch 1, one thread, all graph optimisations, IOBinding); float µs:",
        "  NNCG's C of the float model on the same target. The three are timed interleaved, µs medians of the",
        "  batches; vs ORT int8 and int8 vs float: the medians of the per-batch ratios ORT int8 time / int8 time and",
        "  float time / int8 time (a batch times the three within seconds, so a slow spell of the machine cancels).",
        *runs_lines(runs_of(rows, "vs_ort"), "ratios", "vs ORT range and vs float range"),
        f"- max steps / identical: NNCG's int8 outputs against onnxruntime on {ERROR_INPUTS} seeded inputs (its",
        "  exact integer products: session.x64quantprecision, where its uint8 x int8 kernels saturate without VNNI),",
        "  in quantisation steps of each output (its DequantizeLinear's scale). The final Softmax is",
        "  onnxruntime's QLinearSoftmax arithmetic in NNCG too (tests/test_int8_softmax.py).",
        "- arena B: NAME_ARENA_BYTES; weights B: the constants at their type; text and rodata of the int8 object.",
        speed_targets(rows),
        "",
        int8_table(rows),
    ]
    if m4_rows:
        lines += [
            "Cortex-M4 (ansi-c, arm-none-eabi-gcc -Os, run on QEMU's MPS2 AN386; tests/cross_helpers.py): flash =",
            "text + rodata + data, RAM = data + bss (the arena) + the stack's deepest use, of the model's object;",
            "int8 vs ORT: the int8 run's outputs against onnxruntime on the QDQ model (seed 0 input).",
            "",
            cortex_m4_table(m4_rows),
        ]
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--models", nargs="+", default=MODELS, choices=MODELS)
    parser.add_argument("--targets", nargs="+", default=host_targets(), choices=list(TARGET_ISA))
    parser.add_argument("--cpu", type=int, help="pin the measurements to this core")
    parser.add_argument(
        "--batches", type=positive_number, default=15, help="timed batches per model and target (median)"
    )
    parser.add_argument("--runs", type=positive_number, default=1, help=RUNS_HELP)
    parser.add_argument("--no-cortex-m4", action="store_true", help="skip the Cortex-M4 builds and runs")
    parser.add_argument("--note", default="", help="a line for the section, e.g. the machine's load")
    parser.add_argument(
        "--reduce-range", action="store_true", help="quantise with 7-bit weights (nncg.quantize reduce_range=True)"
    )
    parser.add_argument("--out-dir", type=Path, default=ROOT / "benchmarks")
    args = parser.parse_args(argv)
    models = {name: quantized_model(name, args.reduce_range) for name in args.models}
    rows = repeated(args.runs, lambda: run_int8_suite(models, args.targets, cpu=args.cpu, batches=args.batches),
                    merged_int8_row)  # fmt: skip
    helpers = None if args.no_cortex_m4 else cross_helpers()
    m4_rows = cortex_m4_rows(helpers, models) if helpers else {}
    command = shlex.join(["python3", "-m", "benchmarks.int8_suite", *(argv if argv is not None else sys.argv[1:])])
    today = datetime.date.today().isoformat()
    section = section_markdown(rows, m4_rows, args.cpu, today, command, args.note, args.reduce_range)
    write_section(args.out_dir, SECTION, section)
    print(section)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
