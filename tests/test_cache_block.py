"""Cache-blocked, packed direct convolution: the cache-block pass's choices, the packed weight order,
read-back partial sums under register blocking, zero halos for its inputs, and every panel/block
shape against onnxruntime on every host target (ASan/UBSan on some)."""

import numpy as np
import pytest
from helpers import check_against_onnxruntime, onnx_model, weights
from onnx import helper
from test_ops import conv_model

import nncg
from nncg.errors import NncgError
from nncg.frontend import import_onnx
from nncg.ir.loops import Affine, Assign, Binary, Kernel, Let, Load, LocalRef, Loop, Store
from nncg.lowering.conv_blocked import _packed
from nncg.passes import PassManager, default_pipeline
from nncg.passes.cache_block import OFF, chosen_blocks, input_block, parse_layers
from nncg.passes.register_block import jammable
from nncg.report import layer_choices

GRAPH = "drop-identity,fold-batchnorm,fuse-bias,fuse-residual,fuse-activation"
TARGETS = ("ansi-c", "ssse3", "avx2", "avx512")
AVX2 = nncg.get_target("avx2")


def graph_after(m, passes: str, facts=AVX2):
    return PassManager(f"{GRAPH},{passes}", facts).run(import_onnx(m))


def pipeline(facts, layers: str, halos: str = "auto") -> str:
    """The default pipeline for `facts` without Winograd, with cache-block's `layers` and lower's `halos`."""
    text = default_pipeline(facts).replace(",winograd,", ",").replace(",cache-block", "")
    return text.replace(",lower,", f",cache-block{{layers={layers}}},lower{{halos={halos}}},")


# ------------------------------------------------------------------------------------ the pass


def test_cost_model_blocks_layers_whose_weights_exceed_l1():
    big = conv_model((1, 64, 6, 6), 64, (3, 3), pads=[1, 1, 1, 1])  # 147 KiB of weights
    small = conv_model((1, 8, 6, 6), 16, (3, 3), pads=[1, 1, 1, 1])  # 4.6 KiB
    (conv,) = graph_after(big, "cache-block").nodes
    # avx2: 8 channel vectors -> register blocks of 4 (32 channels); 32 * 9 taps * 4 B per input
    # channel, half of 32 KiB L1 holds 14 of them: the largest divisor of 64 is 8.
    assert (conv.attrs.panel, conv.attrs.ci_block) == (32, 8)
    assert graph_after(small, "cache-block").nodes[0].attrs.panel == 0
    assert chosen_blocks(import_onnx(big), import_onnx(big).nodes[0], nncg.get_target("ansi-c")) == OFF


def test_layer_choices_override_and_are_checked():
    big = conv_model((1, 64, 6, 6), 64, (3, 3), pads=[1, 1, 1, 1])
    assert graph_after(big, "cache-block{layers=Conv_0:off}").nodes[0].attrs.panel == 0
    small = conv_model((1, 8, 6, 6), 16, (3, 3))
    (conv,) = graph_after(small, "cache-block{layers=Conv_0:8x2}").nodes
    assert (conv.attrs.panel, conv.attrs.ci_block) == (8, 2)
    with pytest.raises(NncgError, match="block 3 does not divide 8"):
        graph_after(small, "cache-block{layers=Conv_0:8x3}")
    with pytest.raises(NncgError, match="a panel of 32 is more than its 16 channels"):
        graph_after(small, "cache-block{layers=Conv_0:32x2}")
    depthwise = conv_model((1, 8, 6, 6), 8, (3, 3), group=8)
    assert graph_after(depthwise, "cache-block{layers=Conv_0:4}").nodes[0].attrs.channel_block == 4
    with pytest.raises(NncgError, match="a depthwise Conv: give its channel block alone"):
        graph_after(depthwise, "cache-block{layers=Conv_0:8x1}")
    with pytest.raises(NncgError, match="neither a direct Conv"):
        pixels = "vectorize-pixels{layers=Conv_0:true},cache-block{layers=Conv_0:8}"
        graph_after(conv_model((1, 8, 6, 6), 8, (3, 3)), pixels)
    grouped = conv_model((1, 8, 6, 6), 16, (3, 3), group=2)  # 8 output channels from 4 inputs a group
    assert graph_after(grouped, "cache-block{layers=Conv_0:8x2}").nodes[0].attrs.ci_block == 2
    with pytest.raises(NncgError, match="a grouped Conv's panel is its group, 8"):
        graph_after(grouped, "cache-block{layers=Conv_0:16x2}")
    with pytest.raises(NncgError, match="block 3 does not divide 4"):
        graph_after(grouped, "cache-block{layers=Conv_0:8x3}")
    assert parse_layers("a:32x8;b:off;c:32") == {"a": (32, 8), "b": OFF, "c": (32, 0)}
    for bad in ("a:32x", "a:0x8", "a:x8", "a:on", "a:32x0"):
        with pytest.raises(ValueError):
            parse_layers(bad)


def test_cost_model_computes_a_grouped_conv_one_group_per_panel():
    # 4.6 KiB of weights (fits L1), but unblocked its register block would jam groups, sharing nothing
    (conv,) = graph_after(conv_model((1, 32, 6, 6), 32, (3, 3), group=2), "cache-block").nodes
    assert (conv.attrs.panel, conv.attrs.ci_block) == (16, 16)
    # the whole reduction of a group fits: avx2's 16 channels x 9 taps x 4 B per input channel
    depthwise = graph_after(conv_model((1, 32, 6, 6), 32, (3, 3), group=32), "cache-block").nodes[0]
    assert depthwise.attrs.panel == 0  # one channel a group: the group loop is the vector loop


@pytest.mark.parametrize("target_name", TARGETS)
@pytest.mark.parametrize(
    "shape,c_out,kernel,attrs,choice",
    [
        # regnet's 16-channel groups, stride 2 and padded; two reduction blocks per group
        ((1, 48, 9, 9), 48, (3, 3), dict(pads=[1, 1, 1, 1], strides=[2, 2], group=3), "16x8"),
        # groups narrower than a vector, each taking a different count of input channels than it makes
        ((1, 12, 5, 7), 24, (3, 3), dict(pads=[1, 0, 1, 2], group=4), "6x3"),
        # a grouped 1x1 conv (its pixels as one dim), one block per group, a batch of 2
        ((2, 16, 4, 5), 32, (1, 1), dict(group=2), "16x8"),
    ],
    ids=["regnet_like", "narrow_groups", "pointwise_batch_2"],
)
def test_grouped_conv_by_group_panels_matches_onnxruntime(target_name, shape, c_out, kernel, attrs, choice):
    m = conv_model(shape, c_out, kernel, **attrs)
    facts = nncg.get_target(target_name)
    for halos in ("auto", "false"):
        compiled = nncg.compile(m, target=target_name, pipeline=pipeline(facts, f"Conv_0:{choice}", halos))
        check_against_onnxruntime(m, compiled)
    # and as the default pipeline chooses it
    check_against_onnxruntime(m, nncg.compile(m, target=target_name), sanitize=target_name == "avx2")


def test_input_block_is_the_largest_divisor_that_fits_half_of_l1():
    assert input_block(64, 9, 32, AVX2) == 8
    assert input_block(3, 49, 64, AVX2) == 1  # nothing fits: one input channel at a time
    assert input_block(24, 1, 32, AVX2) == 24  # a 1x1 conv's whole reduction fits


def test_winograd_leaves_convs_with_few_output_tiles_to_direct():
    tiny = conv_model((1, 64, 6, 6), 64, (3, 3), pads=[1, 1, 1, 1])  # 3x3 tiles of 2x2
    enough = conv_model((1, 64, 8, 8), 64, (3, 3), pads=[1, 1, 1, 1])  # 4x4 tiles
    assert graph_after(tiny, "winograd").nodes[0].attrs.algorithm == "direct"
    assert graph_after(enough, "winograd").nodes[0].attrs.algorithm == "winograd"


# ------------------------------------------------------------------------------------ lowering


def test_packed_weights_are_in_the_order_the_nests_stream_them():
    w = np.arange(4 * 6 * 2 * 3, dtype=np.float32).reshape(4, 6, 2, 3)  # [c_out, c_in, kh, kw]
    packed = _packed(w, panels=2, block=3)  # [panel][block][kh][kw][ci][co]
    assert packed.shape == (2, 2, 2, 3, 3, 2)
    for p, b, kh, kw, ci, co in np.ndindex(packed.shape):
        assert packed[p, b, kh, kw, ci, co] == w[2 * p + co, 3 * b + ci, kh, kw]


def test_a_partial_sum_read_back_is_jammable_but_a_neighbour_is_not():
    def loop(read_at):
        init = Load("out", Affine.of("i") + read_at)
        body = (Assign("acc", Binary("+", LocalRef("acc"), Load("x", Affine.of("i")))),)
        store = Store("out", Affine.of("i"), LocalRef("acc"))
        return Loop("i", 8, (Let("acc", init, (*body, store)),), parallel=True)

    assert jammable(loop(0))
    assert not jammable(loop(1))


def test_partial_sums_of_vectors_and_a_tail_side_by_side_are_jammable():
    """40 channels = a loop of 2 vectors of 16 and a tail of 8, each pixel 40 apart: every pixel reads
    back only what it stores; at 36 apart the tail would overlap the next pixel's first vector."""

    def loop(stride):
        def nest(index, lanes):
            init = Load("out", index, lanes)
            body = (Assign("acc", Binary("+", LocalRef("acc"), Load("x", Affine.of("p"), lanes))),)
            return Let("acc", init, (*body, Store("out", index, LocalRef("acc", lanes))))

        vectors = Loop("c", 2, (nest(Affine.of("p") * stride + Affine.of("c") * 16, 16),), parallel=True)
        return Loop("p", 9, (vectors, nest(Affine.of("p") * stride + 32, 8)), parallel=True)

    assert jammable(loop(40))
    assert not jammable(loop(36))


def blocked_stages(compiled):
    return compiled.source.count("for (kb = 0;")


@pytest.mark.parametrize("target_name", TARGETS)
@pytest.mark.parametrize(
    "shape,c_out,kernel,attrs,choice",
    [
        # one reduction block; panels 16 + a rest of 8
        ((1, 8, 7, 9), 24, (3, 3), dict(pads=[1, 1, 1, 1]), "16x8"),
        # first, a loop of middle blocks, last; stride 2 and asymmetric padding
        ((1, 12, 9, 8), 16, (3, 3), dict(pads=[0, 1, 2, 1], strides=[2, 2]), "8x2"),
        # first, one middle block, last; dilated
        ((1, 6, 9, 9), 12, (3, 3), dict(pads=[2, 2, 2, 2], dilations=[2, 2]), "12x2"),
        # first and last only; a 1x1 conv (its pixels as one dim) with a panel narrower than a vector
        ((1, 8, 4, 5), 6, (1, 1), dict(), "3x4"),
        # a strided 1x1 conv keeps its rows and columns
        ((1, 8, 5, 5), 8, (1, 1), dict(strides=[2, 2]), "8x4"),
        # no bias, 1-D and 3-D
        ((1, 4, 11), 8, (3,), dict(pads=[1, 1], strides=[2]), "8x1"),
        ((1, 4, 4, 5, 5), 8, (2, 3, 3), dict(pads=[0, 1, 1, 1, 1, 1]), "4x2"),
        ((2, 6, 5, 5), 8, (3, 3), dict(pads=[1, 1, 1, 1]), "8x3"),
    ],
    ids=["rest_panel", "middle_loop", "one_middle", "pointwise", "pointwise_stride2", "conv1d", "conv3d", "batch_2"],
)
def test_blocked_conv_matches_onnxruntime(target_name, shape, c_out, kernel, attrs, choice):
    m = conv_model(shape, c_out, kernel, bias=len(kernel) != 1, **attrs)
    facts = nncg.get_target(target_name)
    for halos in ("auto", "false"):
        compiled = nncg.compile(m, target=target_name, pipeline=pipeline(facts, f"Conv_0:{choice}", halos))
        check_against_onnxruntime(m, compiled)


@pytest.mark.parametrize("target_name", TARGETS)
def test_pointwise_conv_with_a_channel_tail_jams_every_reduction_block(target_name):
    # mnasnet's project convs: 40 output channels (avx512: 16 + 16 + 8) over 3x3 pixels, 3 reduction blocks
    m = conv_model((1, 24, 3, 3), 40, (1, 1), bias=False)
    facts = nncg.get_target(target_name)
    compiled = nncg.compile(m, target=target_name, pipeline=pipeline(facts, "Conv_0:40x8"))
    if target_name == "avx512":  # after the first block, 2-D blocks of the vectors and the tail read back together
        assert "acc_1_s0_1 = _mm512_loadu_ps" in compiled.source and "acc_s1_1 = _mm256_loadu_ps" in compiled.source
    check_against_onnxruntime(m, compiled)


def residual_relu_model(c, size):
    nodes = [
        helper.make_node("Conv", ["x", "w1", "b1"], ["a"], pads=[1, 1, 1, 1]),
        helper.make_node("Relu", ["a"], ["r"]),
        helper.make_node("Conv", ["r", "w2", "b2"], ["c"], pads=[1, 1, 1, 1]),
        helper.make_node("Add", ["c", "r"], ["s"]),
        helper.make_node("Relu", ["s"], ["y"]),
    ]
    inits = {"w1": weights(c, c, 3, 3), "b1": weights(c), "w2": weights(c, c, 3, 3), "b2": weights(c)}
    return onnx_model(nodes, inputs={"x": (1, c, size, size)}, initializers=inits)


@pytest.mark.parametrize("target_name", TARGETS)
def test_residual_and_activation_are_applied_once_after_the_last_block(target_name):
    m = residual_relu_model(16, 5)
    facts = nncg.get_target(target_name)
    layers = "Conv_0:8x4;Conv_2:16x4"
    compiled = nncg.compile(m, target=target_name, pipeline=pipeline(facts, layers))
    assert blocked_stages(compiled) == 2  # 4 blocks each: first, a loop of 2 middle ones, last
    assert "halo_" in compiled.source  # the blocked convs' input is stored in a zero border
    check_against_onnxruntime(m, compiled, sanitize=target_name in ("ansi-c", "avx2"))


def test_default_pipeline_blocks_a_wide_layer_and_matches_onnxruntime():
    m = residual_relu_model(64, 6)  # 147 KiB per conv: blocked; 6x6 outputs: direct, not Winograd
    compiled = nncg.compile(m, target="avx2")
    assert "cache-block" in compiled.pipeline
    assert blocked_stages(compiled) == 2
    check_against_onnxruntime(m, compiled, sanitize=True)


# ------------------------------------------------------------------------------------ Gemm/MatMul


def gemm_model(rows, k, n, trans_b=False, bias=True):
    w = weights(n, k) if trans_b else weights(k, n)
    inputs = ["x", "w"] + (["b"] if bias else [])
    node = helper.make_node("Gemm", inputs, ["y"], transB=int(trans_b), alpha=1.0, beta=1.0)
    inits = {"w": w, **({"b": weights(n)} if bias else {})}
    return onnx_model([node], inputs={"x": (rows, k)}, initializers=inits)


def matmul_model(x_shape, n):
    node = helper.make_node("MatMul", ["x", "w"], ["y"])
    return onnx_model([node], inputs={"x": x_shape}, initializers={"w": weights(x_shape[-1], n)})


def test_cost_model_packs_a_wide_gemm_in_panels_of_one_register_block():
    (gemm,) = graph_after(gemm_model(2, 512, 100), "cache-block").nodes  # 200 KiB
    assert (gemm.attrs.panel, gemm.attrs.streams) == (32, 1)  # avx2: 4 vectors of 8; rows reuse the weights
    # one row (a GEMV): MAX_CHANNEL_BLOCK = 5 vectors, in as many streams as (registers - 6) // 5 allow
    (gemv,) = graph_after(gemm_model(1, 512, 100), "cache-block").nodes
    assert (gemv.attrs.panel, gemv.attrs.streams) == (40, 2)
    # 128 columns: panels of 4 vectors leave no rest (5 would leave one vector)
    (gemv,) = graph_after(gemm_model(1, 512, 128), "cache-block").nodes
    assert (gemv.attrs.panel, gemv.attrs.streams) == (32, 2)
    (gemv,) = graph_after(gemm_model(1, 512, 100), "cache-block", nncg.get_target("avx512")).nodes
    assert (gemv.attrs.panel, gemv.attrs.streams) == (80, 4)  # 26 // 5 = 5 streams, at most 4
    loop = Loop("k", 1, ())
    assert "weights packed in panels of 80 columns, each read in 4 reduction streams" in layer_choices(
        Kernel("Gemm_0", "Dense", (loop,)), gemv, None
    )
    assert graph_after(gemm_model(1, 16, 10), "cache-block").nodes[0].attrs.panel == 0
    with pytest.raises(NncgError, match="give its panel alone"):
        graph_after(gemm_model(1, 16, 10), "cache-block{layers=Gemm_0:8x2}")


@pytest.mark.parametrize("target_name", TARGETS)
@pytest.mark.parametrize(
    "model,choice",
    [
        (lambda: gemm_model(1, 40, 50), "16"),  # 3 panels and a rest of 2
        (lambda: gemm_model(3, 17, 24, trans_b=True, bias=False), "24"),  # one panel, transposed w
        (lambda: matmul_model((2, 3, 9), 20), "8"),  # rows over two leading dims
    ],
    ids=["gemm_rest", "gemm_trans_b", "matmul_3d"],
)
def test_packed_gemm_matches_onnxruntime(target_name, model, choice):
    m = model()
    facts = nncg.get_target(target_name)
    compiled = nncg.compile(m, target=target_name, pipeline=pipeline(facts, f"{import_onnx(m).nodes[0].name}:{choice}"))
    assert "for (p = 0;" in compiled.source or choice == "24"
    check_against_onnxruntime(m, compiled, sanitize=target_name == "avx2")


# Streams per target: ansi-c's panel of 8 (given by hand) is 8 scalar accumulators, one stream of
# (16 - 6) registers; ssse3 and avx2 take 5 vectors in 2 streams, avx512 in 4 (where the output has
# 5 vectors and the reduction 16 steps a stream).
@pytest.mark.parametrize("target_name", TARGETS)
@pytest.mark.parametrize(
    "model,streams",
    [
        # K = 4 x 32 + 3, N = 100: panels and a rest off the vector width
        (lambda: gemm_model(1, 131, 100), {"ansi-c": 1, "ssse3": 2, "avx2": 2, "avx512": 4}),
        (lambda: gemm_model(1, 97, 91, trans_b=True, bias=False), {"ansi-c": 1, "ssse3": 2, "avx2": 2, "avx512": 4}),
        # one row over two leading dims; avx512: 45 columns are 3 vectors, 26 // 3 streams, at most 4
        (lambda: matmul_model((1, 1, 201), 45), {"ansi-c": 1, "ssse3": 2, "avx2": 2, "avx512": 4}),
        # K = 63: at most 3 streams of 16 steps and more
        (lambda: gemm_model(1, 63, 150), {"ansi-c": 1, "ssse3": 2, "avx2": 2, "avx512": 3}),
        (lambda: gemm_model(2, 131, 100), {}),  # two rows reuse the weights: no streams
    ],
    ids=["gemv_tails", "gemv_odd", "matmul_gemv", "gemv_short", "two_rows"],
)
def test_gemv_reads_its_reduction_in_streams_and_matches_onnxruntime(target_name, model, streams):
    m = model()
    facts = nncg.get_target(target_name)
    name = import_onnx(m).nodes[0].name
    # ansi-c: no cache-block in its pipeline (nothing to pack without vectors); give it a panel by hand
    text = default_pipeline(facts)
    if target_name == "ansi-c":
        text = text.replace(",lower,", f",cache-block{{layers={name}:8}},lower,")
    compiled = nncg.compile(m, target=target_name, pipeline=text)
    expected = streams.get(target_name, 1)
    assert f"acc_seg{expected - 1}" in compiled.source or expected == 1
    assert f"acc_seg{expected}" not in compiled.source
    check_against_onnxruntime(m, compiled, sanitize=target_name == "avx2")


def test_a_pointwise_conv_blocks_pixels_across_rows():
    m = conv_model((1, 16, 3, 3), 16, (1, 1))
    facts = nncg.get_target("avx2")
    compiled = nncg.compile(m, target="avx2", pipeline=pipeline(facts, "Conv_0:16x8"))
    assert "oh" not in compiled.source.split("Conv_0")[-1]  # one loop over the 9 pixels
    check_against_onnxruntime(m, compiled)


# ------------------------------------------------------------------------------------ prefetch


@pytest.mark.parametrize("target_name", TARGETS)
@pytest.mark.parametrize(
    "model",
    [
        lambda: conv_model((1, 64, 3, 3), 256, (1, 1)),  # 64 KiB on 9 pixels, mobilenet_v2's last stages
        lambda: gemm_model(1, 320, 100),  # 125 KiB, a classifier
    ],
    ids=["pointwise", "gemv"],
)
def test_weights_beyond_l1_are_prefetched_ahead_within_their_array(target_name, model):
    m = model()
    compiled = nncg.compile(m, target=target_name)
    prefetches = [line.strip() for line in compiled.source.splitlines() if "_mm_prefetch(" in line]
    # ansi-c prints no intrinsics; x86 targets prefetch at the top of the conv's reduction loops only,
    # the GEMV's streams (a multiply-add per weight vector) are left to the hardware prefetcher
    assert bool(prefetches) == (target_name != "ansi-c" and m.graph.node[0].op_type == "Conv")
    if prefetches:
        # the lookahead of the last panel's last iterations would pass the array's end: clamped
        assert any(" ? " in p for p in prefetches)
    check_against_onnxruntime(m, compiled, sanitize=target_name == "avx2")


def test_prefetch_takes_one_line_per_cache_line_of_a_streamed_load_ahead_of_it():
    from nncg.backends.prefetch import PREFETCH_BYTES, prefetch_addresses

    ci = Affine.of("ci")

    def load(const: int) -> Load:
        return Load("w", ci * 64 + const, lanes=8)

    # 8 vectors of 8 floats: 4 cache lines, each vector for 2 pixels; the small constant `v` and the
    # accumulator-only loop are not streamed
    pixels = [Load("v", ci + 8 * p, lanes=8) for p in (0, 1)]
    reads = [Assign(f"acc_{k}_{p}", Binary("*", load(8 * k), v)) for k in range(8) for p, v in enumerate(pixels)]
    loop = Loop("ci", 40, tuple(reads))
    ahead = PREFETCH_BYTES // 4
    extents = {"ci": 40}
    lines = prefetch_addresses(loop, {"w": 40 * 64 + ahead + 64}, extents)
    assert lines == [("w", f"64 * ci + {ahead + 16 * k}") for k in range(4)]
    assert prefetch_addresses(Loop("ci", 40, tuple(reads), parallel=True), {"w": 10**6}, extents) == []
    last = 40 * 64 - 1  # no room to look ahead: every address is clamped to the last element
    clamped = prefetch_addresses(loop, {"w": 40 * 64}, extents)
    assert [i for _, i in clamped] == [
        f"64 * ci + {ahead + c} < {last} ? 64 * ci + {ahead + c} : {last}" for c in (0, 16, 32, 48)
    ]
    # a GEMV's loop: every weight vector read by one multiply-add, nothing prefetched
    assert prefetch_addresses(Loop("ci", 40, tuple(reads[::2])), {"w": 10**6}, extents) == []
