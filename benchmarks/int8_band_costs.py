"""What an int8 Conv costs in bands against run whole, per x86 target: the figure BandCosts.integer_banded
(nncg/lowering/band_costs.py) prices. Instruction counts (callgrind Ir, so a loaded machine does not
matter), of the same two int8 3x3 Convs (Conv -> QLinearConv of `kind`: dense, strided or depthwise) at
--memory speed and in one band group of `rows`, the group's line buffers and per-band loops included.

    python3 -m benchmarks.int8_band_costs [--targets ssse3 avx2] [--rows 1 4]

With --quantize, what the model input's QuantizeLinear costs in bands (BandCosts has no price of its own for it:
it costs what it costs whole): mobilenet_v1_025 int8 at --memory speed, at balanced's plan, and at that plan with
the QuantizeLinear run whole (the first group starting after it). --cc picks the C compiler (valgrind 3.19 cannot
decode an AVX2 move GCC emits in mobilenet's avx2 build: clang there).
"""

from __future__ import annotations

import argparse
import re
import subprocess
import sys
import tempfile
from dataclasses import replace
from pathlib import Path

import numpy as np
from onnx import helper
from onnxruntime.quantization import CalibrationDataReader, QuantFormat, QuantType, quantize_static

import nncg
from nncg import lowering
from nncg.lowering.band_plan import BandPlan, plan_layers
from nncg.lowering.bands import BandGroup
from nncg.verify import build_model

from .int8_suite import quantized_model

# kind: (channels in, channels out, group, stride, image side)
SHAPES = {"dense": (16, 16, 1, 1, 32), "strided": (16, 32, 1, 2, 32), "depthwise": (16, 16, 16, 1, 32)}


class _Feeds(CalibrationDataReader):
    def __init__(self, shape: list[int]):
        rng = np.random.default_rng(0)
        self.feeds = iter([{"x": rng.standard_normal(shape).astype(np.float32)} for _ in range(4)])

    def get_next(self):
        return next(self.feeds, None)


def conv_pair(kind: str, workdir: Path):
    """The int8 QDQ model of Conv 3x3 (3 -> C) then the Conv of `kind`."""
    cin, cout, group, stride, side = SHAPES[kind]
    rng = np.random.default_rng(1)
    weights = {
        "w1": rng.standard_normal((cin, 3, 3, 3)).astype(np.float32) * 0.3,
        "w2": rng.standard_normal((cout, cin // group, 3, 3)).astype(np.float32) * 0.3,
    }
    nodes = [
        helper.make_node("Conv", ["x", "w1"], ["a"], pads=[1, 1, 1, 1]),
        helper.make_node("Conv", ["a", "w2"], ["y"], pads=[1, 1, 1, 1], group=group, strides=[stride, stride]),
    ]
    graph = helper.make_graph(
        nodes,
        "pair",
        [helper.make_tensor_value_info("x", 1, [1, 3, side, side])],
        [helper.make_tensor_value_info("y", 1, None)],
        [helper.make_tensor(n, 1, a.shape, a.flatten()) for n, a in weights.items()],
    )
    src, dst = workdir / f"{kind}.onnx", workdir / f"{kind}_int8.onnx"
    import onnx

    onnx.save(helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)]), src)
    quantize_static(
        str(src), str(dst), _Feeds([1, 3, side, side]), quant_format=QuantFormat.QDQ,
        activation_type=QuantType.QUInt8, weight_type=QuantType.QInt8, per_channel=True,
    )  # fmt: skip
    return onnx.load(dst)


def instructions(model, target: str, rows: int | None, workdir: Path) -> int:
    """Callgrind's Ir of one run of the model compiled for `target`, whole (rows None) or in one group."""
    if rows is None:
        return planned_instructions(model, target, None, workdir)
    return planned_instructions(
        model, target, lambda graph, *_: BandPlan((BandGroup(tuple(n.name for n in graph.nodes[:-1]), rows),)), workdir
    )


def planned_instructions(model, target: str, planner, workdir: Path, cc: str | None = None) -> int:
    """Callgrind's Ir of one run of the model compiled for `target` under `planner` (a stand-in for
    lowering.plan_layers; None: --memory speed), on a seeded standard-normal input."""
    original = lowering.plan_layers
    if planner is not None:
        lowering.plan_layers = planner
    try:
        compiled = nncg.compile(model, target=target, memory="min" if planner else "speed")
    finally:
        lowering.plan_layers = original
    built = build_model(compiled, workdir, cc=cc)
    out = workdir / "callgrind.out"
    shape = compiled.inputs[0].shape
    np.random.default_rng(0).standard_normal(shape).astype(np.float32).tofile(workdir / "input0.bin")
    command = ["valgrind", "--tool=callgrind", f"--callgrind-out-file={out}", str(built.program), "input0.bin"]
    subprocess.run([*command, "output0.bin"], cwd=workdir, check=True, capture_output=True)
    summary = re.search(r"^summary: (\d+)", out.read_text(), re.M)
    return int(summary.group(1))


def quantize_in_bands(targets: list[str], workdir: Path, cc: str | None) -> None:
    """mobilenet_v1_025 int8's Ir at speed, at balanced's plan and at that plan with its QuantizeLinear whole."""
    model = quantized_model("mobilenet_v1_025")
    print("| target | speed Ir | balanced Ir (x speed) | balanced, QuantizeLinear whole: Ir (x speed) |")
    print("|---|---:|---:|---:|")
    for target in targets:
        speed = planned_instructions(model, target, None, workdir, cc)
        cells = " | ".join(f"{ir} ({ir / speed:.3f})" for ir in _balanced_instructions(model, target, workdir, cc))
        print(f"| {target} | {speed} | {cells} |", flush=True)


def _balanced_instructions(model, target: str, workdir: Path, cc: str | None) -> tuple[int, int]:
    """Ir at balanced's plan, and at that plan with its first group starting after the QuantizeLinear."""
    plans = []

    def balanced(graph, _memory, *rest):  # lowering's planner at balanced, its plan kept
        plans.append((graph, plan_layers(graph, "balanced", *rest)))
        return plans[-1][1]

    banded = planned_instructions(model, target, balanced, workdir, cc)
    graph, plan = plans[0]
    first, *others = plan.groups
    if len(first.nodes) < 2 or graph.nodes[0].name != first.nodes[0] or graph.nodes[0].op != "QuantizeLinear":
        raise SystemExit(f"{target}: balanced's first group {first} does not start at the input's QuantizeLinear")
    whole = BandPlan((replace(first, nodes=first.nodes[1:]), *others))
    return banded, planned_instructions(model, target, lambda *_: whole, workdir, cc)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--targets", nargs="+", default=["ssse3", "avx2"])
    parser.add_argument("--rows", nargs="+", type=int, default=[1, 4])
    parser.add_argument("--quantize", action="store_true", help="the input QuantizeLinear in bands (mobilenet)")
    parser.add_argument("--cc", help="the C compiler (default: the tests')")
    args = parser.parse_args(argv)
    with tempfile.TemporaryDirectory(prefix="nncg-band-costs-") as tmp:
        workdir = Path(tmp)
        if args.quantize:
            quantize_in_bands(args.targets, workdir, args.cc)
            return 0
        print("| target | conv | whole Ir | " + " | ".join(f"bands of {r}: Ir (x whole)" for r in args.rows) + " |")
        print("|---|---|---:|" + "---:|" * len(args.rows))
        for target in args.targets:
            for kind in SHAPES:
                model = conv_pair(kind, workdir)
                whole = instructions(model, target, None, workdir)
                cells = []
                for rows in args.rows:
                    banded = instructions(model, target, rows, workdir)
                    cells.append(f"{banded} ({banded / whole:.2f})")
                print(f"| {target} | {kind} | {whole} | " + " | ".join(cells) + " |", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
