"""The benchmark harness, profile and report run and give well-formed output (never timing claims)."""

import io
import math
import re
import statistics
from pathlib import Path

import onnxruntime
import pytest
from helpers import nncg_onnx

from nncg.bench.benchmark import (
    BenchResult,
    benchmark,
    format_profile,
    format_results,
    interleaved_samples,
    paired_ratio,
    percent_of_sampled_peak,
    profile,
)
from nncg.bench.harness import ObjectSizes
from nncg.bench.macs import total_macs
from nncg.bench.progress import progress_bar
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
    for value in (r.nncg_us, r.ort_bound_us, r.ort_run_us, r.speedup, r.gflops, r.generate_seconds, r.compile_seconds):
        assert math.isfinite(value) and value > 0
    assert len(r.batch_us) == 3 and r.nncg_us == sorted(r.batch_us)[1]  # the median batch
    assert r.percent_of_peak == pytest.approx(100 * r.gflops / 10.0)
    assert r.max_rel_err < 1e-4 and r.macs == total_macs(import_onnx(BALL))
    assert r.sizes.text > 0 and r.sizes.bss >= r.arena_bytes > 0 and r.peak_isa == "sse"
    assert r.arena_bytes < r.activation_bytes  # ball is a chain: the plan reuses memory
    table = format_results([r]).splitlines()
    assert table[0].split()[:3] == ["model", "target", "NNCG"] and table[1].split()[:2] == ["ball", target]


def test_percent_of_peak_pairs_each_batch_with_the_peak_sampled_beside_it():
    # 5e8 MACs: 1 GFLOP per inference. Batches 2 and 3 ran in a slow spell that halved the peak kernel too.
    assert percent_of_sampled_peak(500_000_000, [1.0, 2.0, 2.0], [2.0, 1.0, 1.0]) == pytest.approx(50.0)


def test_benchmark_without_given_peaks_times_the_peak_in_its_batches():
    r = benchmark(BALL, target="ssse3", batches=3, min_batch_seconds=0.001)
    assert r.paired_percent is not None and r.percent_of_peak == r.paired_percent
    assert r.paired_percent > 0 and r.peak_gflops > 0 and r.peak_isa == "sse"


def test_profile_reports_every_layer_with_its_macs():
    rows = profile(BALL, target="ssse3", min_seconds=0.01)
    assert [r.layer for r in rows] == ["conv1", "pool1", "conv2", "conv3", "softmax1"]
    assert sum(r.percent for r in rows) == pytest.approx(100.0)
    assert all(r.us >= 0 for r in rows) and sum(r.macs for r in rows) == total_macs(import_onnx(BALL))
    assert format_profile(rows).splitlines()[-1].split()[0] == "total"


@pytest.mark.parametrize("target", ["ansi-c", "ssse3"])
def test_profile_in_cpu_time_reports_every_layer(target):
    # the build with the thread-CPU-time clock compiles (ansi-c: C89 with the harness's flags) and times
    rows = profile(BALL, target=target, min_seconds=0.01, cpu_time=True)
    assert [r.layer for r in rows] == ["conv1", "pool1", "conv2", "conv3", "softmax1"]
    assert all(r.us >= 0 for r in rows) and sum(r.us for r in rows) > 0


def test_profile_clock_is_the_wall_clock_unless_the_build_says_otherwise():
    import nncg
    from nncg.backends.c_file import PROFILE_CPU_TIME_FLAG
    from nncg.c_harness import harness_source

    compiled = nncg.compile(BALL, target="ansi-c", profile=True)
    for source in (compiled.source, harness_source(compiled, commands=True, profile=True)):
        assert "#ifndef NNCG_PROFILE_CLOCK\n#define NNCG_PROFILE_CLOCK CLOCK_MONOTONIC\n#endif" in source
        assert "clock_gettime(NNCG_PROFILE_CLOCK, &" in source and "CLOCK_MONOTONIC, &" not in source
    assert PROFILE_CPU_TIME_FLAG == "-DNNCG_PROFILE_CLOCK=CLOCK_THREAD_CPUTIME_ID"


def test_cli_benchmark_and_profile_print_their_tables(tmp_path):
    args = [BALL, "--target", "ssse3", "-o", tmp_path, "--benchmark", "--profile", "--cpu", "0"]
    result = nncg_onnx(*args)
    assert result.returncode == 0, result.stderr
    assert re.search(r"^ball\s+ssse3\s+[\d.]+\s+[\d.]+\s+[\d.]+\s+[\d.]+x", result.stdout, re.M)
    assert re.search(r"^conv1\s+[\d.]+\s+[\d.]+\s+12800\s", result.stdout, re.M)
    assert f"ORT: onnxruntime {onnxruntime.__version__}, 1 thread," in result.stdout
    assert "\r" not in result.stderr  # stderr is a pipe here: no progress bar


def result_at(percent: float | None, version: str = "1.2.3") -> BenchResult:
    """A result whose GFLOP/s are `percent` of a 10 GFLOP/s peak (None: no peak known); no timing."""
    return BenchResult(
        model="m", target="avx2", nncg_us=2.0, ort_bound_us=4.0, ort_run_us=5.0, speedup=2.0, max_abs_err=0.0,
        max_rel_err=0.0,
        sizes=ObjectSizes(1, 1, 0, 1), macs=int(percent or 1) * 100, peak_isa="avx2-fma",
        peak_gflops=None if percent is None else 10.0, generate_seconds=0.1, compile_seconds=0.1, ort_version=version,
    )  # fmt: skip


def test_percent_of_peak_above_100_is_labelled_effective():
    assert result_at(150).percent_of_peak == pytest.approx(150.0)  # 2 * 15000 MACs in 2 us = 15 GFLOP/s
    assert result_at(150).peak_cell() == "150.0 effective (avx2-fma)"
    assert result_at(50).peak_cell() == "50.0 (avx2-fma)" and result_at(100).peak_cell() == "100.0 (avx2-fma)"
    assert result_at(None).peak_cell() == "n/a"
    assert "effective: above 100 %" in format_results([result_at(50), result_at(150)])
    assert "effective" not in format_results([result_at(50), result_at(None)])


def test_the_report_names_the_onnxruntime_version_and_threads_once():
    text = format_results([result_at(50, "1.2.3"), result_at(60, "1.2.3")])
    assert text.count("ORT: onnxruntime 1.2.3, 1 thread, all graph optimisations") == 1


class Terminal(io.StringIO):
    def isatty(self) -> bool:
        return True


def test_progress_bar_draws_on_a_terminal_only(monkeypatch):
    for stream, drawn in ((io.StringIO(), False), (Terminal(), True)):
        monkeypatch.setattr("sys.stderr", stream)
        with progress_bar(3, "benchmark: batches") as bar:
            for _ in range(3):
                bar.update()
        assert ("benchmark: batches" in stream.getvalue()) is drawn


def test_interleaved_timing_is_quiet_when_stderr_is_not_a_terminal(capsys):
    samples = interleaved_samples({"a": lambda calls: 1.0, "b": lambda calls: 2.0}, batches=4, min_seconds=0.5)
    assert samples == {"a": [1.0] * 4, "b": [2.0] * 4}
    assert capsys.readouterr().err == ""


def test_a_paired_ratio_cancels_a_slow_spell_a_ratio_of_medians_does_not():
    # ORT's and NNCG's seconds in five batches, ORT 2x slower with some noise of its own per batch
    ort, nncg = [2.4, 1.6, 2.0, 2.0, 2.0], [1.0] * 5
    assert paired_ratio(ort, nncg) == 2.0 and statistics.median(ort) / statistics.median(nncg) == 2.0
    slow = [1.0, 1.0, 1.0, 3.0, 3.0]  # the machine 3x slower for the last two batches, both timers
    ort_slow, nncg_slow = [t * s for t, s in zip(ort, slow)], [t * s for t, s in zip(nncg, slow)]
    assert paired_ratio(ort_slow, nncg_slow) == pytest.approx(2.0)
    assert statistics.median(ort_slow) / statistics.median(nncg_slow) == pytest.approx(2.4)


def test_a_paired_ratio_pairs_samples_of_one_run_only():
    with pytest.raises(ValueError):
        paired_ratio([1.0, 2.0], [1.0])


def test_interleaved_samples_pair_up_by_batch():
    # a machine 5x slower from the third batch on (the 7th timer call: two calibrate, two a batch)
    timer_calls = iter(range(100))

    def timer(seconds_per_call: float):
        return lambda calls: calls * seconds_per_call * (1.0 if next(timer_calls) < 6 else 5.0)

    samples = interleaved_samples({"a": timer(1.0), "b": timer(2.0)}, batches=5, min_seconds=0.5)
    assert samples == {"a": [1.0, 1.0, 5.0, 5.0, 5.0], "b": [2.0, 2.0, 10.0, 10.0, 10.0]}
    assert paired_ratio(samples["b"], samples["a"]) == 2.0


def test_interleaved_batches_rotate_the_order():
    order = []
    timers = {key: (lambda calls, key=key: order.append(key) or 1.0) for key in "abc"}
    interleaved_samples(timers, batches=3, min_seconds=0.5)
    assert "".join(order) == "abc" + "abcbcacab"  # calibration, then each batch starting one later
