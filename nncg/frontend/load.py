"""ONNX front end (ONNX -> graph IR), step 1: read and validate the model and fix its input shapes.

The result is the exact model NNCG compiles, so callers can run onnxruntime on it for comparison.
"""

from __future__ import annotations

import os
import warnings
from collections.abc import Mapping

import numpy as np
import onnx
import onnx.inliner
from onnx.external_data_helper import load_external_data_for_model, uses_external_data

from nncg.errors import NncgError, NncgWarning, UnsupportedOpsError
from nncg.frontend.empty_reductions import reduced_empty_inputs
from nncg.frontend.names import node_names
from nncg.frontend.shapes import dtype_name, format_shape, inferred_shapes, one_line, static_shape
from nncg.frontend.wiring import check_operators, check_wiring
from nncg.ir.graph import Shape
from nncg.limits import check_tensor_size
from nncg.safe_text import capped, escaped, shown

ModelSource = str | os.PathLike | bytes | onnx.ModelProto
MIN_OPSET = 7
DEFAULT_DOMAINS = ("", "ai.onnx")
# onnxruntime's contrib ops (domain com.microsoft) that a model may hold as they are
CONTRIB_OPS = {
    "com.microsoft": (
        "QLinearAdd",
        "QLinearAveragePool",
        "QLinearConcat",
        "QLinearGlobalAveragePool",
        "QLinearLeakyRelu",
        "QLinearMul",
        "QLinearSigmoid",
        "QLinearSoftmax",
    )
}


def load_model(model: ModelSource, input_shapes: Mapping[str, tuple[int, ...]] | None = None) -> onnx.ModelProto:
    """The validated model with static float32 inputs (value_info dropped); raises NncgError."""
    return load_with_shapes(model, input_shapes)[0]


def load_with_shapes(
    model: ModelSource, input_shapes: Mapping[str, tuple[int, ...]] | None = None
) -> tuple[onnx.ModelProto, dict[str, Shape]]:
    """load_model's result and the static shapes strict ONNX shape inference gives its values."""
    proto, where = _read(model)
    _check_structure(proto, where)
    _check_ir_version(proto)
    _check_external_data(proto, where)
    proto = _inline_local_functions(proto)
    _normalise_default_domain(proto)
    _check_domains(proto)
    opset = opset_version(proto)
    # Inputs, outputs, wiring and operators first: onnx.checker would reject them with messages that
    # do not say how to fix them.
    fix_input_shapes(proto.graph, dict(input_shapes or {}))
    indices = index_outputs(proto.graph)
    for value in proto.graph.output:
        if value.name not in indices:
            _check_tensor_type(value, "output")
    check_wiring(proto.graph)
    check_operators(proto.graph, opset, proto.ir_version)
    _run_checker(proto)
    # Exporters' value_info can contradict ONNX inference (ceil-mode MaxPool before opset 22) and
    # adds nothing once the inputs are static, so shapes are inferred from scratch.
    proto.graph.ClearField("value_info")
    return proto, inferred_shapes(proto)


def read_model(model: ModelSource) -> onnx.ModelProto:
    """The parsed model (a private copy), unchecked; raises NncgError when it cannot be read."""
    return _read(model)[0]


def opset_version(model: onnx.ModelProto) -> int:
    """The default-domain opset, which must be one NNCG knows the semantics of."""
    versions = [o.version for o in model.opset_import if o.domain in DEFAULT_DOMAINS]
    if not versions:
        raise NncgError("the model imports no ONNX opset (opset_import is empty); re-export it")
    version, newest = versions[0], onnx.defs.onnx_opset_version()
    if not MIN_OPSET <= version <= newest:
        raise NncgError(
            f"the model uses ONNX opset {version}; NNCG supports opsets {MIN_OPSET} to {newest}: "
            "convert it with onnx.version_converter.convert_version(model, 13)"
        )
    return version


def real_inputs(graph: onnx.GraphProto) -> list[onnx.ValueInfoProto]:
    """Graph inputs without an initializer; the others are constants with a default value."""
    constants = {t.name for t in graph.initializer} | {t.values.name for t in graph.sparse_initializer}
    return [v for v in graph.input if v.name not in constants]


# --- reading -------------------------------------------------------------------------------------


def _read(model: ModelSource) -> tuple[onnx.ModelProto, str]:
    """The parsed model (a private copy) and how to name its source in messages."""
    if isinstance(model, onnx.ModelProto):
        proto = onnx.ModelProto()
        proto.CopyFrom(model)
        return proto, "the given ModelProto"
    if isinstance(model, (bytes, bytearray, memoryview)):
        return _parse(bytes(model), "the given bytes"), "the given bytes"
    if isinstance(model, (str, os.PathLike)):
        return _read_file(os.fspath(model))
    raise NncgError(f"cannot load a model from a {type(model).__name__}; pass a file path, bytes or an onnx.ModelProto")


def _read_file(path: str) -> tuple[onnx.ModelProto, str]:
    where = shown(path, 200)
    if not os.path.exists(path):
        raise NncgError(f"model file {where} does not exist; check the path")
    if not os.path.isfile(path):
        raise NncgError(f"model path {where} is not a file; pass the .onnx file itself")
    try:
        with open(path, "rb") as f:
            data = f.read()
    except OSError as exc:
        raise NncgError(f"cannot read model file {where}: {one_line(exc)}") from None
    proto = _parse(data, where)
    if _external_tensors(proto):
        try:
            load_external_data_for_model(proto, os.path.dirname(os.path.abspath(path)))
        except Exception as exc:
            raise NncgError(
                f"cannot load the external weight data of {where}: {one_line(exc)}; "
                "keep the data files next to the model"
            ) from None
    return proto, where


def _parse(data: bytes, where: str) -> onnx.ModelProto:
    if not data:
        raise NncgError(f"{where} is empty, not an ONNX model; pass the .onnx file your exporter wrote")
    try:
        return onnx.load_model_from_string(data)
    except Exception as exc:  # protobuf DecodeError and friends
        raise NncgError(
            f"{where} is not a valid ONNX model ({one_line(exc, 120)}); "
            "the file is truncated or not ONNX: re-export or re-download it"
        ) from None


# --- validation ----------------------------------------------------------------------------------


def _check_structure(model: onnx.ModelProto, where: str) -> None:
    """Catch what protobuf parses silently: text or truncated bytes lose whole top-level fields."""
    graph = model.graph
    problem = None
    if model.ir_version <= 0:
        problem = "it has no ir_version"
    elif not model.HasField("graph"):
        problem = "it has no graph"
    elif not model.opset_import:
        problem = "it has no opset_import"
    elif not graph.output:
        problem = "its graph has no outputs"
    else:
        known = {v.name for v in graph.input} | {t.name for t in graph.initializer}
        known |= {t.values.name for t in graph.sparse_initializer}
        known |= {out for node in graph.node for out in node.output}
        missing = [v.name for v in graph.output if v.name not in known]
        if missing:
            problem = f"graph output {shown(missing[0])} is produced by nothing"
    if problem:
        raise NncgError(
            f"{where} is not a complete ONNX model ({problem}); "
            "the file is truncated or not ONNX: re-export or re-download it"
        )


def _check_ir_version(model: onnx.ModelProto) -> None:
    """The IR version is one this onnx package reads, from the first with opset imports (IR 3)."""
    newest = onnx.IR_VERSION
    if model.ir_version > newest:
        raise NncgError(
            f"the model has ONNX IR version {model.ir_version}, newer than the {newest} the installed onnx "
            f"{onnx.__version__} reads: upgrade onnx (pip install -U onnx) or export with an older IR version"
        )
    if model.ir_version < 3:
        raise NncgError(
            f"the model has ONNX IR version {model.ir_version}, from before opset imports (IR 3, ONNX 1.0); "
            "re-export it with a current exporter"
        )


def _external_tensors(model: onnx.ModelProto) -> list[str]:
    return [t.name for t in model.graph.initializer if uses_external_data(t)]


def _check_external_data(model: onnx.ModelProto, where: str) -> None:
    external = _external_tensors(model)
    if external:
        raise NncgError(
            f"tensor {shown(external[0])} of {where} keeps its data in an external file; "
            "pass the model as a file path so NNCG can find the data"
        )


def _inline_local_functions(model: onnx.ModelProto) -> onnx.ModelProto:
    """The model with its calls of model-local functions (torch's dynamo exporter, onnxscript) replaced
    by the functions' nodes: NNCG compiles standard operators only."""
    if not model.functions:
        return model
    try:
        return onnx.inliner.inline_local_functions(model, convert_version=True)
    except Exception as exc:  # the inliner's C++ errors surface as RuntimeError and others
        raise NncgError(
            f"cannot inline the model's local functions ({one_line(exc)}); re-export the model without "
            "local functions, or with them at the model's opset (onnx converts only typed function bodies)"
        ) from None


def _normalise_default_domain(model: onnx.ModelProto) -> None:
    """Spell the default domain "" everywhere: onnx's checker and shape inference know ONNX's
    operators only under "", not under its alias "ai.onnx" (onnxruntime accepts both)."""
    for node in model.graph.node:
        if node.domain == "ai.onnx":
            node.domain = ""
    aliases = [o for o in model.opset_import if o.domain == "ai.onnx"]
    if aliases and not any(o.domain == "" for o in model.opset_import):
        aliases[0].domain = ""
        aliases = aliases[1:]
    for alias in aliases:
        model.opset_import.remove(alias)


def _check_domains(model: onnx.ModelProto) -> None:
    names = node_names(model.graph)
    foreign = [
        f"{capped(escaped(node.domain))}.{capped(escaped(node.op_type))} (node {shown(name)})"
        for node, name in zip(model.graph.node, names, strict=True)
        if node.domain not in DEFAULT_DOMAINS and node.op_type not in CONTRIB_OPS.get(node.domain, ())
    ]
    if foreign:
        raise UnsupportedOpsError(
            f"unsupported operators from non-default domains: {', '.join(foreign)}; "
            "NNCG compiles only standard ONNX (ai.onnx) operators: re-export without custom ops"
        )


def _run_checker(model: onnx.ModelProto) -> None:
    try:
        onnx.checker.check_model(_with_output_shapes(model))
    except Exception as exc:  # ValidationError, or C++ errors surfacing as others
        raise NncgError(
            f"the model is not valid ONNX (onnx.checker: {one_line(exc)}); fix what the checker names "
            "(onnx.checker.check_model(model) shows it) or re-export the model"
        ) from None


def _with_output_shapes(model: onnx.ModelProto) -> onnx.ModelProto:
    """A copy in which shapeless outputs have a shape field: the checker demands one (it does not
    check its dims), onnxruntime does not, so the model itself stays as it is."""

    def shapeless(value: onnx.ValueInfoProto) -> bool:
        return value.type.HasField("tensor_type") and not value.type.tensor_type.HasField("shape")

    if not any(shapeless(v) for v in model.graph.output):
        return model
    copy = onnx.ModelProto()
    copy.CopyFrom(model)
    for value in copy.graph.output:
        if shapeless(value):
            value.type.tensor_type.shape.SetInParent()
    return copy


# --- inputs and outputs --------------------------------------------------------------------------


def fix_input_shapes(graph: onnx.GraphProto, input_shapes: dict[str, tuple[int, ...]]) -> None:
    """Check every real input is a float32, int8 or uint8 tensor and make its shape static, from
    input_shapes if given."""
    inputs = real_inputs(graph)
    _check_shape_keys(graph, inputs, input_shapes)
    reduced_away = reduced_empty_inputs(graph)
    for value in inputs:
        _check_tensor_type(value, "input")
        if value.name in input_shapes:
            _set_shape(value, input_shapes[value.name])
        elif _only_batch_is_dynamic(value):
            _default_batch(value)
        else:
            _require_static(value, value.name in reduced_away)
        check_tensor_size(f"input {shown(value.name)}", static_shape(value))


def _check_shape_keys(graph: onnx.GraphProto, inputs: list, input_shapes: dict) -> None:
    names = [v.name for v in inputs]
    constants = {v.name for v in graph.input} - set(names)
    for key in input_shapes:
        if key in names:
            continue
        what = "a constant (it has an initializer)" if key in constants else "not an input of the model"
        raise NncgError(
            f"input_shapes names {shown(key)}, which is {what}; the model's inputs are " + ", ".join(map(shown, names))
        )


def index_outputs(graph: onnx.GraphProto) -> set[str]:
    """Graph outputs declared int64 that an ArgMax or ArgMin computes: the one int64 result NNCG
    produces (its indices written as int32, see ops_reduce.convert_arg_extreme)."""
    declared = {v.name for v in graph.output if v.type.tensor_type.elem_type == onnx.TensorProto.INT64}
    arg_extremes = [node for node in graph.node if node.op_type in ("ArgMax", "ArgMin") and not node.domain]
    produced = {node.output[0] for node in arg_extremes if node.output}
    return declared & produced


# The element types of the graph inputs and outputs NNCG's C takes and writes: float32, quantized
# values (int8, uint8) and, as outputs, the int32 of a ConvInteger or MatMulInteger.
IO_TYPES = {
    "input": (onnx.TensorProto.FLOAT, onnx.TensorProto.INT8, onnx.TensorProto.UINT8),
    "output": (onnx.TensorProto.FLOAT, onnx.TensorProto.INT8, onnx.TensorProto.UINT8, onnx.TensorProto.INT32),
}


def _check_tensor_type(value: onnx.ValueInfoProto, kind: str) -> None:
    kind_of = value.type.WhichOneof("value")
    if kind_of is None:
        raise NncgError(
            f"graph {kind} {shown(value.name)} has no type; declare it a float32 tensor (with onnx.helper: "
            f"make_tensor_value_info({shown(value.name)}, TensorProto.FLOAT, None) leaves the shape to inference)"
        )
    if kind_of != "tensor_type":
        raise NncgError(
            f"{kind} {shown(value.name)} is not a tensor (its type is {kind_of.removesuffix('_type')}); "
            "NNCG compiles models whose inputs and outputs are float32 tensors"
        )
    elem = value.type.tensor_type.elem_type
    if elem not in IO_TYPES[kind]:
        types = ", ".join(dtype_name(t) for t in IO_TYPES[kind])
        raise NncgError(
            f"{kind} {shown(value.name)} is {dtype_name(elem)}; NNCG compiles models whose {kind}s are {types}: "
            f"re-export the model with a float32 {kind}"
        )


def _is_static(dim: onnx.TensorShapeProto.Dimension) -> bool:
    return dim.HasField("dim_value") and dim.dim_value > 0


def _only_batch_is_dynamic(value: onnx.ValueInfoProto) -> bool:
    """The first of two or more dims has no size (a dim_param such as N, batch_size, unk__0), the rest do."""
    ttype = value.type.tensor_type
    dims = ttype.shape.dim if ttype.HasField("shape") else []
    return len(dims) >= 2 and not dims[0].HasField("dim_value") and all(_is_static(d) for d in dims[1:])


def _default_batch(value: onnx.ValueInfoProto) -> None:
    """Fix a dynamic batch dimension at 1, as exporters with dynamic axes (torch, tf2onnx, Keras) leave
    it, telling the user (NncgWarning, a note in the CLI) how to choose another batch size."""
    dims = value.type.tensor_type.shape.dim
    example = "x".join(["B", *(str(d.dim_value) for d in dims[1:])])
    warnings.warn(
        NncgWarning(
            f"input {shown(value.name)} has a dynamic batch dimension {format_shape(value.name, value)}; "
            f"compiled for batch 1: for batch B give --input-shape {capped(escaped(value.name))}={example} "
            "(input_shapes in Python)"
        ),
        stacklevel=1,  # shown once per input: the warnings registry keys on the text and this line
    )
    dims[0].dim_value = 1


def _require_static(value: onnx.ValueInfoProto, may_be_empty: bool = False) -> None:
    """A static shape of sizes >= 1; 0 too for an input only reductions over that axis read."""
    ttype = value.type.tensor_type
    sizes_ok = [
        _is_static(d) or (may_be_empty and d.HasField("dim_value") and d.dim_value == 0) for d in ttype.shape.dim
    ]
    if ttype.HasField("shape") and all(sizes_ok):
        return
    declared = format_shape(value.name, value)
    if ttype.HasField("shape") and all(d.HasField("dim_value") for d in ttype.shape.dim):
        raise NncgError(
            f"input {shown(value.name)} has a dimension below 1 {declared}; NNCG does not support empty tensors: "
            "give every dimension a size of at least 1 (--input-shape)"
        )
    if not ttype.HasField("shape"):
        dims = "1x3x224x224"
    else:
        dims = "x".join(str(d.dim_value) if _is_static(d) else "1" for d in ttype.shape.dim)
    raise NncgError(
        f"input {shown(value.name)} has a dynamic shape {declared}; fix it with --input-shape "
        f"{capped(escaped(value.name))}={dims} (input_shapes in Python), using the sizes you need"
    )


def _set_shape(value: onnx.ValueInfoProto, dims: tuple[int, ...]) -> None:
    """Replace the declared shape by `dims` after checking they agree with its static dims."""
    name = value.name
    if not isinstance(dims, (tuple, list)) or not all(_positive_int(d) for d in dims):
        raise NncgError(f"input_shapes[{shown(name)}] must be a tuple of positive ints, got {shown(repr(dims))}")
    dims = tuple(int(d) for d in dims)
    ttype = value.type.tensor_type
    if ttype.HasField("shape"):
        declared = ttype.shape.dim
        given = format_shape(name, value)
        if len(declared) != len(dims):
            raise NncgError(
                f"input_shapes gives input {shown(name)} {len(dims)} dims {tuple(dims)} but the model "
                f"declares {given} with {len(declared)}; give all {len(declared)} dims"
            )
        for i, (dim, size) in enumerate(zip(declared, dims, strict=True)):
            if _is_static(dim) and dim.dim_value != size:
                raise NncgError(
                    f"input_shapes gives input {shown(name)} dim {i} = {size}, but the model fixes it "
                    f"at {dim.dim_value} ({given}); use {dim.dim_value} there"
                )
    ttype.ClearField("shape")
    ttype.shape.SetInParent()  # rank 0 still needs a (dimensionless) shape
    for size in dims:
        ttype.shape.dim.add().dim_value = size


def _positive_int(d: object) -> bool:
    return isinstance(d, (int, np.integer)) and not isinstance(d, bool) and d > 0
