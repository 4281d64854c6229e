"""NNCG as an ONNX backend (`onnx.backend.base.Backend`), so onnx's own backend test suite can run it.

    rep = NncgBackend.prepare(model)          # nncg.compile + build with the host C compiler
    (y,) = rep.run([x])                       # or rep.run({"x": x}); outputs in graph order

`prepare` compiles the model to C and builds it once, with the test harness of nncg.verify, into a
program in a private temporary directory; every `run` feeds the inputs through files and reads the
outputs back, shaped as the ONNX outputs. NNCG compiles float32 models with static shapes only:
anything else is refused with an NncgError (a BackendError for what is wrong with the inputs).
"""

from __future__ import annotations

import tempfile
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import onnx
from onnx.backend.base import Backend, BackendRep, Device, DeviceType

from nncg.compiler import CompiledModel
from nncg.compiler import compile as nncg_compile
from nncg.errors import NncgError
from nncg.verify import BuiltModel, build_model

# Keyword arguments of prepare; onnx's test runner also passes its comparison tolerances through.
_COMPILE_KWARGS = ("target", "unroll", "input_shapes", "pipeline", "weights", "code_budget")
_BUILD_KWARGS = ("cc", "opt", "extra_cflags")
_IGNORED_KWARGS = ("rtol", "atol")


class BackendError(NncgError):
    """The backend cannot run this model or these inputs (wrong device, dtype, shape or count)."""


class NncgBackendRep(BackendRep):
    """A model compiled and built by NNCG; `run` may be called many times (not concurrently)."""

    def __init__(self, compiled: CompiledModel, built: BuiltModel, workdir: tempfile.TemporaryDirectory) -> None:
        self.compiled = compiled
        self._built = built
        self._workdir = workdir  # removed when this object is garbage collected

    @property
    def input_names(self) -> tuple[str, ...]:
        return tuple(p.name for p in self.compiled.inputs)

    @property
    def output_names(self) -> tuple[str, ...]:
        return tuple(p.name for p in self.compiled.outputs)

    def run(self, inputs: Any, **kwargs: Any) -> tuple[np.ndarray, ...]:
        """Inputs as a list in graph order, a dict by name, or one array for a one-input model;
        returns the outputs as float32 arrays with the ONNX output shapes, in graph order."""
        if kwargs:
            raise TypeError(f"NncgBackendRep.run() got unexpected keyword arguments {sorted(kwargs)}")
        arrays = [self._checked(spec, array) for spec, array in zip(self.compiled.inputs, self._ordered(inputs))]
        return tuple(self._built.run(arrays))

    def _ordered(self, inputs: Any) -> list[Any]:
        names = self.input_names
        if isinstance(inputs, Mapping):
            missing = [n for n in names if n not in inputs]
            extra = [n for n in inputs if n not in names]
            if missing or extra:
                raise BackendError(
                    f"model {self.compiled.name!r} takes inputs {list(names)}; missing {missing}, unknown {extra}"
                )
            return [inputs[n] for n in names]
        if isinstance(inputs, np.ndarray):
            inputs = [inputs]
        if not isinstance(inputs, Sequence) or isinstance(inputs, (str, bytes)):
            raise BackendError(f"inputs must be a list or a dict of numpy arrays, not {type(inputs).__name__}")
        if len(inputs) != len(names):
            raise BackendError(
                f"model {self.compiled.name!r} takes {len(names)} inputs {list(names)}, got {len(inputs)}"
            )
        return list(inputs)

    @staticmethod
    def _checked(spec: Any, value: Any) -> np.ndarray:
        array = np.asarray(value)
        if array.dtype != np.float32:
            raise BackendError(
                f"input {spec.name!r} is {array.dtype}; NNCG compiles float32 models and takes float32 inputs only"
            )
        if tuple(array.shape) != tuple(spec.shape):
            raise BackendError(
                f"input {spec.name!r} has shape {tuple(array.shape)}; the model was compiled for {tuple(spec.shape)}"
            )
        return array


class NncgBackend(Backend):
    """prepare(model, device="CPU", target="ansi-c", unroll=2, opt="-O0", ...) -> NncgBackendRep.

    Compile options: target, unroll, input_shapes, pipeline, weights, code_budget (as for nncg.compile). Build options:
    cc (default: the first of cc, gcc, clang), opt (default -O0: fast builds), extra_cflags. The C is compiled
    with the target's strict flags in one compiler call; a warning fails the build.
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
        compiled = nncg_compile(model if isinstance(model, onnx.ModelProto) else _load(model), **options)
        workdir = tempfile.TemporaryDirectory(prefix="nncg-backend-")
        try:
            built = build_model(
                compiled,
                Path(workdir.name),
                cc=kwargs.get("cc"),
                opt=kwargs.get("opt", cls.default_opt),
                extra_cflags=tuple(kwargs.get("extra_cflags", ())),
                single_invocation=True,
            )
        except BaseException:
            workdir.cleanup()
            raise
        return NncgBackendRep(compiled, built, workdir)

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
        """Runs one node: wraps it in a float32 model with the inputs' shapes (outputs inferred)."""
        arrays = list(inputs.values()) if isinstance(inputs, Mapping) else list(inputs)
        names = [n for n in node.input if n]
        if len(names) != len(arrays):
            raise BackendError(f"node {node.op_type} has {len(names)} inputs, got {len(arrays)} arrays")
        opset = kwargs.pop("opset_version", onnx.defs.onnx_opset_version())
        helper = onnx.helper
        graph = helper.make_graph(
            [node],
            node.name or node.op_type.lower(),
            [
                helper.make_tensor_value_info(n, helper.np_dtype_to_tensor_dtype(np.asarray(a).dtype), np.shape(a))
                for n, a in zip(names, arrays)
            ],
            [helper.make_tensor_value_info(n, onnx.TensorProto.FLOAT, None) for n in node.output if n],
        )
        model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", opset)])
        return cls.prepare(model, device, **kwargs).run(arrays)

    @classmethod
    def supports_device(cls, device: str) -> bool:
        try:
            return Device(device).type == DeviceType.CPU
        except (AttributeError, ValueError):
            return False


def _load(model: Any) -> onnx.ModelProto | bytes | str:
    """Paths and bytes go to nncg.compile as they are (it reads external data next to a file)."""
    if isinstance(model, (str, Path, bytes)):
        return str(model) if isinstance(model, Path) else model
    raise BackendError(f"cannot prepare a {type(model).__name__}; pass an onnx.ModelProto, a path or bytes")


prepare = NncgBackend.prepare
run_model = NncgBackend.run_model
run_node = NncgBackend.run_node
supports_device = NncgBackend.supports_device
