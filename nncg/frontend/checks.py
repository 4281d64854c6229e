"""ONNX front end (ONNX -> graph IR), step 4: what the graph IR must satisfy before any pass sees it:
every computed tensor non-empty and small enough for int indexing, no NaN weight or parameter."""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence

import numpy as np
import onnx

from nncg.errors import NncgError
from nncg.frontend.folding import Folded
from nncg.ir.graph import Graph
from nncg.limits import check_tensor_size
from nncg.safe_text import shown


def check_computed_shapes(nodes: list[tuple[str, str, Sequence[str]]], shapes: dict, used=None) -> None:
    """Every tensor the C computes (outputs of the (name, op, outputs) nodes that `used` accepts and
    whose shape is known) has at least one element and fits int indexing (nncg.limits)."""
    for name, op, outputs in nodes:
        for output in outputs:
            if output not in shapes or (used is not None and not used(output)):
                continue
            shape = shapes[output]
            what = f"output {shown(output)} of {op} node {shown(name)}"
            if min(shape, default=1) < 1:
                raise NncgError(
                    f"{what} has the empty shape {list(shape)}; NNCG does not support empty tensors: "
                    "change the node's parameters so that every dimension is at least 1, or remove it"
                )
            check_tensor_size(what, shape)


def check_constants(graph: Graph, origins: dict[str, str]) -> None:
    """The weights the C holds are finite or infinite floats, never NaN (a NaN weight makes every
    output it reaches NaN; no trained model has one), and fit int indexing. `origins` says where
    each came from, for the message."""
    for name, array in graph.constants.items():
        what = origins.get(name, f"constant {shown(name)}")
        check_tensor_size(what, array.shape, "NNCG cannot compile weights this large")
        nan = np.isnan(array)
        if nan.any():
            first = [int(i) for i in np.argwhere(nan)[0]]
            raise NncgError(
                f"{what} holds NaN ({int(nan.sum()):,} of {array.size:,} values, the first at index {first}); "
                "NNCG refuses NaN weights: the model is damaged or its training diverged: replace them "
                "(e.g. numpy.nan_to_num on the tensor) and re-export"
            )


def check_attributes(graph: Graph) -> None:
    """No float attribute the C prints (alpha, clip bounds, pad value, epsilon, scales) is NaN."""
    for node in graph.nodes:
        if not dataclasses.is_dataclass(node.attrs):
            continue
        for field in dataclasses.fields(node.attrs):
            if any(math.isnan(v) for v in _floats(getattr(node.attrs, field.name))):
                raise NncgError(
                    f"{node.op} node {shown(node.name)} has {field.name} NaN; NNCG refuses NaN parameters, which "
                    "make every output they reach NaN: give it a number"
                )


def _floats(value: object):
    """The floats in an attribute value, nested tuples included."""
    if isinstance(value, float):
        yield value
    elif isinstance(value, tuple):
        for item in value:
            yield from _floats(item)


def constant_origins(graph: onnx.GraphProto, folded: Folded) -> dict[str, str]:
    """How messages name each constant: as an initializer, or as the result of the node folded into it."""
    origins = {t.name: f"initializer {shown(t.name)}" for t in graph.initializer}
    origins |= {t.values.name: f"sparse initializer {shown(t.values.name)}" for t in graph.sparse_initializer}
    origins |= {
        value: f"constant {shown(value)} (computed at compile time by node {shown(node)})"
        for value, node in folded.folded_by.items()
    }
    return origins
