"""The real-size benchmark models (benchmarks/torch_models.py, benchmarks/nhwc_model.py), small: the torch.nn
rebuilds have torchvision's parameter counts, export deterministically, and NNCG matches onnxruntime on them
at 32x32 with reduced width. Marked `zoo` (whole-model tests); the torch ones skip when torch is absent."""

import onnx
import pytest
from helpers import check_against_onnxruntime

import nncg
from benchmarks.nhwc_model import keras_mobilenet_nhwc

pytestmark = pytest.mark.zoo

# SE blocks with HardSwish/HardSigmoid; channel shuffle (Split, Reshape, Transpose) and ReduceMean.
SMALL = [("mobilenet_v3_small", 0.5), ("shufflenet_v2_x0_5", 0.5)]


@pytest.fixture
def torch_models():
    pytest.importorskip("torch")
    from benchmarks import torch_models

    return torch_models


def test_architectures_have_torchvisions_parameter_counts(torch_models):
    for name, expected in torch_models.TORCHVISION_PARAMS.items():
        model = torch_models.build(name)
        assert sum(p.numel() for p in model.parameters()) == expected, name


def test_export_is_deterministic(torch_models):
    from benchmarks.real_models import export_bytes

    first, second = (export_bytes("mobilenet_v3_small", 32, width=0.25, num_classes=10) for _ in range(2))
    assert first == second


@pytest.mark.parametrize("name, width", SMALL)
def test_small_architecture_matches_onnxruntime(torch_models, name, width):
    from benchmarks.real_models import export_bytes

    model = onnx.load_from_string(export_bytes(name, 32, width=width, num_classes=10))
    check_against_onnxruntime(model, nncg.compile(model, target="ssse3"))


def test_nhwc_model_matches_onnxruntime():
    model = keras_mobilenet_nhwc(size=32)
    transposes = sum(node.op_type == "Transpose" for node in model.graph.node)
    assert transposes == 2 * sum(node.op_type == "Conv" for node in model.graph.node)
    check_against_onnxruntime(model, nncg.compile(model, target="ssse3"))
