"""Checks of the Python API's arguments (nncg.compile, CompiledModel.write): a wrong type or value is
an NncgError naming the argument and what it takes, not an AttributeError from deep inside."""

from __future__ import annotations

import io
import numbers
import os
from collections.abc import Mapping

import onnx

from .errors import NncgError
from .frontend.keras_export import is_keras_model
from .frontend.layout import check_layout
from .frontend.torch_export import check_exporter, is_torch_module
from .lowering.requantize import FORMS as REQUANTIZE_FORMS
from .passes.plan_memory import WEIGHTS_MODES
from .safe_text import capped, shown

DIM_MAX = 2**63 - 1  # ONNX dims are int64
MODEL_TYPES = (str, os.PathLike, bytes, bytearray, memoryview, onnx.ModelProto)


def check_compile_arguments(
    model, target, unroll, name, input_shapes, pipeline, print_ir_after_all, verify_ir, profile, weights, code_budget,
    example_inputs, exporter, expose_layers, input_layout=None, requantize="float",
) -> None:  # fmt: skip
    """Raises NncgError for the first argument of nncg.compile that has the wrong type or value."""
    _check_model(model)
    _check_torch_arguments(model, input_shapes, example_inputs, exporter)
    _check_str("target", target)
    _check_unroll(unroll)
    _check_str("name", name, optional=True)
    check_input_shapes(input_shapes)
    _check_str("pipeline", pipeline, optional=True)
    _check_stream("print_ir_after_all", print_ir_after_all)
    _check_bool("verify_ir", verify_ir)
    _check_bool("profile", profile)
    _check_bool("expose_layers", expose_layers)
    check_layout(input_layout)
    if weights not in WEIGHTS_MODES:
        raise NncgError(f"weights must be one of {', '.join(WEIGHTS_MODES)}; {_got(weights)}")
    if requantize not in REQUANTIZE_FORMS:
        raise NncgError(f"requantize must be one of {', '.join(REQUANTIZE_FORMS)}; {_got(requantize)}")
    if code_budget is not None and not _whole(code_budget):
        raise NncgError(f"code_budget must be an int >= 0 (0: no cap) or None; {_got(code_budget)}")


def check_write_arguments(directory, cmake) -> None:
    """Raises NncgError unless `directory` is a path (str or os.PathLike) and `cmake` a bool."""
    _check_path("directory", directory)
    _check_bool("cmake", cmake)


def _check_model(model) -> None:
    if not isinstance(model, MODEL_TYPES) and not is_torch_module(model) and not is_keras_model(model):
        raise NncgError(
            f"model must be a file path, bytes, an onnx.ModelProto, a torch.nn.Module or a keras.Model; {_got(model)}"
        )
    if isinstance(model, (str, os.PathLike)):
        _check_path("model", model)


def _check_torch_arguments(model, input_shapes, example_inputs, exporter) -> None:
    """example_inputs fix a torch module's input shapes; input_shapes fix an ONNX model's."""
    check_exporter(exporter)
    if not is_torch_module(model) and example_inputs is not None:
        raise NncgError("example_inputs is for a torch.nn.Module; an ONNX model's input shapes are set by input_shapes")
    if is_torch_module(model) and input_shapes is not None:
        raise NncgError("input_shapes is for ONNX models; a torch.nn.Module's input shapes are its example_inputs'")


def _check_path(what: str, path) -> None:
    if not isinstance(path, (str, os.PathLike)):
        raise NncgError(f"{what} must be a path (str or os.PathLike); {_got(path)}")
    text = os.fspath(path)
    if not isinstance(text, str) or not text or "\0" in text:
        raise NncgError(f"{what} must be a non-empty path without NUL characters; {_got(path)}")


def _check_str(what: str, value, optional: bool = False) -> None:
    if value is None and optional:
        return
    if not isinstance(value, str) or not value:
        none = " or None" if optional else ""
        raise NncgError(f"{what} must be a non-empty str{none}; {_got(value)}")


def _check_bool(what: str, value) -> None:
    if not isinstance(value, bool):
        raise NncgError(f"{what} must be True or False; {_got(value)}")


def _check_unroll(unroll) -> None:
    # The text of a str is checked with the pipeline it goes into ("auto", "none", a level).
    if unroll is not None and not isinstance(unroll, str) and not _whole(unroll):
        raise NncgError(f'unroll must be "auto", "none", None or a level (an int >= 0); {_got(unroll)}')


def check_input_shapes(shapes) -> None:
    if shapes is None:
        return
    if not isinstance(shapes, Mapping):
        raise NncgError(
            f"input_shapes must be a dict of input name to shape, e.g. {{'image': (1, 3, 60, 80)}}; {_got(shapes)}"
        )
    for key, dims in shapes.items():
        if not isinstance(key, str):
            raise NncgError(f"input_shapes must be keyed by input name (str); {_got(key)}")
        if not isinstance(dims, (tuple, list)) or not all(_whole(d) and 0 < d <= DIM_MAX for d in dims):
            raise NncgError(
                f"input_shapes[{shown(key)}] must be a tuple of ints from 1 to 2**63-1, e.g. (1, 3, 60, 80); "
                f"{_got(dims)}"
            )


def _check_stream(what: str, stream) -> None:
    if stream is None:
        return
    if isinstance(stream, (io.RawIOBase, io.BufferedIOBase)) or not callable(getattr(stream, "write", None)):
        raise NncgError(f"{what} must be a writable text stream such as sys.stderr, or None; {_got(stream)}")
    if getattr(stream, "closed", False) or not _writable(stream):
        raise NncgError(f"{what} must be an open, writable text stream; {_got(stream)}")


def _writable(stream) -> bool:
    writable = getattr(stream, "writable", None)
    return not callable(writable) or writable()


def _whole(value) -> bool:
    """An int >= 0 (numpy's ints too; bool is no number here)."""
    return isinstance(value, numbers.Integral) and not isinstance(value, bool) and value >= 0


def _got(value) -> str:
    return f"got {type(value).__name__} {capped(repr(value), 60)}"
