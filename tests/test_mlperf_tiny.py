"""The four MLPerf-Tiny-shaped models of the benchmark suite compile and match onnxruntime on every target."""

from pathlib import Path

import pytest
from helpers import check_against_onnxruntime
from test_networks import optimisation_for

import nncg

MODELS = Path(__file__).resolve().parent.parent / "benchmarks" / "models"
# MobileNet's 1x1 convs at level 2 unroll c_out x c_in (up to 65k statements per pixel, 9.6 MB of C);
# until unrolling is chosen under a code budget it is compiled with its loops kept.
CASES = [("resnet8", 2), ("dscnn", 2), ("autoencoder", 2), ("mobilenet_v1_025", None)]
TARGETS = ["ansi-c", "ssse3"]


@pytest.mark.parametrize("target", TARGETS)
@pytest.mark.parametrize("name, unroll", CASES, ids=[c[0] for c in CASES])
def test_mlperf_tiny_model_matches_onnxruntime(name, unroll, target):
    path = MODELS / f"{name}.onnx"
    compiled = nncg.compile(path, target=target, unroll=unroll)
    check_against_onnxruntime(nncg.load_model(path), compiled, opt=optimisation_for(compiled))


# With loops kept: the level-2 bodies of the 64-channel layers take gcc more than 10 minutes with ASan.
@pytest.mark.parametrize("target", TARGETS)
@pytest.mark.parametrize("name", [c[0] for c in CASES])
def test_mlperf_tiny_model_is_clean_under_sanitizers(name, target):
    path = MODELS / f"{name}.onnx"
    compiled = nncg.compile(path, target=target, unroll=None)
    check_against_onnxruntime(nncg.load_model(path), compiled, sanitize=True, opt="-O1")
