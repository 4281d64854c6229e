"""Register blocks of SSE int8 kernels of pmaddwd pairs (register_block.pair_dot_block, issue 16): on
ssse3 a reduction over input channels as dots of 2 adjacent activations is blocked as one pixel of up to
PAIR_DOT_CHANNELS channel vectors; a first layer's tap dots, KxK convolutions and the other targets keep
the cost model's blocks. Odd channel counts (13 -> 37 -> 42 -> 9: channel-vector tails, a block tail of
1 vector) stay bit-identical to onnxruntime on every target."""

from __future__ import annotations

import numpy as np
import pytest
from helpers import skip_unless_host_runs
from int8_models import _model, _weights, compare, quantized, random_feeds
from onnx import helper

import nncg
from nncg.backends import get_backend
from nncg.passes.register_block import PAIR_DOT_CHANNELS, chosen_blocks


def pointwise_model(seed: int = 7):
    """A 3x3 stem of 3 -> 13 channels, two 1x1 Convs 13 -> 37 -> 42 (channels-last inputs), a 3x3 Conv
    42 -> 9 of stride 2 (direct: no integer Winograd)."""
    rng = np.random.default_rng(seed)
    layers = [  # name, input channels, output channels, kernel, attributes
        ("stem", 3, 13, 3, {"pads": [1, 1, 1, 1]}),
        ("pw1", 13, 37, 1, {}),
        ("pw2", 37, 42, 1, {}),
        ("k3", 42, 9, 3, {"pads": [1, 1, 1, 1], "strides": [2, 2]}),
    ]
    init, nodes, x = {}, [], "x"
    for i, (name, c_in, c_out, k, attrs) in enumerate(layers):
        init[f"w{i}"], init[f"b{i}"] = _weights(rng, c_out, c_in, k, k), rng.standard_normal(c_out) * 0.3
        y = "y" if i == len(layers) - 1 else f"c{i}"
        nodes.append(helper.make_node("Conv", [x, f"w{i}", f"b{i}"], [y], name=name, **attrs))
        if y != "y":
            x = f"r{i}"
            nodes.append(helper.make_node("Relu", [y], [x]))
    return _model(nodes, [1, 3, 5, 7], init)


def blocks(model, target: str) -> dict[str, tuple[int, int]]:
    compiled = nncg.compile(model, target=target)
    return chosen_blocks(compiled.record.before_register_block, get_backend(target).target)


def test_pointwise_layers_block_one_pixel_on_ssse3():
    model = quantized(pointwise_model())
    ssse3, avx2 = blocks(model, "ssse3"), blocks(model, "avx2")
    pointwise = [name for name in ssse3 if name.startswith("pw")]
    assert len(pointwise) == 2
    for name in pointwise:  # 10 and 11 channel vectors of 4 lanes
        assert ssse3[name] == (1, PAIR_DOT_CHANNELS)
        assert avx2[name][0] > 1  # avx2 keeps the cost model's pixel blocks
    for prefix in ("stem", "k3"):  # a first layer's tap dots, a 3x3 Conv's loops over taps
        name = next(name for name in ssse3 if name.startswith(prefix))
        assert ssse3[name][0] > 1


@pytest.mark.parametrize("target", ["ansi-c", "ssse3", "avx2", "avx512vnni"])
def test_pointwise_identical_to_onnxruntime(target):
    skip_unless_host_runs(target)
    float_model = pointwise_model()
    model = quantized(float_model)
    compiled = nncg.compile(model, target=target, verify_ir=True)
    result = compare(model, compiled, random_feeds(float_model, 2, 13))
    assert result.max_steps == 0 and result.identical == 1.0, result
