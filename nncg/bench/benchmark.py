"""`--benchmark` and `--profile`: NNCG's generated C against onnxruntime on the same model and inputs,
measured interleaved (A B A B ...) so the ratio holds while the machine drifts, and against the
peak of the instruction set the target uses. Every ratio is paired: the median over batches of the
two timers' ratio within a batch (paired_ratio), as a batch's timers run seconds apart."""

from __future__ import annotations

import os
import statistics
import tempfile
import time
from collections.abc import Sequence
from contextlib import ExitStack, contextmanager
from dataclasses import dataclass
from pathlib import Path

from ..compiler import compile as compile_model
from ..compiler import memory_figures
from ..errors import NncgError
from ..frontend import load_model
from ..safe_text import shown
from ..verify import compare, find_c_compiler, random_inputs
from .harness import CompiledHarness, ObjectSizes
from .onnxruntime_timer import THREADS, OnnxruntimeTimer
from .peak import TARGET_ISA, PeakTimer, supported_isas
from .progress import progress_bar


@dataclass(frozen=True)
class BenchResult:
    model: str
    target: str
    nncg_us: float  # median µs per inference
    ort_bound_us: float  # onnxruntime, IOBinding
    ort_run_us: float  # onnxruntime, InferenceSession.run
    speedup: float  # ORT (IOBinding) over NNCG: the median of the per-batch ratios (paired_ratio)
    max_abs_err: float
    max_rel_err: float
    sizes: ObjectSizes
    macs: int
    peak_isa: str
    peak_gflops: float | None  # the ISA's peak: given, or the median of the peak sampled in each batch
    generate_seconds: float
    compile_seconds: float
    arena_bytes: int = 0  # the planned activation memory (NAME_ARENA_BYTES)
    activation_bytes: int = 0  # all activations side by side, without reuse
    layer_bound_bytes: int = 0  # the most one layer computed whole needs (the arena at --memory speed, about)
    all_activation_bytes: int = 0  # every activation of the model computed whole, side by side (the plan aside)
    plan: str = ""  # the layers run in bands (--memory, --ram-budget)
    ort_version: str = ""  # onnxruntime's, as the report names the opponent
    ort_threads: int = THREADS
    batch_us: tuple[float, ...] = ()  # NNCG's µs per inference in each batch, to pair with variants of its run
    paired_percent: float | None = None  # % of the peak kernel timed in the same batches; None: fixed peaks

    @property
    def gflops(self) -> float:
        return 2 * self.macs / (self.nncg_us * 1e-6) / 1e9

    @property
    def percent_of_peak(self) -> float | None:
        if self.paired_percent is not None:
            return self.paired_percent
        return None if not self.peak_gflops else 100 * self.gflops / self.peak_gflops

    @property
    def effective_peak(self) -> bool:
        """Above 100 %: GFLOP/s count a direct convolution's multiply-adds, and Winograd does fewer, so
        the percentage is an effective one, not the share of the peak the code reaches."""
        percent = self.percent_of_peak
        return percent is not None and percent > 100

    def peak_cell(self) -> str:
        percent = self.percent_of_peak
        if percent is None:
            return "n/a"
        return f"{percent:.1f}{' effective' if self.effective_peak else ''} ({self.peak_isa})"


def calibrate(timer, min_seconds: float) -> int:
    """Calls per batch so a batch lasts at least min_seconds; the calls made doubling are warm-up."""
    calls = 1
    while (elapsed := timer(calls)) < min_seconds:
        calls = max(calls * 2, int(calls * 1.2 * min_seconds / max(elapsed, 1e-9)))
    return calls


def interleaved_samples(timers: dict, batches: int, min_seconds: float) -> dict[str, list[float]]:
    """Seconds per call of each timer in each batch, batches run in turn A B C B C A C A B ... (a progress
    bar on a terminal): the order rotates so no timer always runs after the same one. Sample i of every
    timer comes from batch i, so paired_ratio can set them against each other."""
    calls = {key: calibrate(timer, min_seconds) for key, timer in timers.items()}
    samples: dict[str, list[float]] = {key: [] for key in timers}
    keys = list(timers)
    with progress_bar(batches, "benchmark: batches") as bar:
        for batch in range(batches):
            for key in keys[batch % len(keys) :] + keys[: batch % len(keys)]:
                samples[key].append(timers[key](calls[key]) / calls[key])
            bar.update()
    return samples


def paired_ratio(numerator: Sequence[float], denominator: Sequence[float]) -> float:
    """The median of numerator[i] / denominator[i], samples of the same batches: a slow spell of the
    machine lasting a batch or more slows both of a pair and cancels, where it moves a ratio of medians."""
    return statistics.median(n / d for n, d in zip(numerator, denominator, strict=True))


def percent_of_sampled_peak(macs: int, seconds: Sequence[float], peak_gflops: Sequence[float]) -> float:
    """% of peak paired like a ratio: the median over batches of the code's GFLOP/s in a batch (`seconds`
    per inference) over the peak kernel's in the same batch, so a slow spell of the machine, which slows
    both, cancels instead of reading as inefficient code."""
    return 100 * paired_ratio([2 * macs / s * 1e-9 for s in seconds], peak_gflops)


def benchmark(
    model,
    target: str = "ssse3",
    unroll: str | int | None = "auto",
    *,
    batches: int = 15,
    min_batch_seconds: float = 0.02,
    cc: str | None = None,
    cpu: int | None = None,
    peaks: dict[str, float | None] | None = None,
    input_shapes=None,
    **compile_options,
) -> BenchResult:
    """Compiles `model` (compile_options go to nncg.compile), then times it and onnxruntime side by
    side. `peaks` (GFLOP/s per ISA, from nncg.bench.peak.measure_peaks) fixes the peak; without it the
    peak kernel runs in every batch beside them and the % of peak is paired like the speed-up."""
    timing = Timing(batches, min_batch_seconds, cc, cpu, peaks)
    variants = {"": compile_options}
    return benchmark_variants(model, target, variants, unroll, timing, input_shapes=input_shapes)[""]


@dataclass(frozen=True)
class Timing:
    """How benchmark_variants times: `batches` medians of batches lasting `min_batch_seconds`, built
    with `cc`, on core `cpu`; `peaks` as benchmark() takes them."""

    batches: int = 15
    min_batch_seconds: float = 0.02
    cc: str | None = None
    cpu: int | None = None
    peaks: dict[str, float | None] | None = None


def benchmark_variants(
    model, target: str, variants: dict[str, dict], unroll="auto", timing: Timing = Timing(), input_shapes=None
) -> dict[str, BenchResult]:
    """Compiles `model` once per variant (its nncg.compile options, e.g. {"min": {"memory": "min"}}),
    then times every variant and onnxruntime in one interleaved run, so the variants' ratios to each
    other are measured side by side, on the same inputs."""
    if target not in TARGET_ISA:  # neon: ARM code, which the x86 host neither builds nor has a peak for
        raise NncgError(f"--benchmark times x86 targets ({', '.join(TARGET_ISA)}) on this host, not {shown(target)}")
    cc, peaks = find_c_compiler(timing.cc), timing.peaks
    proto = load_model(model, input_shapes)
    builds = {
        name: _generate(model, target, unroll, input_shapes=input_shapes, **options)
        for name, options in variants.items()
    }
    first = next(iter(builds.values()))[0]
    inputs = random_inputs(first.inputs, seed=0)
    isa = TARGET_ISA[target]
    with pinned(timing.cpu), tempfile.TemporaryDirectory(prefix="nncg-bench-") as tmp, ExitStack() as running:
        harnesses = {name: _start(compiled, Path(tmp) / str(i), cc, inputs, running)
                     for i, (name, (compiled, _)) in enumerate(builds.items())}  # fmt: skip
        ort = OnnxruntimeTimer(proto, [p.name for p in first.inputs], inputs)
        timers = {("nncg", name): harness.run for name, harness in harnesses.items()}
        timers |= {"ort_bound": ort.run_bound, "ort_run": ort.run_plain}
        peak = peaks[isa] if peaks is not None else _peak_timer(isa, cc, running)
        if isinstance(peak, PeakTimer):
            timers["peak"] = peak
        samples = interleaved_samples(timers, timing.batches, timing.min_batch_seconds)
        names = [p.name for p in first.outputs]
        stats = {name: compare(harness.outputs(), ort.outputs(), names) for name, harness in harnesses.items()}
    return {
        name: _result(build, samples["nncg", name], samples, stats[name], harnesses[name], peak, ort.version)
        for name, build in builds.items()
    }


def _peak_timer(isa: str, cc: str, running: ExitStack) -> PeakTimer | None:
    """The ISA's peak kernel as one more timer of the batches; None where the CPU lacks the ISA."""
    if isa not in supported_isas():
        return None
    timer = PeakTimer(isa, cc)
    running.callback(timer.close)
    return timer


def _start(compiled, workdir: Path, cc: str, inputs, running: ExitStack) -> CompiledHarness:
    """A harness in its own folder (the variants share the model's file names), closed with `running`."""
    workdir.mkdir()
    harness = CompiledHarness(compiled, workdir, cc, inputs)
    running.callback(harness.close)
    return harness


def _generate(model, target: str, unroll, **options):
    """The compiled model and the seconds its generation took."""
    start = time.perf_counter()
    compiled = compile_model(model, target=target, unroll=unroll, **options)
    return compiled, time.perf_counter() - start


def _result(build, nncg_samples, samples, stats, harness, peak, ort_version) -> BenchResult:
    """`peak`: the ISA's GFLOP/s as given, or the PeakTimer whose samples are in `samples["peak"]`."""
    compiled, generate_seconds = build
    paired_percent = None
    if isinstance(peak, PeakTimer):
        peak_gflops = [peak.gflops(seconds) for seconds in samples["peak"]]
        paired_percent = percent_of_sampled_peak(compiled.macs, nncg_samples, peak_gflops)
        peak = statistics.median(peak_gflops)
    figures = memory_figures(compiled)
    return BenchResult(
        model=compiled.name,
        target=compiled.target,
        nncg_us=statistics.median(nncg_samples) * 1e6,
        ort_bound_us=statistics.median(samples["ort_bound"]) * 1e6,
        ort_run_us=statistics.median(samples["ort_run"]) * 1e6,
        speedup=paired_ratio(samples["ort_bound"], nncg_samples),
        max_abs_err=max(s.max_abs for s in stats),
        max_rel_err=max(s.max_rel for s in stats),
        sizes=harness.sizes,
        macs=compiled.macs,
        peak_isa=TARGET_ISA[compiled.target],
        peak_gflops=peak,
        generate_seconds=generate_seconds,
        compile_seconds=harness.compile_seconds,
        arena_bytes=compiled.arena_bytes,
        activation_bytes=compiled.activation_bytes,
        layer_bound_bytes=figures.layer_bound_bytes,
        all_activation_bytes=figures.all_activation_bytes,
        plan=figures.plan,
        ort_version=ort_version,
        batch_us=tuple(seconds * 1e6 for seconds in nncg_samples),
        paired_percent=paired_percent,
    )


@dataclass(frozen=True)
class LayerTime:
    layer: str
    us: float
    percent: float
    macs: int

    @property
    def gflops(self) -> float:
        return 2 * self.macs / (self.us * 1e-6) / 1e9 if self.us > 0 else 0.0


def profile(
    model,
    target: str = "ssse3",
    unroll: str | int | None = "auto",
    *,
    min_seconds: float = 0.2,
    cc: str | None = None,
    cpu: int | None = None,
    cpu_time: bool = False,
    **compile_options,
) -> list[LayerTime]:
    """Time per layer, from timers the profile build puts around each layer's function, in wall time
    or with `cpu_time` in the thread's CPU time (compile_options go to nncg.compile)."""
    cc = find_c_compiler(cc)
    compiled = compile_model(model, target=target, unroll=unroll, profile=True, **compile_options)
    macs = dict(compiled.layer_macs)
    inputs = random_inputs(compiled.inputs, seed=0)
    with pinned(cpu), tempfile.TemporaryDirectory(prefix="nncg-profile-") as tmp:
        harness = CompiledHarness(compiled, Path(tmp), cc, inputs, profile=True, cpu_time=cpu_time)
        try:
            calls = calibrate(harness.run, min_seconds)  # also warms up
            harness.layer_seconds()  # discard what calibration accumulated
            harness.run(calls)
            rows = harness.layer_seconds()
        finally:
            harness.close()
    total = sum(seconds for _, seconds in rows) or 1.0
    return [
        LayerTime(layer, seconds / calls * 1e6, 100 * seconds / total, macs.get(layer, 0)) for layer, seconds in rows
    ]


@contextmanager
def pinned(cpu: int | None):
    """Runs the block (and the processes it starts) on one core when `cpu` is given."""
    if cpu is None:
        yield
        return
    before = os.sched_getaffinity(0)
    os.sched_setaffinity(0, {cpu})
    try:
        yield
    finally:
        os.sched_setaffinity(0, before)


SPEEDUP_NOTE = "speed-up: the median of the per-batch ratios ORT µs / NNCG µs (µs: medians of the batches)"


def format_results(results: list[BenchResult]) -> str:
    header = (
        "model",
        "target",
        "NNCG µs",
        "ORT µs",
        "ORT run µs",
        "speed-up",
        "GFLOP/s",
        "% peak",
        "max rel err",
        "text B",
        "rodata B",
        "bss B",
        "arena B",
        "layer bound B",
        "activations B",
    )
    rows = [header]
    for r in results:
        rows.append((
            r.model, r.target, f"{r.nncg_us:.2f}", f"{r.ort_bound_us:.2f}", f"{r.ort_run_us:.2f}",
            f"{r.speedup:.2f}x", f"{r.gflops:.2f}", r.peak_cell(), f"{r.max_rel_err:.1e}",
            str(r.sizes.text), str(r.sizes.rodata), str(r.sizes.bss), str(r.arena_bytes), str(r.layer_bound_bytes),
            str(r.activation_bytes),
        ))  # fmt: skip
    notes = [f"ORT: {opponent}" for opponent in dict.fromkeys(_opponent(r) for r in results)]
    notes.append(SPEEDUP_NOTE)
    notes += [f"memory plan of {r.model}: {r.plan}" for r in results if r.plan]
    if any(r.effective_peak for r in results):
        notes.append("effective: above 100 % as GFLOP/s count direct convolution's multiply-adds; Winograd does fewer")
    return "\n".join([_table(rows), *notes])


def _opponent(r: BenchResult) -> str:
    threads = f"{r.ort_threads} thread{'' if r.ort_threads == 1 else 's'}"
    return (
        f"onnxruntime {r.ort_version or '(version unknown)'}, {threads}, all graph optimisations "
        "(ORT µs: inputs and outputs bound with IOBinding; ORT run µs: InferenceSession.run)"
    )


def format_profile(rows: list[LayerTime]) -> str:
    table = [("layer", "µs", "%", "MACs", "GFLOP/s")]
    table += [(r.layer, f"{r.us:.2f}", f"{r.percent:.1f}", str(r.macs), f"{r.gflops:.2f}") for r in rows]
    total_us = sum(r.us for r in rows)
    table.append(("total", f"{total_us:.2f}", "100.0", str(sum(r.macs for r in rows)), ""))
    return _table(table)


def _table(rows) -> str:
    widths = [max(len(row[i]) for row in rows) for i in range(len(rows[0]))]
    return "\n".join("  ".join(cell.ljust(w) for cell, w in zip(row, widths)).rstrip() for row in rows)
