"""The MLPerf Tiny reference models as users get them (benchmarks/mlperf_tiny.py): written in Keras as the
mlcommons/tiny training scripts define them, converted Keras -> TFLite float -> ONNX with tf2onnx's
from_tflite. The conversion is deterministic, folds BatchNormalization away, and NNCG's C matches
onnxruntime on the KWS DS-CNN and the IC ResNet-8 for ansi-c and ssse3; the KWS DS-CNN's full-integer TFLite
conversion (a QDQ model) too, step for step. Skipped without TensorFlow or tf2onnx (the keras extra)."""

from __future__ import annotations

import os

import numpy as np
import onnx
import pytest
from helpers import check_against_onnxruntime, skip_unless_host_runs
from int8_models import compare

os.environ.setdefault("TF_CPP_MIN_LOG_LEVEL", "3")  # TensorFlow's C++ start-up log
pytest.importorskip("tensorflow")
pytest.importorskip("tf2onnx")

import nncg  # noqa: E402
from benchmarks import mlperf_tiny  # noqa: E402

TARGETS = ("ansi-c", "ssse3")
CHECKED = ("mlperf_kws_dscnn", "mlperf_ic_resnet8")
# Conv layers of the Keras definitions (IC: 7 3x3 + 2 1x1 shortcuts; KWS: 1 + 4 x (depthwise + pointwise)).
CONVS = {"mlperf_ic_resnet8": 9, "mlperf_kws_dscnn": 9}


@pytest.fixture(scope="module")
def converted() -> dict[str, bytes]:
    return {name: mlperf_tiny.onnx_bytes(name) for name in CHECKED}


def test_conversion_is_deterministic(converted):
    assert mlperf_tiny.onnx_bytes("mlperf_kws_dscnn") == converted["mlperf_kws_dscnn"]


@pytest.mark.parametrize("name", CHECKED)
def test_batchnorm_is_folded_into_the_convs(converted, name):
    model = onnx.load_from_string(converted[name])
    ops = [node.op_type for node in model.graph.node]
    assert ops.count("Conv") == CONVS[name] and "BatchNormalization" not in ops and "Mul" not in ops
    assert model.opset_import[0].version == mlperf_tiny.OPSET


@pytest.mark.parametrize("target", TARGETS)
@pytest.mark.parametrize("name", CHECKED)
def test_tf2onnx_model_matches_onnxruntime(converted, name, target):
    model = onnx.load_from_string(converted[name])
    check_against_onnxruntime(model, nncg.compile(model, target=target))


@pytest.fixture(scope="module")
def kws_int8() -> bytes:
    return mlperf_tiny.onnx_bytes("mlperf_kws_dscnn", int8=True)


def test_int8_conversion_is_deterministic_and_quantised(kws_int8):
    assert mlperf_tiny.onnx_bytes("mlperf_kws_dscnn", int8=True) == kws_int8
    ops = {node.op_type for node in onnx.load_from_string(kws_int8).graph.node}
    assert {"QuantizeLinear", "DequantizeLinear", "Conv"} <= ops and "BatchNormalization" not in ops


@pytest.mark.parametrize("target", [*TARGETS, "avx512vnni"])  # vpdpbusd on the int8 activations read as uint8
def test_tflite_int8_model_matches_onnxruntime(kws_int8, target):
    skip_unless_host_runs(target)
    model = onnx.load_from_string(kws_int8)
    (given,) = model.graph.input
    shape = [d.dim_value for d in given.type.tensor_type.shape.dim]
    feeds = [{given.name: np.random.default_rng(seed).standard_normal(shape, np.float32)} for seed in range(3)]
    result = compare(model, nncg.compile(model, target=target), feeds)
    assert result.max_steps == 0 and result.identical == 1.0, result
