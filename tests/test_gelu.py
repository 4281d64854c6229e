"""Erf and GELU: ONNX Erf and Gelu (opset 20, both approximations), and the GELU decompositions
torch.onnx exports below opset 20, which fuse-activation makes one gelu activation applied at x's
producer's store. Graph-level Before/Expected and refusals, the scalar erf helper's accuracy
against math.erf, then ONNX models against onnxruntime on every target (NEON under qemu-user)."""

import math
from dataclasses import replace

import numpy as np
import pytest
from cross_helpers import NEON_TOOLCHAINS, check_on_neon
from helpers import compile_and_check, kernel_ops, onnx_model, scalar_math_values, weights
from onnx import helper
from test_vector_math import sweep, ulp_errors

import nncg
from nncg.backends.scalar_math import ULP_BOUNDS
from nncg.errors import NncgError
from nncg.ir.graph import Activation, ConvAttrs, Graph, Node, Value
from nncg.passes.fuse_activation import fuse_activation

TARGETS = ("ansi-c", "ssse3", "avx2", "avx512")
CONV = ConvAttrs((1, 1), (1, 1), (1, 1), (0, 0), (0, 0))
SHAPE = (1, 4, 3, 3)
GELU = Activation("gelu")
GELU_TANH = Activation("gelu", approximate="tanh")

# The constants of the decompositions, as float32 initializers.
CONSTANTS = {
    "sqrt2": math.sqrt(2),
    "inv_sqrt2": math.sqrt(0.5),
    "one": 1.0,
    "half": 0.5,
    "cubic": 0.044715,
    "sqrt_2_over_pi": math.sqrt(2 / math.pi),
    "three": 3.0,
}

# ------------------------------------------------------------------- the decompositions, as steps
# A step is (op, inputs, output); the same steps build graph IR nodes and ONNX nodes.


def erf_gate(x, scale="div"):
    """g = 1 + Erf(x / sqrt(2)), by Div (torch) or Mul by 1/sqrt(2)."""
    scaled = ("Div", (x, "sqrt2"), "s") if scale == "div" else ("Mul", ("inv_sqrt2", x), "s")
    return [scaled, ("Erf", ("s",), "e"), ("Add", ("e", "one"), "g")]


# x^3 as torch's legacy exporter writes it (x * x first, then either way round) or as onnxscript does
CUBES = {
    "square_first": lambda x: [("Mul", (x, x), "x2"), ("Mul", (x, "x2"), "x3")],
    "square_last": lambda x: [("Mul", (x, x), "x2"), ("Mul", ("x2", x), "x3")],
    "pow": lambda x: [("Pow", (x, "three"), "x3")],
}


def tanh_gate(x, cube="square_first"):
    """g = 1 + Tanh(sqrt(2/pi) * (x + 0.044715 * x * x * x))."""
    return [
        *CUBES[cube](x),
        ("Mul", ("cubic", "x3"), "t3"),
        ("Add", (x, "t3"), "v"),
        ("Mul", ("sqrt_2_over_pi", "v"), "u"),
        ("Tanh", ("u",), "t"),
        ("Add", ("one", "t"), "g"),
    ]


# y = the product of x, 0.5 and g as exporters multiply them: the legacy exporter, onnxscript,
# and x * 0.5 * gate (transformers' modules)
PRODUCTS = {
    "legacy": lambda x: [("Mul", (x, "g"), "p"), ("Mul", ("p", "half"), "y")],
    "onnxscript": lambda x: [("Mul", ("half", "g"), "p"), ("Mul", (x, "p"), "y")],
    "x_half_first": lambda x: [("Mul", (x, "half"), "p"), ("Mul", ("p", "g"), "y")],
}


def gelu_steps(x, approximate="none", product="legacy", scale="div"):
    gate = erf_gate(x, scale) if approximate == "none" else tanh_gate(x)
    return gate + PRODUCTS[product](x)


def used_constants(steps):
    return {name: np.float32(v) for name, v in CONSTANTS.items() if any(name in inputs for _, inputs, _ in steps)}


# ------------------------------------------------------------------------------------ graph level

ACTIVATION_OF = {"Erf": Activation("erf"), "Tanh": Activation("tanh"), "Pow": Activation("pow", alpha=3.0)}


def graph(steps, outputs=("y",), constants=None, conv=True):
    """x -> [Conv writing c] -> the steps; every value of SHAPE."""
    nodes = [Node("Conv", "conv", ("x", "w"), ("c",), CONV)] if conv else []
    steps = [(op, inputs[:1] if op == "Pow" else inputs, out) for op, inputs, out in steps]  # the exponent: an attr
    nodes += [Node(op, f"n_{out}", tuple(inputs), (out,), ACTIVATION_OF.get(op)) for op, inputs, out in steps]
    consts = {"w": np.ones((4, 4, 1, 1), np.float32)} if conv else {}
    consts |= used_constants(steps) if constants is None else constants
    values = {name for n in nodes for name in (*n.inputs, *n.outputs)} - set(consts)
    outs = tuple(Value(name, SHAPE) for name in outputs)
    return Graph("g", (Value("x", SHAPE),), outs, tuple(nodes), consts, dict.fromkeys(values, SHAPE))


def conv_with(activation):
    """The expected result: the Conv writing y, applying `activation` at its store."""
    conv = Node("Conv", "conv", ("x", "w"), ("y",), ConvAttrs(**{**vars(CONV), "activation": activation}))
    weights_ = {"w": np.ones((4, 4, 1, 1), np.float32)}
    return Graph("g", (Value("x", SHAPE),), (Value("y", SHAPE),), (conv,), weights_, {"x": SHAPE, "y": SHAPE})


@pytest.mark.parametrize("scale", ["div", "mul"])
@pytest.mark.parametrize("product", PRODUCTS)
def test_conv_exact_gelu_decomposition_becomes_conv_with_gelu(product, scale):
    assert fuse_activation(graph(gelu_steps("c", "none", product, scale))) == conv_with(GELU)


@pytest.mark.parametrize("cube", CUBES)
@pytest.mark.parametrize("product", PRODUCTS)
def test_conv_tanh_gelu_decomposition_becomes_conv_with_gelu_tanh(product, cube):
    steps = tanh_gate("c", cube) + PRODUCTS[product]("c")
    assert fuse_activation(graph(steps)) == conv_with(GELU_TANH)


def test_gelu_without_producer_is_one_standalone_node_named_after_the_last_mul():
    (node,) = fuse_activation(graph(gelu_steps("x"), conv=False)).nodes
    assert node == Node("Gelu", "n_y", ("x",), ("y",), GELU)


def test_activation_text_names_the_approximation():
    assert (str(GELU), str(GELU_TANH), str(Activation("erf"))) == ("gelu", "gelu(approximate=tanh)", "erf")
    with pytest.raises(ValueError, match="Activation.approximate is 'fast', not one of 'none', 'tanh'"):
        Activation("gelu", approximate="fast")


def ops(g):
    return [n.op for n in g.nodes]


@pytest.mark.parametrize("approximate", ["none", "tanh"])
def test_intermediate_that_is_a_graph_output_is_not_fused(approximate):
    """Every intermediate must be stored when it is an output: the pattern stays as it is."""
    steps = gelu_steps("c", approximate)
    for _, _, value in steps[:-1]:
        before = graph(steps, outputs=("y", value))
        assert ops(fuse_activation(before)) == ops(before), value


def test_intermediate_read_by_another_node_is_not_fused():
    steps = gelu_steps("c") + [("Add", ("e", "c"), "z")]
    before = graph(steps, outputs=("y", "z"))
    assert ops(fuse_activation(before)) == ops(before)


@pytest.mark.parametrize(
    "approximate, name, value",
    [
        ("none", "sqrt2", 1.4142),  # 1e-5 off: another function
        ("none", "half", 0.49),
        ("none", "one", 1.01),
        ("tanh", "cubic", 0.0447),
        ("tanh", "sqrt_2_over_pi", 0.798),
    ],
)
def test_wrong_constant_is_not_fused(approximate, name, value):
    steps = gelu_steps("c", approximate)
    before = graph(steps, constants={**used_constants(steps), name: np.float32(value)})
    assert "Gelu" not in ops(fuse_activation(before))


def test_square_by_pow_is_not_the_cube():
    before = graph(tanh_gate("c", "pow") + PRODUCTS["legacy"]("c"))
    square = Activation("pow", alpha=2.0)
    before = before.with_nodes([replace(n, attrs=square) if n.op == "Pow" else n for n in before.nodes])
    assert "Gelu" not in ops(fuse_activation(before))


def test_product_with_another_tensor_is_not_gelu():
    """0.5 * x * (1 + Erf(c / sqrt(2))) with x other than c is not a GELU of either."""
    steps = erf_gate("c") + PRODUCTS["legacy"]("x")
    assert "Gelu" not in ops(fuse_activation(graph(steps)))


# -------------------------------------------------------------------------------- scalar erf helper


def scalar_erf(x: np.ndarray, workdir) -> np.ndarray:
    """The generated scalar erf of each x."""
    return scalar_math_values("erf", x, workdir)


def test_scalar_erf_is_within_its_ulp_bound_of_math_erf(tmp_path):
    """Every 4096th float32 bit pattern (denormals, NaNs, infinities) and the edges (+-0, +-Inf, the
    thresholds 1 and 4, the tiniest and largest floats)."""
    x = sweep()
    y = scalar_erf(x, tmp_path)
    with np.errstate(invalid="ignore"):  # signalling NaN patterns, quieted
        reference = np.array([math.erf(v) for v in x.astype(np.float64)])
    err = ulp_errors(y, reference)
    worst = np.argsort(err)[-3:]
    assert err.max() <= ULP_BOUNDS["erf"], (err[worst], x[worst])


def test_scalar_erf_specials_are_exact(tmp_path):
    x = np.float32([0.0, -0.0, np.inf, -np.inf, 4.0, -4.0, 1e30, -1e-45, np.nan])
    y = scalar_erf(x, tmp_path)
    np.testing.assert_array_equal(y[:-1], np.float32([0.0, -0.0, 1.0, -1.0, 1.0, -1.0, 1.0, -1e-45]))
    assert list(np.signbit(y[:2])) == [False, True] and np.isnan(y[-1])


# ------------------------------------------------------------------------------ against onnxruntime


def conv_model(steps, channels=5):
    """Conv (3x3, 5 channels: a vector and a scalar tail) writing c, then the steps reading it."""
    nodes = [helper.make_node("Conv", ["x", "w", "b"], ["c"], pads=[1, 1, 1, 1]), *onnx_nodes(steps)]
    initializers = {"w": 3 * weights(channels, 3, 3, 3), "b": weights(channels), **used_constants(steps)}
    return onnx_model(nodes, inputs={"x": (1, 3, 5, 5)}, initializers=initializers, opset=17)


def onnx_nodes(steps):
    return [helper.make_node(op, list(inputs), [out], name=f"n_{out}") for op, inputs, out in steps]


def scaled_model(op, opset, **attrs):
    """y = op(x * k): k spans 1e-2 to 1e4 along the last dim, so x spans tiny to large magnitudes."""
    nodes = [helper.make_node("Mul", ["x", "k"], ["xs"]), helper.make_node(op, ["xs"], ["y"], **attrs)]
    k = np.logspace(-2, 4, 13, dtype=np.float32)
    return onnx_model(nodes, inputs={"x": (1, 3, 4, 13)}, initializers={"k": k}, opset=opset)


# Each product order once, and both ways of scaling x by 1/sqrt(2).
CONV_CASES = {
    "exact_legacy": gelu_steps("c"),
    "exact_onnxscript_mul": gelu_steps("c", product="onnxscript", scale="mul"),
    "exact_x_half_first": gelu_steps("c", product="x_half_first"),
    "tanh_legacy": gelu_steps("c", "tanh"),
    "tanh_onnxscript_pow": tanh_gate("c", "pow") + PRODUCTS["onnxscript"]("c"),
}


@pytest.mark.parametrize("target", TARGETS)
@pytest.mark.parametrize("case", CONV_CASES)
def test_conv_gelu_decomposition_is_fused_into_the_conv(target, case):
    compiled = compile_and_check(conv_model(CONV_CASES[case]), target)
    assert kernel_ops(compiled) == ["Conv", "Copy"]  # the copy converts channels-last to NCHW


@pytest.mark.parametrize("target", TARGETS)
@pytest.mark.parametrize("approximate", ["none", "tanh"])
def test_gelu_op_is_fused_into_the_conv(target, approximate):
    conv = helper.make_node("Conv", ["x", "w", "b"], ["c"], pads=[1, 1, 1, 1])
    gelu = helper.make_node("Gelu", ["c"], ["y"], approximate=approximate)
    inits = {"w": 3 * weights(5, 3, 3, 3), "b": weights(5)}
    compiled = compile_and_check(
        onnx_model([conv, gelu], inputs={"x": (1, 3, 5, 5)}, initializers=inits, opset=20), target
    )
    assert kernel_ops(compiled) == ["Conv", "Copy"]


@pytest.mark.parametrize("target", TARGETS)
@pytest.mark.parametrize("linear", ["Gemm", "MatMul"])
def test_gemm_and_matmul_gelu_are_one_dense(target, linear):
    """MatMul + Add is a Dense with bias (fuse-bias), which then applies the GELU."""
    first = ["Gemm", ["x", "w", "b"], ["c"]] if linear == "Gemm" else ["MatMul", ["x", "w"], ["m"]]
    nodes = [helper.make_node(*first)]
    nodes += [] if linear == "Gemm" else [helper.make_node("Add", ["m", "b"], ["c"])]
    steps = gelu_steps("c", "none", "onnxscript")
    inits = {"w": 3 * weights(10, 9), "b": weights(9), **used_constants(steps)}
    model = onnx_model(nodes + onnx_nodes(steps), inputs={"x": (2, 10)}, initializers=inits, opset=18)
    assert kernel_ops(compile_and_check(model, target)) == ["Dense"]


@pytest.mark.parametrize("target", TARGETS)
@pytest.mark.parametrize("op, attrs", [("Erf", {}), ("Gelu", {}), ("Gelu", {"approximate": "tanh"})])
def test_standalone_erf_and_gelu_over_large_magnitudes(target, op, attrs):
    model = scaled_model(op, 13 if op == "Erf" else 20, **attrs)
    assert kernel_ops(compile_and_check(model, target)) == ["Mul", op]


@pytest.mark.parametrize("target", ["ansi-c", "avx2"])
def test_unfused_decomposition_with_an_intermediate_output(target):
    """Erf's output is also a graph output: the decomposition runs node by node, Erf standalone."""
    model = conv_model(gelu_steps("c"))
    model.graph.output.append(helper.make_tensor_value_info("e", 1, None))
    assert "Erf" in kernel_ops(compile_and_check(model, target))


@pytest.mark.parametrize("target", ["ansi-c", "avx2"])
def test_gelu_under_sanitizers(target):
    compile_and_check(conv_model(gelu_steps("c")), target, sanitize=True)


def test_scalar_erf_helper_is_printed_only_where_called():
    """The vector erf and, for the scalar tail of 5 channels, the scalar one; none for tanh's GELU."""
    exact = nncg.compile(conv_model(gelu_steps("c")), target="ssse3").source
    assert "nncg_erf_ps(" in exact and "nncg_erf(" in exact
    assert "nncg_erf" not in nncg.compile(conv_model(gelu_steps("c", "tanh")), target="ansi-c").source


def test_gelu_with_an_unknown_approximation_is_refused():
    gelu = helper.make_node("Gelu", ["x"], ["y"], name="g", approximate="fast")
    with pytest.raises(NncgError, match="^Gelu 'g' has approximate 'fast'; NNCG supports none and tanh$"):
        nncg.compile(onnx_model([gelu], inputs={"x": (1, 4)}, opset=20))


NEON_MODELS = {
    "conv_exact": lambda: conv_model(gelu_steps("c")),
    "conv_tanh": lambda: conv_model(gelu_steps("c", "tanh")),
    "erf_large": lambda: scaled_model("Erf", 13),
}


@pytest.mark.parametrize("toolchain", NEON_TOOLCHAINS)
@pytest.mark.parametrize("case", NEON_MODELS)
def test_neon_matches_onnxruntime(case, toolchain):
    check_on_neon(toolchain, NEON_MODELS[case]())
