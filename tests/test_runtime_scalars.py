"""Operator parameters that exported models feed as graph inputs and NNCG reads at run time: Clip's
min and max (a Max and a Min with the scalar, either or both at run time, the other constant) and
Pad's constant_value; each compiled for every target and compared with onnxruntime, after a Conv
too (channels-last input), and the C function takes the scalars as parameters."""

import numpy as np
import pytest
from helpers import compile_and_check, kernel_ops, onnx_model, weights
from onnx import helper
from test_ops import TARGETS
from test_ops_data import fails

BOUNDS = {"runtime_both": ("in", "in"), "runtime_min": ("in", None), "runtime_max": (None, "in"),
          "runtime_min_constant_max": ("in", "const"), "constant_min_runtime_max": ("const", "in")}  # fmt: skip


def clip_model(low, high, with_conv=False):
    """Clip(x, lo, hi) with each bound a graph input ("in"), an initializer ("const") or left out."""
    inputs, inits, names = {"x": (1, 3, 4, 5)}, {}, []
    for kind, name, value in ((low, "lo", -0.3), (high, "hi", 0.4)):
        names.append(name if kind else "")
        if kind == "in":
            inputs[name] = ()
        elif kind == "const":
            inits[name] = np.float32(value)
    if not with_conv:
        return onnx_model([helper.make_node("Clip", ["x", *names], ["y"])], inputs=inputs, initializers=inits)
    conv = helper.make_node("Conv", ["x", "w"], ["c"], pads=[1, 1, 1, 1])
    nodes = [conv, helper.make_node("Clip", ["c", *names], ["t"]), helper.make_node("Relu", ["t"], ["y"])]
    return onnx_model(nodes, inputs=inputs, initializers={**inits, "w": weights(6, 3, 3, 3)})


@pytest.mark.parametrize("target", TARGETS)
@pytest.mark.parametrize("case", BOUNDS)
@pytest.mark.parametrize("with_conv", [False, True])
def test_clip_with_runtime_bounds(case, with_conv, target):
    compiled = compile_and_check(clip_model(*BOUNDS[case], with_conv=with_conv), target, unroll=None)
    assert "Clip" not in kernel_ops(compiled) or "const" in BOUNDS[case]


def test_clip_bounds_are_parameters_of_the_c_function():
    compiled = compile_and_check(clip_model("in", "in"), "ansi-c")
    assert "const float *lo, const float *hi, float *y" in compiled.header


def pad_model(value_shape=(), with_conv=False):
    inputs = {"x": (1, 3, 4, 5), "v": value_shape}
    inits = {"pads": np.array([0, 0, 1, 2, 0, 0, 2, 1], np.int64)}
    if not with_conv:
        return onnx_model([helper.make_node("Pad", ["x", "pads", "v"], ["y"])], inputs=inputs, initializers=inits)
    conv = helper.make_node("Conv", ["x", "w"], ["c"], pads=[1, 1, 1, 1])
    nodes = [conv, helper.make_node("Pad", ["c", "pads", "v"], ["t"]), helper.make_node("Relu", ["t"], ["y"])]
    return onnx_model(nodes, inputs=inputs, initializers={**inits, "w": weights(6, 3, 3, 3)})


@pytest.mark.parametrize("target", TARGETS)
@pytest.mark.parametrize("value_shape", [(), (1,)])
@pytest.mark.parametrize("with_conv", [False, True])
def test_pad_with_runtime_constant_value(value_shape, with_conv, target):
    compile_and_check(pad_model(value_shape, with_conv), target, unroll=None)


def test_runtime_parameters_must_be_scalars():
    fails(_clip_with_vector_bound(), "min or max of shape [3]", "scalars")
    fails(pad_model((2,)), "constant_value of shape [2]", "one float")


def _clip_with_vector_bound():
    node = helper.make_node("Clip", ["x", "lo"], ["y"])
    return onnx_model([node], inputs={"x": (1, 3, 4, 5), "lo": (3,)})
