"""Data-movement and resampling operators (Concat, Split, Slice, Transpose, Pad, Squeeze, Unsqueeze,
Resize, Upsample): one small ONNX model per attribute combination, compiled for every target and
compared with onnxruntime. Cases with a Conv in front read a channels-last internal activation;
the others read the row-major graph input directly."""

from __future__ import annotations

import itertools

import numpy as np
import onnxruntime as ort
import pytest
from helpers import check_against_onnxruntime, compile_and_check, kernel_ops, onnx_model
from onnx import TensorProto, helper

import nncg
from nncg.errors import NncgError
from nncg.frontend import import_onnx
from nncg.frontend.context import Context, OnnxOp
from nncg.frontend.ops import CONVERTERS
from nncg.ir.graph import PadAttrs, ResizeAttrs, SliceAttrs, SplitAttrs
from nncg.ir.loops import Store, walk_stmts
from nncg.lowering.resize import dim_taps, periodic_pieces, resize_taps, windowed_pieces
from nncg.passes import PassManager

RNG = np.random.default_rng(7)
TARGETS = ["ansi-c", "ssse3"]
INT64_MIN, INT64_MAX = -(2**63), 2**63 - 1


def ints(*values):
    return np.array(values, dtype=np.int64)


def floats(*values):
    return np.array(values, dtype=np.float32)


def conv(x, y, c_in, c_out, name):
    """A 3x3 'same' Conv node and its weight by name: its output is a channels-last internal buffer."""
    w = (RNG.standard_normal((c_out, c_in, 3, 3)) / 3).astype(np.float32)
    return helper.make_node("Conv", [x, f"w_{name}"], [y], pads=[1, 1, 1, 1], name=name), {f"w_{name}": w}


def one_op(op, x_shape, extra=(), inits=None, opset=13, with_conv=False, c_out=6, **attrs):
    """op(x, *extra) -> y; with_conv makes it Conv -> op -> Relu, so that the op reads and writes
    internal (channels-last) buffers instead of the row-major graph input and output."""
    inits = inits or {}
    if not with_conv:
        node = helper.make_node(op, ["x", *extra], ["y"], **attrs)
        return onnx_model([node], inputs={"x": x_shape}, initializers=inits, opset=opset)
    node, weight = conv("x", "c", x_shape[1], c_out, "conv")
    nodes = [node, helper.make_node(op, ["c", *extra], ["t"], **attrs), helper.make_node("Relu", ["t"], ["y"])]
    return onnx_model(nodes, inputs={"x": x_shape}, initializers={**inits, **weight}, opset=opset)


# --- Concat --------------------------------------------------------------------------------------


def concat_model(shapes, axis, constant=None, opset=13):
    """Concat of graph inputs x0, x1, ... (and a constant input last when given)."""
    names = [f"x{i}" for i in range(len(shapes))]
    inits = {} if constant is None else {"k": constant}
    node = helper.make_node("Concat", names + ([] if constant is None else ["k"]), ["y"], axis=axis)
    return onnx_model([node], inputs=dict(zip(names, shapes)), initializers=inits, opset=opset)


CONCAT_CASES = {
    "channels_2_inputs": (((1, 3, 4, 5), (1, 5, 4, 5)), 1, None, None),
    "negative_axis_3_inputs": (((1, 2, 3, 4), (1, 2, 3, 1), (1, 2, 3, 6)), -1, None, 2),
    "axis_0": (((2, 3, 4), (1, 3, 4)), 0, None, 1),
    "constant_input": (((1, 4, 3, 3),), 1, RNG.standard_normal((1, 2, 3, 3)).astype(np.float32), None),
    "rank_2_with_constant": (((3, 5),), -2, RNG.standard_normal((2, 5)).astype(np.float32), 2),
}


@pytest.mark.parametrize("target", TARGETS)
@pytest.mark.parametrize("case", CONCAT_CASES)
def test_concat_graph_inputs(case, target):
    shapes, axis, constant, unroll = CONCAT_CASES[case]
    compile_and_check(concat_model(shapes, axis, constant), target, unroll=unroll)


@pytest.mark.parametrize("target", TARGETS)
@pytest.mark.parametrize("axis", [1, 2, -1])
@pytest.mark.parametrize("unroll", [None, 1])
def test_concat_of_conv_outputs_and_graph_input(axis, unroll, target):
    """Channels-last conv outputs (and, on the channel axis, the row-major graph input) into an
    internal output that a Relu reads."""
    conv_a, w_a = conv("x", "a", 3, 4, "conv_a")
    conv_b, w_b = conv("x", "b", 3, 8 if axis == 1 else 4, "conv_b")  # spatial concat: equal channels
    inputs = ["a", "b", "x"] if axis == 1 else ["a", "b"]
    nodes = [
        conv_a,
        conv_b,
        helper.make_node("Concat", inputs, ["t"], axis=axis),
        helper.make_node("Relu", ["t"], ["y"]),
    ]
    compile_and_check(onnx_model(nodes, inputs={"x": (1, 3, 5, 6)}, initializers=w_a | w_b), target, unroll=unroll)


def test_concat_under_sanitizers():
    conv_a, w_a = conv("x", "a", 2, 5, "conv_a")
    node = helper.make_node("Concat", ["a", "k", "x"], ["y"], axis=1)
    k = RNG.standard_normal((1, 3, 4, 4)).astype(np.float32)
    m = onnx_model([conv_a, node], inputs={"x": (1, 2, 4, 4)}, initializers={**w_a, "k": k})
    for target in TARGETS:
        compile_and_check(m, target, unroll=2, sanitize=True)


# --- Split ---------------------------------------------------------------------------------------


def split_model(x_shape, n_out, opset, split=None, with_conv=False, **attrs):
    """Split into y0..y{n-1}; `split` as attribute before opset 13, else input. with_conv makes it
    Conv -> Split with y0 through a Relu (an internal output) and the others graph outputs."""
    outputs = [f"y{i}" for i in range(n_out)]
    inits, extra = {}, []
    if split is not None and opset >= 13:
        inits, extra = {"split": ints(*split)}, ["split"]
    elif split is not None:
        attrs["split"] = split
    if not with_conv:
        node = helper.make_node("Split", ["x", *extra], outputs, **attrs)
        return onnx_model([node], inputs={"x": x_shape}, outputs=outputs, initializers=inits, opset=opset)
    node, weight = conv("x", "c", x_shape[1], 7, "conv")
    nodes = [
        node,
        helper.make_node("Split", ["c", *extra], ["s0", *outputs[1:]], **attrs),
        helper.make_node("Relu", ["s0"], ["y0"]),
    ]
    return onnx_model(nodes, inputs={"x": x_shape}, outputs=outputs, initializers=inits | weight, opset=opset)


SPLIT_CASES = {
    "opset11_attribute_split": ((1, 6, 3, 4), 2, 11, [2, 4], dict(axis=1)),
    "opset13_input_split": ((1, 3, 4, 9), 3, 13, [2, 3, 4], dict(axis=-1)),
    "opset13_equal": ((2, 6, 5), 3, 13, None, dict(axis=1)),
    "opset11_equal_axis0_default": ((4, 3, 2), 2, 11, None, {}),
    "opset18_num_outputs_uneven": ((1, 2, 7, 3), 3, 18, None, dict(axis=2, num_outputs=3)),
    "opset18_input_split": ((1, 5, 3, 3), 2, 18, [1, 4], dict(axis=1)),
}


@pytest.mark.parametrize("target", TARGETS)
@pytest.mark.parametrize("case", SPLIT_CASES)
def test_split(case, target):
    x_shape, n_out, opset, split, attrs = SPLIT_CASES[case]
    compile_and_check(split_model(x_shape, n_out, opset, split, **attrs), target, unroll=None)


@pytest.mark.parametrize("target", TARGETS)
@pytest.mark.parametrize("unroll", [None, 2])
def test_split_of_conv_output(unroll, target):
    m = split_model((1, 2, 4, 5), 2, 13, [3, 4], with_conv=True, axis=1)
    compile_and_check(m, target, unroll=unroll, sanitize=unroll == 2)


def test_split_computes_only_used_outputs():
    nodes = [
        helper.make_node("Split", ["x", "split"], ["a", "b", "c"], axis=1, name="split"),
        helper.make_node("Relu", ["b"], ["y"]),
    ]
    m = onnx_model(nodes, inputs={"x": (1, 6, 2)}, initializers={"split": ints(1, 2, 3)})
    split = import_onnx(m).nodes[0]
    assert (split.outputs, split.attrs) == (("b",), SplitAttrs(1, (1,)))
    compile_and_check(m, "ansi-c")


# --- Slice ---------------------------------------------------------------------------------------


def slice_model(x_shape, starts, ends, axes=None, steps=None, opset=13, with_conv=False):
    if opset < 10:
        attrs = dict(starts=starts, ends=ends, **({} if axes is None else {"axes": axes}))
        return one_op("Slice", x_shape, opset=opset, with_conv=with_conv, **attrs)
    params = [("starts", starts), ("ends", ends), ("axes", axes), ("steps", steps)]
    extra = [name if value is not None else "" for name, value in params]
    while extra and not extra[-1]:
        extra.pop()
    inits = {name: ints(*value) for name, value in params if value is not None}
    return one_op("Slice", x_shape, extra, inits, opset, with_conv=with_conv)


SLICE_CASES = {
    "spatial_crop": ((1, 3, 6, 7), [1, 2], [5, -1], [2, 3], None),
    "steps_2": ((1, 4, 7, 8), [0, 1], [7, 8], [2, 3], [2, 3]),
    "negative_steps": ((1, 3, 5, 6), [-1, 4], [INT64_MIN, 0], [3, 2], [-1, -2]),
    "clamped_out_of_range": ((1, 5, 4, 4), [2, -100], [1000, INT64_MAX], [1, 3], None),
    "axes_omitted": ((2, 4, 3), [1, 1, 0], [2, 3, 2], None, None),
    "negative_axes_and_channels": ((1, 8, 3, 3), [1, 2], [7, 3], [-3, -1], [2, 1]),
    "reverse_everything": ((2, 3, 4), [-1, -1, -1], [INT64_MIN] * 3, [0, 1, 2], [-1, -1, -1]),
}


@pytest.mark.parametrize("target", TARGETS)
@pytest.mark.parametrize("case", SLICE_CASES)
@pytest.mark.parametrize("with_conv", [False, True])
def test_slice(case, with_conv, target):
    x_shape, starts, ends, axes, steps = SLICE_CASES[case]
    if with_conv and len(x_shape) != 4:
        pytest.skip("the conv producer needs a 4-D input")
    m = slice_model(x_shape, starts, ends, axes, steps, with_conv=with_conv)
    compile_and_check(m, target, unroll=None if with_conv else 2)


@pytest.mark.parametrize("target", TARGETS)
@pytest.mark.parametrize("axes", [None, [3, 2]])
def test_slice_opset_1_attribute_form(axes, target):
    starts, ends = ([0, 0, 1, -3], [1, 3, 4, 100]) if axes is None else ([-3, 1], [100, 4])
    compile_and_check(slice_model((1, 3, 5, 6), starts, ends, axes, opset=9), target)


def test_slice_under_sanitizers_and_clamping_in_the_ir():
    m = slice_model((1, 3, 5, 6), [-1, 4], [INT64_MIN, 0], [3, 2], [-2, -3], with_conv=True)
    node = import_onnx(m).nodes[1]
    assert node.attrs == SliceAttrs((0, 0, 4, 5), (1, 1, -3, -2))
    for target in TARGETS:
        compile_and_check(m, target, unroll=1, sanitize=True)


# --- Transpose -----------------------------------------------------------------------------------


TRANSPOSE_CASES = {
    "default_reverse": ((2, 3, 4), {}),
    "nchw_to_nhwc": ((1, 3, 4, 5), dict(perm=[0, 2, 3, 1])),
    "nhwc_to_nchw": ((1, 4, 5, 3), dict(perm=[0, 3, 1, 2])),
    "rank_5": ((1, 2, 3, 2, 4), dict(perm=[4, 0, 3, 1, 2])),
}


@pytest.mark.parametrize("target", TARGETS)
@pytest.mark.parametrize("case", TRANSPOSE_CASES)
@pytest.mark.parametrize("unroll", [None, 1])
def test_transpose_graph_input_to_output(case, unroll, target):
    x_shape, attrs = TRANSPOSE_CASES[case]
    compile_and_check(one_op("Transpose", x_shape, **attrs), target, unroll=unroll)


@pytest.mark.parametrize("target", TARGETS)
@pytest.mark.parametrize("perm", [[0, 2, 3, 1], [0, 3, 1, 2], [3, 2, 1, 0]])
def test_internal_transpose_moves_no_data(perm, target):
    """An internal Transpose moves no data: Relu and a second Conv read through the permuted view."""
    conv_a, w_a = conv("x", "c", 3, 4, "conv_a")
    t_shape = tuple((1, 4, 5, 6)[p] for p in perm)
    conv_b, w_b = conv("r", "y", t_shape[1], 5, "conv_b")
    nodes = [conv_a, helper.make_node("Transpose", ["c"], ["t"], perm=perm), helper.make_node("Relu", ["t"], ["r"])]
    compiled = compile_and_check(
        onnx_model([*nodes, conv_b], inputs={"x": (1, 3, 5, 6)}, initializers=w_a | w_b), target, unroll=2
    )
    assert "Transpose" not in kernel_ops(compiled)


@pytest.mark.parametrize("unroll", [None, 2])
def test_transpose_of_conv_output_under_sanitizers(unroll):
    m = one_op("Transpose", (1, 3, 4, 5), with_conv=True, perm=[0, 3, 1, 2])
    for target in TARGETS:
        compile_and_check(m, target, unroll=unroll, sanitize=True)


# --- Pad -----------------------------------------------------------------------------------------


def pad_model(x_shape, pads, mode="constant", value=None, axes=None, opset=13, with_conv=False):
    """Pads as attribute before opset 11, as constant inputs from 11."""
    attrs = {} if mode == "constant" and opset >= 11 else {"mode": mode}
    if opset < 11:
        attrs.update(pads=pads, **({} if value is None else {"value": value}))
        return one_op("Pad", x_shape, opset=opset, with_conv=with_conv, **attrs)
    extra, inits = ["pads"], {"pads": ints(*pads)}
    if value is not None or axes is not None:
        extra.append("" if value is None else "value")
        inits |= {} if value is None else {"value": floats(value)}
    if axes is not None:
        extra.append("axes")
        inits["axes"] = ints(*axes)
    return one_op("Pad", x_shape, extra, inits, opset, with_conv=with_conv, **attrs)


PAD_CASES = {
    "constant_zero": ((1, 3, 4, 5), [0, 0, 1, 2, 0, 0, 2, 1], "constant", None, None, 13),
    "constant_value": ((1, 3, 4, 5), [0, 0, 1, 1, 0, 0, 1, 1], "constant", -1.5, None, 13),
    "constant_channels_and_batch": ((1, 3, 2, 2), [1, 2, 0, 0, 0, 3, 1, 0], "constant", 0.5, None, 13),
    "constant_crop": ((1, 3, 6, 6), [0, 0, -1, 2, 0, 0, 1, -2], "constant", 0.25, None, 13),
    "opset7_attributes": ((1, 2, 4, 4), [0, 0, 2, 1, 0, 0, 0, 3], "constant", 2.0, None, 7),
    "opset7_reflect_attribute": ((1, 2, 4, 5), [0, 0, 1, 2, 0, 0, 3, 2], "reflect", None, None, 7),
    "reflect": ((1, 3, 5, 6), [0, 0, 2, 1, 0, 0, 4, 3], "reflect", None, None, 13),
    "reflect_crop": ((1, 3, 6, 6), [0, 0, -2, 2, 0, 0, 3, -1], "reflect", None, None, 13),
    "edge": ((1, 3, 4, 5), [0, 0, 3, 1, 0, 0, 2, 6], "edge", None, None, 13),
    "edge_crop": ((1, 3, 5, 5), [0, 0, 2, -1, 0, 0, -2, 3], "edge", None, None, 13),
    "wrap": ((1, 2, 4, 5), [0, 0, 4, 2, 0, 0, 3, 5], "wrap", None, None, 19),
    "wrap_crop": ((1, 2, 5, 5), [0, 0, -1, 2, 0, 0, 2, -1], "wrap", None, None, 19),
    "opset18_axes": ((1, 3, 4, 5), [2, 1, 1, 3], "constant", 1.0, [-1, 2], 18),
    "opset18_axes_reflect": ((1, 3, 4, 5), [1, 2], "reflect", None, [3], 18),
    "rank_2_edge": ((3, 4), [1, 2, 2, 1], "edge", None, None, 13),
}


@pytest.mark.parametrize("target", TARGETS)
@pytest.mark.parametrize("case", PAD_CASES)
@pytest.mark.parametrize("with_conv", [False, True])
def test_pad(case, with_conv, target):
    x_shape, pads, mode, value, axes, opset = PAD_CASES[case]
    if with_conv and len(x_shape) != 4:
        pytest.skip("the conv producer needs a 4-D input")
    m = pad_model(x_shape, pads, mode, value, axes, opset, with_conv=with_conv)
    compile_and_check(m, target, unroll=None if with_conv else 1)


@pytest.mark.parametrize("mode", ["constant", "reflect", "edge"])
def test_pad_under_sanitizers(mode):
    m = pad_model((1, 3, 5, 6), [0, 0, 2, 1, 0, 0, 1, 2], mode, with_conv=True)
    for target in TARGETS:
        compile_and_check(m, target, unroll=2, sanitize=True)


def test_pad_attrs_resolve_axes():
    m = pad_model((1, 3, 4, 5), [2, 1, 1, 3], "constant", 1.0, [-1, 2], 18)
    assert import_onnx(m).nodes[0].attrs == PadAttrs((0, 0, 1, 2), (0, 0, 3, 1), "constant", 1.0)


# --- Squeeze, Unsqueeze --------------------------------------------------------------------------


@pytest.mark.parametrize("target", TARGETS)
@pytest.mark.parametrize("opset", [11, 13])
@pytest.mark.parametrize("op", ["Squeeze", "Unsqueeze"])
@pytest.mark.parametrize("with_conv", [False, True])
def test_squeeze_unsqueeze_attribute_and_input_forms(op, opset, with_conv, target):
    axes = [0] if op == "Squeeze" else [0, -1]
    if opset >= 13:
        m = one_op(op, (1, 3, 4, 5), ["axes"], {"axes": ints(*axes)}, opset, with_conv=with_conv)
    else:
        m = one_op(op, (1, 3, 4, 5), opset=opset, with_conv=with_conv, axes=axes)
    compile_and_check(m, target, unroll=2)


@pytest.mark.parametrize("target", TARGETS)
def test_squeeze_opset_13_without_axes_drops_every_unit_dim(target):
    m = one_op("Squeeze", (1, 3, 1, 5), opset=13, with_conv=True)
    assert import_onnx(m).shapes["t"] == (6, 5)
    compile_and_check(m, target, unroll=None)


# --- Resize, Upsample ----------------------------------------------------------------------------


def resize_model(x_shape, opset=13, scales=None, sizes=None, with_conv=False, **attrs):
    """Resize with constant scales or sizes; opset 10 has inputs (X, scales), 11 needs roi and an
    empty scales next to sizes, 13 leaves unused inputs out."""
    if opset == 10:
        return one_op("Resize", x_shape, ["scales"], {"scales": floats(*scales)}, 10, with_conv, **attrs)
    inits = {"scales": floats(*scales)} if scales is not None else {}
    extra = ["roi" if opset < 13 else "", "scales" if scales is not None else ""]
    if opset < 13:
        inits["roi"] = np.zeros(0, np.float32)
        if scales is None:
            extra[1] = "scales"
            inits["scales"] = np.zeros(0, np.float32)
    if sizes is not None:
        extra.append("sizes")
        inits["sizes"] = ints(*sizes)
    return one_op("Resize", x_shape, extra, inits, opset, with_conv, **attrs)


NEAREST_CASES = {
    "x2_asymmetric_floor": (dict(scales=[1, 1, 2, 2]), "asymmetric", "floor"),
    "x2_half_pixel_round_prefer_floor": (dict(scales=[1, 1, 2, 2]), "half_pixel", "round_prefer_floor"),
    "x3_half_pixel_round_prefer_ceil": (dict(scales=[1, 1, 3, 3]), "half_pixel", "round_prefer_ceil"),
    "sizes_asymmetric_round_prefer_ceil": (dict(sizes=[1, 3, 9, 7]), "asymmetric", "round_prefer_ceil"),
    "sizes_align_corners_ceil": (dict(sizes=[1, 3, 7, 11]), "align_corners", "ceil"),
    "x1.5_pytorch_half_pixel_floor": (dict(scales=[1, 1, 1.5, 1.5]), "pytorch_half_pixel", "floor"),
    "down_half_pixel_round_prefer_floor": (dict(scales=[1, 1, 0.5, 0.6]), "half_pixel", "round_prefer_floor"),
    "down_sizes_asymmetric_ceil": (dict(sizes=[1, 3, 3, 2]), "asymmetric", "ceil"),
    "tf_half_pixel_for_nn": (dict(scales=[1, 1, 2, 3]), "tf_half_pixel_for_nn", "round_prefer_floor"),
    "channels_and_width": (dict(scales=[1, 2, 1, 2]), "asymmetric", "floor"),
}


@pytest.mark.parametrize("target", TARGETS)
@pytest.mark.parametrize("case", NEAREST_CASES)
@pytest.mark.parametrize("with_conv", [False, True])
def test_resize_nearest(case, with_conv, target):
    size, coordinates, nearest = NEAREST_CASES[case]
    attrs = dict(mode="nearest", coordinate_transformation_mode=coordinates, nearest_mode=nearest)
    if with_conv:
        size = _channels(size, 6)
    m = resize_model((1, 3, 5, 6), opset=13, with_conv=with_conv, **size, **attrs)
    compile_and_check(m, target, unroll=None if with_conv else 2)


LINEAR_CASES = {
    "x2_half_pixel": (dict(scales=[1, 1, 2, 2]), "half_pixel"),
    "x2_asymmetric": (dict(scales=[1, 1, 2, 2]), "asymmetric"),
    "sizes_align_corners": (dict(sizes=[1, 3, 9, 11]), "align_corners"),
    "x2.5_pytorch_half_pixel": (dict(scales=[1, 1, 2.5, 1.5]), "pytorch_half_pixel"),
    "sizes_pytorch_half_pixel_to_1": (dict(sizes=[1, 3, 1, 4]), "pytorch_half_pixel"),
    "down_half_pixel": (dict(scales=[1, 1, 0.5, 0.75]), "half_pixel"),
    "down_align_corners": (dict(sizes=[1, 3, 3, 4]), "align_corners"),
    "half_pixel_symmetric": (dict(scales=[1, 1, 1.7, 2.3]), "half_pixel_symmetric"),
}


@pytest.mark.parametrize("target", TARGETS)
@pytest.mark.parametrize("case", LINEAR_CASES)
@pytest.mark.parametrize("with_conv", [False, True])
def test_resize_linear(case, with_conv, target):
    size, coordinates = LINEAR_CASES[case]
    opset = 19 if coordinates == "half_pixel_symmetric" else 13
    attrs = dict(mode="linear", coordinate_transformation_mode=coordinates)
    if with_conv:
        size = _channels(size, 6)
    m = resize_model((1, 3, 5, 6), opset=opset, with_conv=with_conv, **size, **attrs)
    compile_and_check(m, target, unroll=1 if with_conv else None)


def _channels(size: dict, channels: int) -> dict:
    """The same resize after a conv with `channels` output channels (sizes name the channel count)."""
    if "sizes" not in size:
        return size
    return {"sizes": [size["sizes"][0], channels, *size["sizes"][2:]]}


@pytest.mark.parametrize("target", TARGETS)
@pytest.mark.parametrize(
    ("opset", "mode", "size"),
    [
        (10, "nearest", dict(scales=[1, 1, 2, 3])),
        (10, "linear", dict(scales=[1, 1, 2, 2])),
        (10, "nearest", dict(scales=[1, 1, 0.5, 0.7])),
        (11, "nearest", dict(sizes=[1, 3, 10, 9])),
        (11, "linear", dict(scales=[1, 1, 1.5, 2])),
    ],
)
def test_resize_opset_10_and_11_forms(opset, mode, size, target):
    compile_and_check(resize_model((1, 3, 5, 6), opset=opset, mode=mode, **size), target, unroll=2)


@pytest.mark.parametrize("target", TARGETS)
@pytest.mark.parametrize("mode", ["nearest", "linear"])
def test_resize_opset_18_axes(mode, target):
    m = resize_model((1, 3, 4, 5), opset=18, sizes=[9, 7], axes=[3, 2], mode=mode)
    assert import_onnx(m).shapes["y"] == (1, 3, 7, 9)
    compile_and_check(m, target, unroll=2)


def test_resize_nearest_integer_scale_is_a_loop_over_periods():
    """x2 asymmetric floor: one store per (row, column) residue inside block loops, not one per
    output position; the channel loop inside stays plain (it vectorises)."""
    m = resize_model(
        (1, 4, 16, 16),
        scales=[1, 1, 2, 2],
        with_conv=True,
        mode="nearest",
        coordinate_transformation_mode="asymmetric",
        nearest_mode="floor",
    )
    program = PassManager("lower").run(import_onnx(m))
    (kernel,) = [k for k in program.kernels if k.op == "Resize"]
    assert len([s for s in walk_stmts(kernel.body) if isinstance(s, Store)]) == 4
    compile_and_check(m, "ssse3", unroll=None)


@pytest.mark.parametrize("target", TARGETS)
@pytest.mark.parametrize("nearest", ["ceil", "round_prefer_ceil"])
@pytest.mark.parametrize("sizes", [[1, 2, 3, 3], [1, 2, 3, 2], [2, 2, 3, 3]])
def test_resize_tf_half_pixel_for_nn_keeps_the_dims_it_does_not_resize(sizes, nearest, target):
    """(o + 0.5) / 1 rounds up to o + 1: a dim of scale 1 (channels, batch) must still map onto
    itself, as onnxruntime does, not read the next channel."""
    m = resize_model(
        (sizes[0], 2, 2, 2),
        sizes=sizes,
        mode="nearest",
        coordinate_transformation_mode="tf_half_pixel_for_nn",
        nearest_mode=nearest,
    )
    compile_and_check(m, target, unroll=None)


def odd_ratio_resize(mode, with_conv=False, **attrs):
    """60x80 -> 97x131: no period shorter than the dims themselves."""
    return resize_model(
        (1, 3, 60, 80), sizes=[1, 6 if with_conv else 3, 97, 131], with_conv=with_conv, mode=mode, **attrs
    )


@pytest.mark.parametrize("target", TARGETS)
@pytest.mark.parametrize("with_conv", [False, True])
def test_resize_odd_ratio_is_small_code_with_loops(with_conv, target):
    """Periodic coordinates with weight tables, one dim at a time: with --unroll none the C stays
    small (one statement per position would be 2.25 MB); the unroll pass still decides the rest."""
    m = odd_ratio_resize("linear", with_conv)
    compiled = compile_and_check(m, target, unroll=None)
    assert len(compiled.source) < 50_000
    assert kernel_ops(compiled).count("Resize") == 2
    compile_and_check(m, target, unroll="auto")


@pytest.mark.parametrize("target", TARGETS)
@pytest.mark.parametrize(
    "attrs",
    [
        dict(mode="nearest", coordinate_transformation_mode="asymmetric", nearest_mode="floor"),
        dict(mode="nearest", coordinate_transformation_mode="half_pixel", nearest_mode="round_prefer_ceil"),
        dict(mode="linear", coordinate_transformation_mode="align_corners"),
        dict(mode="linear", coordinate_transformation_mode="pytorch_half_pixel"),
    ],
)
def test_resize_odd_ratio_modes(attrs, target):
    compiled = compile_and_check(odd_ratio_resize(**attrs), target, unroll=None)
    assert len(compiled.source) < 50_000


def test_resize_odd_ratios_shrinking_and_growing_under_sanitizers():
    """Windows must never read outside the input: 37x29 -> 23x61 (shrinks one dim, grows the other)."""
    m = resize_model((1, 3, 37, 29), sizes=[1, 6, 23, 61], with_conv=True, mode="linear")
    for target in TARGETS:
        for unroll in (None, "auto"):
            compile_and_check(m, target, unroll=unroll, sanitize=True)


def test_resize_to_one_pixel_reading_pixel_zero_still_shrinks_the_dim():
    """3 -> 1 columns where the one output reads input column 0: the taps look like an identity, but
    the dim shrinks (fuzz-found: rows of 3 were stored into a 146x1 output, caught by the IR's bounds
    check)."""
    m = resize_model((1, 1, 49, 3), sizes=[1, 1, 146, 1], mode="nearest", coordinate_transformation_mode="asymmetric")
    for target in TARGETS:
        compile_and_check(m, target, unroll=None, sanitize=target == "ansi-c")


@pytest.mark.parametrize("unroll", [None, 0])
def test_resize_under_sanitizers(unroll):
    m = resize_model((1, 3, 4, 5), scales=[1, 1, 2.5, 1.5], with_conv=True, mode="linear")
    for target in TARGETS:
        compile_and_check(m, target, unroll=unroll, sanitize=True)


@pytest.mark.parametrize("target", TARGETS)
@pytest.mark.parametrize("opset", [7, 9])
@pytest.mark.parametrize("mode", ["nearest", "linear"])
@pytest.mark.parametrize("with_conv", [False, True])
def test_upsample(opset, mode, with_conv, target):
    scales = [1.0, 1.0, 2.0, 3.0] if mode == "nearest" else [1.0, 1.0, 2.0, 2.0]
    if opset == 7:
        m = one_op("Upsample", (1, 3, 4, 5), opset=7, with_conv=with_conv, mode=mode, scales=scales)
    else:
        m = one_op("Upsample", (1, 3, 4, 5), ["s"], {"s": floats(*scales)}, 9, with_conv, mode=mode)
    (node,) = [n for n in import_onnx(m).nodes if n.op == "Resize"]
    nearest = "simple" if mode == "nearest" else "round_prefer_floor"
    assert node.attrs == ResizeAttrs(tuple(scales), mode, "asymmetric", nearest)
    compile_and_check(m, target, unroll=2)


# --- constant folding of shape arithmetic --------------------------------------------------------


@pytest.mark.parametrize("target", TARGETS)
def test_shape_gather_cast_concat_reshape_folds_to_a_constant_shape(target):
    """The usual flatten-before-classifier chain: Shape -> Gather -> Cast -> Concat -> Reshape
    leaves only the Conv and a Reshape with a static shape."""
    conv_node, weight = conv("x", "c", 2, 4, "conv")
    nodes = [
        conv_node,
        helper.make_node("Shape", ["c"], ["s"]),
        helper.make_node("Gather", ["s", "zero"], ["n"], axis=0),
        helper.make_node("Cast", ["n"], ["nf"], to=TensorProto.FLOAT),
        helper.make_node("Unsqueeze", ["nf", "axes"], ["n1"]),
        helper.make_node("Concat", ["n1", "minus1"], ["target_f"], axis=0),
        helper.make_node("Cast", ["target_f"], ["target"], to=TensorProto.INT64),
        helper.make_node("Reshape", ["c", "target"], ["y"], name="flatten"),
    ]
    inits = {**weight, "zero": np.array(0, np.int64), "axes": ints(0), "minus1": floats(-1)}
    m = onnx_model(nodes, inputs={"x": (2, 2, 3, 4)}, initializers=inits)
    graph = import_onnx(m)
    assert [n.op for n in graph.nodes] == ["Conv", "Reshape"]
    assert graph.nodes[1].attrs.shape == (2, 48)
    compile_and_check(m, target)


# --- errors --------------------------------------------------------------------------------------


def fails(m, *fragments):
    with pytest.raises(NncgError) as info:
        import_onnx(m)
    message = str(info.value)
    assert "\n" not in message
    for fragment in fragments:
        assert fragment in message, message


def test_resize_runtime_scales_are_refused():
    node = helper.make_node("Resize", ["x", "", "s"], ["y"])
    graph = helper.make_graph(
        [node],
        "g",
        [
            helper.make_tensor_value_info("x", TensorProto.FLOAT, (1, 1, 2, 2)),
            helper.make_tensor_value_info("s", TensorProto.FLOAT, (4,)),
        ],
        [helper.make_tensor_value_info("y", TensorProto.FLOAT, None)],
    )
    m = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 13)])
    with pytest.raises(NncgError, match="scales 's' computed at runtime"):
        import_onnx(m)


def refused(node, x_shape, *fragments, constants=(), opset=13):
    """The converter itself refuses `node` (on input x) with a message naming every fragment; ONNX
    shape inference catches some of these before, so the converter is called directly."""
    ctx = Context(opset, {n: np.asarray(a) for n, a in constants}, {"x": x_shape}, {"y"}, set())
    with pytest.raises(NncgError) as info:
        CONVERTERS[node.op_type](OnnxOp.of(node, "op"), ctx)
    for fragment in fragments:
        assert fragment in str(info.value), str(info.value)


def test_pad_errors():
    fails(pad_model((1, 1, 3, 3), [0, 0, 3, 0, 0, 0, 0, 0], "reflect"), "in reflect mode", "at most 2")
    pad = helper.make_node("Pad", ["x", "p"], ["y"])
    symmetric = helper.make_node("Pad", ["x", "p"], ["y"], mode="symmetric")
    refused(symmetric, (1, 1, 3, 3), "'symmetric'", constants=[("p", ints(0, 0, 0, 0, 0, 0, 0, 0))])
    refused(pad, (1, 1, 3, 3), "empty", constants=[("p", ints(0, 0, -2, 0, 0, 0, -1, 0))])
    refused(pad, (1, 1, 3, 3), "integers", constants=[("p", floats(1, 1))])


def test_slice_split_concat_transpose_errors():
    slice_ = helper.make_node("Slice", ["x", "s", "e", "a", "st"], ["y"])
    bounds = [("s", ints(0)), ("e", ints(3)), ("a", ints(1))]
    refused(slice_, (1, 3, 4), "step 0", constants=[*bounds, ("st", ints(0))])
    refused(slice_, (1, 3, 4), "selects nothing", constants=[*bounds[1:], ("s", ints(3)), ("st", ints(1))])
    refused(helper.make_node("Split", ["x"], ["y", "z"], axis=1), (1, 5, 2), "equal outputs")
    refused(helper.make_node("Split", ["x"], ["y", "z"], split=[1, 2]), (4, 2), "split [1, 2]", opset=11)
    concat = helper.make_node("Concat", ["x", "k"], ["y"], axis=1)
    refused(concat, (1, 2, 3), "differ outside axis 1", constants=[("k", np.zeros((1, 3, 4), np.float32))])
    refused(helper.make_node("Transpose", ["x"], ["y"], perm=[0, 1]), (1, 2, 3), "not a permutation")


# --- Resize's compile-time index tables ----------------------------------------------------------


@pytest.mark.parametrize("mode", ["nearest", "linear"])
@pytest.mark.parametrize("coordinates", ["half_pixel", "asymmetric", "align_corners", "pytorch_half_pixel"])
def test_resize_windowed_pieces_reproduce_every_output_coordinate(mode, coordinates):
    """Windows at periodic coordinates with tabled weights stand for exactly the taps of every
    output coordinate (zero weights where a window is wider), and stay inside the input."""
    for n_in, n_out in [(60, 97), (80, 131), (131, 80), (7, 100), (100, 7), (33, 34), (1000, 1617), (5, 12)]:
        attrs = ResizeAttrs((n_out / n_in,), mode, coordinates)
        taps = dim_taps(attrs, 0, n_in, n_out)
        pieces, weights = windowed_pieces(taps, n_in)
        rebuilt = {}
        for piece in pieces:
            for b, (r, residue) in itertools.product(range(piece.blocks), enumerate(piece.taps)):
                if piece.table is None:
                    reads = {c + piece.step * b: w for c, w in residue}
                else:
                    reads = {c + piece.step * b: weights[b * piece.table_step + k] for c, k in residue}
                assert all(0 <= c < n_in for c in reads)
                rebuilt[piece.start + piece.period * b + r] = {c: w for c, w in reads.items() if w}
        assert sorted(rebuilt) == list(range(n_out))
        for o, expected in enumerate(taps):
            assert sorted(rebuilt[o]) == sorted(c for c, _ in expected)
            np.testing.assert_array_equal([rebuilt[o][c] for c, _ in expected], [np.float32(w) for _, w in expected])


@pytest.mark.parametrize("mode", ["nearest", "linear"])
@pytest.mark.parametrize("coordinates", ["half_pixel", "asymmetric", "align_corners", "pytorch_half_pixel"])
def test_resize_pieces_reproduce_every_output_coordinate(mode, coordinates):
    """The periodic pieces stand for exactly the taps computed one output coordinate at a time."""
    for n_in, n_out in [(1, 3), (3, 1), (4, 8), (5, 12), (7, 3), (8, 5), (6, 6), (13, 40), (40, 13)]:
        attrs = ResizeAttrs((n_out / n_in,), mode, coordinates)
        taps = dim_taps(attrs, 0, n_in, n_out)
        rebuilt = {}
        for piece in periodic_pieces(taps):
            for b in range(piece.blocks):
                for r, residue in enumerate(piece.taps):
                    rebuilt[piece.start + piece.period * b + r] = [(c + piece.step * b, w) for c, w in residue]
        assert sorted(rebuilt) == list(range(n_out))
        for o, expected in enumerate(taps):
            assert [c for c, _ in rebuilt[o]] == [c for c, _ in expected]
            np.testing.assert_allclose([w for _, w in rebuilt[o]], [w for _, w in expected], atol=1e-6)


@pytest.mark.parametrize("mode", ["nearest", "linear"])
def test_resize_coordinates_match_onnxruntime_on_a_grid_of_sizes(mode):
    """Every input index (nearest) or weighted sum (linear) for 1..12 -> 1..12 pixels, given as sizes
    or as a float scale, in every coordinate and nearest mode: near-ties (7 -> 4 asymmetric hits 3.5
    exactly, 3.4999998 in float32) and sizes that do not change (scale 1.013 on 10 pixels) included."""
    rng = np.random.default_rng(0)
    options = ort.SessionOptions()
    options.log_severity_level = 3
    nearest_modes = ["round_prefer_floor", "round_prefer_ceil", "floor", "ceil"] if mode == "nearest" else [None]
    for coords, nearest, n, m, given_scale in itertools.product(
        ["asymmetric", "half_pixel", "pytorch_half_pixel", "align_corners", "half_pixel_symmetric",
         "tf_half_pixel_for_nn"], nearest_modes, range(1, 13), range(1, 13), (False, True),
    ):  # fmt: skip
        if mode == "linear" and coords == "tf_half_pixel_for_nn":
            continue
        scale = float(np.float32(m / n + 0.013 * ((n * m) % 3))) if given_scale else None
        out = int(np.floor(np.float32(scale) * np.float32(n))) if given_scale else m
        if out < 1:
            continue
        x = rng.standard_normal(n).astype(np.float32)
        extra = {"nearest_mode": nearest} if nearest else {}
        node = helper.make_node("Resize", ["x", "", *(["s"] if given_scale else ["", "s"])], ["y"], mode=mode,
                                coordinate_transformation_mode=coords, **extra)  # fmt: skip
        s = helper.make_tensor("s", *((TensorProto.FLOAT, [3], [1, 1, scale]) if given_scale else
                                      (TensorProto.INT64, [3], [1, 1, out])))  # fmt: skip
        graph = helper.make_graph([node], "g", [helper.make_tensor_value_info("x", TensorProto.FLOAT, [1, 1, n])],
                                  [helper.make_tensor_value_info("y", TensorProto.FLOAT, None)], [s])  # fmt: skip
        session = ort.InferenceSession(
            helper.make_model(graph, opset_imports=[helper.make_opsetid("", 19)]).SerializeToString(), options
        )
        expected = session.run(None, {"x": x.reshape(1, 1, n)})[0].ravel()
        used = np.float32(scale) if given_scale else np.float32(out) / np.float32(n)
        attrs = ResizeAttrs((1.0, 1.0, float(used)), mode, coords, nearest or "round_prefer_floor")
        dim = resize_taps(attrs, (1, 1, n), (1, 1, out))[2]
        got = np.array([sum(w * x[i] for i, w in taps) for taps in dim], dtype=np.float32)
        assert np.abs(got - expected).max() <= 1e-6, (coords, nearest, n, out, scale, got, expected)


@pytest.mark.parametrize(
    "n, scale, coords, nearest",
    [
        (7, 1.3, "pytorch_half_pixel", "round_prefer_floor"),  # 6.5 / 1.3f - 0.5 is a tie in float32
        (9, 1.2, "asymmetric", "round_prefer_ceil"),  # 9 / 1.2f = 7.4999995: a tie 1 ulp below
        (16, 1.3, "half_pixel", "round_prefer_floor"),  # 19.5 / 1.3f - 0.5 = 14.500001: 1 ulp above
        (14, 1.2, "asymmetric", "round_prefer_ceil"),
    ],
)
def test_resize_near_ties_break_as_onnxruntime(n, scale, coords, nearest):
    options = ort.SessionOptions()
    options.log_severity_level = 3
    node = helper.make_node("Resize", ["x", "", "s"], ["y"], mode="nearest", coordinate_transformation_mode=coords,
                            nearest_mode=nearest)  # fmt: skip
    graph = helper.make_graph([node], "g", [helper.make_tensor_value_info("x", TensorProto.FLOAT, [1, 1, n])],
                              [helper.make_tensor_value_info("y", TensorProto.FLOAT, None)],
                              [helper.make_tensor("s", TensorProto.FLOAT, [3], [1, 1, scale])])  # fmt: skip
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 13)])
    x = np.arange(n, dtype=np.float32).reshape(1, 1, n)
    expected = ort.InferenceSession(model.SerializeToString(), options).run(None, {"x": x})[0].ravel()
    out = len(expected)
    attrs = ResizeAttrs((1.0, 1.0, float(np.float32(scale))), "nearest", coords, nearest)
    assert [taps[0][0] for taps in resize_taps(attrs, (1, 1, n), (1, 1, out))[2]] == expected.astype(int).tolist()


def test_resize_copies_only_when_the_whole_shape_stays():
    """onnxruntime copies a Resize whose output shape is its input's (scale 1.3 on 3 pixels), but
    resizes that dim by its scale when another dim changes size (3 -> 3 reads rows 0, 1, 1)."""
    coords = {"coordinate_transformation_mode": "half_pixel"}
    resize = helper.make_node("Resize", ["x", "", "s"], ["y"], mode="nearest", **coords)
    model_proto = onnx_model([resize], inputs={"x": (1, 2, 3, 2)}, initializers={"s": floats(1, 1, 1.3, 1.5)})
    check_against_onnxruntime(model_proto, nncg.compile(model_proto, "ssse3"))
    same_node = helper.make_node("Resize", ["x", "", "s"], ["y"], mode="nearest")
    same = onnx_model([same_node], inputs={"x": (1, 2, 3, 2)}, initializers={"s": floats(1, 1, 1.3, 1.2)})
    check_against_onnxruntime(same, nncg.compile(same, "ansi-c"))
