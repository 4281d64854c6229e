"""Zero halos: a tensor read only by padded Convs is stored inside a border of zeros, so the Convs
read it without bounds checks. Structure of the lowered program, and numerics against onnxruntime."""

import pytest
from helpers import check_against_onnxruntime, onnx_model, weights
from onnx import helper

import nncg
from nncg.frontend import import_onnx
from nncg.ir.loops import If, walk_stmts
from nncg.lowering import lower
from nncg.lowering.halo import conv_halos


def chain(x_shape, layers, residual=False):
    """Conv/MaxPool layers in sequence: ("conv", c_out, kernel, attrs) or ("pool", kernel, attrs)."""
    nodes, inits, value, c = [], {}, "x", x_shape[1]
    for i, layer in enumerate(layers):
        out = f"v{i}"
        if layer[0] == "conv":
            _, c_out, kernel, attrs = layer
            inits |= {f"w{i}": weights(c_out, c, *kernel), f"b{i}": weights(c_out)}
            nodes.append(helper.make_node("Conv", [value, f"w{i}", f"b{i}"], [out], **attrs))
            c = c_out
        else:
            _, kernel, attrs = layer
            nodes.append(helper.make_node("MaxPool", [value], [out], kernel_shape=kernel, **attrs))
        value = out
    if residual:  # the last conv's output plus the one before it (same shape): a fused shortcut
        nodes.append(helper.make_node("Add", [value, f"v{len(layers) - 2}"], ["s"]))
        value = "s"
    nodes.append(helper.make_node("Relu", [value], ["y"]))
    return onnx_model(nodes, inputs={"x": x_shape}, initializers=inits)


def with_halos(target: str) -> str:
    pipeline = nncg.default_pipeline(nncg.get_target(target))
    return pipeline.replace(",lower,", ",lower{halos=true},")


PAD1 = {"pads": [1, 1, 1, 1]}
CASES = {
    "conv_conv": chain((1, 3, 9, 11), [("conv", 8, (3, 3), PAD1), ("conv", 12, (3, 3), PAD1)]),
    "pool_conv": chain((1, 4, 10, 12), [("conv", 8, (3, 3), {}), ("pool", (2, 2), {"strides": [2, 2]}),
                                        ("conv", 12, (3, 3), PAD1)]),
    "asymmetric_stride2": chain((1, 3, 11, 9), [("conv", 8, (3, 3), PAD1),
                                                ("conv", 8, (3, 3), {"pads": [0, 2, 1, 0], "strides": [2, 2]})]),
    "wide_dilated": chain((1, 2, 12, 12), [("conv", 4, (3, 3), PAD1),
                                           ("conv", 6, (3, 3), {"pads": [2, 2, 2, 2], "dilations": [2, 2]})]),
    "residual": chain((1, 8, 8, 10), [("conv", 8, (3, 3), PAD1), ("conv", 8, (3, 3), PAD1),
                                      ("conv", 8, (3, 3), PAD1)], residual=True),
    "conv1d": chain((1, 3, 17), [("conv", 5, (3,), {"pads": [1, 1]}), ("conv", 4, (5,), {"pads": [2, 2]})]),
    "conv3d": chain((1, 2, 4, 5, 6), [("conv", 4, (3, 3, 3), {"pads": [1] * 6}),
                                      ("conv", 4, (3, 3, 3), {"pads": [1] * 6})]),
}  # fmt: skip


def test_halo_goes_where_only_padded_convs_read():
    graph = import_onnx(CASES["conv_conv"])
    assert conv_halos(graph) == {"v0": ((0, 0), (0, 0), (1, 1), (1, 1))}
    # the second conv's output goes to Relu (not a Conv): no halo; the model input is the caller's
    assert set(conv_halos(import_onnx(CASES["pool_conv"]))) == {"v1"}  # the pool's output, read by a conv


def test_convs_reading_a_halo_have_no_bounds_checks():
    program = lower(import_onnx(CASES["conv_conv"]), halos=True)
    ops = [k.op for k in program.kernels]
    assert ops[:3] == ["ZeroHalo", "Conv", "Conv"]  # the border is zeroed before conv1 writes the inside
    checks = [[s for s in walk_stmts(k.body) if isinstance(s, If)] for k in program.kernels]
    assert checks[1] and not checks[2]  # conv1 checks the caller's input; conv2 reads the halo
    stored = next(b for b in program.buffers if b.name == "t_v0")
    assert stored.size == 8 * 11 * 13  # 9x11 inside a 1-wide border


@pytest.mark.parametrize("target", ["ansi-c", "ssse3", "avx2"])
@pytest.mark.parametrize("case", CASES)
def test_halo_models_match_onnxruntime(case, target):
    from helpers import HOST

    if target == "avx2" and not {"avx2", "fma"} <= HOST:
        pytest.skip("the host CPU lacks avx2, fma")
    compiled = nncg.compile(CASES[case], target=target, pipeline=with_halos(target), verify_ir=True)
    check_against_onnxruntime(CASES[case], compiled, opt="-O1")


@pytest.mark.parametrize("case", ["pool_conv", "asymmetric_stride2", "residual"])
def test_halo_reads_stay_in_bounds_under_sanitizers(case):
    compiled = nncg.compile(CASES[case], target="ssse3", pipeline=with_halos("ssse3"))
    check_against_onnxruntime(CASES[case], compiled, sanitize=True, opt="-O1")


def test_halos_are_off_by_default():
    assert "halo" not in nncg.compile(CASES["conv_conv"], target="ssse3").source
