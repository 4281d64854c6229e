"""Sweeps a vector math function (default sigmoid) of one build of tests/test_vector_math.py over
float32 bit patterns against float64 scipy: every `--stride`th pattern of all 2^32, plus every
pattern whose magnitude lies in `--full LO HI` (the steep region), and prints the worst ULP error
and its input. Not a CI test: a whole sweep under qemu takes minutes.

    python3 scripts/sigmoid_sweep.py --build neon-4 --stride 16 --full 0 104
    python3 scripts/sigmoid_sweep.py --build neon-4-armv7 --stride 1
(build ids as the test's: ssse3-4, avx2-8, avx2-4, avx512-16, neon-4, neon-4-armv7; the two ARMv7
builds share an id, `--nofma` picks the one without VFPv4)."""

from __future__ import annotations

import argparse
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path[:0] = [str(ROOT), str(ROOT / "tests")]  # this tree's nncg, not an installed one
from test_vector_math import BUILDS, OPT, Build, reference, target_errors  # noqa: E402

from nncg.backends import BACKENDS  # noqa: E402
from nncg.backends.c_file import PORTABILITY_MACROS  # noqa: E402
from nncg.backends.simd_needs import Needs  # noqa: E402
from nncg.backends.vector_math import operations_used, with_callees  # noqa: E402
from nncg.cli import positive_number  # noqa: E402

CHUNK = 1 << 22  # patterns per chunk the program writes (lanes divide it)


def program(build: Build, fn: str) -> str:
    """C: argv = first pattern, count, stride; writes fn of each pattern (as float32) to stdout."""
    printer_class = BACKENDS[build.target]
    width = printer_class.widths[build.lanes]
    used = [op for f in with_callees({fn}) for op in operations_used(f, width)]
    definitions = tuple(dict.fromkeys((build.lanes, op) for op in used if op in width.helpers))
    printer = printer_class(Needs(definitions, frozenset({(build.lanes, fn)})))
    call = width.spell("math", fn=fn) + "(" + width.spell("load", address="&x[i]") + ")"
    return "\n".join(
        [
            "#include <stdio.h>",
            "#include <stdlib.h>",
            "#include <string.h>",
            *(f"#include {h}" for h in printer_class.includes),
            *PORTABILITY_MACROS,
            *printer.preamble(),
            f"static float x[{CHUNK}], y[{CHUNK}];",
            "int main(int argc, char **argv)",
            "{",
            "    unsigned long u, stride, left, n, i;",
            "    unsigned int bits;",
            "    if (argc != 4) return 2;",
            "    u = strtoul(argv[1], 0, 0); left = strtoul(argv[2], 0, 0); stride = strtoul(argv[3], 0, 0);",
            "    while (left) {",
            f"        n = left < {CHUNK} ? left : {CHUNK};",
            "        for (i = 0; i < n; ++i, u += stride) { bits = (unsigned int)u; memcpy(&x[i], &bits, 4); }",
            f"        for (i = n; i % {build.lanes}; ++i) x[i] = 0.0f;",
            f"        for (i = 0; i < n; i += {build.lanes}) {width.spell('store', address='&y[i]', value=call)};",
            "        if (fwrite(y, sizeof(float), n, stdout) != n) return 3;",
            "        left -= n;",
            "    }",
            "    return 0;",
            "}",
            "",
        ]
    )


def ranges(stride: int, full: tuple[float, float] | None) -> list[tuple[int, int, int]]:
    """(first pattern, count, stride) runs: all patterns at `stride`, then both signs' patterns with
    magnitude in [lo, hi] at stride 1 (those the strided run skipped; a few are counted twice)."""
    runs = [(0, (1 << 32) // stride, stride)]
    if full:
        lo, hi = (int(np.float32(v).view(np.uint32)) for v in full)
        runs += [(sign | lo, hi - lo + 1, 1) for sign in (0, 1 << 31)]
    return runs


def sweep(build: Build, fn: str, runs, exe: Path) -> tuple[float, float, int]:
    worst, at, count = -1.0, float("nan"), 0
    for first, total, stride in runs:
        command = [*build.emulator, str(exe), str(first), str(total), str(stride)]
        proc = subprocess.Popen(command, stdout=subprocess.PIPE)
        done = 0
        while done < total:
            n = min(CHUNK, total - done)
            y = np.frombuffer(proc.stdout.read(4 * n), dtype=np.float32)
            u = (first + stride * np.arange(done, done + n, dtype=np.uint64)).astype(np.uint32)
            x = u.view(np.float32)
            err = target_errors(build, fn, x, y, reference(fn, x))
            k = int(np.argmax(err))
            if err[k] > worst:
                worst, at = float(err[k]), float(x[k])
            done, count = done + n, count + n
        if proc.wait():
            raise SystemExit(f"{exe} failed")
    return worst, at, count


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--build", default="neon-4")
    parser.add_argument("--nofma", action="store_true", help="the ARMv7 build without VFPv4")
    parser.add_argument("--fn", default="sigmoid")
    parser.add_argument("--stride", type=positive_number, default=1)
    parser.add_argument("--full", type=float, nargs=2, metavar=("LO", "HI"))
    args = parser.parse_args()
    builds = [b for b in BUILDS if b.id == args.build]
    if not builds:
        raise SystemExit(f"no build {args.build}: {', '.join(b.id for b in BUILDS)}")
    build = builds[-1] if args.nofma else builds[0]
    with tempfile.TemporaryDirectory() as tmp:
        source, exe = Path(tmp) / "sweep.c", Path(tmp) / "sweep"
        source.write_text(program(build, args.fn))
        printer_class = BACKENDS[build.target]
        flags = [*build.flags, *printer_class.cflags, *printer_class.strict_cflags]
        subprocess.run([build.cc, OPT, *flags, str(source), "-o", str(exe), "-lm"], check=True)
        worst, at, count = sweep(build, args.fn, ranges(args.stride, args.full), exe)
    print(
        f"{args.fn} {build.id}{' (no VFPv4)' if args.nofma else ''} {build.flags}: {count} patterns, "
        f"worst {worst:.3f} ULP at x = {at!r} ({np.float32(at).view(np.uint32):#010x})"
    )


if __name__ == "__main__":
    main()
