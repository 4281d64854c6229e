"""The int8 kernels besides the multiply-accumulates on int32 vectors over channels (issue 16): an int8
MaxPool (int32 maxima; ssse3 without pmaxsd takes them with pmaxsw, exact for 8-bit values),
QLinearGlobalAveragePool (int32 sums, requantised per vector), DequantizeLinear (one float32 product
of the int32 difference), QLinearAdd on ssse3 (its fused multiply-adds in double, as the scalar C
computes them; the FMA targets had it already) and QLinearMul (int32 products, a float32 multiply, the
float32 sum as an Fma by 1 the C compiler cannot contract with it): bit-identical with onnxruntime on ssse3, avx2,
avx512, avx512vnni and NEON under qemu (AArch64 and ARMv7), uint8 and int8 activations; 20 channels
leave tails (avx2: 8 + 8 + 4). The lookups (QLinearSigmoid, LeakyRelu, HardSwish as 256-entry
tables) stay scalar: no target here has a byte shuffle over 256 entries."""

from __future__ import annotations

import numpy as np
import pytest
from cross_helpers import TOOLCHAINS, missing_tools, runner
from helpers import skip_unless_host_runs
from int8_models import _model, _weights, add_model, clip_gemm_model, compare, quantized, random_feeds, spread_feeds
from onnx import helper
from test_cross_targets import require

import nncg

CHANNELS = 20


def pool_model(op: str, **attrs):
    """Conv to CHANNELS channels, then the pool (padded windows for MaxPool), the output."""
    rng = np.random.default_rng(5)
    nodes = [
        helper.make_node("Conv", ["x", "w"], ["c"], pads=[1, 1, 1, 1]),
        helper.make_node(op, ["c"], ["y"], **attrs),
    ]
    return _model(nodes, [1, 4, 9, 9], {"w": _weights(rng, CHANNELS, 4, 3, 3)})


def mul_model():
    """Two Convs to CHANNELS channels (one with a bias) multiplied: 9 columns leave tails (ssse3: 4 + 4 + 1)."""
    rng = np.random.default_rng(6)
    init = {
        "w1": _weights(rng, CHANNELS, 4, 3, 3),
        "w2": _weights(rng, CHANNELS, 4, 1, 1) * 3,
        "b2": rng.standard_normal(CHANNELS),
    }
    nodes = [
        helper.make_node("Conv", ["x", "w1"], ["c1"], pads=[1, 1, 1, 1]),
        helper.make_node("Conv", ["x", "w2", "b2"], ["c2"]),
        helper.make_node("Mul", ["c1", "c2"], ["y"]),
    ]
    return _model(nodes, [1, 4, 9, 9], init)


MODELS = {
    "MaxPool": lambda: pool_model("MaxPool", kernel_shape=[3, 3], strides=[2, 2], pads=[1, 1, 1, 1]),
    "QLinearGlobalAveragePool": lambda: pool_model("GlobalAveragePool"),
    "DequantizeLinear": clip_gemm_model,  # the Gemm's 5 outputs dequantised: 4 lanes and a scalar tail
    "QLinearAdd": add_model,
    "QLinearMul": mul_model,
    # padded windows: the counts differ (a table), the int8 pool computed in uint8 as onnxruntime does
    "QLinearAveragePool": lambda: pool_model("AveragePool", kernel_shape=[3, 3], strides=[2, 2], pads=[1, 1, 1, 1]),
}
# what each target's vector form of each kernel prints
GLOBAL = "QLinearGlobalAveragePool"
VECTOR = {
    "ssse3": {"MaxPool": "_mm_max_epi16(", GLOBAL: "_mm_cvtps_epi32(", "DequantizeLinear": "_mm_cvtepi32_ps("},
    "avx2": {"MaxPool": "_max_epi32(", GLOBAL: "_mm256_cvtps_epi32(", "DequantizeLinear": "_cvtepi32_ps("},
    "neon": {"MaxPool": "vmaxq_s32(", GLOBAL: "nncg_vrequantizeq_s32(", "DequantizeLinear": "vcvtq_f32_s32("},
}
# QLinearAdd's fused multiply-adds: in double on ssse3 (no FMA), over the 8 columns of its NCHW output
VECTOR["ssse3"]["QLinearAdd"] = "nncg_fma_pd("
VECTOR["avx2"]["QLinearAdd"] = "_mm256_fmadd_ps("
VECTOR["neon"]["QLinearAdd"] = "nncg_vfmaq_f32("
# QLinearMul's float32 sum: an Fma by 1, which no C compiler contracts with the product before it
VECTOR["ssse3"]["QLinearMul"] = "_mm_add_ps(_mm_mul_ps("  # no FMA: nothing contracts
VECTOR["avx2"]["QLinearMul"] = "_mm256_fmadd_ps(_mm256_mul_ps("
VECTOR["neon"]["QLinearMul"] = "nncg_vfmaq_f32("
# QLinearAveragePool's float32 sums of its products, two roundings (an Fma by 1 where there is FMA)
AVERAGE = "QLinearAveragePool"
VECTOR["ssse3"][AVERAGE] = "_mm_add_ps(_mm_mul_ps("
VECTOR["avx2"][AVERAGE] = "_mm256_fmadd_ps(_mm256_mul_ps("
VECTOR["neon"][AVERAGE] = "nncg_vfmaq_f32(acc_0, vmulq_f32("  # register blocked
VECTOR["avx512"] = VECTOR["avx512vnni"] = {
    **VECTOR["avx2"],
    GLOBAL: "_mm512_cvtps_epi32(",
    "QLinearMul": "_mm512_fmadd_ps(_mm512_mul_ps(",  # channels last there: 20 = 16 + 4
    AVERAGE: "_mm512_fmadd_ps(_mm512_mul_ps(",
}
X86 = ("ssse3", "avx2", "avx512", "avx512vnni")
ARM = ("aarch64-neon", "armhf-neon")


def kernel_source(source: str, op: str) -> str:
    """The C function of the (one) kernel of `op`."""
    start = source.index(f": {op} */")
    return source[start : source.index("\n}\n", start)]


def check(op: str, target: str, activations: str, **run) -> None:
    float_model = MODELS[op]()
    model = quantized(float_model, activations)
    compiled = nncg.compile(model, target=target, verify_ir=True)
    assert VECTOR[target][op] in kernel_source(compiled.source, op)
    wide = spread_feeds(float_model, (6.0,), 8)  # beyond the calibrated ranges: saturates both ends
    result = compare(model, compiled, random_feeds(float_model, 3, 7) + wide, **run)
    assert result.max_steps == 0 and result.identical == 1.0, result


@pytest.mark.parametrize("activations", ["uint8", "int8"])
@pytest.mark.parametrize("target", X86)
@pytest.mark.parametrize("op", sorted(MODELS))
def test_x86_vectors_match_onnxruntime_to_the_bit(op, target, activations):
    skip_unless_host_runs(target)
    check(op, target, activations)


@pytest.mark.parametrize("activations", ["uint8", "int8"])
@pytest.mark.parametrize("toolchain", ARM)
@pytest.mark.parametrize("op", sorted(MODELS))
def test_neon_vectors_match_onnxruntime_to_the_bit(op, toolchain, activations):
    tc = TOOLCHAINS[toolchain]
    require(missing_tools(tc))
    check(op, tc.target, activations, cc=tc.cc, extra_cflags=tc.flags, runner=runner(tc))


def test_maxpool_of_8_bit_values_only():
    """pmaxsw is exact for int32 lanes holding int16 values: only an 8-bit MaxPool is vectorised so."""
    source = nncg.compile(MODELS["MaxPool"](), target="ssse3").source  # a float MaxPool: maxps
    assert "_mm_max_ps(" in kernel_source(source, "MaxPool") and "_mm_max_epi16(" not in source
