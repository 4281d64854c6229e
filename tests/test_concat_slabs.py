"""Zero-copy Concat: producers write their slab of the Concat output in place (nncg/lowering/slabs.py);
every case against onnxruntime on every host target."""

import pytest
from helpers import check_against_onnxruntime, onnx_model, weights
from onnx import helper

import nncg

TARGETS = ("ansi-c", "ssse3", "avx2", "avx512")


def fire(x_shape=(1, 8, 6, 7), extra=None, twice=False):
    """squeezenet's fire module: squeeze 1x1, expand 1x1 and 3x3 concatenated, a 3x3 conv after."""
    c = x_shape[1]
    nodes = [
        helper.make_node("Conv", ["x", "ws", "bs"], ["s"]),
        helper.make_node("Relu", ["s"], ["sr"]),
        helper.make_node("Conv", ["sr", "we1", "be1"], ["e1"]),
        helper.make_node("Relu", ["e1"], ["e1r"]),
        helper.make_node("Conv", ["sr", "we3", "be3"], ["e3"], pads=[1, 1, 1, 1]),
        helper.make_node("Relu", ["e3"], ["e3r"]),
    ]
    inputs = ["e1r", "e3r", *([extra] if extra else []), *(["e1r"] if twice else [])]
    nodes.append(helper.make_node("Concat", inputs, ["cat"], axis=1))
    cat_channels = 12 + 16 + (c if extra == "x" else 0) + (12 if twice else 0)
    nodes.append(helper.make_node("Conv", ["cat", "wo"], ["y"], pads=[1, 1, 1, 1]))
    inits = {
        "ws": weights(4, c, 1, 1), "bs": weights(4), "we1": weights(12, 4, 1, 1), "be1": weights(12),
        "we3": weights(16, 4, 3, 3), "be3": weights(16), "wo": weights(8, cat_channels, 3, 3),
    }  # fmt: skip
    return onnx_model(nodes, inputs={"x": x_shape}, initializers=inits)


def concat_kernels(compiled) -> int:
    return compiled.source.count(": Concat */")


@pytest.mark.parametrize("target", TARGETS)
def test_producers_write_their_slabs_and_no_copy_is_left(target):
    m = fire()
    compiled = nncg.compile(m, target)
    assert concat_kernels(compiled) == 0
    check_against_onnxruntime(m, compiled, sanitize=target in ("ansi-c", "avx2"))


@pytest.mark.parametrize("target", ["ansi-c", "avx2"])
@pytest.mark.parametrize("case", ["graph_input", "input_twice"])
def test_inputs_that_cannot_be_slabs_are_copied(target, case):
    m = fire(extra="x") if case == "graph_input" else fire(twice=True)
    compiled = nncg.compile(m, target)
    assert concat_kernels(compiled) == 1  # the graph input / the second e1r is copied
    check_against_onnxruntime(m, compiled)


def test_a_slab_inside_a_zero_halo_and_a_pooled_producer():
    nodes = [
        helper.make_node("Conv", ["x", "w1"], ["a"], pads=[1, 1, 1, 1]),
        helper.make_node("MaxPool", ["x"], ["b"], kernel_shape=[3, 3], strides=[1, 1], pads=[1, 1, 1, 1]),
        helper.make_node("Concat", ["a", "b"], ["cat"], axis=1),
        helper.make_node("Conv", ["cat", "w2"], ["y"], pads=[1, 1, 1, 1]),
    ]
    m = onnx_model(
        nodes, inputs={"x": (1, 8, 5, 6)}, initializers={"w1": weights(8, 8, 3, 3), "w2": weights(4, 16, 3, 3)}
    )
    for target in ("ssse3", "avx2"):
        pipeline = nncg.default_pipeline(nncg.get_target(target)).replace(",lower,", ",lower{halos=true},")
        compiled = nncg.compile(m, target, pipeline=pipeline)
        assert concat_kernels(compiled) == 0 and "halo_" in compiled.source
        check_against_onnxruntime(m, compiled, sanitize=target == "avx2")
