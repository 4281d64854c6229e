"""The paper's three networks (examples/) x every target x unroll levels, compared with onnxruntime."""

from pathlib import Path

import pytest
from helpers import check_against_onnxruntime

import nncg

EXAMPLES = Path(__file__).resolve().parent.parent / "examples"
NETWORKS = ["ball", "pedestrian", "robot"]
TARGETS = ["ansi-c", "ssse3"]
# Level 0 only where the file stays reasonable (ball: ~0.3 MB of C; pedestrian and robot: tens of MB).
LEVELS = [("ball", 0)] + [(net, level) for net in NETWORKS for level in (1, 2, None)]


def optimisation_for(compiled) -> str:
    # gcc -O2 spends minutes in tree-PRE on the multi-megabyte straight-line bodies of level 1;
    # the check here is numerical, so those files are built at -O0 (the same printer paths are
    # built at -O2 for the smaller files).
    return "-O0" if len(compiled.source) > 1_000_000 else "-O2"


@pytest.mark.parametrize("target", TARGETS)
@pytest.mark.parametrize("network, level", LEVELS, ids=[f"{n}-unroll{lv}" for n, lv in LEVELS])
def test_network_matches_onnxruntime(network, level, target):
    path = EXAMPLES / f"{network}.onnx"
    compiled = nncg.compile(path, target=target, unroll=level)
    check_against_onnxruntime(nncg.load_model(path), compiled, opt=optimisation_for(compiled))
    if level == 0:
        assert "for (" not in compiled.source
    if target == "ssse3":
        assert "_mm_max_ps" in compiled.source and "#include <tmmintrin.h>" in compiled.source
    else:
        assert "_mm_" not in compiled.source


@pytest.mark.parametrize("target", TARGETS)
@pytest.mark.parametrize("network", NETWORKS)
def test_network_is_clean_under_sanitizers(network, target):
    path = EXAMPLES / f"{network}.onnx"
    check_against_onnxruntime(nncg.load_model(path), nncg.compile(path, target=target), sanitize=True)


@pytest.mark.parametrize("target", TARGETS)
def test_same_model_and_options_give_identical_c(target):
    path = EXAMPLES / "robot.onnx"
    a = nncg.compile(path, target=target, unroll=2)
    b = nncg.compile(path.read_bytes(), target=target, unroll=2, name="robot")
    assert (a.source, a.header) == (b.source, b.header)


def test_unroll_levels_trade_code_size():
    sizes = [len(nncg.compile(EXAMPLES / "ball.onnx", target="ssse3", unroll=lv).source) for lv in (None, 2, 1, 0)]
    assert sizes == sorted(sizes)
