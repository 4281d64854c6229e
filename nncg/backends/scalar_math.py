"""Backend: the math functions scalar C calls that C89's math.h lacks, as static helpers printed
before the kernels only when the program calls them (from scalar code, the scalar tails of SIMD
code, or a lane-wise vector helper): erf (C99's), computed in double, with math.h's exp, from the
coefficients of the vector erf (vector_math.py), so scalar code and vector lanes share one
approximation; and softplus log(1 + exp(x)).

erf: x + x P(x^2) below |x| = 1, 1 - exp(-x^2) R(1/|x|) up to |x| = 4, +-1 beyond (erf(4) rounds
to 1 in float). In double only the fits err, then the one rounding to float: the bound is 1 ULP,
0.533 ULP measured over every 64th float32 bit pattern against float64 scipy; tests/test_gelu.py
checks the bound against math.erf over every 4096th bit pattern and the edges. Specials are exact:
NaN in, NaN out; erf(+-Inf) = +-1; erf(-0) = -0; denormals are computed, not flushed.

softplus: max(x, 0) + log1p(exp(-|x|)) in double, log1p (C99's) as log(u) - ((u - 1) - e) / u with
u = 1 + e, which corrects the rounding of u; 0.5 ULP plus double's error, checked like erf's."""

from __future__ import annotations

from collections.abc import Callable, Iterable, Sequence

from ..ir.loops import Call, Program, stmt_exprs, walk_exprs, walk_stmts
from .c_text import INDENT, c_float
from .vector_math import ERF_HIGH, ERF_P, ERF_R

ULP_BOUNDS = {"erf": 1.0, "softplus": 1.0}  # asserted by tests/test_gelu.py and tests/test_unary_ops.py


def helper_name(fn: str) -> str:
    """The C name of the helper computing fn: nncg_ names are never a model's (ir/c_names.py)."""
    return f"nncg_{fn}"


def _horner(x: str, coefficients: Sequence[float]) -> str:
    """c0 x^n + ... + cn, in Horner's form; each coefficient the float32 value it was fitted as."""
    acc = c_float(coefficients[0])
    for k in coefficients[1:]:
        sign = "-" if k < 0 else "+"
        acc = f"({acc} * {x} {sign} {c_float(abs(k))})"
    return acc


def _erf() -> tuple[str, ...]:
    name = helper_name("erf")
    return (
        "/* erf(x), which C89's math.h lacks, in double: x + x P(x^2) below |x| = 1, 1 - exp(-x^2) R(1/|x|)"
        f" above; max error {ULP_BOUNDS['erf']:g} ULP (nncg/backends/scalar_math.py) */",
        f"static float {name}(float x)",
        "{",
        f"{INDENT}const double d = x;",
        f"{INDENT}double a = d < 0.0 ? -d : d;",
        f"{INDENT}double u, r;",
        f"{INDENT}if (a < 1.0) {{",
        f"{INDENT * 2}const double z = d * d;",
        f"{INDENT * 2}return (float)(d + d * {_horner('z', ERF_P)});",  # odd: erf(-0) = -0
        f"{INDENT}}}",
        f"{INDENT}a = a > {ERF_HIGH:.1f} ? {ERF_HIGH:.1f} : a; /* a NaN stays */",
        f"{INDENT}u = 1.0 / a;",
        f"{INDENT}r = 1.0 - exp(-(a * a)) * {_horner('u', ERF_R)};",
        f"{INDENT}return (float)(d < 0.0 ? -r : r);",
        "}",
    )


def _softplus() -> tuple[str, ...]:
    return (
        "/* softplus(x) = log(1 + exp(x)), in double: max(x, 0) + log1p(exp(-|x|)), log1p (C89's math.h lacks",
        f"   it) as log(1 + e) corrected; max error {ULP_BOUNDS['softplus']:g} ULP (nncg/backends/scalar_math.py) */",
        f"static float {helper_name('softplus')}(float x)",
        "{",
        f"{INDENT}const double d = x;",
        f"{INDENT}const double e = exp(-fabs(d));",
        f"{INDENT}const double u = 1.0 + e;",
        f"{INDENT}return (float)((d > 0.0 ? d : 0.0) + (log(u) - ((u - 1.0) - e) / u)); /* a NaN stays */",
        "}",
    )


HELPERS: dict[str, Callable[[], tuple[str, ...]]] = {"erf": _erf, "softplus": _softplus}


def scalar_calls(program: Program) -> frozenset[str]:
    """The math functions the program's scalar (1-lane) expressions call."""
    return frozenset(
        e.fn
        for kernel in program.kernels
        for stmt in walk_stmts(kernel.body)
        for top in stmt_exprs(stmt)
        for e in walk_exprs(top)
        if isinstance(e, Call) and e.lanes == 1
    )


def helper_definitions(functions: Iterable[str]) -> list[str]:
    """The definitions of the helpers of those functions that need one, by name, a blank line before each."""
    return [line for fn in sorted(set(functions) & set(HELPERS)) for line in ("", *HELPERS[fn]())]
