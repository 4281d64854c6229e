"""Layout-changing copies (a channels-last value into a row-major graph output, a Transpose to a
graph output) are tiled (lowering/reshape.py tiled_nest): checked against onnxruntime with extents
that are no multiple of the tile, so whole tiles and tails meet."""

from __future__ import annotations

import re

import pytest
from onnx import helper

import nncg
from nncg.lowering.reshape import TILE
from nncg.passes.unroll import AUTO_BUDGET
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


def _copy_loops(source: str) -> list[str]:
    """The loop variables of the converting copy's function, in order."""
    start = source.index("_to_y: Copy")
    return re.findall(r"for \((\w+) = 0;", source[start : source.index("\n}\n", start)])


# The copy's nests for a 21-channel 3x19 output: h, then per combination of whole channel/column
# tiles and tails (ct, wt: tiles; c, w: inside a tile) one nest. A level counts these loops as it
# counts a convolution's: level 1 keeps h, level 2 each nest's first loop under h.
COPY_LOOPS = {
    1: ["h"],
    2: ["h", "ct", "ct", "wt", "c"],
    # auto: every loop of at most 64 statements, so each whole 8x8 tile and the tails (the 8x3 ones
    # with their ct loop too)
    "auto": ["h", "ct", "wt", "wt"],
    None: ["h", "ct", "wt", "c", "w", "ct", "c", "w", "wt", "c", "w", "c", "w"],
}


@pytest.mark.parametrize("level", list(COPY_LOOPS), ids=str)
def test_copy_keeps_the_loops_its_unroll_level_keeps(level):
    model = conv_output_model()
    compiled = nncg.compile(model, target="avx2", unroll=level, verify_ir=True)
    assert _copy_loops(compiled.source) == COPY_LOOPS[level]
    check_against_onnxruntime(model, compiled)


def test_auto_unrolls_a_whole_tile():
    """--unroll auto unrolls loops of at most AUTO_BUDGET statements: a whole 8x8 tile, which gcc
    then stores as 8 row vectors. A larger TILE would keep the tile a loop under auto."""
    assert TILE * TILE <= AUTO_BUDGET
