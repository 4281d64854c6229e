"""The avx2 (8 lanes, FMA) and avx512 (16 lanes) targets: the networks and one model per vector hook
against onnxruntime, run on the host when its CPU has the instruction set."""

from pathlib import Path

import pytest
from helpers import check_against_onnxruntime
from onnx import helper
from test_ops import conv_model, model, weights

import nncg

ROOT = Path(__file__).resolve().parent.parent
NETWORKS = [ROOT / "examples" / f"{n}.onnx" for n in ("ball", "pedestrian", "robot")]
NETWORKS += [ROOT / "benchmarks" / "models" / f"{n}.onnx" for n in ("resnet8", "dscnn", "mobilenet_v1_025")]
CPU_FLAGS = {"avx2": {"avx2", "fma"}, "avx512": {"avx512f"}}


def host_flags() -> set[str]:
    try:
        text = Path("/proc/cpuinfo").read_text()
    except OSError:
        return set()
    return {flag for line in text.splitlines() if line.startswith("flags") for flag in line.split(":")[1].split()}


HOST = host_flags()
TARGETS = [
    pytest.param(t, marks=pytest.mark.skipif(not flags <= HOST, reason=f"the host CPU lacks {', '.join(flags)}"))
    for t, flags in CPU_FLAGS.items()
]


@pytest.mark.parametrize("target", TARGETS)
@pytest.mark.parametrize("path", NETWORKS, ids=lambda p: p.stem)
def test_network_matches_onnxruntime(path, target):
    compiled = nncg.compile(path, target=target)
    check_against_onnxruntime(nncg.load_model(path), compiled, opt="-O1")


def activation_after_conv(op, **attrs):
    nodes = [
        helper.make_node("Conv", ["x", "w", "b"], ["c"], pads=[1, 1, 1, 1]),
        helper.make_node(op, ["c"], ["y"], **attrs),
    ]
    return model(nodes, {"x": (1, 3, 6, 7)}, None, [("w", weights(20, 3, 3, 3)), ("b", weights(20))])


# 20 output channels: full vectors plus a scalar tail at 8 and 16 lanes.
HOOKS = {
    "fma_and_tail": conv_model((1, 3, 6, 7), 20, (3, 3), pads=[1, 1, 1, 1]),
    "select": activation_after_conv("LeakyRelu", alpha=-0.5),  # a negative slope: a select, not a max
    "max": activation_after_conv("Relu"),
    "lane_wise_call": activation_after_conv("Sigmoid"),
}


@pytest.mark.parametrize("target", TARGETS)
@pytest.mark.parametrize("case", HOOKS)
def test_vector_hooks_match_onnxruntime(case, target):
    m = HOOKS[case]
    for unroll in (None, 2):
        compiled = nncg.compile(m, target=target, unroll=unroll, verify_ir=True)
        check_against_onnxruntime(m, compiled, sanitize=unroll is None)
    prefix = {"avx2": "_mm256", "avx512": "_mm512"}[target]
    assert f"{prefix}_fmadd_ps" in compiled.source or case != "fma_and_tail"
    if case == "select":
        assert ("blendv_ps" if target == "avx2" else "mask_blend_ps") in compiled.source
