"""The fixed-point requantisation helper (nncg/backends/c_integer.py, --requantize fixed) against
exact integer arithmetic: x * M / 2^(31 + s) rounded half away from zero, plus the zero point,
saturated. C89 has no 64-bit integer, so the helper builds the 62-bit product from 16-bit halves in
unsigned long; it runs here where long is 64 bits (the host) and where it is 32 bits (armhf and
i686 under qemu), on random cases and on the edges: |x| at 0, 1 and 2^31, M at both ends of
[2^30, 2^31), every shift, and products that land exactly on a half."""

from __future__ import annotations

import numpy as np
import pytest
from cross_helpers import TOOLCHAINS, missing_tools, runner

from nncg.backends.c_integer import REQUANTIZE_FIXED, TYPEDEFS
from nncg.tools import run_tool

INT32_MIN, INT32_MAX = -(2**31), 2**31 - 1

PROGRAM = "\n".join(
    [
        "#include <stdio.h>",
        *TYPEDEFS,
        *REQUANTIZE_FIXED,
        "int main(void)",
        "{",
        "    long x, m, s, zp, low, high;",
        '    while (scanf("%ld %ld %ld %ld %ld %ld", &x, &m, &s, &zp, &low, &high) == 6)',
        '        printf("%ld\\n", (long)nncg_requantize_fixed((nncg_int32)x, (nncg_int32)m, (nncg_int32)s,',
        "                                                     (nncg_int32)zp, (nncg_int32)low, (nncg_int32)high));",
        "    return 0;",
        "}",
        "",
    ]
)


def expected(x: int, m: int, s: int, zp: int, low: int, high: int) -> int:
    denominator = 2 ** (31 + s)
    q = (2 * abs(x) * m + denominator) // (2 * denominator)  # |x| * m / 2^(31+s), half rounded up
    y = q if x >= 0 else -q
    return min(max(y + zp, low), high)


def cases() -> list[tuple[int, ...]]:
    rng = np.random.default_rng(0)
    rows = []
    for x in (0, 1, -1, 2, -2, 255, -255, INT32_MAX, INT32_MIN, INT32_MIN + 1, 2**30, -(2**30)):
        for m in (2**30, 2**30 + 1, 2**31 - 1, 1518500250):
            for s in range(32):
                rows.append((x, m, s, 0, INT32_MIN, INT32_MAX))
    for s in range(1, 32):  # m = 2^30: x * m / 2^(31+s) = x / 2^(s+1), exactly 1.5 for x = 3 * 2^s
        for x in (3 * 2**s, -3 * 2**s, 2**s + 1, -(2**s) - 1):
            if INT32_MIN <= x <= INT32_MAX:
                rows.append((x, 2**30, s, 0, INT32_MIN, INT32_MAX))
    for _ in range(20000):
        x = int(rng.integers(INT32_MIN, INT32_MAX, endpoint=True)) >> int(rng.integers(0, 31))
        m = int(rng.integers(2**30, 2**31))
        s = int(rng.integers(0, 32))
        zp = int(rng.integers(-128, 256))
        low, high = (0, 255) if rng.random() < 0.5 else (-128, 127)
        rows.append((x, m, s, zp, low, high))
    return rows


@pytest.mark.parametrize("toolchain", ["host", "armhf", "i686-ansi-c"])
def test_fixed_point_helper_is_exact(toolchain, tmp_path):
    if toolchain == "host":
        cc, flags, prefix = "cc", (), ()
    else:
        tc = TOOLCHAINS[toolchain]
        if missing := missing_tools(tc):
            pytest.skip(f"needs {', '.join(missing)} (scripts/install-test-deps.sh installs it)")
        cc, flags, prefix = tc.cc, tc.flags, runner(tc)
    source, program = tmp_path / "fixed.c", tmp_path / "fixed"
    source.write_text(PROGRAM)
    run_tool(
        [cc, *flags, "-std=c89", "-pedantic", "-Wall", "-Wextra", "-Werror", "-O2", source, "-o", program], "build"
    )
    rows = cases()
    stdin = "".join(" ".join(map(str, r)) + "\n" for r in rows).encode()
    out = run_tool([*prefix, program], "run", stdin=stdin, text=False, timeout=300).stdout.decode().split()
    got = [int(v) for v in out]
    want = [expected(*r) for r in rows]
    assert len(got) == len(rows)
    wrong = [(r, g, w) for r, g, w in zip(rows, got, want) if g != w]
    assert not wrong, f"{len(wrong)} of {len(rows)} differ, first: {wrong[:3]}"
