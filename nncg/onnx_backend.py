"""NNCG as an ONNX backend (`onnx.backend.base.Backend`), so onnx's own backend test suite can run it.

    rep = NncgBackend.prepare(model)          # nncg.compile + build with the host C compiler
    (y,) = rep.run([x])                       # or rep.run({"x": x}); outputs in graph order

`prepare` compiles the model to C and builds it once, with the test harness of nncg.verify, into a
program in a private temporary directory; every `run` feeds the inputs through files and reads the
outputs back, shaped as the ONNX outputs. NNCG compiles models with static shapes whose inputs and
outputs are float32, or int8/uint8 quantised values (int32 sums of ConvInteger and MatMulInteger,
ArgMax's indices as int64 out): anything else is refused with an NncgError (a BackendError for what
is wrong with the inputs).

Parameter inputs. NNCG needs operator parameters (Reshape's shape, Slice's starts/ends/axes/steps,
Pad's pads, Resize's scales, ...) as compile-time constants, while onnx's test cases
often feed them as graph inputs. As an ahead-of-time backend would, this adapter specialises on
them: a graph input is a parameter input when every node reading it reads it in a slot listed in
PARAMETER_INPUTS (made from the op records in nncg/frontend/ops.py) and the graph does not return
it (the weights of the integer kernels in CONSTANT_WEIGHTS count as parameters here), or when it
is neither float32 nor int8/uint8 read as data. For a model with parameter inputs,
`prepare` only checks the model and the first `run` binds the values given for those inputs as
initializers (they are no longer graph inputs), compiles and builds; the build is cached by the
bound values, so a later run with the same values reuses it and one with other values compiles
again. The other (data) inputs are passed to the C program as usual. This is the adapter's behaviour
only: nncg.compile and `nncg-onnx` still refuse parameters that are not constants.
"""

from __future__ import annotations

import tempfile
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import onnx
from onnx import helper, numpy_helper
from onnx.backend.base import Backend, BackendRep, Device, DeviceType

from nncg.compiler import CompiledModel
from nncg.compiler import compile as nncg_compile
from nncg.errors import NncgError
from nncg.frontend.load import index_outputs
from nncg.frontend.ops import PARAMETER_INPUTS
from nncg.frontend.shapes import dtype_name
from nncg.verify import BuiltModel, build_model

# Element types of the data inputs and outputs the C function takes and writes (int32: ConvInteger's sums)
DATA_INPUT_TYPES = frozenset({onnx.TensorProto.FLOAT, onnx.TensorProto.INT8, onnx.TensorProto.UINT8})
DATA_OUTPUT_TYPES = DATA_INPUT_TYPES | {onnx.TensorProto.INT32}
# Weights that NNCG's integer kernels take as constants, not operator parameters for nncg.compile: onnx's
# node tests feed them as graph inputs, so the adapter binds them as it binds parameters.
CONSTANT_WEIGHTS: dict[str, tuple[int, ...]] = {
    "QLinearConv": (3, 8), "QLinearMatMul": (3,), "ConvInteger": (1,), "MatMulInteger": (1,),
}  # fmt: skip
BOUND_INPUTS = {
    op: (*PARAMETER_INPUTS.get(op, ()), *CONSTANT_WEIGHTS.get(op, ())) for op in {*PARAMETER_INPUTS, *CONSTANT_WEIGHTS}
}
# Keyword arguments of prepare; onnx's test runner also passes its comparison tolerances through.
_COMPILE_KWARGS = ("target", "unroll", "input_shapes", "pipeline", "weights", "code_budget")
_BUILD_KWARGS = ("cc", "opt", "extra_cflags")
_IGNORED_KWARGS = ("rtol", "atol")


class BackendError(NncgError):
    """The backend cannot run this model or these inputs (wrong device, dtype, shape or count)."""


@dataclass(frozen=True)
class _Build:
    compiled: CompiledModel
    built: BuiltModel
    workdir: tempfile.TemporaryDirectory  # removed when the build is garbage collected
    index_outputs: frozenset[str] = frozenset()  # ArgMax/ArgMin outputs: int64 in ONNX, int32 in the C


class NncgBackendRep(BackendRep):
    """A model compiled and built by NNCG; `run` may be called many times (not concurrently).

    With parameter inputs (see the module docstring) the model is compiled at the first run and
    again for every new set of parameter values; `builds` counts the builds cached so far."""

    def __init__(
        self,
        input_names: Sequence[str],
        output_names: Sequence[str],
        name: str,
        *,
        build: _Build | None = None,
        model: onnx.ModelProto | None = None,
        parameters: Sequence[onnx.ValueInfoProto] = (),
        options: Mapping[str, Any] | None = None,
        build_options: Mapping[str, Any] | None = None,
    ) -> None:
        self._input_names = tuple(input_names)
        self._output_names = tuple(output_names)
        self._name = name
        self._model = model  # kept only when compilation waits for the parameter values
        self._parameters = {p.name: p for p in parameters}
        self._options = dict(options or {})
        self._build_options = dict(build_options or {})
        self._builds: dict[tuple, _Build] = {} if build is None else {(): build}
        self._last = build

    @property
    def input_names(self) -> tuple[str, ...]:
        """All inputs `run` takes, parameter inputs included, in graph order."""
        return self._input_names

    @property
    def output_names(self) -> tuple[str, ...]:
        return self._output_names

    @property
    def parameter_names(self) -> tuple[str, ...]:
        """The inputs whose values are bound as constants at compile time (empty: compiled at prepare)."""
        return tuple(n for n in self._input_names if n in self._parameters)

    @property
    def compiled(self) -> CompiledModel | None:
        """The model compiled for the latest run (None before the first run of a deferred model)."""
        return None if self._last is None else self._last.compiled

    @property
    def builds(self) -> int:
        return len(self._builds)

    def run(self, inputs: Any, **kwargs: Any) -> tuple[np.ndarray, ...]:
        """Inputs as a list in graph order, a dict by name, or one array for a one-input model;
        returns the outputs as arrays of their ONNX types (float32, int8, uint8, int32; ArgMax/ArgMin's
        as int64) with the ONNX output shapes, in graph order."""
        if kwargs:
            raise TypeError(f"NncgBackendRep.run() got unexpected keyword arguments {sorted(kwargs)}")
        given = dict(zip(self._input_names, self._ordered(inputs)))
        bound = {n: self._checked_parameter(self._parameters[n], given[n]) for n in self.parameter_names}
        build = self._build_for(bound)
        arrays = [self._checked(spec, given[spec.name]) for spec in build.compiled.inputs]
        outputs = zip(build.compiled.outputs, build.built.run(arrays))
        return tuple(array.astype(np.int64) if spec.name in build.index_outputs else array for spec, array in outputs)

    def _build_for(self, bound: dict[str, np.ndarray]) -> _Build:
        key = tuple((n, a.dtype.str, a.shape, a.tobytes()) for n, a in bound.items())
        build = self._builds.get(key)
        if build is None:
            assert self._model is not None, "a model compiled at prepare has no parameter inputs"
            build = _compile_and_build(bind_inputs(self._model, bound), self._options, self._build_options)
            self._builds[key] = build
        self._last = build
        return build

    def _ordered(self, inputs: Any) -> list[Any]:
        names = self._input_names
        if isinstance(inputs, Mapping):
            missing = [n for n in names if n not in inputs]
            extra = [n for n in inputs if n not in names]
            if missing or extra:
                raise BackendError(
                    f"model {self._name!r} takes inputs {list(names)}; missing {missing}, unknown {extra}"
                )
            return [inputs[n] for n in names]
        if isinstance(inputs, np.ndarray):
            inputs = [inputs]
        if not isinstance(inputs, Sequence) or isinstance(inputs, (str, bytes)):
            raise BackendError(f"inputs must be a list or a dict of numpy arrays, not {type(inputs).__name__}")
        if len(inputs) != len(names):
            raise BackendError(f"model {self._name!r} takes {len(names)} inputs {list(names)}, got {len(inputs)}")
        return list(inputs)

    @staticmethod
    def _checked(spec: Any, value: Any) -> np.ndarray:
        array = np.asarray(value)
        if array.dtype != np.dtype(spec.dtype):
            raise BackendError(f"input {spec.name!r} is {array.dtype}; the model takes {spec.dtype}")
        if tuple(array.shape) != tuple(spec.shape):
            raise BackendError(
                f"input {spec.name!r} has shape {tuple(array.shape)}; the model was compiled for {tuple(spec.shape)}"
            )
        return array

    @staticmethod
    def _checked_parameter(value_info: onnx.ValueInfoProto, value: Any) -> np.ndarray:
        """The value of a parameter input, of the type the graph declares (it becomes an initializer)."""
        array = np.asarray(value)
        tensor = value_info.type.tensor_type
        want = helper.tensor_dtype_to_np_dtype(tensor.elem_type)
        if array.dtype != want:
            raise BackendError(f"parameter input {value_info.name!r} is {array.dtype}; the model declares {want}")
        dims = tensor.shape.dim if tensor.HasField("shape") else None
        if dims is not None and (
            len(dims) != array.ndim
            or any(d.HasField("dim_value") and d.dim_value != n for d, n in zip(dims, array.shape))
        ):
            declared = [d.dim_value if d.HasField("dim_value") else (d.dim_param or "?") for d in dims]
            raise BackendError(
                f"parameter input {value_info.name!r} has shape {list(array.shape)}; the model declares {declared}"
            )
        return array


class NncgBackend(Backend):
    """prepare(model, device="CPU", target="ansi-c", unroll=2, opt="-O0", ...) -> NncgBackendRep.

    Compile options: target, unroll, input_shapes, pipeline, weights, code_budget (as for nncg.compile). Build options:
    cc (default: the first of cc, gcc, clang), opt (default -O0: fast builds), extra_cflags. The C is compiled
    with the target's strict flags in one compiler call; a warning fails the build. A model with
    parameter inputs (see the module docstring) is compiled at its first run instead.
    """

    default_target = "ansi-c"
    default_unroll: str | int | None = 2
    default_opt = "-O0"

    @classmethod
    def prepare(cls, model: Any, device: str = "CPU", **kwargs: Any) -> NncgBackendRep:
        if not cls.supports_device(device):
            raise BackendError(f"NNCG runs on the CPU only, not on device {device!r}")
        unknown = [k for k in kwargs if k not in (*_COMPILE_KWARGS, *_BUILD_KWARGS, *_IGNORED_KWARGS)]
        if unknown:
            raise TypeError(f"NncgBackend.prepare() got unexpected keyword arguments {unknown}")
        options = {"target": cls.default_target, "unroll": cls.default_unroll}
        options.update({k: kwargs[k] for k in _COMPILE_KWARGS if k in kwargs})
        build_options = {
            "cc": kwargs.get("cc"),
            "opt": kwargs.get("opt", cls.default_opt),
            "extra_cflags": tuple(kwargs.get("extra_cflags", ())),
        }
        source = model if isinstance(model, onnx.ModelProto) else _load(model)
        proto = _parsed(source)
        parameters = parameter_inputs(proto.graph) if proto is not None else []
        if not parameters:  # compiled now; nncg.compile reports whatever is wrong with the model
            build = _compile_and_build(source, options, build_options)
            inputs, outputs = build.compiled.inputs, build.compiled.outputs
            return NncgBackendRep([p.name for p in inputs], [p.name for p in outputs], build.compiled.name, build=build)
        indices = index_outputs(proto.graph)
        for value in proto.graph.output:  # refused now rather than at the first run
            elem = value.type.tensor_type.elem_type if value.type.HasField("tensor_type") else None
            if elem not in DATA_OUTPUT_TYPES and value.name not in indices:
                what = dtype_name(elem) if elem is not None else "not a tensor"
                raise BackendError(
                    f"NNCG writes float32, int8, uint8 or int32 outputs; output {value.name!r} is {what}"
                )
        if isinstance(source, onnx.ModelProto):  # a snapshot: the caller may change theirs
            proto = onnx.ModelProto()
            proto.CopyFrom(source)
        else:  # read again with its external data, if any
            proto = onnx.load(source) if isinstance(source, str) else onnx.load_model_from_string(source)
        return NncgBackendRep(
            [v.name for v in _real_inputs(proto.graph)],
            [v.name for v in proto.graph.output],
            proto.graph.name,
            model=proto,
            parameters=parameters,
            options=options,
            build_options=build_options,
        )

    @classmethod
    def run_model(cls, model: Any, inputs: Any, device: str = "CPU", **kwargs: Any) -> tuple[np.ndarray, ...]:
        return cls.prepare(model, device, **kwargs).run(inputs)

    @classmethod
    def run_node(
        cls,
        node: onnx.NodeProto,
        inputs: Any,
        device: str = "CPU",
        outputs_info: Sequence[tuple[np.dtype, tuple[int, ...]]] | None = None,
        **kwargs: Any,
    ) -> tuple[np.ndarray, ...]:
        """Runs one node: wraps it in a model with the inputs' types and shapes; the outputs are of the
        types in `outputs_info` (default float32), their shapes inferred."""
        arrays = list(inputs.values()) if isinstance(inputs, Mapping) else list(inputs)
        names = [n for n in node.input if n]
        if len(names) != len(arrays):
            raise BackendError(f"node {node.op_type} has {len(names)} inputs, got {len(arrays)} arrays")
        opset = kwargs.pop("opset_version", onnx.defs.onnx_opset_version())
        outputs = [n for n in node.output if n]
        graph = helper.make_graph(
            [node],
            node.name or node.op_type.lower(),
            [
                helper.make_tensor_value_info(n, helper.np_dtype_to_tensor_dtype(np.asarray(a).dtype), np.shape(a))
                for n, a in zip(names, arrays)
            ],
            [
                helper.make_tensor_value_info(n, elem, None)
                for n, elem in zip(outputs, _output_types(outputs, outputs_info))
            ],
        )
        model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", opset)])
        return cls.prepare(model, device, **kwargs).run(arrays)

    @classmethod
    def supports_device(cls, device: str) -> bool:
        try:
            return Device(device).type == DeviceType.CPU
        except (AttributeError, ValueError):
            return False


def _output_types(outputs: Sequence[str], outputs_info: Sequence[tuple[np.dtype, Any]] | None) -> list[int]:
    if outputs_info is None:
        return [onnx.TensorProto.FLOAT] * len(outputs)
    return [helper.np_dtype_to_tensor_dtype(np.dtype(dtype)) for dtype, _ in outputs_info]


def parameter_inputs(graph: onnx.GraphProto) -> list[onnx.ValueInfoProto]:
    """The graph inputs (without an initializer) the adapter binds at the first run: those read only in
    PARAMETER_INPUTS slots of the graph's nodes (not returned), and those of another type than the C
    function takes (float32, and int8/uint8 quantised values read as data)."""
    slots: dict[str, set[bool]] = {}  # input name -> {read as a parameter?} over its readers
    for node in graph.node:
        params = BOUND_INPUTS.get(node.op_type, ()) if node.domain in ("", "ai.onnx") else ()
        for index, name in enumerate(node.input):
            if name:
                slots.setdefault(name, set()).add(index in params)
    returned = {v.name for v in graph.output}
    found = []
    for value in _real_inputs(graph):
        tensor = value.type.tensor_type if value.type.HasField("tensor_type") else None
        if tensor is not None and tensor.elem_type not in DATA_INPUT_TYPES:
            found.append(value)
        elif (
            tensor is not None and tensor.elem_type != onnx.TensorProto.FLOAT and False not in slots.get(value.name, ())
        ):
            found.append(value)  # an integer read only as a parameter (a zero point)
        elif tensor is not None and slots.get(value.name) == {True} and value.name not in returned:
            found.append(value)
    return found


def _real_inputs(graph: onnx.GraphProto) -> list[onnx.ValueInfoProto]:
    constants = {t.name for t in graph.initializer} | {t.values.name for t in graph.sparse_initializer}
    return [v for v in graph.input if v.name not in constants]


def bind_inputs(model: onnx.ModelProto, values: Mapping[str, np.ndarray]) -> onnx.ModelProto:
    """A copy of `model` with the inputs in `values` turned into initializers of those values."""
    bound = onnx.ModelProto()
    bound.CopyFrom(model)
    graph = bound.graph
    kept = [v for v in graph.input if v.name not in values]
    del graph.input[:]
    graph.input.extend(kept)
    graph.initializer.extend(numpy_helper.from_array(np.asarray(a), n) for n, a in values.items())
    return bound


def _compile_and_build(model: Any, options: Mapping[str, Any], build_options: Mapping[str, Any]) -> _Build:
    compiled = nncg_compile(model, **options)
    workdir = tempfile.TemporaryDirectory(prefix="nncg-backend-")
    try:
        built = build_model(compiled, Path(workdir.name), single_invocation=True, **build_options)
    except BaseException:
        workdir.cleanup()
        raise
    proto = _parsed(model)
    return _Build(compiled, built, workdir, frozenset(index_outputs(proto.graph)) if proto is not None else frozenset())


def _parsed(source: onnx.ModelProto | bytes | str) -> onnx.ModelProto | None:
    """The model to look for parameter inputs in (without external data), or None when it cannot
    be read (nncg.compile then says why)."""
    if isinstance(source, onnx.ModelProto):
        return source
    try:
        if isinstance(source, str):
            return onnx.load(source, load_external_data=False)
        return onnx.load_model_from_string(source)
    except Exception:  # noqa: BLE001 - any unreadable model is nncg.compile's to report
        return None


def _load(model: Any) -> onnx.ModelProto | bytes | str:
    """Paths and bytes go to nncg.compile as they are (it reads external data next to a file)."""
    if isinstance(model, (str, Path, bytes)):
        return str(model) if isinstance(model, Path) else model
    raise BackendError(f"cannot prepare a {type(model).__name__}; pass an onnx.ModelProto, a path or bytes")


prepare = NncgBackend.prepare
run_model = NncgBackend.run_model
run_node = NncgBackend.run_node
supports_device = NncgBackend.supports_device
