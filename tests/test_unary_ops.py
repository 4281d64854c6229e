"""The unary math ops: Abs, Neg, Sqrt, Exp, Log, Reciprocal, Pow by a constant exponent, Softplus,
Softsign, Mish, Selu, Celu, ThresholdedRelu and HardSigmoid's attributes. Each standalone over
tiny to large magnitudes (positive ones where the op's domain is) against onnxruntime on every
target (NEON under qemu-user), fused into a Conv's store, the special values (zeros, infinities,
NaN, negative bases) element by element, the scalar softplus helper's accuracy and the refusals."""

import re

import numpy as np
import pytest
from cross_helpers import check_on_neon
from helpers import compile_and_check, kernel_ops, onnx_model, scalar_math_values, skip_unless_host_runs, weights
from onnx import helper, numpy_helper
from test_vector_math import sweep, ulp_errors

import nncg
from nncg.backends.scalar_math import ULP_BOUNDS
from nncg.errors import NncgError
from nncg.verify import reference_outputs, run_compiled

TARGETS = ("ansi-c", "ssse3", "avx2", "avx512")
SHAPE = (1, 3, 4, 13)


class Case:
    """One op with its attributes (Pow: its exponent, or one per element of the last dim), the opset
    it needs and the range of its input: x times a constant spanning `scales` along the last dim,
    squared first for a positive domain."""

    def __init__(self, op, scales=(-2, 3), positive=False, opset=13, exponent=None, **attrs):
        self.op, self.scales, self.positive, self.opset = op, scales, positive, opset
        self.exponent, self.attrs = exponent, attrs
        self.kernel = "PowPerElement" if isinstance(exponent, list) else op

    def nodes(self, x):
        inputs = [x] if self.exponent is None else [x, "e"]
        return [helper.make_node(self.op, inputs, ["y"], name="unary", **self.attrs)]

    def initializers(self):
        return {} if self.exponent is None else {"e": np.float32(self.exponent)}

    def model(self):
        """y = op(x k) or op(x x k), k spanning 10^scales[0] to 10^scales[1] along the last dim."""
        k = np.logspace(*self.scales, SHAPE[-1], dtype=np.float32)
        first = helper.make_node("Mul", ["x", "x"], ["sq"]) if self.positive else None
        scaled = helper.make_node("Mul", ["sq" if self.positive else "x", "k"], ["xs"])
        nodes = [n for n in (first, scaled) if n is not None] + self.nodes("xs")
        inits = {"k": k, **self.initializers()}
        return onnx_model(nodes, inputs={"x": SHAPE}, initializers=inits, opset=self.opset)


# One per element of the last dim: the special ones, odd and even integers, others.
EXPONENTS = [2.0, 3.0, -1.0, 0.5, 2.5, 0.0, 4.0, 5.0, -2.0, -3.0, 1.5, 1.0, -0.5]

CASES = {
    "abs": Case("Abs", (-3, 4)),
    "neg": Case("Neg", (-3, 4)),
    "sqrt": Case("Sqrt", (-4, 4), positive=True),
    "exp": Case("Exp", (-2, 1.3)),  # |x k| < 88: no overflow to compare
    "log": Case("Log", (-4, 4), positive=True),
    "reciprocal": Case("Reciprocal", (-3, 3)),
    "softplus": Case("Softplus", (-2, 2.5)),  # |x| up to a few hundred: x, and exp(x) far below 0
    "softsign": Case("Softsign", (-3, 4)),
    "mish": Case("Mish", (-2, 2.5), opset=18),
    "selu": Case("Selu"),
    "selu_attrs": Case("Selu", alpha=2.0, gamma=0.5),
    "celu": Case("Celu", opset=12),
    "celu_alpha": Case("Celu", opset=12, alpha=0.3),
    "thresholded_relu": Case("ThresholdedRelu", (-3, 4), opset=10),
    "thresholded_relu_alpha": Case("ThresholdedRelu", opset=10, alpha=-0.5),
    "hard_sigmoid": Case("HardSigmoid"),
    "hard_sigmoid_attrs": Case("HardSigmoid", alpha=0.5, beta=0.6),
    "hard_sigmoid_steep": Case("HardSigmoid", alpha=3.0, beta=-1.0),
    "hard_sigmoid_falling": Case("HardSigmoid", alpha=-0.25, beta=0.0),
    "pow_2": Case("Pow", (-3, 3), exponent=2.0),
    "pow_3": Case("Pow", (-3, 2), exponent=3.0),
    "pow_1": Case("Pow", exponent=1.0),
    "pow_minus_1": Case("Pow", (-3, 3), exponent=-1.0),
    "pow_0": Case("Pow", exponent=0.0),
    "pow_half": Case("Pow", (-4, 4), positive=True, exponent=0.5),
    "pow_minus_half": Case("Pow", (-4, 4), positive=True, exponent=-0.5),
    "pow_2_5": Case("Pow", (-3, 3), positive=True, exponent=2.5),
    "pow_minus_0_3": Case("Pow", (-4, 4), positive=True, exponent=-0.3),
    "pow_4": Case("Pow", (-3, 2), exponent=4.0),  # even: |x|^4 for negative x
    "pow_5": Case("Pow", (-3, 1.5), exponent=5.0),  # odd: the sign of x
    "pow_minus_3": Case("Pow", (-2, 3), exponent=-3.0),
    "pow_per_element": Case("Pow", (-2, 2), exponent=EXPONENTS),  # negative x to 0.5, 2.5, ...: NaN
    "pow_per_element_positive": Case("Pow", (-3, 3), positive=True, exponent=EXPONENTS),
}


@pytest.mark.parametrize("target", TARGETS)
@pytest.mark.parametrize("case", CASES)
def test_op_over_small_to_large_magnitudes(target, case):
    c = CASES[case]
    compiled = compile_and_check(c.model(), target)
    ops = ["Mul", "Mul", c.kernel] if c.positive else ["Mul", c.kernel]
    assert kernel_ops(compiled) == ops


def test_pow_exponent_from_a_constant_node():
    nodes = [
        helper.make_node("Constant", [], ["e"], value=numpy_helper.from_array(np.float32([3.0]), "e")),
        helper.make_node("Pow", ["x", "e"], ["y"]),
    ]
    compile_and_check(onnx_model(nodes, inputs={"x": SHAPE}), "avx2")


# ---------------------------------------------------------------------- fused into a Conv's store

# Each op whose input may be any sign; Sqrt and Log see negative values too (NaN, not compared).
FUSED = ("abs", "neg", "exp", "log", "sqrt", "reciprocal", "softplus", "softsign", "mish", "selu_attrs")
FUSED += ("celu_alpha", "thresholded_relu_alpha", "hard_sigmoid_attrs", "pow_2", "pow_half", "pow_4", "pow_5")
# (an exponent per element is no activation: PowPerElement reads the Conv's output)


# Reciprocal's and Log's Conv output is kept away from 0: near it, 1/c and log c magnify the Conv's own
# rounding (its summation order differs from onnxruntime's by an ulp) past any tolerance, whatever their
# accuracy (the weights come from a shared generator, so which c land near 0 depends on test order).
BIAS_SHIFT = {"reciprocal": 20.0, "log": 20.0}


def conv_model(case):
    """A 3x3 Conv of 5 channels (a vector and a scalar tail) writing c, then the op."""
    c = CASES[case]
    conv = helper.make_node("Conv", ["x", "w", "b"], ["c"], pads=[1, 1, 1, 1])
    inits = {"w": 3 * weights(5, 3, 3, 3), "b": weights(5) + np.float32(BIAS_SHIFT.get(case, 0.0)), **c.initializers()}
    return onnx_model([conv, *c.nodes("c")], inputs={"x": (1, 3, 5, 5)}, initializers=inits, opset=c.opset)


@pytest.mark.parametrize("target", ["ansi-c", "avx2"])
@pytest.mark.parametrize("case", FUSED)
def test_op_is_fused_into_the_conv(target, case):
    compiled = compile_and_check(conv_model(case), target)
    assert kernel_ops(compiled) == ["Conv", "Copy"]  # the copy converts channels-last to NCHW


# ------------------------------------------------------------------------------- special values

SPECIAL_INPUTS = np.float32(
    [0.0, -0.0, 1.0, -1.0, 2.5, -2.5, np.inf, -np.inf, np.nan, 1e-30, -1e-30, 1e30, -1e30, 100.0, -100.0, 0.5]
)
# Op and exponent; pow's exceptions (-Inf to an exponent that is no integer, sqrt(-0)) are left out.
SPECIAL_CASES = {
    "abs": Case("Abs"),
    "neg": Case("Neg"),
    "sqrt": Case("Sqrt"),
    "exp": Case("Exp"),
    "log": Case("Log"),
    "reciprocal": Case("Reciprocal"),
    "softplus": Case("Softplus"),
    "softsign": Case("Softsign"),
    "pow_3": Case("Pow", exponent=3.0),
    "pow_4": Case("Pow", exponent=4.0),
    "pow_5": Case("Pow", exponent=5.0),
    "pow_minus_2": Case("Pow", exponent=-2.0),
    "pow_minus_3": Case("Pow", exponent=-3.0),
    "pow_0": Case("Pow", exponent=0.0),
}


TWO_ULPS = 2.0**-22  # relative: 2 ULP at the least
EXP_LOG_POWERS = ("pow_4", "pow_5", "pow_minus_2", "pow_minus_3")


@pytest.mark.parametrize("target", TARGETS)
@pytest.mark.parametrize("case", SPECIAL_CASES)
def test_special_values_as_onnxruntime(target, case):
    """Element by element: the same NaNs, infinities and signed zeros, finite values within 2 ULP,
    or for a power computed as exp(y log x), 2 ULP of exp's argument ln(result) more: log's error
    grows by y (1e30^3 overflows, 1e-30^-3 too, pow(-1e-30, 5) underflows to -0)."""
    c = SPECIAL_CASES[case]
    x = SPECIAL_INPUTS.reshape(1, 16)
    model = onnx_model(c.nodes("x"), inputs={"x": x.shape}, initializers=c.initializers(), opset=c.opset)
    compiled = nncg.compile(model, target=target, verify_ir=True)
    skip_unless_host_runs(target)
    (out,) = run_compiled(compiled, [x])
    (ref,) = reference_outputs(model, compiled.inputs, [x])
    np.testing.assert_array_equal(np.isnan(out), np.isnan(ref))
    exact = np.isinf(ref) | (ref == 0)
    np.testing.assert_array_equal(out[exact], ref[exact])
    np.testing.assert_array_equal(np.signbit(out[exact]), np.signbit(ref[exact]))
    finite = np.isfinite(ref) & ~exact
    conditioning = np.abs(np.log(np.abs(ref[finite]))) if case in EXP_LOG_POWERS else 0.0
    assert np.all(np.abs(out[finite] - ref[finite]) <= TWO_ULPS * (1 + conditioning) * np.abs(ref[finite]))


@pytest.mark.parametrize("target", TARGETS)
def test_special_values_to_an_exponent_per_element(target):
    """Each row of specials to its own exponent, as onnxruntime; the exceptions (-0 counts as +0,
    -Inf to an exponent that is no integer is NaN) are left out of the inputs."""
    x = np.tile(np.where(SPECIAL_INPUTS == -np.inf, -3.0, SPECIAL_INPUTS + 0.0), (5, 1)).astype(np.float32)
    exponents = np.float32([[3.0], [-2.0], [0.0], [2.5], [-3.0]])
    assert not np.any(np.signbit(x) & (x == 0))
    pow_ = helper.make_node("Pow", ["x", "e"], ["y"])
    model = onnx_model([pow_], inputs={"x": x.shape}, initializers={"e": exponents})
    compiled = nncg.compile(model, target=target, verify_ir=True)
    skip_unless_host_runs(target)
    (out,) = run_compiled(compiled, [x])
    (ref,) = reference_outputs(model, compiled.inputs, [x])
    np.testing.assert_array_equal(np.isnan(out), np.isnan(ref))
    exact = np.isinf(ref) | (ref == 0)
    np.testing.assert_array_equal(out[exact], ref[exact])
    np.testing.assert_array_equal(np.signbit(out[exact]), np.signbit(ref[exact]))
    finite = np.isfinite(ref) & ~exact
    conditioning = np.abs(np.log(np.abs(ref[finite])))
    assert np.all(np.abs(out[finite] - ref[finite]) <= TWO_ULPS * (1 + conditioning) * np.abs(ref[finite]))


# ---------------------------------------------------------------------------- scalar softplus


def scalar_softplus(x: np.ndarray, workdir) -> np.ndarray:
    """The generated scalar softplus of each x."""
    return scalar_math_values("softplus", x, workdir)


def test_scalar_softplus_is_within_its_ulp_bound(tmp_path):
    """Every 4096th float32 bit pattern and the edges, against float64 log(1 + exp(x))."""
    x = sweep()
    y = scalar_softplus(x, tmp_path)
    with np.errstate(invalid="ignore"):
        reference = np.logaddexp(0.0, x.astype(np.float64))
    err = ulp_errors(y, reference)
    worst = np.argsort(err)[-3:]
    assert err.max() <= ULP_BOUNDS["softplus"], (err[worst], x[worst])


def test_scalar_helper_is_printed_only_where_called():
    """Mish on 5 channels: the vector softplus and, for the scalar tail, the scalar one."""
    source = nncg.compile(conv_model("mish"), target="ssse3").source
    assert "nncg_softplus_ps(" in source and "static float nncg_softplus(float x)" in source
    assert "nncg_softplus" not in nncg.compile(conv_model("selu_attrs"), target="ansi-c").source


@pytest.mark.parametrize("target", ["ssse3", "avx2", "avx512", "neon"])
def test_vector_code_calls_no_math_h(target):
    """A chain of the ops over rows of 16 (no scalar tail on any width): sqrt, abs, exp, log and
    softplus are instructions and polynomials, nothing calls math.h (but ARMv7, which has no vector
    square root)."""
    chain = ["Abs", "Sqrt", "Log", "Softplus", "Mish", "Exp", "Softsign", "Neg", "Reciprocal", "Selu", "Celu"]
    names = ["x", *(f"t{i}" for i in range(len(chain))), "p"]
    nodes = [helper.make_node(op, [a], [b]) for op, a, b in zip(chain, names, names[1:])]
    nodes.append(helper.make_node("Pow", [names[-2], "e"], ["y"]))
    model = onnx_model(nodes, inputs={"x": (1, 2, 16)}, initializers={"e": np.float32(-2.5)}, opset=18)
    compiled = compile_and_check(model, target) if target != "neon" else nncg.compile(model, target=target)
    code = re.sub(r"/\*.*?\*/", "", compiled.source, flags=re.S)  # the helpers' comments name them
    code = re.sub(r"#else.*?#endif", "", code, flags=re.S)  # NEON on ARMv7, no vector sqrt: per lane
    assert re.findall(r"\b(?:exp|log|sqrt|sqrtf|fabs|tanh)\(", code) == []


# ------------------------------------------------------------------------------------ refusals


def test_pow_with_a_runtime_exponent_is_refused():
    pow_ = helper.make_node("Pow", ["x", "e"], ["y"], name="p")
    model = onnx_model([pow_], inputs={"x": (1, 4), "e": (1,)})
    message = (
        "^Pow 'p' has its exponent 'e' computed at runtime; NNCG compiles Pow by a constant exponent: "
        "make it an initializer or a Constant$"
    )
    with pytest.raises(NncgError, match=message):
        nncg.compile(model)


def test_pow_with_an_infinite_exponent_is_refused():
    pow_ = helper.make_node("Pow", ["x", "e"], ["y"], name="p")
    model = onnx_model([pow_], inputs={"x": (1, 3)}, initializers={"e": np.float32([1, np.inf, 3])})
    message = "^Pow 'p' has an infinite or NaN exponent; NNCG compiles Pow by finite exponents$"
    with pytest.raises(NncgError, match=message):
        nncg.compile(model)


def test_pow_whose_exponent_broadcasts_x_up_is_refused():
    pow_ = helper.make_node("Pow", ["x", "e"], ["y"], name="p")
    model = onnx_model([pow_], inputs={"x": (1, 3)}, initializers={"e": np.full((2, 3), 2, np.float32)})
    with pytest.raises(NncgError, match=r"^Pow 'p' has an exponent of shape \[2, 3\], which broadcasts X \[1, 3\] up"):
        nncg.compile(model)


# ------------------------------------------------------------------------------------------ NEON

NEON_CASES = [(case, "aarch64-neon") for case in CASES]
NEON_CASES += [
    (case, tc) for case in ("sqrt", "pow_half", "softplus", "mish") for tc in ("armhf-neon", "armhf-neon-vfpv3")
]


@pytest.mark.parametrize("case, toolchain", NEON_CASES)
def test_neon_matches_onnxruntime(case, toolchain):
    check_on_neon(toolchain, CASES[case].model())


@pytest.mark.parametrize("case", ["mish", "pow_5", "sqrt"])
def test_neon_fused_into_the_conv(case):
    check_on_neon("aarch64-neon", conv_model(case))
