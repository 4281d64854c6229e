"""Reductions over an empty axis (nncg/frontend/empty_reductions.py): a constant, the reduction's
value over no elements; an empty input is admitted only when such reductions alone read it."""

from __future__ import annotations

import numpy as np
import pytest
from helpers import compile_and_check, onnx_model
from onnx import helper

import nncg
from nncg.errors import NncgError
from nncg.frontend.empty_reductions import EMPTY_VALUES

TARGETS = ("ansi-c", "ssse3", "avx2", "avx512")


def empty_reduce(op: str, keepdims: int = 1, axes=(1,), as_input: bool = True, opset: int = 18):
    """op over axis 1 of a (2, 0, 4) input; axes as an initializer input (opset 18) or an attribute."""
    inputs = ["x", "axes"] if as_input else ["x"]
    attrs = {"keepdims": keepdims} | ({} if as_input else {"axes": list(axes)})
    out = [2, 1, 4] if keepdims else [2, 4]
    inits = {"axes": np.array(axes, np.int64)} if as_input else {}
    return onnx_model(
        [helper.make_node(op, inputs, ["y"], **attrs)], inputs={"x": [2, 0, 4]}, outputs={"y": out},
        initializers=inits, opset=opset,
    )  # fmt: skip


@pytest.mark.parametrize("target", TARGETS)
@pytest.mark.parametrize("op", sorted(EMPTY_VALUES))
def test_reduction_over_an_empty_axis_matches_onnxruntime(op, target):
    compiled = compile_and_check(empty_reduce(op), target)
    assert f"#define {compiled.name.upper()}_X_SIZE 0" in compiled.header


@pytest.mark.parametrize("keepdims", (0, 1))
def test_axes_attribute_and_all_axes(keepdims):
    compile_and_check(empty_reduce("ReduceMax", keepdims, as_input=False, opset=13), "ansi-c")
    everything = onnx_model(
        [helper.make_node("ReduceSum", ["x"], ["y"], keepdims=keepdims)], inputs={"x": [2, 0, 4]},
        outputs={"y": [1, 1, 1] if keepdims else []}, opset=18,
    )  # fmt: skip
    compile_and_check(everything, "ansi-c")


def test_other_readers_of_an_empty_input_are_refused():
    relu = onnx_model([helper.make_node("Relu", ["x"], ["y"])], inputs={"x": [2, 0, 4]}, outputs={"y": [2, 0, 4]})
    with pytest.raises(NncgError, match=r"^input 'x' has a dimension below 1 x\[2,0,4\]; NNCG does not support empty"):
        nncg.compile(relu)
    with pytest.raises(NncgError, match="dimension below 1"):  # the mean over nothing is NaN
        nncg.compile(empty_reduce("ReduceMean"))
    with pytest.raises(NncgError, match="dimension below 1"):  # the 0-sized axis kept: an empty output
        nncg.compile(empty_reduce("ReduceSum", axes=(2,)))
