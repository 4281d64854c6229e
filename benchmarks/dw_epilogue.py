"""What a depthwise convolution's activation costs (issue 15): the real models' depthwise shapes, each
alone between two 1x1 convolutions, with no activation and with the activation its model puts behind
it (ReLU6 = Clip, HardSwish, SiLU = x * Sigmoid(x)), profiled round-robin in one process, the dw
layer's time per variant (median of the rounds, thread CPU time) and its share of the peak.
A depthwise conv has only 9 or 25 MACs per output, so a per-output epilogue weighs as much as the conv.
Every variant is first checked against onnxruntime.

    python3 -m benchmarks.dw_epilogue [--target avx512] [--cpu 0] [--rounds 3] [--peak GFLOPS] [--shapes eff_3 ...]

--peak: the target's peak in GFLOP/s (default: measured now, which a loaded machine underestimates).
"""

from __future__ import annotations

import argparse
import statistics
import tempfile
from pathlib import Path

import numpy as np
import onnx
from onnx import TensorProto, helper, numpy_helper

import nncg
from nncg.bench.benchmark import profile
from nncg.bench.peak import TARGET_ISA, measure_peak
from nncg.cli import positive_number
from nncg.verify import verify

# name: (channels, height = width, kernel, stride, activations), the depthwise layers of the real-size
# suite that the per-layer profile showed below 40 % of the avx512 peak
SHAPES = {
    "eff_1": (32, 48, 3, 1, ("none", "silu")),  # efficientnet_b0_96 features_1
    "eff_2": (96, 48, 3, 2, ("none", "silu")),  # efficientnet_b0_96 features_2
    "eff_3": (144, 24, 3, 1, ("none", "silu")),  # efficientnet_b0_96 features_3
    "eff_5": (240, 12, 5, 1, ("none", "silu")),  # efficientnet_b0_96 features_5
    "mv3_5": (240, 6, 5, 1, ("none", "hswish")),  # mobilenet_v3_small_96 features_5
    "mv3_10": (576, 3, 5, 1, ("none", "hswish")),  # mobilenet_v3_small_96 features_10
    "mv2_1": (32, 112, 3, 1, ("none", "relu6")),  # mobilenet_v2_224 features_1
    "mv2_3": (144, 56, 3, 1, ("none", "relu6")),  # mobilenet_v2_224 features_3
}
DW_LAYER = "dw"


def activation_nodes(act: str, x: str, y: str) -> tuple[list[onnx.NodeProto], list[onnx.TensorProto]]:
    """The nodes (and constants) of the activation `act` from tensor x to tensor y."""
    if act == "relu6":
        bounds = [numpy_helper.from_array(np.float32(v), n) for v, n in ((0.0, "lo"), (6.0, "hi"))]
        return [helper.make_node("Clip", [x, "lo", "hi"], [y])], bounds
    if act == "hswish":
        return [helper.make_node("HardSwish", [x], [y])], []
    if act == "silu":
        return [helper.make_node("Sigmoid", [x], ["sig"]), helper.make_node("Mul", [x, "sig"], [y])], []
    return [helper.make_node("Identity", [x], [y])], []


def dw_model(channels: int, size: int, kernel: int, stride: int, act: str) -> onnx.ModelProto:
    """1x1 conv -> depthwise conv (named DW_LAYER) -> activation -> 1x1 conv, seeded random weights."""
    rng = np.random.default_rng(0)

    def weight(name: str, shape: tuple[int, ...], scale: float = 1.0) -> onnx.TensorProto:
        return numpy_helper.from_array((rng.standard_normal(shape) * scale).astype(np.float32), name)

    pad = kernel // 2
    act_nodes, act_constants = activation_nodes(act, "y0", "y1")
    nodes = [
        helper.make_node("Conv", ["x", "w1"], ["x1"]),
        helper.make_node(
            "Conv", ["x1", "w", "b"], ["y0"], name=DW_LAYER, group=channels,
            kernel_shape=[kernel, kernel], strides=[stride, stride], pads=[pad] * 4,
        ),
        *act_nodes,
        helper.make_node("Conv", ["y1", "w2"], ["y"]),
    ]  # fmt: skip
    constants = [
        weight("w", (channels, 1, kernel, kernel)),
        weight("b", (channels,)),
        weight("w1", (channels, channels, 1, 1), channels**-0.5),
        weight("w2", (channels, channels, 1, 1), channels**-0.5),
        *act_constants,
    ]
    out = (size + 2 * pad - kernel) // stride + 1
    graph = helper.make_graph(
        nodes, "dw",
        [helper.make_tensor_value_info("x", TensorProto.FLOAT, [1, channels, size, size])],
        [helper.make_tensor_value_info("y", TensorProto.FLOAT, [1, channels, out, out])],
        constants,
    )  # fmt: skip
    return helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)])


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--target", default="avx512", choices=sorted(TARGET_ISA))
    parser.add_argument("--cpu", type=int, default=0)
    parser.add_argument("--rounds", type=positive_number, default=3)
    parser.add_argument("--peak", type=float, help="GFLOP/s (default: measured)")
    parser.add_argument("--shapes", nargs="+", choices=SHAPES, default=list(SHAPES))
    args = parser.parse_args(argv)
    peak = args.peak or measure_peak(TARGET_ISA[args.target])
    print(f"peak {TARGET_ISA[args.target]} {peak:.1f} GFLOP/s; dw layer: median us (GFLOP/s, % of peak)")
    with tempfile.TemporaryDirectory(prefix="nncg-dw-") as tmp:
        variants = {}
        for shape in args.shapes:
            channels, size, kernel, stride, acts = SHAPES[shape]
            for act in acts:
                model = dw_model(channels, size, kernel, stride, act)
                report = verify(model, nncg.compile(model, target=args.target))
                if not report.ok:
                    raise SystemExit(f"{shape} {act}: wrong against onnxruntime: {report.stats}")
                variants[shape, act] = Path(tmp) / f"{shape}_{act}.onnx"
                onnx.save(model, variants[shape, act])
        times: dict[tuple[str, str], list[tuple[float, float]]] = {key: [] for key in variants}
        for _ in range(args.rounds):
            for key, path in variants.items():
                row = next(r for r in profile(path, args.target, cpu=args.cpu, cpu_time=True) if r.layer == DW_LAYER)
                times[key].append((row.us, row.gflops))
    for (shape, act), samples in times.items():
        us, gflops = statistics.median(s[0] for s in samples), statistics.median(s[1] for s in samples)
        print(f"{shape:8s} {act:7s} {us:8.1f} us  {gflops:6.1f} GFLOP/s  {100 * gflops / peak:5.1f} %")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
