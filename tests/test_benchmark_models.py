"""The MLPerf Tiny benchmark models (benchmarks/models.py): valid, runnable, deterministic, reference-sized."""

import numpy as np
import onnx
import onnxruntime as ort
import pytest
from onnx import TensorProto

from benchmarks.models import MODELS, OUT_DIR, count_params_and_macs, same_pads

# name: (input shape, output shape, params, MACs, op types). The counts are those of the MLPerf Tiny
# reference Keras models (ResNet-8 78.7k/12.5M, DS-CNN 24.9k/2.66M, MobileNetV1-0.25 222k/7.49M,
# autoencoder 270k/264k), so they pin the architecture down.
CLASSIFIER_OPS = {"Conv", "BatchNormalization", "AveragePool", "Flatten", "Gemm", "Softmax"}
EXPECTED = {
    "resnet8": ((1, 3, 32, 32), (1, 10), 78_666, 12_501_632, CLASSIFIER_OPS | {"Relu", "Add"}),
    "dscnn": ((1, 1, 49, 10), (1, 12), 24_908, 2_656_768, CLASSIFIER_OPS | {"Relu"}),
    "mobilenet_v1_025": ((1, 3, 96, 96), (1, 2), 221_794, 7_489_664, CLASSIFIER_OPS | {"Clip"}),
    "autoencoder": ((1, 640), (1, 640), 269_992, 264_192, {"Gemm", "BatchNormalization", "Relu"}),
}


@pytest.fixture(scope="module", params=sorted(MODELS))
def built(request):
    return request.param, MODELS[request.param]()


def run(model, with_intermediates=False):
    """Run `model` in onnxruntime on a fixed-seed normal input; optionally expose every inferred tensor."""
    if with_intermediates:
        model = onnx.ModelProto.FromString(model.SerializeToString())
        model.graph.output.extend(model.graph.value_info)
    session = ort.InferenceSession(model.SerializeToString(), providers=["CPUExecutionProvider"])
    (inp,) = session.get_inputs()
    x = np.random.default_rng(0).standard_normal(inp.shape).astype(np.float32)
    return dict(zip([o.name for o in session.get_outputs()], session.run(None, {inp.name: x})))


def shape_of(value_info):
    return tuple(d.dim_value for d in value_info.type.tensor_type.shape.dim)


def test_expected_covers_every_model():
    assert set(EXPECTED) == set(MODELS)


def test_model_is_valid_with_the_expected_interface(built):
    name, model = built
    onnx.checker.check_model(model, full_check=True)
    assert model.ir_version == 8 and [(o.domain, o.version) for o in model.opset_import] == [("", 13)]
    (inp,), (out,) = model.graph.input, model.graph.output
    in_shape, out_shape, *_, ops = EXPECTED[name]
    assert (shape_of(inp), shape_of(out)) == (in_shape, out_shape)
    assert inp.type.tensor_type.elem_type == out.type.tensor_type.elem_type == TensorProto.FLOAT
    assert all(t.data_type == TensorProto.FLOAT for t in model.graph.initializer)
    assert {node.op_type for node in model.graph.node} == ops
    names = [node.name for node in model.graph.node]
    assert all(names) and len(set(names)) == len(names)


def test_params_and_macs_match_the_reference(built):
    name, model = built
    assert count_params_and_macs(model) == EXPECTED[name][2:4]


def test_runs_in_onnxruntime_with_activations_of_order_one(built):
    name, model = built
    outputs = run(model, with_intermediates=True)
    (y,) = (outputs[o.name] for o in model.graph.output)
    assert y.shape == EXPECTED[name][1]
    # He-scaled weights: no tensor explodes or vanishes, so relative error checks stay meaningful.
    for tensor, value in outputs.items():
        assert np.isfinite(value).all() and np.abs(value).max() < 100, tensor
    if name != "autoencoder":
        assert y.sum() == pytest.approx(1.0, abs=1e-5) and y.max() < 0.99  # softmax, not saturated
    else:
        assert 0.1 < y.std() < 10


def test_files_on_disk_are_what_the_builders_produce(built):
    name, model = built
    path = OUT_DIR / f"{name}.onnx"
    assert path.is_file(), f"{path} is missing: run python benchmarks/models.py"
    assert path.read_bytes() == model.SerializeToString() == MODELS[name]().SerializeToString()


@pytest.mark.parametrize(
    "size, kernel, stride, pads",
    [(49, 10, 2, (4, 5)), (10, 4, 2, (1, 1)), (32, 3, 1, (1, 1)), (32, 3, 2, (0, 1)), (32, 1, 2, (0, 0))],
)
def test_same_pads_follow_tensorflow(size, kernel, stride, pads):
    assert same_pads(size, kernel, stride) == pads
