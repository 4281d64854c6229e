"""Quantized Add (issue 16): an Add between DequantizeLinear nodes and a QuantizeLinear, which
onnxruntime fuses into its QLinearAdd, and that op itself (com.microsoft), compiled to NNCG's integer
kernel and compared with onnxruntime running the same model: bit-identical on every element, int8
and uint8, zero points other than 0, broadcast either way (onnxruntime's kernel then trades the
operands' places: lowering/quantized_add.py) and with a constant, saturating at both ends, ansi-c
and SIMD targets."""

from __future__ import annotations

import numpy as np
import onnx
import pytest
from cross_helpers import TOOLCHAINS, missing_tools, runner
from helpers import kernel_ops, skip_unless_host_runs
from int8_models import (
    assert_identical,
    broadcast_add_model,
    compare,
    contrib_binary_model,
    qdq_binary_model,
    quantized,
    random_feeds,
    spread_feeds,
    typed,
)
from test_cross_targets import require

import nncg

SHAPE = (1, 4, 5, 6)
# the operands' shapes: one shape; the second broadcast over the channels, the rows, trailing
# dims of 1, or a single value; the first broadcast (onnxruntime passes the second first then)
SHAPES = {
    "same": (SHAPE, SHAPE),
    "channels": (SHAPE, (1, 4, 1, 1)),
    "rows": (SHAPE, (6,)),
    "trailing": ((1, 4, 5, 1), (1, 4, 1, 1)),
    "scalar": (SHAPE, (1,)),
    "first_channels": ((1, 4, 1, 1), SHAPE),
    "first_trailing": ((1, 4, 1, 1), (1, 4, 5, 1)),
    "first_scalar": ((1,), SHAPE),
}
# activation type: zero points of a, b and the sum
ZEROS = {"uint8": (131, 118, 100), "int8": (7, -12, -30)}


def _params(activations: str, scales=(0.04, 0.03, 0.05), zeros=None) -> dict[str, np.ndarray]:
    za, zb, zy = zeros or ZEROS[activations]
    sa, sb, sy = (np.float32(s) for s in scales)
    zero = {name: typed(activations, z) for name, z in (("az", za), ("bz", zb), ("yz", zy))}
    return {"as": sa, "az": zero["az"], "bs": sb, "bz": zero["bz"], "ys": sy, "yz": zero["yz"]}


def qdq_model(activations: str, shapes: str, constant: bool = False) -> onnx.ModelProto:
    """x + z between QuantizeLinear/DequantizeLinear pairs; z a graph input or a quantized constant."""
    return qdq_binary_model("Add", *SHAPES[shapes], _params(activations), constant)


def contrib_model(activations: str, shapes: str, params: dict[str, np.ndarray] | None = None) -> onnx.ModelProto:
    x_shape, z_shape = SHAPES[shapes] if isinstance(shapes, str) else shapes
    return contrib_binary_model("QLinearAdd", x_shape, z_shape, params or _params(activations))


def check(model: onnx.ModelProto, target: str = "ansi-c", feeds_list=None, **run) -> None:
    if not run:
        skip_unless_host_runs(target)
    compiled = nncg.compile(model, target=target, verify_ir=True)
    assert "QLinearAdd" in kernel_ops(compiled)
    assert_identical(model, compiled, feeds_list or spread_feeds(model, (0.5, 2.0, 9.0), 9), **run)  # 9 saturates


@pytest.mark.parametrize("activations", ["uint8", "int8"])
@pytest.mark.parametrize("shapes", sorted(SHAPES))
def test_qdq_add_matches_onnxruntime_to_the_bit(activations, shapes):
    check(qdq_model(activations, shapes))


@pytest.mark.parametrize("activations", ["uint8", "int8"])
@pytest.mark.parametrize("shapes", ["channels", "first_channels"])
def test_qdq_add_of_a_constant(activations, shapes):
    check(qdq_model(activations, shapes, constant=True))


@pytest.mark.parametrize("activations", ["uint8", "int8"])
@pytest.mark.parametrize("shapes", ["rows", "first_channels"])
def test_contrib_qlinear_add(activations, shapes):
    check(contrib_model(activations, shapes))


def test_every_pair_of_values_with_a_contracted_constant():
    """All 65536 pairs of uint8 values, with scales and zero points for which onnxruntime's constant
    y_zp - (r_a a_zp + r_b b_zp), its sum contracted to a fused multiply-add, differs from the
    unfused one (514 of the pairs round differently then)."""
    params = _params("uint8", scales=(0.082, 0.097, 0.024), zeros=(141, 93, 128))
    a, b = np.meshgrid(np.arange(256), np.arange(256), indexing="ij")
    feeds = {
        "x": ((a.reshape(1, -1) - 141) * np.float64(params["as"])).astype(np.float32),
        "z": ((b.reshape(1, -1) - 93) * np.float64(params["bs"])).astype(np.float32),
    }
    check(contrib_model("uint8", ((1, 65536), (1, 65536)), params), feeds_list=[feeds])


@pytest.mark.parametrize("activations", ["uint8", "int8"])
@pytest.mark.parametrize("average_first", [False, True])
def test_conv_plus_its_global_average_either_way(activations, average_first):
    """quantize_static's QDQ model of a Conv and its GlobalAveragePool added (the average broadcast,
    as the second operand or the first): every element of onnxruntime's result."""
    float_model = broadcast_add_model(average_first=average_first, channels=16, size=12)
    model = quantized(float_model, activations)
    compiled = nncg.compile(model, verify_ir=True)
    assert "QLinearAdd" in kernel_ops(compiled)
    result = compare(model, compiled, random_feeds(float_model, 4, 3))
    assert result.max_steps == 0 and result.identical == 1.0, result


@pytest.mark.parametrize("target", ["ssse3", "avx2", "avx512", "avx512vnni"])
@pytest.mark.parametrize("shapes", ["same", "channels", "first_channels"])
def test_simd_targets(target, shapes):
    check(qdq_model("int8", shapes), target)


@pytest.mark.parametrize("toolchain", ["aarch64-neon", "armhf-neon"])
def test_neon_under_qemu(toolchain):
    tc = TOOLCHAINS[toolchain]
    require(missing_tools(tc))
    check(qdq_model("uint8", "first_channels"), "neon", cc=tc.cc, extra_cflags=tc.flags, runner=runner(tc))
