"""The PyTorch route: a torch.nn.Module exported to ONNX in-process with torch.onnx.export, then
compiled like any ONNX model.

Torch is never a dependency of NNCG: this module imports it only when a module is passed, and a
torch.nn.Module can only exist once the caller has imported torch. The dynamo exporter (torch.export,
torch's default since 2.9) needs the onnxscript package too; the TorchScript exporter needs torch only.
"""

from __future__ import annotations

import importlib
import inspect
import io
import logging
import re
import sys
import warnings
from collections.abc import Iterator
from contextlib import contextmanager

import onnx

from nncg.errors import NncgError
from nncg.frontend.shapes import one_line
from nncg.safe_text import capped

EXPORTERS = ("dynamo", "torchscript")
DEFAULT_EXPORTER = "dynamo"


def is_torch_module(model: object) -> bool:
    """True for a torch.nn.Module, without importing torch."""
    torch = sys.modules.get("torch")
    return torch is not None and isinstance(model, torch.nn.Module)


def export_onnx(module, example_inputs, exporter: str = DEFAULT_EXPORTER) -> onnx.ModelProto:
    """`module` as ONNX for inputs shaped like `example_inputs` (a float32 tensor or a tuple of them),
    exported in eval mode (its training flags are restored afterwards) by `exporter` ("dynamo" or
    "torchscript"); the graph is named after the module's class. Raises NncgError."""
    check_exporter(exporter)
    torch = _require("torch", "pip install torch")
    inputs = _example_tuple(torch, example_inputs)
    if exporter == "dynamo":
        _require("onnxscript", "pip install onnxscript, or pass exporter='torchscript'")
    other = EXPORTERS[1 - EXPORTERS.index(exporter)]
    with _eval_mode(module), _quiet_export():
        try:
            proto = _dynamo(torch, module, inputs) if exporter == "dynamo" else _torchscript(torch, module, inputs)
        except Exception as exc:  # torch raises many kinds; all mean the module cannot be exported
            raise NncgError(
                f"torch.onnx.export ({exporter} exporter) cannot export {capped(type(module).__name__)}: "
                f"{_root_cause(exc)}; make forward traceable for these inputs or try exporter='{other}'"
            ) from None
    proto.graph.name = module_name(module)
    return proto


def check_exporter(exporter: object) -> None:
    if exporter not in EXPORTERS:
        raise NncgError(f"exporter must be one of {', '.join(map(repr, EXPORTERS))}; got {capped(repr(exporter), 60)}")


def module_name(module) -> str:
    """The module's class name in snake case (MobileNetV2 -> mobile_net_v2), the default C name."""
    return re.sub(r"(?<=[a-z0-9])(?=[A-Z])", "_", type(module).__name__).lower()


def _require(package: str, how: str):
    try:
        return importlib.import_module(package)
    except ImportError:
        raise NncgError(f"compiling a torch.nn.Module needs {package}, which is not installed: {how}") from None


def _example_tuple(torch, example_inputs) -> tuple:
    if example_inputs is None:
        raise NncgError(
            "compiling a torch.nn.Module needs example_inputs, tensors of the input shapes: "
            "e.g. nncg.compile(module, example_inputs=torch.zeros(1, 3, 32, 32))"
        )
    inputs = (example_inputs,) if isinstance(example_inputs, torch.Tensor) else example_inputs
    if not isinstance(inputs, (tuple, list)) or not inputs or not all(isinstance(x, torch.Tensor) for x in inputs):
        raise NncgError(
            "example_inputs must be a torch.Tensor or a tuple of them, one per input of forward; "
            f"got {type(example_inputs).__name__}"
        )
    for i, x in enumerate(inputs):
        if x.dtype != torch.float32:
            raise NncgError(f"example_inputs[{i}] is {x.dtype}; NNCG compiles float32 models: pass x.float()")
    return tuple(inputs)


def _root_cause(exc: BaseException) -> str:
    """The innermost cause, which names the problem in forward (the dynamo exporter wraps it in a
    TorchExportError of next steps), in one line."""
    while exc.__cause__ is not None:
        exc = exc.__cause__
    return f"{type(exc).__name__}: {one_line(exc, 200)}"


def _dynamo(torch, module, inputs: tuple) -> onnx.ModelProto:
    return torch.onnx.export(module, inputs, dynamo=True, verbose=False).model_proto


def _torchscript(torch, module, inputs: tuple) -> onnx.ModelProto:
    buffer = io.BytesIO()
    torch.onnx.export(module, inputs, buffer, dynamo=False, input_names=_input_names(module, len(inputs)))
    return onnx.load_model_from_string(buffer.getvalue())


def _input_names(module, count: int) -> list[str] | None:
    """forward's parameter names, which the dynamo exporter gives the inputs (TorchScript: input.1)."""
    positional = (inspect.Parameter.POSITIONAL_ONLY, inspect.Parameter.POSITIONAL_OR_KEYWORD)
    names = [p.name for p in inspect.signature(module.forward).parameters.values() if p.kind in positional]
    return names[:count] if len(names) >= count else None


@contextmanager
def _eval_mode(module) -> Iterator[None]:
    """Inference semantics (BatchNorm's running statistics, no Dropout) for the export only."""
    flags = [(m, m.training) for m in module.modules()]
    module.eval()
    try:
        yield
    finally:
        for m, training in flags:
            m.training = training


@contextmanager
def _quiet_export() -> Iterator[None]:
    """Hide what concerns torch, not the model: the deprecation notices of the TorchScript exporter
    and of torch.export's internals, and the dynamo exporter's log of ops it skips (torchvision's)."""
    logger = logging.getLogger("torch.onnx")
    level = logger.level
    logger.setLevel(logging.ERROR)
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", DeprecationWarning)
            warnings.simplefilter("ignore", FutureWarning)
            yield
    finally:
        logger.setLevel(level)
