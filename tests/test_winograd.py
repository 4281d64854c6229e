"""Winograd F(2x2, 3x3): the filter transform's math, the pass's choices, and every border, chunk and
padding case against onnxruntime on every x86 target (ASan/UBSan on some)."""

import numpy as np
import pytest
from helpers import check_against_onnxruntime, onnx_model, target, weights
from onnx import helper
from test_ops import conv_model
from test_x86_targets import TARGETS

import nncg
from nncg.errors import NncgError
from nncg.frontend import import_onnx
from nncg.ir.loops import If, Loop, walk_stmts
from nncg.lowering.winograd import A_T, B_T, transformed_filters
from nncg.passes import PassManager, default_pipeline
from nncg.passes.winograd import padded_channels, parse_layers, winograd_candidates

GRAPH = "drop-identity,fold-batchnorm,fuse-bias,fuse-residual,fuse-activation"


def test_transforms_compute_a_3x3_correlation():
    rng = np.random.default_rng(1)
    d, g = rng.standard_normal((4, 4)), rng.standard_normal((1, 1, 3, 3))
    u = transformed_filters(g.astype(np.float32)).astype(np.float64).reshape(4, 4)
    bt, at = np.array(B_T, float), np.array(A_T, float)
    y = at @ (u * (bt @ d @ bt.T)) @ at.T
    direct = np.array([[np.sum(d[i : i + 3, j : j + 3] * g[0, 0]) for j in range(2)] for i in range(2)])
    np.testing.assert_allclose(y, direct, rtol=1e-6, atol=1e-6)


def graph_after(m, winograd: str, facts=None):
    return PassManager(f"{GRAPH},{winograd}", facts or target()).run(import_onnx(m))


def test_cost_model_takes_3x3_convs_with_enough_input_channels():
    wide = conv_model((1, 8, 8, 8), 12, (3, 3), pads=[1, 1, 1, 1])  # 4x4 output tiles
    narrow = conv_model((1, 3, 8, 8), 12, (3, 3), pads=[1, 1, 1, 1])
    strided = conv_model((1, 8, 8, 8), 12, (3, 3), pads=[1, 1, 1, 1], strides=[2, 2])
    (conv,) = graph_after(wide, "winograd", target(16, 8, 4)).nodes
    assert conv.attrs.algorithm == "winograd" and conv.attrs.gemm_channels == 16
    assert graph_after(narrow, "winograd").nodes[0].attrs.algorithm == "direct"
    assert graph_after(strided, "winograd").nodes[0].attrs.algorithm == "direct"
    assert graph_after(narrow, "winograd{layers=Conv_0:true}").nodes[0].attrs.algorithm == "winograd"
    assert graph_after(wide, "winograd{layers=Conv_0:false}").nodes[0].attrs.algorithm == "direct"


def test_layers_parameter_parses_and_rejects():
    assert parse_layers("conv1:true;conv2:false") == {"conv1": True, "conv2": False}
    with pytest.raises(ValueError):
        parse_layers("conv1:yes")
    strided = conv_model((1, 8, 6, 6), 12, (3, 3), strides=[2, 2])
    with pytest.raises(NncgError, match="Conv_0 is not a 3x3, stride-1"):
        graph_after(strided, "winograd{layers=Conv_0:true}")
    with pytest.raises(NncgError, match="winograd: no layer named conv9; the layers are: Conv_0"):
        graph_after(strided, "winograd{layers=conv9:true}")


def test_gemm_channels_are_padded_only_where_it_saves_vector_instructions():
    assert padded_channels(12, (16, 8, 4)) == 16  # 8 + 4 -> one 16
    assert padded_channels(20, (16, 8, 4)) == 20  # 16 + 4 vs 2 x 16: no saving
    assert padded_channels(8, (16, 8, 4)) == 8
    assert padded_channels(6, (4,)) == 8  # 4 + 2 scalars -> 2 x 4
    assert padded_channels(3, (4,)) == 4
    assert padded_channels(5, (4,)) == 5  # 4 + 1 vs 2 x 4, and 8 would waste 3 of 8
    assert padded_channels(12, (1,)) == 12


def test_border_tiles_get_their_own_loops_without_checks():
    m = conv_model((1, 8, 30, 40), 12, (3, 3), pads=[1, 1, 1, 1])
    avx512 = nncg.get_target("avx512")
    program = PassManager(default_pipeline(avx512), avx512, verify=True).run(import_onnx(m))
    (kernel,) = [k for k in program.kernels if k.op == "Conv"]
    assert not any(isinstance(s, If) for s in walk_stmts(kernel.body))
    # 15 x 20 tiles, 2 tile rows per chunk: the first and last chunk apart, 6 alike ones in a loop
    assert [s.extent for s in walk_stmts(kernel.body) if isinstance(s, Loop) and s.var == "tc"] == [6]
    scratch = {b.name: b.size for b in program.buffers if b.name.startswith(("v_", "m_"))}
    assert scratch == {"v_Conv_0": 16 * 40 * 8, "m_Conv_0": 16 * 40 * 16}


def residual_block(x_shape, c_out, activation="Relu"):
    c_in = x_shape[1]
    nodes = [
        helper.make_node("Conv", ["x", "w", "b"], ["c"], pads=[1, 1, 1, 1]),
        helper.make_node("Add", ["c", "x"], ["s"]),
        helper.make_node(activation, ["s"], ["y"]),
    ]
    return onnx_model(nodes, inputs={"x": x_shape}, initializers={"w": weights(c_out, c_in, 3, 3), "b": weights(c_out)})


def leaky_conv(x_shape, c_out, **attrs):
    nodes = [
        helper.make_node("Conv", ["x", "w"], ["c"], **attrs),
        helper.make_node("LeakyRelu", ["c"], ["y"], alpha=0.1),
    ]
    return onnx_model(nodes, inputs={"x": x_shape}, initializers={"w": weights(c_out, x_shape[1], 3, 3)})


CASES = {
    "pad1_even": conv_model((1, 8, 6, 8), 12, (3, 3), pads=[1, 1, 1, 1]),
    "pad1_odd": conv_model((1, 8, 7, 9), 16, (3, 3), pads=[1, 1, 1, 1]),
    "no_pad": conv_model((1, 8, 7, 6), 8, (3, 3)),
    "asymmetric_pads": conv_model((1, 9, 6, 7), 20, (3, 3), pads=[0, 2, 1, 0]),
    "same_upper": conv_model((1, 8, 5, 5), 6, (3, 3), auto_pad="SAME_UPPER"),
    "pads_beyond_the_patch": conv_model((1, 8, 3, 4), 4, (3, 3), pads=[2, 2, 2, 2]),
    "one_output": conv_model((1, 8, 3, 3), 3, (3, 3), bias=False),
    "one_output_row": conv_model((1, 8, 3, 12), 5, (3, 3)),
    "batch_2": conv_model((2, 8, 5, 6), 12, (3, 3), pads=[1, 1, 1, 1]),
    "many_chunks": conv_model((1, 8, 30, 17), 12, (3, 3), pads=[1, 1, 1, 1]),
    "leaky_no_bias": leaky_conv((1, 12, 9, 4), 32, pads=[1, 1, 1, 1]),
    "residual_relu": residual_block((1, 8, 7, 6), 8),
}


def with_winograd(m, target: str):
    """m compiled by the default pipeline with Winograd forced on every layer it applies to (the cost
    model leaves images this small to direct convolution)."""
    layers = ";".join(f"{name}:true" for name in winograd_candidates(import_onnx(m)))
    text = default_pipeline(nncg.get_target(target)).replace(",winograd", f",winograd{{layers={layers}}}")
    return nncg.compile(m, target, verify_ir=True, pipeline=text)


@pytest.mark.parametrize("case", CASES)
@pytest.mark.parametrize("target", ["ansi-c", "ssse3", *TARGETS])
def test_matches_onnxruntime(case, target):
    m = CASES[case]
    compiled = with_winograd(m, target)
    assert "u_Conv_0" in compiled.source  # the transformed filters: Winograd was taken
    check_against_onnxruntime(m, compiled)


@pytest.mark.parametrize("case", ["pad1_odd", "asymmetric_pads", "batch_2", "residual_relu"])
def test_sanitizers_find_nothing(case):
    check_against_onnxruntime(CASES[case], with_winograd(CASES[case], "ssse3"), sanitize=True)


def test_halo_input_reads_the_border_instead_of_skipping_it():
    nodes = [
        helper.make_node("Conv", ["x", "w1"], ["a"], pads=[1, 1, 1, 1]),
        helper.make_node("Conv", ["a", "w2"], ["y"], pads=[1, 1, 1, 1]),
    ]
    m = onnx_model(
        nodes, inputs={"x": (1, 4, 7, 9)}, initializers={"w1": weights(8, 4, 3, 3), "w2": weights(12, 8, 3, 3)}
    )
    pipeline = default_pipeline(nncg.get_target("ssse3")).replace(",lower,", ",lower{halos=true},")
    check_against_onnxruntime(m, nncg.compile(m, "ssse3", pipeline=pipeline, verify_ir=True), sanitize=True)


@pytest.mark.parametrize("c_in", [1, 3])
def test_narrow_input_forced_through_winograd(c_in):
    m = conv_model((1, c_in, 10, 11), 8, (3, 3), pads=[1, 1, 1, 1])
    pipeline = default_pipeline(nncg.get_target("ssse3")).replace("winograd", "winograd{layers=Conv_0:true}")
    compiled = nncg.compile(m, "ssse3", pipeline=pipeline, verify_ir=True)
    check_against_onnxruntime(m, compiled, sanitize=True)
