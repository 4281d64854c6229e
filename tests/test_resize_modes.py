"""Resize beyond nearest and linear: cubic (cubic_coeff_a, exclude_outside), antialiased linear and
cubic, tf_crop_and_resize with its roi and extrapolation value, keep_aspect_ratio_policy; each
compiled for every target and compared with onnxruntime, after a Conv too (channels-last input)."""

import numpy as np
import pytest
from helpers import compile_and_check, kernel_ops
from test_ops import TARGETS
from test_ops_data import fails, one_op, resize_model

from nncg.frontend.importer import import_onnx


def roi_resize_model(x_shape, roi, sizes, axes=None, with_conv=False, **attrs):
    """Resize with a constant roi and sizes (opset 18, for axes)."""
    inits = {"roi": np.array(roi, np.float32), "sizes": np.array(sizes, np.int64)}
    extra_attrs = {} if axes is None else {"axes": axes}
    return one_op("Resize", x_shape, ["roi", "", "sizes"], inits, 18, with_conv, **attrs, **extra_attrs)


CUBIC_CASES = {
    "x2_half_pixel": (dict(scales=[1, 1, 2, 2]), dict(coordinate_transformation_mode="half_pixel")),
    "sizes_align_corners": (dict(sizes=[1, 3, 9, 11]), dict(coordinate_transformation_mode="align_corners")),
    "asymmetric_a_-0.5": (
        dict(scales=[1, 1, 1.5, 2.5]),
        dict(coordinate_transformation_mode="asymmetric", cubic_coeff_a=-0.5),
    ),
    "pytorch_half_pixel_down": (
        dict(scales=[1, 1, 0.6, 0.5]),
        dict(coordinate_transformation_mode="pytorch_half_pixel"),
    ),
    "exclude_outside": (dict(sizes=[1, 3, 8, 3]), dict(exclude_outside=1, cubic_coeff_a=-0.5)),
    "odd_ratio": (dict(sizes=[1, 3, 13, 17]), {}),
}


@pytest.mark.parametrize("target", TARGETS)
@pytest.mark.parametrize("case", CUBIC_CASES)
@pytest.mark.parametrize("with_conv", [False, True])
def test_resize_cubic(case, with_conv, target):
    size, attrs = CUBIC_CASES[case]
    if with_conv and "sizes" in size:
        size = dict(sizes=[1, 6, *size["sizes"][2:]])
    m = resize_model((1, 3, 5, 6), opset=13, with_conv=with_conv, mode="cubic", **size, **attrs)
    compile_and_check(m, target, unroll=None)


ANTIALIAS_CASES = {
    "linear_down": (dict(sizes=[1, 3, 4, 5]), dict(mode="linear")),
    "linear_down_exclude_outside": (dict(scales=[1, 1, 0.6, 0.35]), dict(mode="linear", exclude_outside=1)),
    "cubic_down": (dict(sizes=[1, 3, 6, 3]), dict(mode="cubic")),
    "cubic_up_and_down": (
        dict(sizes=[1, 3, 17, 4]),
        dict(mode="cubic", coordinate_transformation_mode="align_corners"),
    ),
}


@pytest.mark.parametrize("target", TARGETS)
@pytest.mark.parametrize("case", ANTIALIAS_CASES)
def test_resize_antialias(case, target):
    """A shrinking dim reads every input pixel under the stretched kernel: 13 -> 5 is 6 taps of linear."""
    size, attrs = ANTIALIAS_CASES[case]
    compile_and_check(resize_model((1, 3, 11, 13), opset=18, antialias=1, **size, **attrs), target, unroll=None)


# Dims of scale 1 keep their pixels whatever the roi says, as in onnxruntime (onnx's reference crops them).
TF_CROP_CASES = {
    "linear_inside": (dict(roi=[0, 0, 0.2, 0.1, 1, 1, 0.8, 0.9], sizes=[1, 3, 5, 7]), dict(mode="linear")),
    "linear_extrapolated": (
        dict(roi=[0, 0, -0.2, 0.1, 1, 1, 0.9, 1.4], sizes=[1, 3, 6, 5]),
        dict(mode="linear", extrapolation_value=2.5),
    ),
    "nearest_extrapolated": (dict(roi=[-0.3, 1.2, 0.0, 0.9], sizes=[4, 3], axes=[2, 3]), dict(mode="nearest")),
    "cubic_one_row": (dict(roi=[0.1, 0.2, 0.7, 0.9], sizes=[1, 6], axes=[2, 3]), dict(mode="cubic")),
}


@pytest.mark.parametrize("target", TARGETS)
@pytest.mark.parametrize("case", TF_CROP_CASES)
@pytest.mark.parametrize("with_conv", [False, True])
def test_resize_tf_crop_and_resize(case, with_conv, target):
    params, attrs = TF_CROP_CASES[case]
    if with_conv and "axes" not in params:
        params = dict(params, sizes=[1, 6, *params["sizes"][2:]])
    m = roi_resize_model(
        (1, 3, 5, 6), with_conv=with_conv, coordinate_transformation_mode="tf_crop_and_resize", **params, **attrs
    )
    compile_and_check(m, target, unroll=None)


@pytest.mark.parametrize("target", TARGETS)
@pytest.mark.parametrize("policy", ["not_larger", "not_smaller"])
@pytest.mark.parametrize("mode", ["nearest", "linear", "cubic"])
def test_resize_keep_aspect_ratio(policy, mode, target):
    """5x6 into 8x15: not_larger scales both by 1.6 (8x10), not_smaller by 2.5 (13x15)."""
    m = resize_model((1, 3, 5, 6), opset=18, sizes=[8, 15], axes=[2, 3], mode=mode, keep_aspect_ratio_policy=policy)
    expected = {"not_larger": (1, 3, 8, 10), "not_smaller": (1, 3, 13, 15)}[policy]
    assert import_onnx(m).shapes["y"] == expected
    compile_and_check(m, target, unroll=None)


def test_resize_extrapolated_rows_are_constants_not_loads():
    """Rows tf_crop_and_resize puts outside the input store the extrapolation value itself."""
    attrs = dict(mode="linear", extrapolation_value=7.5, coordinate_transformation_mode="tf_crop_and_resize")
    m = roi_resize_model((1, 1, 4, 4), [-1.0, 0.0, 0.5, 1.0], [3, 4], axes=[2, 3], **attrs)
    compiled = compile_and_check(m, "ansi-c", unroll=0)
    assert kernel_ops(compiled) == ["Resize"]
    assert "7.5f" in compiled.source


def test_resize_refusals():
    fails(resize_model((1, 1, 4, 4), opset=18, scales=[1, 1, 0.5, 0.5], antialias=1), "antialias", "linear and cubic")
    fails(resize_model((1, 1, 4, 4), opset=10, scales=[1, 1, 2, 2], mode="cubic"), "mode 'cubic'", "nearest, linear")
    fails(
        roi_resize_model((1, 1, 4, 4), [0.0, 1.0], [1, 1, 3, 3], coordinate_transformation_mode="tf_crop_and_resize"),
        "roi of 2 values",
        "needs 8 floats",
    )
