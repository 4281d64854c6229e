"""The operator tables agree: the ONNX op records (nncg/frontend/ops.py), the graph IR op records
(nncg/ir/ops.py), the lowerings (nncg/lowering), the ONNX backend's parameter inputs and the README."""

from __future__ import annotations

import re
import warnings
from collections import defaultdict
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import onnx
import pytest
from int8_models import average_pool_model, quantized, residual_model, softmax_head_model
from onnx import TensorProto, helper, numpy_helper
from test_int8_concat import contrib_model as concat_contrib_model
from test_int8_integer_ops import integer_model, raw_model
from test_int8_lookup import contrib_model as lookup_contrib_model
from test_int8_lookup import qdq_model as lookup_qdq_model
from test_int8_matmul_ranks import K, qlinear_matmul_model
from test_int8_mul import contrib_model as mul_contrib_model

import nncg.onnx_backend
from nncg import conformance
from nncg.errors import NncgError
from nncg.frontend import importer
from nncg.frontend.context import Context
from nncg.frontend.ops import FOLDED_PARAMETER_INPUTS, ONNX_OPS, PARAMETER_INPUTS, SUPPORTED_OPS
from nncg.ir.ops import IR_OPS
from nncg.lowering import LOWERINGS

README = Path(__file__).resolve().parent.parent / "README.md"

# Parameter inputs the adapter binds that no converter reads: Dropout's ratio (inference ignores it).
BOUND_BUT_UNREAD = {("Dropout", 1)}


def test_every_ir_op_has_a_lowering_and_every_lowering_an_ir_op() -> None:
    assert sorted(set(IR_OPS) - set(LOWERINGS)) == [], "IR ops without a lowering"
    assert sorted(set(LOWERINGS) - set(IR_OPS)) == [], "lowerings of ops missing from IR_OPS"


def test_every_ir_op_a_converter_yields_has_a_record() -> None:
    """An IR_OPS record carries the op's attribute record and MAC rule; with the test above, the op
    also has a lowering."""
    for name, op in ONNX_OPS.items():
        assert op.ir_ops, name
        assert set(op.ir_ops) <= set(IR_OPS), f"{name} yields ops missing from IR_OPS"
    for name, op in IR_OPS.items():
        assert callable(op.macs) and (op.attrs is None or isinstance(op.attrs, type)), name


def test_parameter_inputs_are_the_records() -> None:
    assert nncg.onnx_backend.PARAMETER_INPUTS is PARAMETER_INPUTS
    for name, op in ONNX_OPS.items():
        assert PARAMETER_INPUTS.get(name, ()) == op.parameter_inputs, name
    assert not set(FOLDED_PARAMETER_INPUTS) & set(ONNX_OPS), "an op either has a converter or only folds"
    assert set(PARAMETER_INPUTS) == {n for n, op in ONNX_OPS.items() if op.parameter_inputs} | set(
        FOLDED_PARAMETER_INPUTS
    )


def test_readme_lists_exactly_the_supported_ops() -> None:
    """Every ONNX op named in the README's operator list (the folded-constants and quantised-models
    bullets aside) has a record, and every record is named there."""
    text = README.read_text()
    section = text[text.index("### Supported operators") : text.index("## The pipeline")]
    # The bullets on folded constants and on quantised models name ops that are folded or refused.
    bullets = [b for b in section.split("\n- ")[1:] if not b.startswith(("Constant subgraphs", "Quantised models"))]
    schemas = {schema.name for schema in onnx.defs.get_all_schemas() if schema.domain == ""}
    # onnxruntime's contrib ops (QLinearAdd, ...) have no onnx schema: named as supported ops
    listed = {word for bullet in bullets for word in re.findall(r"\b[A-Z]\w*", bullet)} & (schemas | set(SUPPORTED_OPS))
    assert sorted(set(SUPPORTED_OPS) - listed) == [], "supported but not in the README"
    assert sorted(listed - set(SUPPORTED_OPS)) == [], "in the README but not supported"


def test_converters_yield_their_ir_ops_and_read_only_their_parameter_inputs(monkeypatch: pytest.MonkeyPatch) -> None:
    """Over every conformance node case (parameter inputs bound as the adapter binds them) and a few
    models for the rarer conversions: each converter yields exactly the IR ops its record lists and
    reads as constants only the inputs its record lists as parameters."""
    yielded: dict[str, set[str]] = defaultdict(set)
    read: dict[str, set[int]] = defaultdict(set)
    constant_input = Context.constant_input

    def spy_constant_input(ctx: Context, op, index: int, *args, **kwargs):
        read[op.type].add(index)
        return constant_input(ctx, op, index, *args, **kwargs)

    def spy_converter(name, convert):
        def converted(op, ctx):
            nodes = convert(op, ctx)
            yielded[name].update(node.op for node in (nodes if isinstance(nodes, tuple) else (nodes,)))
            return nodes

        return converted

    monkeypatch.setattr(Context, "constant_input", spy_constant_input)
    monkeypatch.setattr(importer, "CONVERTERS", {n: spy_converter(n, op.convert) for n, op in ONNX_OPS.items()})
    for model in (*_conformance_models(), *_rare_conversions()):
        try:
            importer.import_onnx(model)
        except NncgError:  # refused (excluded cases): what it converted or read before still counts
            pass
    assert dict(yielded) == {name: set(op.ir_ops) for name, op in ONNX_OPS.items()}
    for name, op in ONNX_OPS.items():
        assert all(map(op.is_parameter, read[name])), f"{name} reads constants at slots missing from its record"
    unread = {(n, i) for n, op in ONNX_OPS.items() for i in op.parameter_inputs if i not in read[n]}
    assert unread == BOUND_BUT_UNREAD
    repeated = {n: op.repeated_parameters for n, op in ONNX_OPS.items() if op.repeated_parameters}
    assert all(any(i in slots for i in read[n] if i >= slots.start) for n, slots in repeated.items())


def _conformance_models() -> Iterator[onnx.ModelProto]:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # onnx's case generators overflow casts on purpose
        cases = conformance.node_test_cases()
    for selected in conformance.select_node_cases():
        if conformance.exclusion_reason(selected.name) in conformance.NARROW_TYPES:
            continue  # float8/4/2-bit graph inputs: bind_inputs cannot bind them
        case = cases[selected.name]
        graph = case.model.graph
        values = dict(zip([v.name for v in graph.input], case.data_sets[0][0]))
        bound = {p.name: values[p.name] for p in nncg.onnx_backend.parameter_inputs(graph)}
        yield nncg.onnx_backend.bind_inputs(case.model, bound)


def _rare_conversions() -> Iterator[onnx.ModelProto]:
    """Max/Min of a scalar constant (a Clip); ReduceMean over the spatial dims (a global pool) and
    ReduceMean/Max/Min over no axes with noop_with_empty_axes (an Identity); ReduceLogSumExp (onnx's
    cases are float64) with its axes input; Tile repeating nothing (a Reshape); Where whose condition
    is true everywhere (X broadcast: a Reshape to Y's rank and a Tile)."""
    bound = numpy_helper.from_array(np.array(0.5, np.float32), "c")
    for op in ("Max", "Min"):
        yield _model([helper.make_node(op, ["x", "c"], ["y"])], [bound], 13)
    yield _model([helper.make_node("ReduceMean", ["x"], ["y"], axes=[2, 3])], [], 13)
    for op in ("ReduceMean", "ReduceMax", "ReduceMin"):
        yield _model([helper.make_node(op, ["x"], ["y"], noop_with_empty_axes=1)], [], 18)
    axes = numpy_helper.from_array(np.array([1], np.int64), "axes")
    yield _model([helper.make_node("ReduceLogSumExp", ["x", "axes"], ["y"])], [axes], 18)
    ones = numpy_helper.from_array(np.ones(4, np.int64), "r")
    yield _model([helper.make_node("Tile", ["x", "r"], ["y"])], [ones], 13)
    true = numpy_helper.from_array(np.ones((1, 1, 1), bool), "m")
    wide = numpy_helper.from_array(np.zeros((2, 1, 2, 3, 3), np.float32), "z")
    yield _model([helper.make_node("Where", ["m", "x", "z"], ["y"])], [true, wide], 16)
    yield from _int8_models()


def _int8_models() -> Iterator[onnx.ModelProto]:
    """QDQ models whose groups become every int8 op (int8_models.py), an AveragePool over the whole
    image among them (QLinearAveragePool falls back to the global pool)."""
    models = (residual_model(), softmax_head_model(), average_pool_model(), average_pool_model(whole_image=True))
    for model in models:
        yield quantized(model)
    # QDQ groups and com.microsoft nodes of the table lookups, QLinearMul and QLinearConcat
    for op in ("LeakyRelu", "Sigmoid", "HardSwish", "Tanh"):
        yield lookup_qdq_model(op, "uint8")
    for op in ("LeakyRelu", "Sigmoid"):
        yield lookup_contrib_model(op, "uint8")
    yield mul_contrib_model("uint8", "same")
    yield concat_contrib_model("uint8")
    # ConvInteger and MatMulInteger with the Cast, Mul and Add that qdq.py fuses into them
    for op in ("ConvInteger", "MatMulInteger"):
        yield integer_model(op)
    yield raw_model("batched")  # a batched MatMulInteger: its A a Reshape of the rows
    yield qlinear_matmul_model((2, 3, K))  # and a batched QLinearMatMul


def _model(nodes: list[onnx.NodeProto], initializers: list[onnx.TensorProto], opset: int) -> onnx.ModelProto:
    graph = helper.make_graph(
        nodes,
        "g",
        [helper.make_tensor_value_info("x", TensorProto.FLOAT, [1, 2, 3, 3])],
        [helper.make_tensor_value_info("y", TensorProto.FLOAT, None)],
        initializers,
    )
    return helper.make_model(graph, opset_imports=[helper.make_opsetid("", opset)])
