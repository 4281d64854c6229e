"""Vectorising over output pixels: the pass's choices and errors, the planar layer's loop nest, and
every padding, stride, group, batch and consumer case against onnxruntime on every x86 target."""

import importlib
from dataclasses import replace as dataclass_replace

import pytest
from helpers import check_against_onnxruntime, onnx_model, target, weights
from onnx import helper
from test_ops import conv_model
from test_x86_targets import TARGETS

import nncg
from nncg.backends import get_target
from nncg.errors import NncgError
from nncg.frontend import import_onnx
from nncg.ir.loops import (
    Affine,
    Assign,
    Binary,
    Bound,
    If,
    Kernel,
    Let,
    Load,
    LocalRef,
    Loop,
    Program,
    Store,
    walk_exprs,
    walk_stmts,
)
from nncg.passes import PassManager, default_pipeline
from nncg.passes.register_block import planar_tensors, reads_across_planes
from nncg.passes.vectorize import vectorize
from nncg.tune import with_layer_choices

GRAPH = "drop-identity,fold-batchnorm,fuse-bias,fuse-residual,fuse-activation,winograd"


def graph_after(m, pixels: str, facts=None):
    return PassManager(f"{GRAPH},{pixels}", facts or target()).run(import_onnx(m))


def pipeline(target: str, **layers: bool) -> str:
    """The target's default pipeline with these choices (ansi-c, without vectors, has no
    vectorize-pixels pass by default: the planar layout is forced in anyway)."""
    base = default_pipeline(get_target(target))
    if "vectorize-pixels" not in base:
        base = base.replace(",lower,", ",vectorize-pixels,lower,")
    return with_layer_choices(base, {"vectorize-pixels": layers}) if layers else base


def test_cost_model_takes_few_channels_on_long_rows():
    robot_like = conv_model((1, 3, 12, 80), 8, (3, 3), pads=[1, 1, 1, 1])
    short_rows = conv_model((1, 3, 12, 18), 8, (3, 3), pads=[1, 1, 1, 1])
    many_channels = conv_model((1, 3, 12, 80), 12, (3, 3), pads=[1, 1, 1, 1])
    avx512 = nncg.get_target("avx512")
    pad, conv = graph_after(robot_like, "vectorize-pixels", avx512).nodes
    assert (pad.op, conv.attrs.vector_axis) == ("Pad", "pixels")
    assert graph_after(robot_like, "vectorize-pixels", nncg.get_target("avx2")).nodes[0].attrs.vector_axis == "channels"
    assert graph_after(short_rows, "vectorize-pixels", avx512).nodes[0].attrs.vector_axis == "channels"
    assert graph_after(many_channels, "vectorize-pixels", avx512).nodes[0].attrs.vector_axis == "channels"
    assert graph_after(robot_like, "vectorize-pixels").nodes[0].attrs.vector_axis == "channels"


def test_padding_becomes_a_pad_node_and_the_conv_reads_it():
    m = conv_model((1, 3, 6, 9), 4, (3, 3), pads=[1, 2, 0, 1])
    pad, conv = graph_after(m, "vectorize-pixels{layers=Conv_0:true}").nodes
    assert pad.attrs.pads_begin == (0, 0, 1, 2) and pad.attrs.pads_end == (0, 0, 0, 1)
    assert conv.inputs[0] == pad.outputs[0] and conv.attrs.pads_begin == (0, 0) == conv.attrs.pads_end


def test_only_layers_with_planar_rows_qualify():
    chain = [
        helper.make_node("Conv", ["x", "w1"], ["a"], pads=[1, 1, 1, 1]),
        helper.make_node("Conv", ["a", "w2"], ["y"], pads=[1, 1, 1, 1]),
    ]
    m = onnx_model(
        chain, inputs={"x": (1, 3, 6, 20)}, initializers={"w1": weights(4, 3, 3, 3), "w2": weights(2, 4, 3, 3)}
    )
    both = graph_after(m, "vectorize-pixels{layers=Conv_0:true;Conv_1:true}")
    assert [n.attrs.vector_axis for n in both.nodes if n.op == "Conv"] == ["pixels", "pixels"]
    with pytest.raises(NncgError, match="layer Conv_1 is not a direct Conv .* reading a planar tensor"):
        graph_after(m, "vectorize-pixels{layers=Conv_1:true}")  # Conv_0's output is channels-last
    strided = conv_model((1, 3, 6, 20), 4, (3, 3), strides=[1, 2])
    with pytest.raises(NncgError, match="stride 1 along its rows"):
        graph_after(strided, "vectorize-pixels{layers=Conv_0:true}")
    with pytest.raises(NncgError, match="vectorize-pixels: no layer named conv9; the layers are: Conv_0"):
        graph_after(strided, "vectorize-pixels{layers=conv9:true}")
    with pytest.raises(NncgError, match="as in conv1:true;conv2:false"):
        PassManager("vectorize-pixels{layers=Conv_0:maybe}")


def test_rows_are_vectorised_without_border_checks():
    m = conv_model((1, 3, 5, 42), 8, (3, 3), pads=[1, 1, 1, 1])
    program = PassManager(pipeline("avx512", Conv_0=True), nncg.get_target("avx512"), verify=True).run(import_onnx(m))
    (conv,) = [k for k in program.kernels if k.op == "Conv"]
    assert not any(isinstance(s, If) for s in walk_stmts(conv.body))
    stores = [s for s in walk_stmts(conv.body) if isinstance(s, Store)]
    assert stores and all(s.value.lanes == 16 for s in stores)
    # 42 columns: 2 vectors of 16, then one more ending at the last column (overlapping by 6)
    assert sorted({s.index.const % 42 for s in stores}) == [0, 16, 26]
    loads = [e for s in walk_stmts(conv.body) for e in walk_exprs(getattr(s, "value", LocalRef("_")))]
    assert any(isinstance(e, Load) and e.lanes == 16 and e.buffer.startswith("t_x_padded") for e in loads)


def test_a_graph_output_is_written_planar_without_a_copy():
    m = conv_model((1, 2, 4, 20), 3, (3, 3), pads=[1, 1, 1, 1])
    compiled = nncg.compile(m, "avx2", pipeline=pipeline("avx2", Conv_0=True))
    default = nncg.compile(m, "avx2")
    assert "Copy" in default.source and "Copy" not in compiled.source


def leaky_pool(x_shape, c_out, **attrs):
    nodes = [
        helper.make_node("Conv", ["x", "w", "b"], ["c"], **attrs),
        helper.make_node("LeakyRelu", ["c"], ["r"], alpha=0.1),
        helper.make_node("MaxPool", ["r"], ["y"], kernel_shape=[2, 2], strides=[2, 2]),
    ]
    k = attrs.get("kernel_shape", [3, 3])
    return onnx_model(
        nodes, inputs={"x": x_shape}, initializers={"w": weights(c_out, x_shape[1], *k), "b": weights(c_out)}
    )


def two_convs(x_shape, mid, c_out):
    nodes = [
        helper.make_node("Conv", ["x", "w1"], ["a"], pads=[1, 1, 1, 1]),
        helper.make_node("Relu", ["a"], ["r"]),
        helper.make_node("Conv", ["r", "w2", "b2"], ["y"], pads=[0, 1, 0, 1], kernel_shape=[1, 3]),
    ]
    inits = {"w1": weights(mid, x_shape[1], 3, 3), "w2": weights(c_out, mid, 1, 3), "b2": weights(c_out)}
    return onnx_model(nodes, inputs={"x": x_shape}, initializers=inits)


def residual(x_shape):
    nodes = [
        helper.make_node("Conv", ["x", "w", "b"], ["c"], pads=[1, 1, 1, 1]),
        helper.make_node("Add", ["c", "x"], ["y"]),
    ]
    c = x_shape[1]
    return onnx_model(nodes, inputs={"x": x_shape}, initializers={"w": weights(c, c, 3, 3), "b": weights(c)})


CASES = {
    "pad1": (conv_model((1, 3, 7, 37), 8, (3, 3), pads=[1, 1, 1, 1]), ["Conv_0"]),
    "no_pad_no_bias": (conv_model((1, 3, 6, 21), 5, (3, 3), bias=False), ["Conv_0"]),
    "asymmetric_pads": (conv_model((1, 2, 6, 19), 3, (3, 3), pads=[0, 2, 1, 0]), ["Conv_0"]),
    "dilated": (conv_model((1, 1, 9, 24), 2, (3, 3), pads=[2, 2, 2, 2], dilations=[2, 2]), ["Conv_0"]),
    "row_stride_2": (conv_model((1, 3, 9, 18), 4, (3, 3), pads=[1, 1, 1, 1], strides=[2, 1]), ["Conv_0"]),
    "grouped": (conv_model((1, 4, 5, 17), 8, (3, 3), pads=[1, 1, 1, 1], group=2), ["Conv_0"]),
    "depthwise": (conv_model((1, 3, 5, 16), 3, (3, 3), pads=[1, 1, 1, 1], group=3), ["Conv_0"]),
    "one_channel": (conv_model((1, 1, 5, 33), 1, (5, 5), pads=[2, 2, 2, 2]), ["Conv_0"]),
    "narrow_rows": (conv_model((1, 3, 4, 3), 4, (3, 3), pads=[1, 1, 1, 1]), ["Conv_0"]),
    "conv_1d": (conv_model((1, 2, 29), 3, (3,), pads=[1, 1]), ["Conv_0"]),
    "batch_2": (conv_model((2, 3, 4, 20), 4, (3, 3), pads=[1, 1, 1, 1]), ["Conv_0"]),
    "maxpool_consumer": (leaky_pool((1, 3, 8, 36), 8, pads=[1, 1, 1, 1]), ["Conv_0"]),
    "pixel_chain": (two_convs((1, 2, 5, 21), 4, 3), ["Conv_0", "Conv_2"]),
    "channels_after_pixels": (two_convs((1, 2, 5, 21), 4, 3), ["Conv_0"]),
    "residual": (residual((1, 3, 4, 18)), ["Conv_0"]),
}


@pytest.mark.parametrize("case", CASES)
@pytest.mark.parametrize("target", ["ansi-c", "ssse3", *TARGETS])
def test_matches_onnxruntime(case, target):
    m, layers = CASES[case]
    compiled = nncg.compile(m, target, pipeline=pipeline(target, **dict.fromkeys(layers, True)), verify_ir=True)
    assert f"{layers[0]}:true" in compiled.pipeline  # an inapplicable layer would have raised
    check_against_onnxruntime(m, compiled)


@pytest.mark.parametrize("case", ["pad1", "grouped", "maxpool_consumer", "pixel_chain"])
def test_sanitizers_find_nothing(case):
    m, layers = CASES[case]
    compiled = nncg.compile(m, "ssse3", pipeline=pipeline("ssse3", **dict.fromkeys(layers, True)))
    check_against_onnxruntime(m, compiled, sanitize=True)


# ---------------------------------------------------------------------------- vectorize mechanics


def accumulate(extent: int, lo: int, hi: int) -> Loop:
    """for j { let acc = b { for k < 3 { if lo <= j + k - 1 < hi { acc += x[j + k - 1] } }; y[j] = acc } }"""
    position = Affine.of("j") + Affine.of("k") - 1
    add = Assign("acc", Binary("+", LocalRef("acc"), Load("x", position)))
    taps = Loop("k", 3, (If((Bound(position, lo, hi),), (add,)),))
    body = (Let("acc", Load("b", Affine()), (taps, Store("y", Affine.of("j"), LocalRef("acc")))),)
    return Loop("j", extent, body, parallel=True)


def vectorized(kernel: Kernel, lanes: tuple[int, ...]) -> Kernel:
    (out,) = vectorize(Program("p", (), (kernel,), {}), target(*lanes)).kernels
    return out


def test_border_iterations_split_off_and_the_tail_overlaps():
    kernel = vectorized(Kernel("k", "Conv", (accumulate(20, 0, 20),)), (8, 4))
    stores = [s for s in walk_stmts(kernel.body) if isinstance(s, Store)]
    assert sorted(s.index.const for s in stores if s.value.lanes == 1) == [0, 19]  # the border columns
    (loop,) = [s for s in kernel.body if isinstance(s, Loop)]
    assert (loop.lanes, loop.extent) == (8, 2)  # columns 1..16
    assert not any(isinstance(s, If) for s in walk_stmts(loop.body))
    overlap = [s.index.const for s in stores if s.value.lanes == 8 and s.index.is_const]
    assert overlap == [11]  # columns 11..18: one more vector ending at the last interior column


def test_elementwise_loops_keep_their_scalar_tail():
    body = (Store("y", Affine.of("j"), Binary("*", Load("x", Affine.of("j")), Load("x", Affine.of("j")))),)
    kernel = vectorized(Kernel("k", "Mul", (Loop("j", 19, body, parallel=True),)), (8,))
    vector, tail = kernel.body
    assert (vector.lanes, vector.extent, tail.lanes, tail.extent) == (8, 2, 1, 3)


def test_a_channels_last_consumer_of_a_planar_tensor_jams_channels_only():
    m = leaky_pool((1, 3, 8, 72), 8, pads=[1, 1, 1, 1])
    for on, expected in ((True, {"Conv_0": False, "MaxPool_2": True}), (False, {"Conv_0": False, "MaxPool_2": False})):
        specs = pipeline("avx512", Conv_0=on).split(",register-block")[0]
        program = PassManager(specs, nncg.get_target("avx512"), finish=False).run(import_onnx(m))
        planar = planar_tensors(program)
        strided = {k.name: reads_across_planes(k.body, planar) for k in program.kernels if k.name in expected}
        assert strided == expected


# ---------------------------------------------------------------------------- stems: planes outside the row taps

STEMS = {
    "3x3_s2_pad1": conv_model((1, 3, 23, 29), 20, (3, 3), pads=[1, 1, 1, 1], strides=[2, 2]),
    "7x7_s2_pad3": conv_model((1, 3, 21, 27), 24, (7, 7), pads=[3, 3, 3, 3], strides=[2, 2]),
}


def planes_outside(m, facts) -> list[bool]:
    return [n.attrs.planes_outside_row for n in graph_after(m, "vectorize-pixels", facts).nodes]


def test_stems_loop_planes_outside_the_row_taps_on_avx512():
    stem = STEMS["3x3_s2_pad1"]
    assert planes_outside(stem, nncg.get_target("avx512")) == [True]
    assert planes_outside(stem, nncg.get_target("avx2")) == [False]  # slower there (see the cost model)
    assert planes_outside(stem, nncg.get_target("ssse3")) == [False]
    assert planes_outside(stem, target()) == [False]
    avx512 = nncg.get_target("avx512")
    assert planes_outside(conv_model((1, 1, 9, 9), 16, (3, 3), strides=[2, 2]), avx512) == [False]  # one plane
    assert planes_outside(conv_model((1, 3, 9, 9), 16, (3, 3)), avx512) == [False]  # stride 1
    assert planes_outside(conv_model((1, 3, 9, 9), 8, (3, 3), strides=[2, 2]), avx512) == [False]  # half a vector
    chain = [
        helper.make_node("Conv", ["x", "w1"], ["a"], strides=[2, 2]),
        helper.make_node("Conv", ["a", "w2"], ["y"], strides=[2, 2]),
    ]
    inits = {"w1": weights(16, 3, 3, 3), "w2": weights(16, 16, 3, 3)}
    channels_last = onnx_model(chain, inputs={"x": (1, 3, 13, 13)}, initializers=inits)
    assert planes_outside(channels_last, avx512) == [True, False]  # the second reads a channels-last tensor


def test_the_plane_loop_wraps_the_row_taps():
    compiled = nncg.compile(STEMS["3x3_s2_pad1"], "avx512", unroll=None)
    nest = [s for k in compiled.record.before_register_block.kernels for s in walk_stmts(k.body) if isinstance(s, Loop)]
    row_taps = [s for s in nest if s.var == "kw"]
    assert row_taps and all(any(s.var == "ci" and t in s.body for s in nest) for t in row_taps)


def forced_planes_outside(monkeypatch):
    """The cost model taking planes outside the row taps on any target (ansi-c, ssse3, avx2 too)."""
    module = importlib.import_module("nncg.passes.vectorize_pixels")
    chosen = module.planes_outside_row_pays
    monkeypatch.setattr(
        module,
        "planes_outside_row_pays",
        lambda graph, node, planar, facts: chosen(
            graph,
            node,
            planar,
            dataclass_replace(facts, fma=True, registers=32, vector_widths=facts.vector_widths or (1,)),
        ),
    )


@pytest.mark.parametrize("case", STEMS)
@pytest.mark.parametrize("target", ["ansi-c", "ssse3", *TARGETS])
def test_stems_match_onnxruntime(case, target, monkeypatch):
    forced_planes_outside(monkeypatch)
    compiled = nncg.compile(STEMS[case], target, pipeline=pipeline(target), verify_ir=True)
    check_against_onnxruntime(STEMS[case], compiled)


@pytest.mark.parametrize("target", ["ssse3", "avx512"])
def test_cache_blocked_stem_matches_onnxruntime(target, monkeypatch):
    forced_planes_outside(monkeypatch)
    stem = STEMS["7x7_s2_pad3"]
    blocked = with_layer_choices(pipeline(target), {"cache-block": {"Conv_0": "16x3"}})
    compiled = nncg.compile(stem, target, pipeline=blocked, verify_ir=True)
    check_against_onnxruntime(stem, compiled)
