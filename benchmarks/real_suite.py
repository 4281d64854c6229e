"""The real-size benchmark suite: torchvision, Keras NHWC and MLPerf Tiny (tf2onnx) models, NNCG vs onnxruntime.

    python3 -m benchmarks.real_suite [--models resnet18 ...] [--targets avx512] [--cpu 0] [--batches 15]
                                     [--size 96] [--runs 3] [--profile [--cpu-time]]

Models (benchmarks/real_models.py) are exported when missing (needs torch: pip install -e .[bench]; the MLPerf
Tiny ones, benchmarks/mlperf_tiny.py, TensorFlow and tf2onnx: the keras extra), compiled
with NNCG's untuned defaults (unroll auto; weights in NAME.weights above 4 MiB) and timed as benchmarks/suite.py
times its models: one onnxruntime thread, interleaved, medians, % of the measured peak. The table replaces the
"real-models" section of benchmarks/RESULTS.md (the small-model table stays) and the chart is redrawn from all
tables. Models NNCG cannot compile are listed with the reason. --runs N measures every model and target N
times (all of them once, then again) and reports the medians and the speed-up's range over the runs.
The MLPerf Tiny models (mlperf_*) have a fixed input size: they run after the others by default, --models
selects them like any model, and --size resizes only the others (the MLPerf ones keep their own input).
--profile prints each model's per-layer times
(with --cpu-time in the thread's CPU time, which leaves out the time other processes hold the core).
"""

from __future__ import annotations

import argparse
import datetime
from pathlib import Path

from nncg.backends import BACKENDS
from nncg.bench.benchmark import format_profile, profile
from nncg.bench.peak import TARGET_ISA
from nncg.cli import positive_number

from .real_models import DEFAULT_CASES, MODELS, case_name, cases_at, ensure
from .runs import runs_of
from .suite import (
    PEAK_NOTE,
    ROOT,
    RUNS_HELP,
    SPEEDUP_COLUMN,
    Row,
    cpu_model,
    first_line,
    merged_row,
    peaks_text,
    repeated,
    results_table,
    run_suite,
    runs_lines,
    sampled_peaks,
    write_section,
)

SECTION = "real-models"


def select_cases(models: list[str] | None, size: int | None) -> dict[str, tuple[str, int | None]]:
    """{case name: (model, size)}: the default cases, those of `models`, or `models` at `size`; the
    fixed-size models (MLPerf Tiny) always at their own input size (size None, case name = model name)."""
    if size:
        cases = cases_at(models or MODELS, size)
    else:
        cases = [(m, s) for m, s in DEFAULT_CASES if not models or m in models]
    return {case_name(m, s): (m, s) for m, s in cases}


def section_markdown(rows: list[Row], peaks: dict, cpu: int | None, date: str, batches: int) -> str:
    lines = [
        "## Real-size models",
        "",
        f"- CPU: {cpu_model()} ({'pinned to core ' + str(cpu) if cpu is not None else 'not pinned'}); date: {date}",
        f"- Peak: {PEAK_NOTE}; medians: {peaks_text(peaks)}",
        "- torchvision's mobilenet_v2, mobilenet_v3_small, resnet18, efficientnet_b0, squeezenet1_1,",
        "  shufflenet_v2_x0_5, mnasnet0_5 and regnet_x_400mf rebuilt in torch.nn (benchmarks/torch_models.py; same",
        "  layers and parameter counts), random weights (seed 0), exported by torch.onnx's TorchScript exporter",
        "  (opset 17, batch 1, NAME_SIZE = input SIZExSIZE); keras_mobilenet_nhwc: Keras' MobileNetV2 (alpha 0.35,",
        "  10 classes) in NHWC with tf2onnx's Transposes around every conv (benchmarks/nhwc_model.py).",
        "- mlperf_*: the MLPerf Tiny reference models (IC ResNet-8 32x32, KWS DS-CNN 49x10, VWW MobileNetV1 0.25",
        "  96x96, AD autoencoder 640) written in Keras as mlcommons/tiny defines them, random weights (seed 0),",
        "  Keras -> TFLite float -> tf2onnx from_tflite (opset 17), as the reference .tflite files are converted",
        "  (benchmarks/mlperf_tiny.py); each at its own input size.",
        "- NNCG untuned defaults (unroll auto; weights auto: NAME.weights above 4 MiB). Columns as in the table",
        f"  above; medians of {batches} batches of >= 20 ms each, NNCG and onnxruntime (one thread) interleaved.",
        f"- {SPEEDUP_COLUMN}.",
        *runs_lines(runs_of(rows, "speedups")),
        "",
    ]
    return "\n".join(lines) + "\n" + results_table(rows)


def print_profiles(cases: dict, targets: list[str], cpu: int | None, cpu_time: bool = False) -> None:
    """The per-layer profile of each case and target (nncg-onnx --profile), or why there is none;
    `cpu_time`: timed in the thread's CPU time."""
    for name, (model, size) in cases.items():
        for target in targets:
            print(f"\n## profile: {name} / {target}")
            try:
                print(format_profile(profile(ensure(model, size), target, cpu=cpu, cpu_time=cpu_time)))
            except Exception as exc:  # noqa: BLE001 - report it and go on with the next model
                print(f"failed: {type(exc).__name__}: {first_line(exc)}")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--models",
        nargs="+",
        choices=MODELS,
        help="default: every model (at 96, two at 224 too; mlperf_* at their own size)",
    )
    parser.add_argument("--targets", nargs="+", default=sorted(t for t in BACKENDS if t in TARGET_ISA))
    parser.add_argument("--cpu", type=int, help="pin the measurements to this core")
    parser.add_argument(
        "--batches", type=positive_number, default=15, help="timed batches per model and target (median)"
    )
    parser.add_argument(
        "--size",
        type=int,
        help="input height and width of every model but the fixed-size mlperf_* ones (default: 96 and 224)",
    )
    parser.add_argument("--runs", type=positive_number, default=1, help=RUNS_HELP)
    parser.add_argument("--profile", action="store_true", help="also print each model's per-layer profile")
    parser.add_argument(
        "--cpu-time", action="store_true",
        help="time the profile in the thread's CPU time, not the wall clock (steadier on a shared core)",
    )  # fmt: skip
    parser.add_argument("--out-dir", type=Path, default=ROOT / "benchmarks")
    args = parser.parse_args(argv)
    cases = select_cases(args.models, args.size)

    def measure() -> list[Row]:
        return run_suite(list(cases), args.targets, cpu=args.cpu, batches=args.batches,
                         path_of=lambda name: ensure(*cases[name]))  # fmt: skip

    rows = repeated(args.runs, measure, merged_row)
    peaks = sampled_peaks([row.result for row in rows])
    section = section_markdown(rows, peaks, args.cpu, datetime.date.today().isoformat(), args.batches)
    write_section(args.out_dir, SECTION, section)
    print(section)
    if args.profile:
        print_profiles(cases, args.targets, args.cpu, args.cpu_time)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
