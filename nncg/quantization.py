"""nncg.quantize: a float ONNX model and calibration inputs to a QDQ model, written by
onnxruntime.quantization, whose calibrators set the activation ranges (NNCG has none of its own).

A model older than opset 13 is converted to 13 first (per-axis QuantizeLinear/DequantizeLinear); then
quant_pre_process runs (ONNX and symbolic shape inference, onnxruntime's basic graph optimisations:
BatchNormalization folded into Conv, constants folded), so that folded layers get one weight scale;
quantize_static then writes QuantizeLinear/DequantizeLinear pairs around the float operators (QDQ format):
activations per tensor (uint8 or int8, asymmetric), weights int8 (-64..64 with reduce_range), symmetric,
per channel on the output-channel axis (Conv: 0, ConvTranspose: 1, Gemm: by transB, MatMul: 1), biases
int32. The result is what nncg.compile takes; the same model and data give the same bytes (onnxruntime's
quantiser is deterministic; the opset imports its optimiser adds for domains no node uses are dropped).
The producer stays the float model's, which says the layout of its inputs."""

from __future__ import annotations

import io
import logging
import os
import tempfile
import warnings
from collections.abc import Iterator, Mapping
from contextlib import contextmanager, redirect_stdout
from pathlib import Path

import numpy as np
import onnx
import onnx.version_converter

from .arguments import check_input_shapes
from .calibration import calibration_samples
from .errors import NncgError
from .frontend.load import DEFAULT_DOMAINS, ModelSource, load_model, opset_version, real_inputs
from .frontend.shapes import one_line
from .safe_text import capped

ACTIVATIONS = ("uint8", "int8")
# onnxruntime's CalibrationMethod. Not Entropy: quantize_static runs it with as many histogram bins as
# quantised bins, so it keeps the whole range and writes the same bytes as MinMax.
ORT_METHODS = {"minmax": "MinMax", "percentile": "Percentile"}
CALIBRATE_METHODS = tuple(ORT_METHODS)
# Operators only a quantised model has (its activations are integers already); QLinear* of any domain too.
QUANTIZED_OPS = {"QuantizeLinear", "DynamicQuantizeLinear", "ConvInteger", "MatMulInteger"}
QDQ_OPSET = 13  # per-axis (per-channel) QuantizeLinear/DequantizeLinear


def quantize(
    model: ModelSource,
    calibration: str | os.PathLike | Mapping[str, np.ndarray] | np.ndarray,
    *,
    activations: str = "uint8",
    per_channel: bool = True,
    calibrate_method: str = "minmax",
    input_shapes: dict[str, tuple[int, ...]] | None = None,
    reduce_range: bool = False,
) -> onnx.ModelProto:
    """The QDQ model of the float ONNX `model` (a file path, bytes or an onnx.ModelProto), its activation
    ranges calibrated by onnxruntime on `calibration` (see nncg/calibration.py: an .npz keyed by input
    name with the samples along the first axis, a folder of .npy files, one per sample, or the same as
    arrays). `activations`: "uint8" (what onnxruntime's x86 kernels prefer) or "int8" (TFLite's choice);
    `per_channel`: one weight scale per output channel; `calibrate_method`: "minmax" (the whole range
    seen) or "percentile" (the 0.001 % of values at either end left out); `input_shapes` fixes dynamic
    input dims as in nncg.compile (a dynamic batch is 1); `reduce_range`: 7-bit weights (-64..64, as
    onnxruntime advises on x86 without VNNI), which ssse3 and avx2 multiply four channels per pmaddubsw
    (full-range weights mostly take pmaddwd pairs there), at half the weight resolution. Raises NncgError."""
    _check_arguments(activations, per_channel, calibrate_method, input_shapes, reduce_range)
    proto = _at_least_opset_13(load_model(model, input_shapes))
    _check_not_quantized(proto)
    samples = calibration_samples(calibration, real_inputs(proto.graph))
    quantized = _quantize_static(proto, samples, activations, per_channel, calibrate_method, reduce_range)
    _drop_unused_domains(quantized)
    # NNCG reads the inputs' layout from the producer (NHWC for tf2onnx's models, see layout.py), which
    # the quantiser overwrites: the QDQ model keeps the float model's.
    quantized.producer_name, quantized.producer_version = proto.producer_name, proto.producer_version
    return quantized


def _check_arguments(activations, per_channel, calibrate_method, input_shapes, reduce_range) -> None:
    if activations not in ACTIVATIONS:
        raise NncgError(f"activations must be one of {', '.join(ACTIVATIONS)}; got {_shown_value(activations)}")
    for name, value in (("per_channel", per_channel), ("reduce_range", reduce_range)):
        if not isinstance(value, bool):
            raise NncgError(f"{name} must be True or False; got {_shown_value(value)}")
    if calibrate_method not in CALIBRATE_METHODS:
        raise NncgError(
            f"calibrate_method must be one of {', '.join(CALIBRATE_METHODS)}; got {_shown_value(calibrate_method)}"
        )
    check_input_shapes(input_shapes)


def _shown_value(value: object) -> str:
    return f"{type(value).__name__} {capped(repr(value), 60)}"


def _at_least_opset_13(model: onnx.ModelProto) -> onnx.ModelProto:
    """Per-axis QuantizeLinear/DequantizeLinear came with opset 13; onnxruntime raises older models only to
    11 and then writes per-channel scales that opset 11 does not have (an invalid model)."""
    if opset_version(model) >= QDQ_OPSET:
        return model
    try:
        return onnx.version_converter.convert_version(model, QDQ_OPSET)
    except Exception as exc:  # the converter's errors come as several kinds
        raise NncgError(
            f"the model uses ONNX opset {opset_version(model)}, and onnx.version_converter cannot raise it to the "
            f"{QDQ_OPSET} that per-channel quantisation needs ({one_line(exc, 200)}): re-export it with opset "
            f"{QDQ_OPSET} or newer"
        ) from None


def _check_not_quantized(model: onnx.ModelProto) -> None:
    types = {node.op_type for node in model.graph.node}
    found = sorted(t for t in types if t in QUANTIZED_OPS or t.startswith("QLinear"))
    if found:
        raise NncgError(
            f"the model is quantised already ({', '.join(found)}): compile it as it is, or quantise the float "
            "model it was made from"
        )


def _quantize_static(
    model: onnx.ModelProto,
    samples: list[dict[str, np.ndarray]],
    activations: str,
    per_channel: bool,
    method: str,
    reduce_range: bool,
) -> onnx.ModelProto:
    from onnxruntime import quantization as q

    with tempfile.TemporaryDirectory(prefix="nncg-quantize-") as folder, _quiet():
        float_path, prepared, quantized = (Path(folder) / name for name in ("float.onnx", "pre.onnx", "qdq.onnx"))
        onnx.save(model, float_path)
        try:
            q.quant_pre_process(float_path, prepared)
            q.quantize_static(
                prepared,
                quantized,
                _reader(samples),
                quant_format=q.QuantFormat.QDQ,
                per_channel=per_channel,
                reduce_range=reduce_range,
                activation_type=q.QuantType.QUInt8 if activations == "uint8" else q.QuantType.QInt8,
                weight_type=q.QuantType.QInt8,
                calibrate_method=q.CalibrationMethod[ORT_METHODS[method]],
            )
        except Exception as exc:  # onnxruntime raises many kinds; all mean it cannot quantise this model
            raise NncgError(
                f"onnxruntime.quantization cannot quantise the model: {type(exc).__name__}: {one_line(exc, 200)}"
            ) from None
        return onnx.load(quantized)


def _reader(samples: list[dict[str, np.ndarray]]):
    """The samples as the CalibrationDataReader quantize_static pulls them from, one feed at a time."""
    from onnxruntime.quantization import CalibrationDataReader

    class Samples(CalibrationDataReader):
        def __init__(self):
            self._feeds = iter(samples)

        def get_next(self):
            return next(self._feeds, None)

    return Samples()


@contextmanager
def _quiet() -> Iterator[None]:
    """onnxruntime.quantization prints its calibrators' progress and logs advice as warnings on the root
    logger and through `warnings`; the user has nothing to act on there (pre-processing is done), and
    the CLI's stdout is for its own report, so all of it is hidden."""
    previous = logging.root.manager.disable
    logging.disable(logging.WARNING)
    try:
        with warnings.catch_warnings(), redirect_stdout(io.StringIO()):
            warnings.simplefilter("ignore")
            yield
    finally:
        logging.disable(previous)


def _drop_unused_domains(model: onnx.ModelProto) -> None:
    used = {node.domain for node in model.graph.node} | set(DEFAULT_DOMAINS)
    kept = [opset for opset in model.opset_import if opset.domain in used]
    del model.opset_import[:]
    model.opset_import.extend(kept)
