"""The PyTorch route: nncg.compile(module, example_inputs=...) exports through torch.onnx.export (the
dynamo and the TorchScript exporter) and compiles. Every compiled module is run once and checked against
onnxruntime on the same export and against the module's own output. Skipped without torch; the dynamo
cases also need onnxscript."""

from __future__ import annotations

import importlib.util
import sys
from collections.abc import Callable

import numpy as np
import pytest
from helpers import skip_unless_host_runs

import nncg
from nncg.errors import NncgError
from nncg.frontend.torch_export import export_onnx
from nncg.verify import compare, reference_outputs, run_compiled

torch = pytest.importorskip("torch")
from torch import nn  # noqa: E402

TOLERANCE = 1e-4  # max abs error relative to the output's largest magnitude, as --verify
NEEDS_ONNXSCRIPT = pytest.mark.skipif(importlib.util.find_spec("onnxscript") is None, reason="needs onnxscript")
EXPORTERS = [pytest.param("dynamo", marks=NEEDS_ONNXSCRIPT), "torchscript"]


class SmallCnn(nn.Module):
    def __init__(self):
        super().__init__()
        self.features = nn.Sequential(
            nn.Conv2d(3, 8, 3, padding=1), nn.BatchNorm2d(8), nn.ReLU(), nn.MaxPool2d(2),
            nn.Conv2d(8, 16, 3, stride=2, bias=False), nn.BatchNorm2d(16), nn.ReLU(), nn.Dropout(0.5),
        )  # fmt: skip
        self.head = nn.Sequential(nn.Flatten(), nn.Linear(16 * 3 * 3, 10))

    def forward(self, x):
        return self.head(self.features(x))


def seeded(build: Callable[[], nn.Module], seed: int = 0) -> nn.Module:
    """The module `build` makes, its random weights fixed by `seed`, with random BatchNorm statistics and
    affine parameters, so that the normalisation is not the identity and the outputs are of order one."""
    torch.manual_seed(seed)
    module = build()
    for m in module.modules():
        if isinstance(m, nn.BatchNorm2d):
            n = m.num_features
            m.running_mean.copy_(torch.randn(n) * 0.1)
            m.running_var.copy_(torch.rand(n) + 0.5)
            m.weight.data.copy_(torch.rand(n) + 0.5)
            m.bias.data.copy_(torch.randn(n) * 0.1)
        elif isinstance(m, nn.Linear):
            m.reset_parameters()
    return module


def inference(module: nn.Module, x) -> np.ndarray:
    """The module's eval-mode output on `x` (the module is left in eval mode)."""
    with torch.no_grad():
        return module.eval()(x).numpy()


def max_errors(compiled, proto, expected: np.ndarray, x) -> tuple[float, float]:
    """Max relative errors of the compiled model run on `x` against onnxruntime on `proto` (the export
    it was compiled from) and against the module's output `expected`."""
    skip_unless_host_runs(compiled.target)
    inputs = [x.numpy()]
    (output,) = run_compiled(compiled, inputs)
    (against_ort,) = compare([output], reference_outputs(proto, compiled.inputs, inputs))
    (against_torch,) = compare([output], [expected])
    return against_ort.max_rel, against_torch.max_rel


@pytest.mark.parametrize("exporter", EXPORTERS)
def test_small_cnn_compiles_deterministically_and_matches_onnxruntime_and_torch(exporter):
    module = seeded(SmallCnn)
    x = torch.randn(1, 3, 16, 16)
    expected = inference(module, x)
    module.train()  # compiled for inference whatever its mode
    module.head.eval()
    proto = export_onnx(module, x, exporter)
    for target in ["ansi-c", "ssse3"]:
        compiled = nncg.compile(module, target=target, example_inputs=(x,), exporter=exporter)
        assert module.training and module.features.training and not module.head.training  # as it was
        assert max(max_errors(compiled, proto, expected, x)) <= TOLERANCE, target
    assert nncg.compile(module, target="ssse3", example_inputs=x, exporter=exporter).source == compiled.source
    assert f"torch-exporter={exporter};" in compiled.source.splitlines()[0]
    assert compiled.name == "small_cnn" and [p.name for p in compiled.inputs] == ["x"]


@pytest.fixture(scope="module")
def torch_models():
    from benchmarks import torch_models

    return torch_models


@pytest.mark.parametrize("exporter", EXPORTERS)
@pytest.mark.parametrize("name", ["mobilenet_v2", "resnet18"])
def test_torchvision_architecture_matches_onnxruntime_and_torch(torch_models, name, exporter):
    # nncg.compile(module) is export_onnx then the ONNX compile: exporting once keeps the test quick.
    module = seeded(lambda: torch_models.ARCHITECTURES[name](width=0.25, num_classes=10))
    x = torch.randn(1, 3, 32, 32)
    proto = export_onnx(module, x, exporter)
    against_ort, against_torch = max_errors(nncg.compile(proto, target="ssse3"), proto, inference(module, x), x)
    print(f"{name} {exporter}: max rel err {against_ort:.3g} vs onnxruntime, {against_torch:.3g} vs torch")
    assert max(against_ort, against_torch) <= TOLERANCE


class Failing(nn.Module):
    def forward(self, x):
        raise ValueError("no forward here")


BAD_CALLS = {
    "no example_inputs": (dict(), "needs example_inputs"),
    "example_inputs a list of arrays": (dict(example_inputs=[np.zeros(3)]), "must be a torch.Tensor or a tuple"),
    "example_inputs float64": (dict(example_inputs=torch.zeros(1, 3, 8, 8, dtype=torch.float64)), "float32"),
    "input_shapes": (dict(example_inputs=torch.zeros(1, 3, 8, 8), input_shapes={"x": (1, 3, 8, 8)}), "input_shapes"),
    "unknown exporter": (dict(example_inputs=torch.zeros(1, 3, 8, 8), exporter="fx"), "exporter must be one of"),
}


@pytest.mark.parametrize("case", BAD_CALLS)
def test_bad_torch_calls_raise_nncg_errors(case):
    options, message = BAD_CALLS[case]
    with pytest.raises(NncgError, match=message):
        nncg.compile(SmallCnn(), **options)


def test_example_inputs_with_an_onnx_model_is_an_error():
    with pytest.raises(NncgError, match="example_inputs is for a torch.nn.Module"):
        nncg.compile("examples/ball.onnx", example_inputs=torch.zeros(1, 3, 16, 16))


@pytest.mark.parametrize("exporter", EXPORTERS)
def test_a_module_torch_cannot_export_is_an_nncg_error(exporter):
    message = f"\\({exporter} exporter\\) cannot export Failing: ValueError: no forward here"
    with pytest.raises(NncgError, match=message):
        nncg.compile(Failing(), example_inputs=torch.zeros(1, 4), exporter=exporter)


def test_dynamo_exporter_without_onnxscript_says_how_to_fix_it(monkeypatch):
    monkeypatch.setitem(sys.modules, "onnxscript", None)  # import onnxscript now raises ImportError
    with pytest.raises(NncgError, match="pip install onnxscript, or pass exporter='torchscript'"):
        nncg.compile(SmallCnn(), example_inputs=torch.zeros(1, 3, 16, 16))
