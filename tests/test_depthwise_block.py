"""Depthwise Convs on x86 FMA targets: a line of 16 channels at a time over all pixels, a row of pixels
a register block; unblocked, at most 3 pixels of 4 channel vectors (avx512's 32 registers would give 6),
chosen from the loop nest; blocked code against onnxruntime on every x86 target."""

import numpy as np
import pytest
from helpers import check_against_onnxruntime, onnx_model, weights
from onnx import helper

import nncg
from nncg.passes import REGISTRY
from nncg.passes.register_block import choose_blocks, chosen_blocks
from nncg.report import layer_rows
from nncg.tune import tuning_candidates


def pointwise_then_depthwise(channels: int, size: int, stride: int, residual: bool = False, kernel: int = 3):
    """A 1x1 Conv (so the depthwise Conv reads a channels-last tensor, as in mobilenet_v2), then a 3x3
    depthwise Conv with Relu6; with `residual`, a dense 3x3 Conv adding the 1x1 Conv's output instead."""
    group = 1 if residual else channels
    nodes = [
        helper.make_node("Conv", ["x", "w0"], ["p"], name="pointwise"),
        helper.make_node(
            "Conv", ["p", "w1", "b1"], ["c"], name="conv", group=group, pads=[kernel // 2] * 4, strides=[stride, stride]
        ),  # fmt: skip
    ]
    if residual:
        nodes.append(helper.make_node("Add", ["c", "p"], ["s"], name="add"))
    nodes.append(helper.make_node("Clip", ["s" if residual else "c", "lo", "hi"], ["y"], name="relu6"))
    inits = {
        "w0": weights(channels, 8, 1, 1),
        "w1": weights(channels, channels // group, kernel, kernel),
        "b1": weights(channels),
        "lo": np.array(0.0, np.float32),
        "hi": np.array(6.0, np.float32),
    }
    return onnx_model(nodes, inputs={"x": (1, 8, size, size)}, initializers=inits)


def test_cost_model_caps_vector_input_pixels_where_fused():
    assert choose_blocks((40, 9), 32, fused=True, vector_inputs=True) == (3, 4)
    assert choose_blocks((40, 9), 32, fused=True) == (6, 4)  # dense: one broadcast serves 4 vectors
    assert choose_blocks((40, 9), 16, fused=True, vector_inputs=True) == (3, 4)  # avx2 as before
    assert choose_blocks((40, 9), 16, vector_inputs=True) == (2, 4)  # no FMA from memory: as before
    assert choose_blocks((40, 2), 32, fused=True, vector_inputs=True) == (10, 2)  # few vectors: as before


def _blocks(model, target: str) -> dict[str, tuple[int, int]]:
    compiled = nncg.compile(model, target=target)
    return chosen_blocks(compiled.record.before_register_block, nncg.get_target(target))


def test_depthwise_conv_is_recognised_from_its_loop_nest():
    m = pointwise_then_depthwise(144, 12, 1)
    unblocked = nncg.compile(m, target="avx512").pipeline.replace("cache-block", "cache-block{layers=conv:off}")
    compiled = nncg.compile(m, target="avx512", pipeline=unblocked)
    assert chosen_blocks(compiled.record.before_register_block, nncg.get_target("avx512"))["conv"] == (3, 4)
    blocks = _blocks(m, "avx512")
    assert blocks["conv"] == (12, 1)  # a line of 16 channels: a row of 12 pixels of one vector
    assert blocks["pointwise"][0] > 3  # a 1x1 Conv broadcasts its input: the full register fit
    # a dense Conv whose epilogue loads a residual vector is not depthwise
    assert _blocks(pointwise_then_depthwise(144, 12, 1, residual=True), "avx512")["conv"] == (6, 4)


@pytest.mark.parametrize("target", ["ansi-c", "ssse3", "avx2", "avx512"])
@pytest.mark.parametrize("channels, size, stride", [(144, 11, 1), (72, 12, 2), (80, 9, 1)])
def test_depthwise_blocks_match_onnxruntime(target, channels, size, stride):
    # 144 = 9 vectors of 16 (two 3x4 blocks and one more vector), 72 = 4 of 16 and one of 8, 80 = 5 of 16
    m = pointwise_then_depthwise(channels, size, stride)
    check_against_onnxruntime(m, nncg.compile(m, target=target), opt="-O1")


def test_depthwise_weights_past_l1_put_channel_blocks_outermost():
    # without FMA from memory (SSE): 360 5x5 filters are 36 KB, past the x86 targets' 32 KiB L1; 240 of
    # them (24 KB) stay in it; ansi-c knows no L1 size
    big, small = (nncg.compile(pointwise_then_depthwise(c, 7, 1, kernel=5), target="ssse3") for c in (360, 240))
    assert "for (p = 0; p < 5; ++p)" in big.source  # 5 blocks of 64 channels, then the 40 left
    assert "w_conv_rest[" in big.source and "w_conv_rest" not in small.source
    assert "w_conv_rest" not in nncg.compile(pointwise_then_depthwise(360, 7, 1, kernel=5), target="ansi-c").source


@pytest.mark.parametrize("target", ["avx2", "avx512"])
def test_depthwise_convs_run_a_cache_line_of_channels_at_a_time_where_fma_reads_memory(target):
    # whatever their weights: 360 = 22 lines of 16 channels and 8 left; 16 channels are one line already
    for channels, kernel in ((360, 5), (40, 3)):
        source = nncg.compile(pointwise_then_depthwise(channels, 7, 1, kernel=kernel), target=target).source
        assert f"for (p = 0; p < {channels // 16}; ++p)" in source  # then the rest
    assert "w_conv_rest" not in nncg.compile(pointwise_then_depthwise(16, 7, 1), target=target).source


def test_cache_block_pass_marks_depthwise_channel_blocks_and_layers_override_them():
    # the pass's choice is a ConvAttrs field: the report says it, and `layers` sets or removes it
    m = pointwise_then_depthwise(360, 7, 1, kernel=5)
    compiled = nncg.compile(m, target="avx2")
    (row,) = (row for row in layer_rows(compiled) if row.name == "conv")
    assert "depthwise in channel blocks of 16" in row.choices
    pipeline = compiled.pipeline.replace("cache-block", "cache-block{layers=conv:off}")
    assert "w_conv_rest" not in nncg.compile(m, target="avx2", pipeline=pipeline).source
    blocks_of_32 = nncg.compile(m, target="avx2", pipeline=pipeline.replace("conv:off", "conv:32"))
    assert "for (p = 0; p < 11; ++p)" in blocks_of_32.source  # 11 blocks of 32 channels, then the 8 left
    check_against_onnxruntime(m, blocks_of_32, opt="-O1")


def test_tune_times_every_depthwise_conv_in_lines_and_unblocked():
    m = pointwise_then_depthwise(144, 12, 1)  # 5 KB of weights: within L1, blocked only in lines
    for target, first in (("avx512", "16"), ("ssse3", "off")):
        facts = nncg.get_target(target)
        options = tuning_candidates(m, nncg.default_pipeline(facts), "cache-block", facts)
        assert [REGISTRY["cache-block"].tunable.format_value(o) for o in options["conv"]][0] == first
        assert {(16, 0), (0, 0)} <= set(options["conv"])


@pytest.mark.parametrize("target", ["ansi-c", "ssse3", "avx2", "avx512"])
@pytest.mark.parametrize("channels, size, kernel, stride", [(360, 7, 5, 1), (1000, 5, 3, 2)])
def test_channel_blocks_outermost_match_onnxruntime(target, channels, size, kernel, stride):
    # 360 = 5 blocks of 64 and 40 (2 vectors of 16 and one of 8 on avx512), 1000 = 15 of 64 and 40; on
    # 7x7 pixels and 3x3 (stride 2) every or almost every pixel reads the zero padding
    m = pointwise_then_depthwise(channels, size, stride, kernel=kernel)
    check_against_onnxruntime(m, nncg.compile(m, target=target), opt="-O1")
