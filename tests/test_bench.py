"""The benchmark harness, profile and report run and give well-formed output (never timing claims)."""

import math
import re
from pathlib import Path

import pytest
from helpers import nncg_onnx

from nncg.bench.benchmark import benchmark, format_profile, format_results, profile
from nncg.bench.macs import total_macs
from nncg.frontend import import_onnx

EXAMPLES = Path(__file__).resolve().parent.parent / "examples"
BALL = EXAMPLES / "ball.onnx"
FAST = dict(batches=3, min_batch_seconds=0.001, peaks={"sse": 10.0, "avx2-fma": None, "avx512-fma": None})


def test_macs_of_the_ball_network():
    # conv 8x(5x5x1) on 8x8, conv 12x(3x3x8) on 2x2, conv 2x(2x2x12) on 1x1
    assert total_macs(import_onnx(BALL)) == 8 * 8 * 8 * 25 + 2 * 2 * 12 * 72 + 2 * 48


@pytest.mark.parametrize("target", ["ansi-c", "ssse3"])
def test_benchmark_result_is_well_formed(target):
    r = benchmark(BALL, target=target, **FAST)
    for value in (r.nncg_us, r.ort_bound_us, r.ort_run_us, r.gflops, r.generate_seconds, r.compile_seconds):
        assert math.isfinite(value) and value > 0
    assert r.speedup == pytest.approx(r.ort_bound_us / r.nncg_us)
    assert r.percent_of_peak == pytest.approx(100 * r.gflops / 10.0)
    assert r.max_rel_err < 1e-4 and r.macs == total_macs(import_onnx(BALL))
    assert r.sizes.text > 0 and r.sizes.bss >= r.arena_bytes > 0 and r.peak_isa == "sse"
    assert r.arena_bytes < r.activation_bytes  # ball is a chain: the plan reuses memory
    table = format_results([r]).splitlines()
    assert table[0].split()[:3] == ["model", "target", "NNCG"] and table[1].split()[:2] == ["ball", target]


def test_profile_reports_every_layer_with_its_macs():
    rows = profile(BALL, target="ssse3", min_seconds=0.01)
    assert [r.layer for r in rows] == ["conv1", "pool1", "conv2", "conv3", "softmax1"]
    assert sum(r.percent for r in rows) == pytest.approx(100.0)
    assert all(r.us >= 0 for r in rows) and sum(r.macs for r in rows) == total_macs(import_onnx(BALL))
    assert format_profile(rows).splitlines()[-1].split()[0] == "total"


def test_cli_benchmark_and_profile_print_their_tables(tmp_path):
    args = [BALL, "--target", "ssse3", "-o", tmp_path, "--benchmark", "--profile", "--cpu", "0"]
    result = nncg_onnx(*args)
    assert result.returncode == 0, result.stderr
    assert re.search(r"^ball\s+ssse3\s+[\d.]+\s+[\d.]+\s+[\d.]+\s+[\d.]+x", result.stdout, re.M)
    assert re.search(r"^conv1\s+[\d.]+\s+[\d.]+\s+12800\s", result.stdout, re.M)
