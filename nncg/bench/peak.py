"""Peak single-precision GFLOP/s of this core per instruction set, from a register-only C microbenchmark:
the hardware limit that "% of peak" of generated code is measured against."""

from __future__ import annotations

import math
import re
import sys
import tempfile
from dataclasses import dataclass
from pathlib import Path

from ..errors import NncgError
from ..host_cpu import cpu_flags
from ..tools import run_tool
from ..verify import find_c_compiler

COMPILE_TIMEOUT_S = 120
RUN_TIMEOUT_S = 600
UNROLL = 4  # kernel bodies per loop iteration, so the loop counter and branch are noise
CLOCK_ADDS = 100  # dependent integer adds per clock-loop iteration: one cycle each


@dataclass(frozen=True)
class _Isa:
    """How to build one ISA's kernel: the host CPU flags it needs, compiler flags, intrinsics."""

    cpu_flags: tuple[str, ...]
    cflags: tuple[str, ...]
    prefix: str  # intrinsic prefix: _mm, _mm256, _mm512
    vector: str  # C vector type
    lanes: int
    chains: int  # independent vector registers in flight; must cover latency x throughput
    fma: bool  # False: separate mul and add chains (SSE has no FMA)

    def body(self) -> list[str]:
        """One kernel body: one operation on each chain; no chain depends on another."""
        if self.fma:
            return [f"acc{k} = {self.prefix}_fmadd_ps(acc{k}, m, a);" for k in range(self.chains)]
        # Half the chains multiply, half add, so the mul and add ports are both busy every cycle.
        lines = []
        for k in range(0, self.chains, 2):
            lines.append(f"acc{k} = {self.prefix}_mul_ps(acc{k}, m);")
            lines.append(f"acc{k + 1} = {self.prefix}_add_ps(acc{k + 1}, a);")
        return lines

    @property
    def flops_per_body(self) -> int:
        # An FMA is 2 FLOPs per lane; a mul or an add is 1 (so a mul+add pair is 2 per lane).
        return self.chains * self.lanes * (2 if self.fma else 1)


# Chain counts cover latency x throughput: FMA is 4 cycles x 2 ports (8 in flight) on current Intel
# and AMD cores, so 12 FMA chains (plus m and a: 14 of 16 ymm registers) leave headroom; AVX-512 has
# 32 zmm registers, so 16 fit easily. SSE mul and add each have 2 ports of 3-4 cycles on Zen 4 and
# Golden Cove (12 in flight), so SSE uses 7 mul + 7 add chains: all 16 xmm registers with m and a.
ISAS: dict[str, _Isa] = {
    "sse": _Isa(("sse2", "ssse3"), ("-O2", "-mssse3", "-ffp-contract=off"), "_mm", "__m128", 4, 14, False),
    "avx2-fma": _Isa(("avx2", "fma"), ("-O2", "-mavx2", "-mfma"), "_mm256", "__m256", 8, 12, True),
    "avx512-fma": _Isa(("avx512f",), ("-O2", "-mavx512f"), "_mm512", "__m512", 16, 16, True),
}

# The ISA whose peak a target's code is measured against. ansi-c is built by the host compiler at
# -O3 with its default x86-64 ISA, i.e. SSE2, so its ceiling is the SSE mul+add peak. avx512vnni's
# float code is avx512's, so it shares that peak.
TARGET_ISA = {
    "ansi-c": "sse",
    "ssse3": "sse",
    "avx2": "avx2-fma",
    "avx512": "avx512-fma",
    "avx512vnni": "avx512-fma",
}

# Calibrates the trip count until one run lasts min_seconds, then times `repeats` runs and prints the
# best rate: the peak is what the core can do, and slower runs are interference (other VMs, interrupts).
_MAIN = r"""
static double now(void)
{
    struct timespec t;
    clock_gettime(CLOCK_MONOTONIC, &t);
    return (double)t.tv_sec + 1e-9 * (double)t.tv_nsec;
}

static double timed(long long iters)
{
    double start = now();
    kernel(iters);
    return now() - start;
}

int main(int argc, char **argv)
{
    double min_seconds, seconds, best = 1e300;
    long long iters = 1000;
    int repeats, r;
    if (argc == 2) { /* one timed run of ITERS iterations, as a timer beside other code */
        iters = atoll(argv[1]);
        printf("seconds=%.9g checksum=%.9g\n", timed(iters), sink);
        return 0;
    }
    if (argc != 3) {
        fprintf(stderr, "usage: %s MIN_SECONDS REPEATS | %s ITERS\n", argv[0], argv[0]);
        return 2;
    }
    min_seconds = atof(argv[1]);
    repeats = atoi(argv[2]);
    while ((seconds = timed(iters)) < min_seconds) {
        double scale = seconds > 0.0 ? 1.25 * min_seconds / seconds : 100.0;
        iters = (long long)((double)iters * (scale < 2.0 ? 2.0 : scale > 100.0 ? 100.0 : scale));
    }
    for (r = 0; r < repeats; ++r) {
        seconds = timed(iters);
        if (seconds < best) best = seconds;
    }
    printf("rate=%.9g iters=%lld seconds=%.9g checksum=%.9g\n",
           (double)iters * WORK_PER_ITER / best * 1e-9, iters, best, sink);
    return 0;
}
"""


def kernel_source(isa: str) -> str:
    """The complete C benchmark program for `isa`; it prints rate=<GFLOP/s> and a checksum."""
    spec = _spec(isa)
    p, names = spec.prefix, [f"acc{k}" for k in range(spec.chains)]
    body = [f"        {line}" for _ in range(UNROLL) for line in spec.body()]
    # Distinct starting values: identical chains could legally be merged into one by the compiler.
    inits = [f"    {spec.vector} acc{k} = {p}_set1_ps(init + {k}.0f);" for k in range(spec.chains)]
    total = names[0]
    for name in names[1:]:
        total = f"{p}_add_ps({total}, {name})"
    return "\n".join(
        [
            "#define _POSIX_C_SOURCE 199309L",
            "#include <immintrin.h>",
            "#include <stdio.h>",
            "#include <stdlib.h>",
            "#include <time.h>",
            "",
            f"#define WORK_PER_ITER {spec.flops_per_body * UNROLL}.0",
            "/* Volatile: the compiler cannot know these, so it can neither fold nor hoist the arithmetic.",
            "   m = 1 and a small a keep every value normal (no denormal slow path, no overflow). */",
            "static volatile float mul_in = 1.0f, add_in = 1e-7f, init_in = 1.0f;",
            "static volatile double sink;",
            "",
            "static __attribute__((noinline)) void kernel(long long iters)",
            "{",
            "    const float init = init_in;",
            f"    const {spec.vector} m = {p}_set1_ps(mul_in), a = {p}_set1_ps(add_in);",
            *inits,
            f"    float lanes[{spec.lanes}];",
            "    long long i;",
            "    int k;",
            "    for (i = 0; i < iters; ++i) {",
            *body,
            "    }",
            "    /* The checksum depends on every chain, so none of the work is dead. */",
            f"    {p}_storeu_ps(lanes, {total});",
            f"    for (k = 0; k < {spec.lanes}; ++k) sink += lanes[k];",
            "}",
            _MAIN,
        ]
    )


def clock_source() -> str:
    """C program timing a chain of dependent integer adds (1 cycle each on every x86): rate = GHz."""
    adds = "\\n\\t".join(["add $1, %0"] * CLOCK_ADDS)
    return "\n".join(
        [
            "#define _POSIX_C_SOURCE 199309L",
            "#include <stdio.h>",
            "#include <stdlib.h>",
            "#include <time.h>",
            "",
            f"#define WORK_PER_ITER {CLOCK_ADDS}.0",
            "static volatile unsigned long init_in = 1;",
            "static volatile double sink;",
            "",
            "static __attribute__((noinline)) void kernel(long long iters)",
            "{",
            "    unsigned long x = init_in;",
            "    long long i;",
            "    for (i = 0; i < iters; ++i)",
            f'        __asm__ volatile("{adds}" : "+r"(x));',
            "    sink = (double)x;",
            "}",
            _MAIN,
        ]
    )


def supported_isas() -> list[str]:
    """The ISAs of ISAS the host CPU supports; [] where that cannot be determined."""
    flags = cpu_flags()
    return [name for name, spec in ISAS.items() if flags.issuperset(spec.cpu_flags)]


def measure_peak(isa: str, cc: str | None = None, min_seconds: float = 0.02, repeats: int = 7) -> float:
    """Peak GFLOP/s of one core for `isa`: the best of `repeats` runs of at least `min_seconds`."""
    spec = _spec(isa)
    if isa not in supported_isas():
        needs = " and ".join(spec.cpu_flags)
        raise NncgError(f"ISA {isa!r} is not supported by this CPU (it needs {needs} in /proc/cpuinfo)")
    return _build_and_run(kernel_source(isa), spec.cflags, cc, min_seconds, repeats, f"{isa} peak benchmark")


def measure_peaks(cc: str | None = None) -> dict[str, float | None]:
    """measure_peak for every ISA in ISAS; None for those the host CPU does not support."""
    supported = supported_isas()
    return {isa: measure_peak(isa, cc) if isa in supported else None for isa in ISAS}


class PeakTimer:
    """The peak kernel of `isa` as a timer beside the code it is the peak of: timer(calls) runs the
    built program for `calls` x ITERS_PER_CALL iterations and returns the seconds it took, so the
    peak can be sampled in every batch of an interleaved benchmark and a % of peak paired like a
    ratio (a slow spell of the machine slows both). Close it to delete the program."""

    ITERS_PER_CALL = 1000  # a few us of work per call: calibrate() sizes the calls of a batch

    def __init__(self, isa: str, cc: str | None = None) -> None:
        spec = _spec(isa)
        self.flops_per_call = spec.flops_per_body * UNROLL * self.ITERS_PER_CALL
        self._tmp = tempfile.TemporaryDirectory(prefix="nncg_peak_")
        self._exe = _build(kernel_source(isa), spec.cflags, cc, Path(self._tmp.name), f"{isa} peak benchmark")

    def __call__(self, calls: int) -> float:
        out = run_tool([self._exe, str(calls * self.ITERS_PER_CALL)], "running the peak benchmark",
                       timeout=RUN_TIMEOUT_S).stdout  # fmt: skip
        return _printed_positive("seconds", out, "peak benchmark")

    def gflops(self, seconds_per_call: float) -> float:
        return self.flops_per_call / seconds_per_call * 1e-9

    def close(self) -> None:
        self._tmp.cleanup()


def measure_clock_ghz(cc: str | None = None, min_seconds: float = 0.02, repeats: int = 7) -> float:
    """The core clock in GHz while running scalar code, from dependent integer adds (x86 only).

    Heavy AVX-512 code may run at a lower clock, so FLOP/cycle derived from this is a lower bound.
    """
    if not supported_isas():
        raise NncgError("clock estimate needs an x86 CPU with a readable /proc/cpuinfo")
    return _build_and_run(clock_source(), ("-O2",), cc, min_seconds, repeats, "clock benchmark")


def _spec(isa: str) -> _Isa:
    if isa not in ISAS:
        raise NncgError(f"unknown ISA {isa!r}; choose one of {', '.join(ISAS)}")
    return ISAS[isa]


def _build_and_run(
    source: str, cflags: tuple[str, ...], cc: str | None, min_seconds: float, repeats: int, what: str
) -> float:
    """Compile `source` in a temporary directory, run it, and return the rate it prints."""
    if not (min_seconds > 0 and repeats >= 1):
        raise NncgError(f"{what}: min_seconds must be > 0 and repeats >= 1 (got {min_seconds}, {repeats})")
    with tempfile.TemporaryDirectory(prefix="nncg_peak_") as tmp:
        exe = _build(source, cflags, cc, Path(tmp), what)
        out = run_tool([exe, repr(min_seconds), str(repeats)], f"running the {what}", timeout=RUN_TIMEOUT_S).stdout
    return _printed_positive("rate", out, what)


def _build(source: str, cflags: tuple[str, ...], cc: str | None, folder: Path, what: str) -> Path:
    """`source` compiled with `cflags` into a program in `folder`."""
    src, exe = folder / "peak.c", folder / "peak"
    src.write_text(source)
    run_tool([find_c_compiler(cc), *cflags, "-o", exe, src], f"compiling the {what}", timeout=COMPILE_TIMEOUT_S)
    return exe


def _printed_positive(key: str, out: str, what: str) -> float:
    """The positive number the benchmark program printed as `key=...`."""
    match = re.search(rf"{key}=(\S+)", out)
    value = float(match.group(1)) if match else math.nan
    if not (math.isfinite(value) and value > 0):
        raise NncgError(f"the {what} printed no positive {key}: {out.strip()!r}")
    return value


def main(argv: list[str] | None = None) -> int:
    """Print a table of ISA, peak GFLOP/s and FLOP/cycle (from the measured clock); argv: [C compiler]."""
    cc = argv[0] if argv else None
    try:
        peaks = measure_peaks(cc)
        ghz = measure_clock_ghz(cc) if any(v is not None for v in peaks.values()) else None
    except NncgError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    print(f"{'ISA':<12}{'GFLOP/s':>10}{'FLOP/cycle':>12}")
    for isa, gflops in peaks.items():
        if gflops is None:
            print(f"{isa:<12}{'unsupported':>10}")
            continue
        per_cycle = f"{gflops / ghz:.1f}" if ghz else "-"
        print(f"{isa:<12}{gflops:>10.1f}{per_cycle:>12}")
    if ghz:
        print(f"scalar clock (dependent integer adds): {ghz:.2f} GHz; AVX-512 may run slower, so its FLOP/cycle")
        print("is a lower bound")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
