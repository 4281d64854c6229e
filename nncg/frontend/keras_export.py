"""The Keras route: a keras.Model (or a .keras/.h5 file, or a SavedModel folder) converted to ONNX
in-process by tf2onnx, then compiled like any ONNX model.

TensorFlow and tf2onnx are never dependencies of NNCG (the `keras` extra installs them): this module
imports them only when a Keras model or file is given, and a keras.Model can only exist once the caller
has imported keras. tf2onnx's own Keras entry (tf2onnx.convert.from_keras) does not work with Keras 3,
so the model is wrapped in a tf.function with a batch-dynamic input signature and converted with
tf2onnx.convert.from_function; a SavedModel's serving signature goes the same way. The inputs stay
NHWC as Keras has them (see layout.py for --input-layout nchw).
"""

from __future__ import annotations

import importlib
import logging
import os
import re
import sys
import warnings
from collections.abc import Iterator
from contextlib import contextmanager

import onnx

from nncg.errors import NncgError
from nncg.frontend.shapes import one_line
from nncg.safe_text import shown

KERAS_SUFFIXES = (".keras", ".h5", ".hdf5")
OPSET = 17


def is_keras_model(model: object) -> bool:
    """True for a keras.Model (Keras 3 or tf.keras), without importing keras."""
    for package in ("keras", "tf_keras"):
        keras = sys.modules.get(package)
        if keras is not None and isinstance(model, getattr(keras, "Model", ())):
            return True
    return False


def is_keras_path(model: object) -> bool:
    """A .keras/.h5 file name or a SavedModel folder (one with a saved_model.pb)."""
    if not isinstance(model, (str, os.PathLike)):
        return False
    path = os.fspath(model)
    if not isinstance(path, str):
        return False
    if path.lower().endswith(KERAS_SUFFIXES):
        return True
    return os.path.isdir(path) and os.path.isfile(os.path.join(path, "saved_model.pb"))


def keras_to_onnx(model) -> onnx.ModelProto:
    """A keras.Model, a .keras/.h5 file or a SavedModel folder as ONNX (tf2onnx, inference mode, NHWC
    inputs with a dynamic batch dim). Raises NncgError."""
    tf = _require("tensorflow")
    tf2onnx = _require("tf2onnx")
    with quiet_tf2onnx(), _keras_name_scopes_kept():
        if is_keras_model(model):
            function, signature, name = _model_function(tf, model)
        else:
            function, signature, name = _file_function(tf, os.fspath(model))
        try:
            proto, _ = tf2onnx.convert.from_function(function, input_signature=signature, opset=OPSET)
        except Exception as exc:  # tf2onnx raises many kinds; all mean the model cannot be converted
            raise NncgError(f"tf2onnx cannot convert the Keras model {shown(name)}: {_root_cause(exc)}") from None
    proto.graph.name = name
    proto.graph.doc_string = ""  # names the tf.function's trace, numbered per process
    _canonical_constants(proto.graph)
    _renumber_names(proto.graph)
    return proto


_MADE_CONSTANT = re.compile(r"^const\w*__\d+$")


def _canonical_constants(graph: onnx.GraphProto) -> None:
    """tf2onnx's optimisers walk sets of names, so the constants they make (const_starts__3,
    const_fold_opt__4: equal ones merged under either name) and the initializers' order change with
    Python's hash seed: name them const__1, const__2, ... and order all initializers by first use."""
    first_use: dict[str, int] = {}
    for node in graph.node:
        for name in node.input:
            first_use.setdefault(name, len(first_use))
    taken = {n for node in graph.node for n in (*node.input, *node.output)} | {t.name for t in graph.initializer}
    made = sorted(
        (t for t in graph.initializer if _MADE_CONSTANT.match(t.name)), key=lambda t: first_use.get(t.name, -1)
    )
    renames = {}
    for k, tensor in enumerate(made, 1):
        new = f"const__{k}"
        if new in taken and new != tensor.name:
            return  # an exporter's own name: leave the model as it is
        renames[tensor.name] = new
    order = sorted(
        graph.initializer, key=lambda t: (first_use.get(t.name, len(first_use)), renames.get(t.name, t.name))
    )
    for tensor in graph.initializer:
        tensor.name = renames.get(tensor.name, tensor.name)
    for node in graph.node:
        node.input[:] = [renames.get(n, n) for n in node.input]
    tensors = [onnx.TensorProto() for _ in order]
    for copy, tensor in zip(tensors, order):
        copy.CopyFrom(tensor)
    del graph.initializer[:]
    graph.initializer.extend(tensors)


_COUNTED = re.compile(r"__(\d+)(?=(:\d+)?$)")


def _renumber_names(graph: onnx.GraphProto) -> None:
    """tf2onnx names the nodes and values it makes NAME__N with a process-wide counter, so a second
    conversion in one process gives other names (and other C): number them 1, 2, ... in graph order.
    The numbers are unique, so renumbering them one-to-one keeps the names unique."""
    numbers: dict[str, str] = {}

    def renamed(text: str) -> str:
        def number(match: re.Match) -> str:
            return "__" + numbers.setdefault(match.group(1), str(len(numbers) + 1))

        return _COUNTED.sub(number, text)

    def visit(g: onnx.GraphProto) -> None:
        for value in (*g.input, *g.output, *g.value_info):
            value.name = renamed(value.name)
            for dim in value.type.tensor_type.shape.dim:
                if dim.HasField("dim_param"):
                    dim.dim_param = renamed(dim.dim_param)
        for tensor in g.initializer:
            tensor.name = renamed(tensor.name)
        for node in g.node:
            node.name = renamed(node.name)
            node.input[:] = [renamed(n) for n in node.input]
            node.output[:] = [renamed(n) for n in node.output]
            for attribute in node.attribute:
                for sub in (*([attribute.g] if attribute.HasField("g") else []), *attribute.graphs):
                    visit(sub)

    visit(graph)


def _model_function(tf, model):
    if not model.built or not getattr(model, "inputs", None):
        raise NncgError(
            f"the Keras model {shown(model.name)} has no known input shape: build it (keras.Input or "
            "model.build) or call it once on data before compiling"
        )
    signature = [
        tf.TensorSpec((None, *tuple(x.shape)[1:]), tf.float32, name=_input_name(x, i))
        for i, x in enumerate(model.inputs)
    ]  # fmt: skip
    if any(d is None for spec in signature for d in spec.shape[1:]):
        shapes = ", ".join(str(tuple(spec.shape)) for spec in signature)
        raise NncgError(f"the Keras model {shown(model.name)} has dynamic input dims besides the batch: {shapes}")

    @tf.function(input_signature=signature)
    def inference(*inputs):
        return model(inputs[0] if len(inputs) == 1 else list(inputs), training=False)

    return inference, signature, model.name


def _input_name(tensor, index: int) -> str:
    name = getattr(tensor, "name", "") or f"input_{index}"
    return name.split(":")[0]


def _file_function(tf, path: str):
    where = shown(path, 200)
    if not os.path.exists(path):
        raise NncgError(f"model file {where} does not exist; check the path")
    if os.path.isdir(path):
        return _saved_model_function(tf, path, where)
    keras = _require("keras")
    try:
        model = keras.models.load_model(path, compile=False)
    except Exception as exc:
        raise NncgError(f"cannot load the Keras model {where}: {_root_cause(exc)}") from None
    return _model_function(tf, model)


def _saved_model_function(tf, path: str, where: str):
    try:
        loaded = tf.saved_model.load(path)
    except Exception as exc:
        raise NncgError(f"cannot load the SavedModel {where}: {_root_cause(exc)}") from None
    signatures = getattr(loaded, "signatures", {})
    if "serving_default" not in signatures:
        raise NncgError(f"the SavedModel {where} has no serving_default signature; export it with model.export()")
    serving = signatures["serving_default"]
    specs = [spec for spec in serving.structured_input_signature[1].values()]
    signature = [tf.TensorSpec((None, *tuple(s.shape)[1:]), tf.float32, name=s.name) for s in specs]
    keys = list(serving.structured_input_signature[1])

    @tf.function(input_signature=signature)
    def inference(*inputs):
        outputs = serving(**dict(zip(keys, inputs)))
        return [outputs[k] for k in sorted(outputs)]

    inference._nncg_keep = loaded  # the variables live as long as the function
    return inference, signature, os.path.basename(os.path.normpath(path))


def keras_layout() -> str:
    """The image layout Keras builds layers in (keras.config.image_data_format; channels_last unless
    the user set it), for a converted model whose graph does not show its inputs' layout."""
    return "nhwc" if _require("keras").config.image_data_format() == "channels_last" else "nchw"


def _require(package: str):
    try:
        return importlib.import_module(package)
    except ImportError:
        raise NncgError(
            f"compiling a Keras model needs {package}, which is not installed: pip install 'nncg[keras]'"
        ) from None


def _root_cause(exc: BaseException) -> str:
    """The innermost cause in one line: the last line of its message, where TensorFlow's errors (after
    a traceback of the traced code) say what is wrong."""
    while exc.__cause__ is not None:
        exc = exc.__cause__
    lines = [line for line in str(exc).splitlines() if line.strip()]
    return f"{type(exc).__name__}: {one_line(lines[-1] if lines else exc, 200)}"


@contextmanager
def _keras_name_scopes_kept() -> Iterator[None]:
    """Keras 3 keeps its name-scope stack in process-wide state, and a trace that fails inside a model
    leaves the model's scope pushed: every Keras model built afterwards in the process would be named
    under it (and a scope named with a space breaks their training). The stack is put back as it was."""
    from keras.src.backend.common import global_state

    stack = list(global_state.get_global_attribute("name_scope_stack") or [])
    try:
        yield
    finally:
        global_state.set_global_attribute("name_scope_stack", stack)


@contextmanager
def quiet_tf2onnx() -> Iterator[None]:
    """Hide tf2onnx's and TensorFlow's progress log (INFO lines for every conversion step)."""
    loggers = [logging.getLogger(n) for n in ("tf2onnx", "tensorflow")]
    levels = [logger.level for logger in loggers]
    for logger in loggers:
        logger.setLevel(logging.ERROR)
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", DeprecationWarning)
            warnings.simplefilter("ignore", FutureWarning)
            warnings.simplefilter("ignore", UserWarning)
            yield
    finally:
        for logger, level in zip(loggers, levels):
            logger.setLevel(level)
