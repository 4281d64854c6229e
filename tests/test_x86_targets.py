"""The avx2 (8 lanes, FMA) and avx512 (16 lanes) targets: the networks and one model per vector hook
against onnxruntime, run on the host when its CPU has the instruction set."""

import re
from pathlib import Path

import pytest
from helpers import check_against_onnxruntime, missing_flags, onnx_model, weights
from onnx import helper
from test_ops import conv_model

import nncg
from nncg.backends import BACKENDS, get_backend

ROOT = Path(__file__).resolve().parent.parent
NETWORKS = [ROOT / "examples" / f"{n}.onnx" for n in ("ball", "pedestrian", "robot")]
NETWORKS += [ROOT / "benchmarks" / "models" / f"{n}.onnx" for n in ("resnet8", "dscnn", "mobilenet_v1_025")]
TARGETS = [
    pytest.param(t, marks=pytest.mark.skipif(bool(missing_flags(t)), reason=f"the host CPU lacks {missing_flags(t)}"))
    for t in ("avx2", "avx512", "avx512vnni")
]


@pytest.mark.parametrize("target", TARGETS)
@pytest.mark.parametrize("path", NETWORKS, ids=lambda p: p.stem)
def test_network_matches_onnxruntime(path, target):
    compiled = nncg.compile(path, target=target)
    check_against_onnxruntime(nncg.load_model(path), compiled, opt="-O1")


def activation_after_conv(op, channels=20, **attrs):
    nodes = [
        helper.make_node("Conv", ["x", "w", "b"], ["c"], pads=[1, 1, 1, 1]),
        helper.make_node(op, ["c"], ["y"], **attrs),
    ]
    return onnx_model(
        nodes, inputs={"x": (1, 3, 6, 7)}, initializers={"w": weights(channels, 3, 3, 3), "b": weights(channels)}
    )


# 20 output channels: full vectors plus a 4-lane block at 8 and 16 lanes.
HOOKS = {
    "fma_and_tail": conv_model((1, 3, 6, 7), 20, (3, 3), pads=[1, 1, 1, 1]),
    "select": activation_after_conv("LeakyRelu", alpha=-0.5),  # a negative slope: a select, not a max
    "max": activation_after_conv("Relu"),
    "lane_wise_call": activation_after_conv("Sigmoid"),
}


def checked_builds(m, target) -> list:
    """m compiled without unrolling (run under ASan/UBSan) and at level 2, each checked against onnxruntime."""
    builds = []
    for unroll in (None, 2):
        builds.append(nncg.compile(m, target=target, unroll=unroll, verify_ir=True))
        check_against_onnxruntime(m, builds[-1], sanitize=unroll is None)
    return builds


@pytest.mark.parametrize("target", TARGETS)
@pytest.mark.parametrize("case", HOOKS)
def test_vector_hooks_match_onnxruntime(case, target):
    compiled = checked_builds(HOOKS[case], target)[-1]
    prefix = {"avx2": "_mm256", "avx512": "_mm512", "avx512vnni": "_mm512"}[target]
    assert f"{prefix}_fmadd_ps" in compiled.source or case != "fma_and_tail"
    if case == "select":
        assert ("blendv_ps" if target == "avx2" else "mask_blend_ps") in compiled.source


# Output channels that are not a multiple of the widest vector: blocks of several widths, widest
# first (avx2: 8/4, avx512: 16/8/4), each printed with its own width's intrinsics.
WIDTHS = {
    "conv8": conv_model((1, 3, 6, 7), 8, (3, 3), pads=[1, 1, 1, 1]),
    "conv12": conv_model((1, 3, 6, 7), 12, (3, 3), pads=[1, 1, 1, 1]),
    "conv20": conv_model((1, 3, 6, 7), 20, (3, 3), pads=[1, 1, 1, 1]),
    "select12": activation_after_conv("LeakyRelu", channels=12, alpha=-0.5),
    "lane_wise_call12": activation_after_conv("Sigmoid", channels=12),
}
# The vector stores each case prints, by intrinsic prefix: (avx2, avx512).
STORES = {
    "conv8": ({"_mm256"}, {"_mm256"}),
    "conv12": ({"_mm256", "_mm"}, {"_mm256", "_mm"}),
    "conv20": ({"_mm256", "_mm"}, {"_mm512", "_mm"}),
    "select12": ({"_mm256", "_mm"}, {"_mm256", "_mm"}),
    "lane_wise_call12": ({"_mm256", "_mm"}, {"_mm256", "_mm"}),
}


@pytest.mark.parametrize("target", TARGETS)
@pytest.mark.parametrize("case", WIDTHS)
def test_several_vector_widths_match_onnxruntime(case, target):
    for compiled in checked_builds(WIDTHS[case], target):
        stores = set(re.findall(r"(_mm\d*)_storeu_ps\(&", compiled.source))
        assert stores == STORES[case][target.startswith("avx512")], stores
        assert "float acc" not in compiled.source  # no channel left scalar
    if case == "select12":
        assert "_mm256_blendv_ps" in compiled.source and "_mm_blendv_ps" in compiled.source
    if case == "lane_wise_call12":
        assert re.search(r"^static NNCG_INLINE __m256 nncg256_sigmoid_ps\(__m256 x\)$", compiled.source, re.M)
        assert re.search(r"^static NNCG_INLINE __m128 nncg_sigmoid_ps\(__m128 x\)$", compiled.source, re.M)


def test_backends_declare_the_widths_they_print():
    widths = {name: get_backend(name).vector_widths for name in BACKENDS}
    assert widths == {
        "ansi-c": (),
        "ssse3": (4,),
        "avx2": (8, 4),
        "avx512": (16, 8, 4),
        "avx512vnni": (16, 8, 4),
        "neon": (4,),
        "neon-dotprod": (4,),
    }
    for name in BACKENDS:
        backend = get_backend(name)
        assert backend.lanes == (backend.vector_widths or (1,))[0]
