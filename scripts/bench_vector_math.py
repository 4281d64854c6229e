"""Micro-benchmark of one elementwise math layer (Sigmoid by default) over a 1x96x48x48 tensor, the
size of an EfficientNet-B0 squeeze-excite gate's input, on the x86 targets the host runs: nncg's
median time per inference next to onnxruntime's (nncg.bench.benchmark). Not a test: run it before
and after a change to the vector math functions (nncg/backends/vector_math.py), e.g.

    python scripts/bench_vector_math.py --op Sigmoid Tanh --target avx2 avx512
    NNCG_ROOT=/tmp/old-tree python scripts/bench_vector_math.py   # the nncg package of another tree
"""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

from onnx import TensorProto, helper

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, os.environ.get("NNCG_ROOT", str(ROOT)))

from nncg.bench.benchmark import benchmark  # noqa: E402
from nncg.bench.peak import TARGET_ISA  # noqa: E402

PEAKS: dict[str, float | None] = dict.fromkeys(TARGET_ISA.values())  # no peak measurement


def layer(op: str, shape: tuple[int, ...]):
    node = helper.make_node(op, ["x"], ["y"])
    graph = helper.make_graph(
        [node],
        op.lower(),
        [helper.make_tensor_value_info("x", TensorProto.FLOAT, shape)],
        [helper.make_tensor_value_info("y", TensorProto.FLOAT, shape)],
    )
    return helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)])


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--op", nargs="+", default=["Sigmoid"])
    parser.add_argument("--target", nargs="+", default=["avx2", "avx512"])
    parser.add_argument("--shape", type=int, nargs="+", default=[1, 96, 48, 48])
    parser.add_argument("--batches", type=int, default=15)
    args = parser.parse_args(argv)
    print(f"nncg from {Path(sys.modules['nncg'].__file__).parent}")
    print(f"{'op':<8} {'target':<7} {'nncg us':>10} {'ort us':>10} {'max abs err':>12}")
    for op in args.op:
        for target in args.target:
            result = benchmark(layer(op, tuple(args.shape)), target, batches=args.batches, peaks=PEAKS)
            print(
                f"{op:<8} {target:<7} {result.nncg_us:>10.1f} {result.ort_bound_us:>10.1f} {result.max_abs_err:>12.3g}"
            )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
