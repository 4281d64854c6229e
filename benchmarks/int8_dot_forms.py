"""Which dot product the int8 kernels take on ssse3 and avx2 (issue 16): per model and target, timed
interleaved on one input, NNCG's float C and the int8 C of
  pairs / quads:   the model nncg.quantize writes (full-range int8 weights), with pmaddwd on int16 pairs
                   only (Target.dot_uint8_int16 = 0) / as compiled (pmaddubsw quads in the layers whose
                   weights are proven not to saturate, pairs in the others);
  pairs7 / quads7: the same model quantised with onnxruntime's reduce_range (7-bit weights: every layer
                   proven).
Every variant is checked against onnxruntime on the timed input (0 steps expected) before it is timed.
µs: medians of the batches; float / X: the median of the per-batch ratios.

    python3 -m benchmarks.int8_dot_forms [--models resnet8 ...] [--targets ssse3 avx2] [--cpu 0] [--batches 11]
"""

from __future__ import annotations

import argparse
import contextlib
import statistics
import tempfile
from dataclasses import replace
from pathlib import Path

import nncg
from nncg.backends import BACKENDS
from nncg.bench.benchmark import interleaved_samples, paired_ratio, pinned
from nncg.bench.harness import CompiledHarness
from nncg.bench.onnxruntime_timer import OnnxruntimeTimer
from nncg.quant_steps import compare_steps
from nncg.verify import find_c_compiler, random_inputs

from .int8_suite import quantized_model
from .suite import MLPERF_TINY, model_path


@contextlib.contextmanager
def without_quads(target: str):
    """The target's int8 kernels on int16 pairs only, as before pmaddubsw quads."""
    backend = BACKENDS[target]
    saved = backend.target
    backend.target = replace(saved, dot_uint8_int16=0)
    try:
        yield
    finally:
        backend.target = saved


def variants(name: str, target: str) -> dict[str, tuple]:
    """label -> (compiled model, the QDQ model it matches or None for float)."""
    qdq, qdq7 = quantized_model(name), quantized_model(name, reduce_range=True)
    with without_quads(target):
        pairs, pairs7 = (nncg.compile(m, target=target) for m in (qdq, qdq7))
    return {
        "float": (nncg.compile(model_path(name), target=target), None),
        "pairs": (pairs, qdq),
        "quads": (nncg.compile(qdq, target=target), qdq),
        "pairs7": (pairs7, qdq7),
        "quads7": (nncg.compile(qdq7, target=target), qdq7),
    }


def measure(name: str, target: str, cpu, batches: int) -> dict[str, list[float]]:
    """Each variant's µs per inference in each batch (the batches pair up across variants)."""
    cc = find_c_compiler(None)
    compiled = variants(name, target)
    inputs = random_inputs(compiled["float"][0].inputs, seed=0)
    with pinned(cpu), tempfile.TemporaryDirectory(prefix="nncg-dot-forms-") as tmp:
        harnesses = {label: CompiledHarness(c, Path(tmp, label), cc, inputs) for label, (c, _) in compiled.items()}
        try:
            for label, (c, qdq) in compiled.items():
                if qdq is not None:
                    ort = OnnxruntimeTimer(qdq, [p.name for p in c.inputs], inputs)
                    steps = compare_steps(qdq, [(harnesses[label].outputs(), ort.outputs())])
                    assert steps.max_steps == 0, (name, target, label, steps)
            samples = interleaved_samples({k: h.run for k, h in harnesses.items()}, batches, 0.02)
        finally:
            for harness in harnesses.values():
                harness.close()
    return {label: [s * 1e6 for s in seconds] for label, seconds in samples.items()}


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--models", nargs="+", default=list(MLPERF_TINY))
    parser.add_argument("--targets", nargs="+", default=["ssse3", "avx2"])
    parser.add_argument("--cpu", type=int, default=None)
    parser.add_argument("--batches", type=int, default=11)
    args = parser.parse_args(argv)
    labels = ("pairs", "quads", "pairs7", "quads7")
    columns = ("model", "target", "float µs", *(f"{k} µs" for k in labels), *(f"float / {k}" for k in labels))
    print(f"| {' | '.join(columns)} |")
    print("|---|---|---|" + "---|" * 2 * len(labels))
    for name in args.models:
        for target in args.targets:
            us = measure(name, target, args.cpu, args.batches)
            times = " | ".join(f"{statistics.median(us[k]):.1f}" for k in labels)
            ratios = " | ".join(f"{paired_ratio(us['float'], us[k]):.2f}x" for k in labels)
            print(f"| {name} | {target} | {statistics.median(us['float']):.1f} | {times} | {ratios} |", flush=True)


if __name__ == "__main__":
    main()
