"""The peak-throughput microbenchmark: ISA detection, that each kernel builds and yields a sane rate,
and clear errors. Timings are only checked to be positive and finite: they depend on the machine."""

import math

import pytest

from nncg.bench import peak
from nncg.errors import NncgError

FAST = {"min_seconds": 0.002, "repeats": 3}


def _require(isa: str) -> None:
    if isa not in peak.supported_isas():
        pytest.skip(f"this CPU does not support {isa} ({' and '.join(peak.ISAS[isa].cpu_flags)})")


def test_supported_isas_is_a_subset_in_order():
    supported = peak.supported_isas()
    assert set(supported) <= set(peak.ISAS)
    assert supported == [isa for isa in peak.ISAS if isa in supported]


def test_every_target_maps_to_a_known_isa():
    assert set(peak.TARGET_ISA.values()) <= set(peak.ISAS)


@pytest.mark.parametrize("isa", list(peak.ISAS))
def test_measure_peak_is_positive_and_finite(isa):
    _require(isa)
    gflops = peak.measure_peak(isa, **FAST)
    assert math.isfinite(gflops) and gflops > 0


def test_sse_kernel_uses_separate_mul_and_add():
    source = peak.kernel_source("sse")
    assert "_mm_mul_ps" in source and "_mm_add_ps" in source and "fmadd" not in source
    assert "-ffp-contract=off" in peak.ISAS["sse"].cflags


def test_clock_estimate_is_positive_and_finite():
    _require("sse")
    ghz = peak.measure_clock_ghz(**FAST)
    assert math.isfinite(ghz) and ghz > 0


def test_unknown_isa_raises():
    with pytest.raises(NncgError, match="unknown ISA 'neon'"):
        peak.measure_peak("neon", **FAST)


def test_unsupported_isa_raises(monkeypatch):
    monkeypatch.setattr(peak, "supported_isas", lambda: [])
    with pytest.raises(NncgError, match="not supported by this CPU"):
        peak.measure_peak("sse", **FAST)
    assert peak.measure_peaks() == {isa: None for isa in peak.ISAS}


def test_missing_compiler_raises():
    _require("sse")
    with pytest.raises(NncgError, match="not found on PATH"):
        peak.measure_peak("sse", cc="no-such-cc-nncg", **FAST)


def test_bad_arguments_raise():
    _require("sse")
    with pytest.raises(NncgError, match="min_seconds"):
        peak.measure_peak("sse", min_seconds=0, repeats=3)


def test_peak_timer_times_calls_and_refuses_output_it_cannot_read(monkeypatch):
    _require("sse")
    timer = peak.PeakTimer("sse")
    try:
        seconds = timer(2)
        assert math.isfinite(seconds) and seconds > 0 and timer.gflops(seconds / 2) > 0
        monkeypatch.setattr(peak, "run_tool", lambda *args, **kwargs: type("Done", (), {"stdout": "garbled"})())
        with pytest.raises(NncgError, match="printed no positive seconds"):
            timer(1)
    finally:
        timer.close()
