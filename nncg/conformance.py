"""Which of onnx's backend node tests NNCG runs, which it excludes and why: shared by
tests/test_onnx_conformance.py and scripts/conformance_report.py.

A node test case (onnx.backend.test.case.node, named test_<op>[_variant]) is "for op X" when the
nodes of its graph that do not fold to constants are all X; it is selected when X is in
nncg.frontend.ops.SUPPORTED_OPS, so newly supported operators are picked up automatically.
Function-expanded cases (test_<case>_expanded[_verN]) count for the op of the case they expand and
are selected when that op and all their live ops are supported. Every selected case runs unless
EXCLUDED names it (exact name or regex, matched in full) with a one-line reason. Operator
parameters that a case feeds as graph inputs (Reshape's shape, Slice's starts, ...) are no reason to
exclude it: nncg.onnx_backend binds them as constants at the first run.
"""

from __future__ import annotations

import functools
import re
import unittest
from collections.abc import Iterable
from dataclasses import dataclass
from typing import Any

import onnx

from nncg.frontend.folding import NONDETERMINISTIC
from nncg.frontend.load import index_outputs
from nncg.frontend.ops import PARAMETER_INPUTS, SUPPORTED_OPS

# Ops whose result is known at compile time from static shapes alone.
_SHAPE_OPS = {"Shape", "Size"}
_EXPANDED = re.compile(r"_expanded(_ver\d+)?$")

_F32 = "NNCG compiles float32 models only"
_INFERENCE = "NNCG compiles inference only"
_EMPTY = "NNCG needs at least one element"

_INT8 = "NNCG's quantised tensors are int8 or uint8"
# the types numpy_helper cannot turn into an initializer (so the adapter cannot bind them either)
NARROW_TYPES = (f"float8/float4 quantised tensors: {_INT8}", f"2-bit and 4-bit quantised tensors: {_INT8}")

# Node test cases of selected ops that are not run: {exact name or regex (fullmatch): reason}.
# Exact names are looked up first, then the patterns in this order.
EXCLUDED: dict[str, str] = {
    # --- quantisation: int8/uint8 tensors quantised per tensor (weights per output channel) ----------
    r"test_(de)?quantizelinear_(e4m3fn|e5m2|float4e2m1)(_.*)?": NARROW_TYPES[0],
    r"test_(de)?quantizelinear_u?int(2|4)": NARROW_TYPES[1],
    r"test_(de)?quantizelinear_u?int16": f"int16/uint16 quantised tensors: {_INT8}",
    r"test_(de)?quantizelinear_(axis|blocked(_.*)?)": (
        "a per-axis or blocked (block_size) scale on a tensor computed at run time: NNCG quantises activations "
        "per tensor (the symmetric blocked case also writes int16)"
    ),
    r"test_qlinearmatmul_3D_.*": "a 3-D QLinearMatMul: NNCG's integer matrix product takes 2-D inputs",
    # --- dtypes and types: NNCG's inputs, outputs and arithmetic are float32 tensors ---------------
    r"test_.*_(double|float64)(_.*)?": f"float64 tensors: {_F32}",
    # (QLinearMatMul's float16 scales are constants: those cases compute in integers and run)
    r"test_(?!qlinearmatmul_2D_).*_(float16|bfloat16)(_.*)?": f"float16 tensors: {_F32}",
    # (a float32 base to an integer exponent, a constant, computes in float32: those Pow cases run; so do
    # the int8/uint8 cases of the quantisation operators)
    r"test_(?!pow_types_float32_u?int|qlinearmatmul_2D_).*_u?int(8|16|32|64)(_.*)?": f"integer tensors: {_F32}",
    r"test_(edge|reflect|wrap)_pad": f"integer tensors (int32 data): {_F32}",
    "test_where_long_example": f"int64 X and Y: {_F32}",
    r"test_identity_(opt|sequence)": "optional / sequence input: NNCG compiles models of tensors only",
    r"test_dropout_default_mask(_ratio)?": f"bool mask output: {_F32}",
    r"test_maxpool_with_argmax_.*": f"int64 Indices output: {_F32}",
    r"test_reduce_(max|min)_bool_inputs": f"bool tensors: {_F32}",
    r"test_reduce_max_empty_set_bool": f"bool tensors: {_F32}",
    r"test_reduce_log_sum_exp_(?!empty_set).*": f"float64 tensors (every case of the op but the empty set): {_F32}",
    # --- training mode: NNCG compiles inference graphs ------------------------------------------
    r"test_batchnorm_.*_training_mode": f"training mode (batch statistics, running-mean outputs): {_INFERENCE}",
    r"test_training_dropout.*": f"training mode (random mask, bool training_mode input): {_INFERENCE}",
    # --- empty tensors: NNCG compiles tensors with at least one element ----------------------------
    "test_reshape_allowzero_reordered": f"empty input (a 0-sized dim): {_EMPTY}",
    "test_slice_start_out_of_bounds": f"empty output (start past the end of the axis): {_EMPTY}",
    r"test_split_zero_size_splits_opset\d+": f"empty tensors (zero-size splits): {_EMPTY}",
    r"test_reduce_.*_empty_set_expanded": (
        f"elementwise ops on an empty input (the expansion's Abs or Mul before its ReduceSum): {_EMPTY}, "
        "but for an input only reduced over its empty axis"
    ),
    "test_reduce_sum_empty_set_non_reduced_axis_zero": f"empty output (a 0-sized axis kept): {_EMPTY}",
    # --- attribute combinations NNCG refuses with a clear error ------------------------------------
    # --- where onnx's reference and onnxruntime disagree: NNCG follows onnxruntime ---------------------
    r"test_resize_downsample_scales_(linear|cubic)_align_corners": (
        "align_corners with a fractional output length (4 x 0.6 = 2.4, 4 x 0.8 = 3.2): onnx's reference "
        "divides by 2.4 - 1 (3.2 - 1), onnxruntime and NNCG by the integer length 2 - 1 (3 - 1)"
    ),
}

# The light_* models of onnx/backend/test/data/light, run as BackendTest's "real" model tests.
ZOO_MODELS = (
    "test_bvlc_alexnet",
    "test_densenet121",
    "test_inception_v1",
    "test_inception_v2",
    "test_resnet50",
    "test_shufflenet",
    "test_squeezenet",
    "test_vgg19",
    "test_zfnet512",
)


@dataclass(frozen=True)
class NodeCase:
    name: str  # the onnx test case name, e.g. test_conv_with_strides_padding
    op: str  # the operator it is counted for
    ops: frozenset[str]  # the ops of its graph that do not fold to constants


@functools.cache
def node_test_cases() -> dict[str, Any]:
    """All of onnx's node test cases (onnx.backend.test TestCase objects) by name; loading runs
    onnx's case generators once per process (a few seconds, deterministic: onnx seeds them)."""
    from onnx.backend.test.loader import load_model_tests

    return {case.name: case for case in load_model_tests(kind="node")}


def live_ops(model: onnx.ModelProto) -> frozenset[str]:
    """Op types of the nodes that do not fold to constants (ops of other domains as DOMAIN.Op)."""
    graph = model.graph
    constant = {t.name for t in graph.initializer} | {t.values.name for t in graph.sparse_initializer} | {""}
    ops = set()
    for node in graph.node:
        op = node.op_type if node.domain in ("", "ai.onnx") else f"{node.domain}.{node.op_type}"
        foldable = node.op_type in _SHAPE_OPS or all(i in constant for i in node.input)
        if foldable and op not in NONDETERMINISTIC:
            constant.update(node.output)
        else:
            ops.add(op)
    return frozenset(ops)


@functools.cache
def _all_case_ops() -> dict[str, frozenset[str]]:
    return {name: live_ops(case.model) for name, case in sorted(node_test_cases().items())}


def case_op(name: str) -> str | None:
    """The op a node test case is for: for an expanded case the op of the case it expands, else
    its only live op; None when neither exists (several live ops and no base case, or none)."""
    cases = _all_case_ops()
    base = _EXPANDED.sub("", name)
    for ops in (cases.get(base, frozenset()), cases[name]) if base != name else (cases[name],):
        if len(ops) == 1:
            return next(iter(ops))
    return None


def select_node_cases(supported: Iterable[str] = SUPPORTED_OPS) -> list[NodeCase]:
    """The node test cases NNCG runs (excluded ones included), sorted by name."""
    supported = frozenset(supported)
    selected = []
    for name, ops in _all_case_ops().items():
        op = case_op(name)
        if op in supported and ops and ops <= supported:
            selected.append(NodeCase(name, op, ops))
    return selected


def is_float32_case(name: str) -> bool:
    """Whether a node test case computes on float32 data: every graph output, and every graph input
    some node reads as data (not in a PARAMETER_INPUTS slot: shapes, axes, indices), holds float32
    (ArgMax/ArgMin's int64 indices aside; a sequence or optional holds float32 tensors)."""
    graph = node_test_cases()[name].model.graph
    data = set()
    for node in graph.node:
        params = PARAMETER_INPUTS.get(node.op_type, ()) if node.domain in ("", "ai.onnx") else ()
        data |= {i for index, i in enumerate(node.input) if i and index not in params}
    indices = index_outputs(graph)
    values = [v for v in graph.input if v.name in data] + [v for v in graph.output if v.name not in indices]
    return all(_holds_float32(v.type) for v in values)


def _holds_float32(value_type: onnx.TypeProto) -> bool:
    kind = value_type.WhichOneof("value")
    if kind == "tensor_type":
        return value_type.tensor_type.elem_type == onnx.TensorProto.FLOAT
    if kind == "sequence_type":
        return _holds_float32(value_type.sequence_type.elem_type)
    if kind == "optional_type":
        return _holds_float32(value_type.optional_type.elem_type)
    return False


def exclusion_reason(name: str) -> str | None:
    """Why case `name` is not run (the first EXCLUDED entry matching it in full), or None."""
    if name in EXCLUDED:
        return EXCLUDED[name]
    for pattern, reason in EXCLUDED.items():
        if re.fullmatch(pattern, name):
            return reason
    return None


def backend_test_cases(backend: type, module: str) -> dict[str, type[unittest.TestCase]]:
    """onnx's BackendTest for `backend`: its unittest classes by category name (NodeModel for the
    node cases, RealModel for the light_* models)."""
    from onnx.backend.test import BackendTest

    return BackendTest(backend, module).test_cases


def run_backend_test(test_cases: dict[str, type[unittest.TestCase]], category: str, name: str) -> None:
    """Runs one BackendTest case on the CPU (e.g. category "OnnxBackendNodeModelTest", name
    "test_relu"): prepare, run every data set, compare with onnx's stored outputs and tolerances.
    Raises on failure (AssertionError for wrong numbers, the backend's error if it refuses)."""
    method = f"{name}_cpu"
    getattr(test_cases[category](method), method)()


def run_node_case(test_cases: dict[str, type[unittest.TestCase]], name: str) -> None:
    run_backend_test(test_cases, "OnnxBackendNodeModelTest", name)


def run_zoo_model(test_cases: dict[str, type[unittest.TestCase]], name: str) -> None:
    run_backend_test(test_cases, "OnnxBackendRealModelTest", name)
