"""Layout-changing copies (a channels-last value into a row-major graph output, a Transpose to a
graph output) are tiled (lowering/reshape.py tiled_nest): checked against onnxruntime with extents
that are no multiple of the tile, so whole tiles and tails meet."""

from __future__ import annotations

import pytest
from onnx import helper

import nncg
from nncg.lowering.reshape import TILE
from tests.helpers import check_against_onnxruntime, onnx_model, weights

# 21 channels and a 3x19 image: each tiled dim has whole tiles (more than one) and a tail.
CHANNELS, HEIGHT, WIDTH = 21, 3, 19


def _conv(out: str = "y"):
    return helper.make_node("Conv", ["x", "w", "b"], [out], kernel_shape=[1, 1])


def _initializers():
    return {"w": weights(CHANNELS, 3, 1, 1), "b": weights(CHANNELS)}


def conv_output_model():
    """A 1x1 Conv (written channels last) whose output is the graph output (row-major)."""
    return onnx_model([_conv()], inputs={"x": [1, 3, HEIGHT, WIDTH]}, initializers=_initializers())


def transpose_output_model():
    """The Conv's channels-last output transposed to NCWH as the graph output."""
    nodes = [_conv("c"), helper.make_node("Transpose", ["c"], ["y"], perm=[0, 1, 3, 2])]
    return onnx_model(nodes, inputs={"x": [1, 3, HEIGHT, WIDTH]}, initializers=_initializers())


def test_extents_have_tails():
    assert CHANNELS > TILE and CHANNELS % TILE and WIDTH > TILE and WIDTH % TILE


@pytest.mark.parametrize("target", ["ansi-c", "ssse3", "avx2", "avx512"])
def test_conv_output_copy(target):
    model = conv_output_model()
    compiled = nncg.compile(model, target=target, verify_ir=True)
    copy = compiled.source[compiled.source.index("_to_y: Copy") :]
    assert "for (ct = 0; ct < 2; ++ct)" in copy  # the converting copy runs over whole channel tiles
    check_against_onnxruntime(model, compiled, sanitize=target == "ansi-c")


@pytest.mark.parametrize("target", ["ansi-c", "avx2"])
def test_transpose_output(target):
    model = transpose_output_model()
    compiled = nncg.compile(model, target=target, verify_ir=True)
    check_against_onnxruntime(model, compiled, sanitize=target == "avx2")


def test_transpose_of_row_major_input():
    """A graph input (row-major) transposed: the reads are contiguous along W, the writes along H."""
    model = onnx_model(
        [helper.make_node("Transpose", ["x"], ["y"], perm=[0, 1, 3, 2])], inputs={"x": [1, CHANNELS, WIDTH, HEIGHT + 8]}
    )
    compiled = nncg.compile(model, target="ssse3", verify_ir=True)
    check_against_onnxruntime(model, compiled)
