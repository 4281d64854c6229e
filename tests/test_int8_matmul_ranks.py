"""QLinearMatMul and the QDQ MatMul group (issue 16) of an x of rank 3 ([1, M, K], [B, M, K]) or 1
([K]) and constant weights [K, N], as NumPy's matmul (the ONNX spec's): the rows of all batches in one
integer matrix product, the result in x's rank; uint8 and int8 activations, zero points other than 0,
weight scales per column, uint8 weights; compared with onnxruntime on every element, to the bit, in scalar C and
in avx2's pmaddwd pairs."""

from __future__ import annotations

import numpy as np
import onnx
import pytest
from helpers import kernel_ops, onnx_model, skip_unless_host_runs
from int8_models import onnxruntime_outputs
from onnx import helper

import nncg
from nncg.verify import run_compiled

K, N = 8, 12


def _parameters(x_type, seed: int, w_type=np.int8, w_shape=(K, N)) -> dict[str, np.ndarray]:
    rng = np.random.default_rng(seed)
    info = np.iinfo(w_type)
    columns = w_shape[-1] if len(w_shape) > 1 else 1
    # onnxruntime takes per-column scales of weights of rank 3 as [..., 1, N]
    scale_shape = (*w_shape[:-2], 1, columns) if len(w_shape) > 2 else (columns,)
    return {
        "xs": np.float32(0.05),
        "xz": np.asarray(17 if x_type == np.uint8 else -9, x_type),
        "w": rng.integers(info.min, info.max + 1, w_shape).astype(w_type),
        "ws": rng.uniform(0.002, 0.01, scale_shape).astype(np.float32),
        "wz": np.asarray(0 if w_type == np.int8 else 131, w_type),
        "ys": np.float32(0.2),
        "yz": np.asarray(120 if x_type == np.uint8 else 5, x_type),
    }


def qlinear_matmul_model(
    x_shape: tuple[int, ...], x_type=np.uint8, seed: int = 0, w_type=np.int8, w_shape=(K, N)
) -> onnx.ModelProto:
    """x -> QuantizeLinear -> QLinearMatMul (constant weights [K, N] unless said, per-column scales;
    uint8 weights with a zero point other than 0) -> DequantizeLinear."""
    nodes = [
        helper.make_node("QuantizeLinear", ["x", "xs", "xz"], ["q"]),
        helper.make_node("QLinearMatMul", ["q", "xs", "xz", "w", "ws", "wz", "ys", "yz"], ["yq"]),
        helper.make_node("DequantizeLinear", ["yq", "ys", "yz"], ["y"]),
    ]
    return onnx_model(nodes, inputs={"x": x_shape}, initializers=_parameters(x_type, seed, w_type, w_shape))


def qdq_matmul_model(x_shape: tuple[int, ...], x_type=np.uint8, seed: int = 0, w_shape=(K, N)) -> onnx.ModelProto:
    """The QDQ group around a float MatMul (what quantize_static writes), per-column weight scales."""
    nodes = [
        helper.make_node("QuantizeLinear", ["x", "xs", "xz"], ["q"]),
        helper.make_node("DequantizeLinear", ["q", "xs", "xz"], ["d"]),
        helper.make_node("DequantizeLinear", ["w", "ws", "wz"], ["wd"], axis=len(w_shape) - 1),
        helper.make_node("MatMul", ["d", "wd"], ["m"]),
        helper.make_node("QuantizeLinear", ["m", "ys", "yz"], ["yq"]),
        helper.make_node("DequantizeLinear", ["yq", "ys", "yz"], ["y"]),
    ]
    parameters = _parameters(x_type, seed, w_shape=w_shape)
    parameters["ws"] = parameters["ws"].reshape(-1)  # DequantizeLinear's per-axis scale: a vector
    parameters["wz"] = np.zeros(w_shape[-1], np.int8)
    return onnx_model(nodes, inputs={"x": x_shape}, initializers=parameters)


def check(model: onnx.ModelProto, target: str) -> str:
    """Equal to onnxruntime in every element and in shape, on inputs quantised past both ends; the C."""
    skip_unless_host_runs(target)
    compiled = nncg.compile(model, target=target, verify_ir=True)
    assert "QLinearDense" in kernel_ops(compiled) and "MatMul" not in kernel_ops(compiled)
    shape = tuple(d.dim_value for d in model.graph.input[0].type.tensor_type.shape.dim)
    rng = np.random.default_rng(4)
    for spread in (0.5, 20.0):
        x = (rng.standard_normal(shape) * spread).astype(np.float32)
        expected = onnxruntime_outputs(model, {"x": x})[0]
        ours = run_compiled(compiled, [x])[0]
        assert ours.shape == expected.shape
        np.testing.assert_array_equal(ours, expected)
    return compiled.source


@pytest.mark.parametrize("x_shape", [(1, 3, K), (2, 3, K), (K,)])
@pytest.mark.parametrize("x_type", [np.uint8, np.int8])
def test_qlinear_matmul_of_any_rank(x_shape, x_type):
    check(qlinear_matmul_model(x_shape, x_type), "ansi-c")


@pytest.mark.parametrize("x_shape", [(1, 3, K), (2, 3, K)])
def test_qdq_matmul_of_rank_3(x_shape):
    check(qdq_matmul_model(x_shape, np.int8), "ansi-c")


@pytest.mark.parametrize("x_shape", [(3, K), (2, 3, K)])
@pytest.mark.parametrize("build", [qlinear_matmul_model, qdq_matmul_model])
def test_weights_of_rank_3(build, x_shape):
    """Constant weights [1, K, N] (a batch dim of 1, as exporters write a MatMul by a parameter of rank
    3): one [K, N] matrix over every row, the result of rank 3 even for a 2-D x."""
    check(build(x_shape, w_shape=(1, K, N)), "ansi-c")


def test_weights_of_rank_1():
    """Constant weights [K]: one column, which the result loses."""
    check(qlinear_matmul_model((3, K), w_shape=(K,)), "ansi-c")


def test_weights_of_a_batch_above_1_are_refused():
    with pytest.raises(nncg.NncgError, match=r"takes one \[K, N\] matrix"):
        nncg.compile(qlinear_matmul_model((2, 3, K), w_shape=(2, K, N)))


@pytest.mark.parametrize("build", [qlinear_matmul_model, qdq_matmul_model])
def test_rank_3_in_pmaddwd_pairs(build):
    assert "_mm256_madd_epi16(" in check(build((2, 3, K)), "avx2")


def test_weights_minus_their_zero_point_in_pmaddwd_pairs():
    """uint8 weights minus their zero point: int16 pairs, read as they are by pmaddwd (not widened to
    int32 and multiplied channel by channel)."""
    source = check(qlinear_matmul_model((2, 3, K), w_type=np.uint8), "avx2")
    assert "_madd_epi16(" in source and "nncg_int16 w_" in source and "_mullo_epi32(" not in source
