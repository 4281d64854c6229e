"""Backend: exp, log, tanh, sigmoid, erf and softplus of a float vector as polynomial approximations,
without a math.h call per lane; abs (the sign bit cleared) and sqrt (the ISA's instruction) beside
them. Each algorithm is written once, here, over a width's templates (the float operations of
vector_width.OPERATIONS plus the integer and bit operations of BIT_OPERATIONS), so every ISA prints
the same algorithm with the same constants; an ISA only fills its table (x86.py, neon.py). Where a
template is fused (`fma`) the ISA rounds once, elsewhere twice (SSE has only `fma_exact`, emulated in
double for the int8 kernels' exact sums, ~15 instructions: here SSE multiplies and adds):
the results differ in the last bit between ISAs, all within the bounds below.

Accuracy: the bounds, in ULPs (the float32 spacing at the exact result, 2^-149 for denormals), hold
on SSE (no FMA), AVX2, AVX-512 and NEON (AArch64; ARMv7 with and without VFPv4's FMA), checked by
tests/test_vector_math.py over every 4096th float32 bit pattern plus the edges against float64
numpy/scipy; the largest errors measured, there and over every 64th bit pattern (avx2, ssse3):

    function  bound  measured    function  bound  measured
    exp       1.5    1.01        sigmoid   4      3.25 (x = -16.289): SSE, AVX2, AVX-512 and
                                                  NEON AArch64 over every bit pattern, ARMv7 with
                                                  and without VFPv4 over every 16th + |x| in
                                                  [2, 32] (scripts/sigmoid_sweep.py)
    log       1      0.81        erf       1.5    1.11 (SSE, NEON), 1.03 (AVX)
    tanh      1.5    1.32        softplus  2      1.89
    abs       0      0           sqrt      0.5    0.5 (correctly rounded)

Specials are exact: NaN in, NaN out; exp(+Inf) = +Inf (and every x > 88.7228 overflows to +Inf),
exp(-Inf) = 0; log(+-0) = -Inf, log(x < 0) = NaN, log(+Inf) = +Inf; tanh, erf and sigmoid saturate
to +-1 (0 and 1); tanh(-0) = erf(-0) = -0; softplus(+Inf) = +Inf, softplus(-Inf) = 0.

Denormals are computed, not flushed, where the FPU does not flush them (x86 without DAZ/FTZ,
AArch64): exp of x in [-103.97, -87.34] is a (gradually underflowing) denormal, the product of two
normal scale factors, rounded once; log of a denormal is exact to the bound (the input is scaled by
2^23 first). ARMv7's NEON unit always flushes: there denormal inputs read as +-0 and denormal
results are 0."""

from __future__ import annotations

from collections.abc import Callable, Sequence

from ..ir.kinds import MathFunction
from .c_text import INDENT, c_float
from .vector_width import VectorWidth

# --------------------------------------------------------------------------- the constants, shared

# exp: x = n ln2 + r, |r| <= ln2/2 (Cody-Waite: LN2_HI has 9 significant bits, so n * LN2_HI is
# exact), exp(r) = 1 + r + r^2 P(r), exp(x) = exp(r) 2^n. P: 3e-9 relative error before rounding (a
# least-squares fit in relative error iterated to minimax, each float32 coefficient rounded before the
# next is fitted), one degree below Cephes expf's.
EXP_LOW, EXP_HIGH = -104.0, 89.0  # exp(-104) rounds to 0, exp(89) to +Inf: the clamp changes nothing
LOG2E = 1.44269504088896341
LN2_HI, LN2_LO = 0.693359375, -2.12194440e-4
ROUNDER = 12582912.0  # 1.5 * 2^23: adding it rounds to an integer, which its low bits hold
EXP_P = (1.3820411e-3, 8.368677e-3, 4.166827e-2, 1.6666521e-1, 4.9999994e-1)

# sigmoid's exp(r): 1 + r + r^2 Q(r), Q one degree below EXP_P (1.05e-7 relative error before rounding,
# a least-squares fit in relative error iterated to minimax): cheaper, and within sigmoid's bound.
SIGMOID_EXP_P = (8.312506e-3, 4.1890096e-2, 1.6667114e-1, 4.999923e-1)
# sigmoid(x) = 1 for x above 17.33 (exp(-x) < 2^-25): the clamp keeps 2^(n - 64) normal.
SIGMOID_HIGH = 32.0
# Adding it rounds to an integer n and leaves 256 + 127 - 64 + n in the low 9 bits, which a shift left
# by 23 makes the sign and exponent of -2^(n - 64) (ROUNDER's own bits there are 0).
SIGMOID_ROUNDER = ROUNDER + 256 + 127 - 64

# log: x = m 2^e, sqrt(1/2) <= m < sqrt(2), f = m - 1, log(x) = e ln2 + f - f^2/2 + f^3 P(f) (Cephes logf).
SQRT_HALF = 0.707106781186547524
FLT_MIN = 1.17549435e-38  # the smallest normal float
FLT_MAX = 3.40282347e38
LOG_P = (
    7.0376836292e-2,
    -1.1514610310e-1,
    1.1676998740e-1,
    -1.2420140846e-1,
    1.4249322787e-1,
    -1.6668057665e-1,
    2.0000714765e-1,
    -2.4999993993e-1,
    3.3333331174e-1,
)

# tanh: |x| < 0.625: x + x^3 P(x^2) (Cephes tanhf); beyond: 1 - 2 / (exp(2|x|) + 1), the sign of x.
TANH_SMALL = 0.625
TANH_P = (-5.70498872745e-3, 2.06390887954e-2, -5.37397155531e-2, 1.33314422036e-1, -3.33332819422e-1)

# erf: |x| < 1: x + x P(x^2) (P(0) = 2/sqrt(pi) - 1, so 2/sqrt(pi) is never rounded); 1 <= |x| <= 4:
# 1 - exp(-x^2) R(1/|x|), R a fit of erfc(a) exp(a^2) in 1/a. Both fits: least squares in relative
# error at Chebyshev nodes, each float32 coefficient rounded before the next is fitted. erf(4) rounds to 1.
ERF_HIGH = 4.0
ERF_P = (7.842288e-05, -0.0008006793, 0.0051879627, -0.026853643, 0.112835824, -0.37612626, 0.12837917)
ERF_R = (
    0.029679121,
    -0.17401093,
    0.42460886,
    -0.51841944,
    0.22257608,
    0.23907734,
    -0.37895855,
    0.021223841,
    0.5616815,
    0.00012575778,
)

# The bounds stated above, in ULPs, asserted by tests/test_vector_math.py on every vector target.
ULP_BOUNDS = {"exp": 1.5, "log": 1.0, "tanh": 1.5, "sigmoid": 4.0, "erf": 1.5, "softplus": 2.0, "abs": 0.0, "sqrt": 0.5}

# Float bit patterns, as the int32 an integer splat takes.
SIGN = "(-2147483647 - 1)"  # 0x80000000
MAGNITUDE = "2147483647"  # 0x7fffffff
MANTISSA = "8388607"  # 0x007fffff
HALF_EXPONENT = "1056964608"  # 0x3f000000: the bits of 0.5
QUIET_NAN = "2143289344"  # 0x7fc00000


# --------------------------------------------------------------------------- the algorithms, once


class _Body:
    """The statements of one helper, spelled from a width's templates; each method returns C text."""

    def __init__(self, width: VectorWidth, suffix: str = "") -> None:
        self.w = width
        self.suffix = suffix  # on every name, so that several bodies can share one function
        self.x = "x" + suffix  # the argument
        self.lines: list[str] = []
        self.used: dict[str, None] = {}  # the operations of width.ops spelled, in order

    def spell(self, op: str, **fields: str) -> str:
        self.used[op] = None
        return self.w.spell(op, **fields)

    def let(self, name: str, value: str, integer: bool = False) -> str:
        kind = self.w.bits["type"] if integer else self.w.type
        name += self.suffix
        self.lines.append(f"{INDENT}const {kind} {name} = {value};")
        return name

    # float
    def c(self, value: float) -> str:
        return self.spell("splat", value=c_float(value))

    def op(self, op: str, a: str, b: str) -> str:
        return self.spell(op, a=a, b=b)

    def fma(self, a: str, b: str, c: str) -> str:
        if "fma" in self.w.ops:
            return self.spell("fma", a=a, b=b, c=c)
        return self.op("+", self.op("*", a, b), c)

    def select(self, cmp: str, lhs: str, rhs: str, then: str, otherwise: str) -> str:
        return self.spell(cmp, lhs=lhs, rhs=rhs, then=then, otherwise=otherwise)

    def horner(self, x: str, coefficients: Sequence[float]) -> str:
        acc = self.c(coefficients[0])
        for k in coefficients[1:]:
            acc = self.fma(acc, x, self.c(k))
        return acc

    def call(self, fn: str, x: str) -> str:
        return f"{self.w.spell('math', fn=fn)}({x})"

    # integer and bits
    def i(self, op: str, **fields: str) -> str:
        return self.w.bits[op].format(**fields)

    def ibits(self, value: str) -> str:
        return self.i("splat", value=value)

    def masked(self, x: str, bits: str, op: str = "&") -> str:
        """The float x with its bits and-ed (or or-ed) with the int32 constant `bits`."""
        return self.i("to_float", a=self.i(op, a=self.i("from_float", a=x), b=self.ibits(bits)))


def _exp(b: _Body) -> str:
    x = b.let("xc", b.op("max", b.c(EXP_LOW), b.op("min", b.c(EXP_HIGH), b.x)))  # a NaN stays
    t = b.let("t", b.fma(x, b.c(LOG2E), b.c(ROUNDER)))
    n = b.let("n", b.op("-", t, b.c(ROUNDER)))
    r = b.let("r", b.fma(n, b.c(-LN2_LO), b.fma(n, b.c(-LN2_HI), x)))
    p = b.let("p", b.op("+", b.fma(b.horner(r, EXP_P), b.op("*", r, r), r), b.c(1.0)))
    # 2^n as two normal factors 2^(n/2) 2^(n - n/2), n in [-150, 128]: the second product rounds
    # once, to a denormal or to +Inf where exp does.
    k = b.let("k", b.i("-", a=b.i("from_float", a=t), b=b.i("from_float", a=b.c(ROUNDER))), integer=True)
    half = b.let("k1", b.i(">>", a=k, n="1"), integer=True)
    bias = b.ibits("127")

    def scale(e: str) -> str:
        return b.i("to_float", a=b.i("<<", a=b.i("+", a=e, b=bias), n="23"))

    return b.op("*", b.op("*", p, scale(half)), scale(b.i("-", a=k, b=half)))


def _log(b: _Body) -> str:
    scaled = b.select("<", b.x, b.c(FLT_MIN), b.op("*", b.x, b.c(8388608.0)), b.x)  # a denormal: times 2^23
    i = b.let("i", b.i("from_float", a=scaled), integer=True)
    m = b.let("m", b.i("to_float", a=b.i("|", a=b.i("&", a=i, b=b.ibits(MANTISSA)), b=b.ibits(HALF_EXPONENT))))
    low = b.let("low", b.select("<", m, b.c(SQRT_HALF), b.c(1.0), b.c(0.0)))  # m in [1/2, sqrt(1/2)): 2m
    exponent = b.i("convert", a=b.i(">>", a=i, n="23"))
    bias = b.select("<", b.x, b.c(FLT_MIN), b.c(149.0), b.c(126.0))
    e = b.let("e", b.op("-", b.op("-", exponent, bias), low))
    f = b.let("f", b.fma(m, low, b.op("-", m, b.c(1.0))))  # 2m - 1 or m - 1, exact
    z = b.let("z", b.op("*", f, f))
    y = b.let("y", b.fma(z, b.c(-0.5), b.fma(e, b.c(LN2_LO), b.op("*", b.op("*", f, z), b.horner(f, LOG_P)))))
    r = b.let("r", b.fma(e, b.c(LN2_HI), b.op("+", f, y)))
    nan = b.i("to_float", a=b.ibits(QUIET_NAN))
    finite = b.select("<=", b.x, b.c(FLT_MAX), r, b.x)  # +Inf and NaN are their own log
    return b.select("<", b.x, b.c(0.0), nan, b.select("<=", b.x, b.c(0.0), b.c(float("-inf")), finite))


def _tanh(b: _Body) -> str:
    a = b.let("a", b.masked(b.x, MAGNITUDE))
    z = b.let("z", b.op("*", a, a))
    small = b.let("small", b.fma(b.op("*", a, z), b.horner(z, TANH_P), a))
    e = b.call("exp", b.op("+", a, a))
    large = b.let("large", b.op("-", b.c(1.0), b.op("/", b.c(2.0), b.op("+", e, b.c(1.0)))))
    return _with_sign_of_x(b, b.select("<", a, b.c(TANH_SMALL), small, large))


def _sigmoid(b: _Body) -> str:
    # 1 / (1 + exp(-x)) as 2^-64 / (2^-64 + 2^-64 exp(-x)): one expression for both signs, with a
    # constant numerator (a sigmoid is in every SiLU epilogue: each operation counts). exp's
    # reduction with the signs in the constants: x clamped to [-104, 32], n = round(-x log2(e)),
    # v = x + n ln2 (Cody-Waite), exp(-x) = 2^n exp(-v). 2^(n - 64) is normal for every such n, so
    # nothing overflows or underflows before the division, which alone rounds the tiny results of
    # very negative x (denormals included). exp(-v) = 1 - w, w = v + v^2 q(v), q = -Q(-v) of
    # SIGMOID_EXP_P (one degree below exp's, within the bound), by Estrin: two short chains, not
    # one of five, as latency more than the count of operations bounds an epilogue on SSE. The
    # denominator is then 2^-64 + 2^(n - 64) - w 2^(n - 64), its first sum off the polynomial's path.
    x = b.let("xc", b.op("max", b.c(EXP_LOW), b.op("min", b.c(SIGMOID_HIGH), b.x)))  # a NaN stays
    t = b.let("t", b.fma(x, b.c(-LOG2E), b.c(SIGMOID_ROUNDER)))
    n = b.let("n", b.op("-", t, b.c(SIGMOID_ROUNDER)))
    v = b.let("v", b.fma(n, b.c(LN2_LO), b.fma(n, b.c(LN2_HI), x)))
    v2 = b.let("v2", b.op("*", v, v))
    q3, q2, q1, q0 = SIGMOID_EXP_P
    q = b.fma(v2, b.fma(b.c(q3), v, b.c(-q2)), b.fma(b.c(q1), v, b.c(-q0)))
    w = b.let("w", b.fma(v2, q, v))
    minus_scale = b.let("s", b.i("to_float", a=b.i("<<", a=b.i("from_float", a=t), n="23")))
    tiny = b.c(2.0**-64)
    return b.op("/", tiny, b.fma(w, minus_scale, b.op("-", tiny, minus_scale)))


def _erf(b: _Body) -> str:
    a = b.let("a", b.op("min", b.c(ERF_HIGH), b.masked(b.x, MAGNITUDE)))  # a NaN stays
    z = b.let("z", b.op("*", a, a))
    # Times 16, then 1/16 (both exact): a P(x^2) stays normal for a tiny normal x where a unit that
    # flushes denormals (ARMv7 NEON) multiplies and adds in two steps.
    a16 = b.op("*", a, b.c(16.0))
    small = b.let("small", b.op("*", b.fma(a16, b.horner(z, ERF_P), a16), b.c(0.0625)))
    u = b.let("u", b.op("/", b.c(1.0), a))
    tail = b.op("*", b.call("exp", b.op("-", b.c(0.0), z)), b.horner(u, ERF_R))
    large = b.let("large", b.op("-", b.c(1.0), tail))
    return _with_sign_of_x(b, b.select("<", a, b.c(1.0), small, large))


def _softplus(b: _Body) -> str:
    # max(x, 0) + log(1 + exp(-|x|)): exp never overflows, and log(1 + e) is log1p's: log(u) less
    # ((u - 1) - e) / u, the error of rounding u = 1 + e, so a tiny e (x far below 0) is kept.
    e = b.let("e", b.call("exp", b.masked(b.x, SIGN, "|")))
    u = b.let("u", b.op("+", b.c(1.0), e))
    log1p = b.op("-", b.call("log", u), b.op("/", b.op("-", b.op("-", u, b.c(1.0)), e), u))
    return b.op("+", b.op("max", b.x, b.c(0.0)), log1p)


def _abs(b: _Body) -> str:
    return b.masked(b.x, MAGNITUDE)


def _sqrt(b: _Body) -> str:
    return b.spell("sqrt", a=b.x)


def _with_sign_of_x(b: _Body, magnitude: str) -> str:
    sign = b.i("&", a=b.i("from_float", a=b.x), b=b.ibits(SIGN))
    return b.i("to_float", a=b.i("|", a=b.i("from_float", a=magnitude), b=sign))


ALGORITHMS: dict[str, tuple[Callable[[_Body], str], str]] = {
    "exp": (_exp, "x = n ln2 + r, exp(r) by a degree-6 polynomial, times 2^n"),
    "log": (_log, "x = m 2^e, log(m) by a degree-11 polynomial in m - 1, plus e ln2"),
    "tanh": (_tanh, "an odd polynomial below |x| = 0.625, 1 - 2 / (exp(2|x|) + 1) above"),
    "sigmoid": (_sigmoid, "2^-64 / (2^-64 + 2^-64 exp(-x)), exp(-x) = 2^n exp(-v) by a degree-5 polynomial"),
    "erf": (_erf, "x + x P(x^2) below |x| = 1, 1 - exp(-x^2) R(1/|x|) above"),
    "softplus": (_softplus, "max(x, 0) + log1p(exp(-|x|)), log1p as log(1 + e) corrected"),
    "abs": (_abs, "the sign bit cleared"),
    "sqrt": (_sqrt, "the ISA's square root"),
}
assert set(ALGORITHMS) == set(MathFunction)
# The functions a helper calls, printed before it.
CALLS = {"tanh": ("exp",), "erf": ("exp",), "softplus": ("exp", "log")}


def has_vector_math(width: VectorWidth) -> bool:
    """Whether the width's table has the integer and bit operations the algorithms need."""
    return bool(width.bits)


def _body(fn: str, width: VectorWidth) -> tuple[_Body, str]:
    body = _Body(width)
    return body, ALGORITHMS[fn][0](body)


def operations_used(fn: str, width: VectorWidth) -> tuple[str, ...]:
    """The operations of width.ops the helper of fn spells, in order of first use."""
    return tuple(_body(fn, width)[0].used)


def vector_math_helper(fn: str, width: VectorWidth) -> tuple[str, ...]:
    """The static function NAME(x) computing fn on each lane of a vector of `width`."""
    body, result = _body(fn, width)
    how = ALGORITHMS[fn][1]
    return (
        f"/* {fn} of each lane: {how}; max error {ULP_BOUNDS[fn]:g} ULP (nncg/backends/vector_math.py) */",
        f"static NNCG_INLINE {width.type} {width.spell('math', fn=fn)}({width.type} x)",
        "{",
        *body.lines,
        f"{INDENT}return {result};",
        "}",
    )


def interleaved_name(fn: str, width: VectorWidth, count: int) -> str:
    return f"{width.spell('math', fn=fn)}_x{count}"


def interleaved_math_helper(fn: str, width: VectorWidth, count: int) -> tuple[str, ...]:
    """The static function NAME(v) replacing each of v[0] .. v[count - 1] by fn of its lanes, the
    count evaluations' statements interleaved. A math function is a long chain of dependent
    operations; an out-of-order core holds few of them in its scheduler when they come one after
    another, and runs count side by side when they come side by side (backends/simd.py)."""
    bodies = [_Body(width, f"_{k}") for k in range(count)]
    results = [ALGORITHMS[fn][0](body) for body in bodies]
    return (
        f"/* {fn} of each lane of {count} vectors, interleaved: as {width.spell('math', fn=fn)} */",
        f"static NNCG_INLINE void {interleaved_name(fn, width, count)}({width.type} *v)",
        "{",
        *(f"{INDENT}const {width.type} {body.x} = v[{k}];" for k, body in enumerate(bodies)),
        *(line for lines in zip(*(body.lines for body in bodies), strict=True) for line in lines),
        *(f"{INDENT}v[{k}] = {result};" for k, result in enumerate(results)),
        "}",
    )


def with_callees(functions: set[str]) -> list[str]:
    """The functions and those they call, each after its callees, then by name."""
    needed = set(functions) | {callee for fn in functions for callee in CALLS.get(fn, ())}
    return sorted(needed, key=lambda fn: (fn in CALLS, fn))
