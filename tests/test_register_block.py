"""The register-block pass: structure of the jammed loop nests, and every block shape against onnxruntime."""

from dataclasses import replace

import pytest
from cross_helpers import TOOLCHAINS, missing_tools, verify_on
from helpers import check_against_onnxruntime, onnx_model, target, weights
from onnx import helper
from test_ops import conv_model

import nncg
from nncg.errors import NncgError
from nncg.frontend import import_onnx
from nncg.ir.loops import If, Let, Loop, Store, walk_stmts
from nncg.passes import PassManager
from nncg.passes.register_block import choose_blocks, chosen_blocks, fma_from_memory, parse_layers

LOWER = "drop-identity,fold-batchnorm,fuse-bias,fuse-residual,fuse-activation,lower"


def pipeline(vector: bool, layers: str | None = None, unroll: str = "none") -> str:
    steps = (
        [LOWER]
        + (["vectorize"] if vector else [])
        + [f"register-block{{layers={layers}}}" if layers else "register-block"]
    )
    steps += [] if unroll == "none" else [f"unroll{{level={unroll}}}"]
    return ",".join(steps + ["inline-constants", "plan-memory"])


def lowered(m, widths=(4,), layers=None, registers=16):
    return PassManager(pipeline(bool(widths), layers), target(*widths, registers=registers), verify=True).run(
        import_onnx(m)
    )


def compiled_for(m, name: str, registers: int, layers: str | None, unroll: str = "auto"):
    """The C of `m` for the backend `name`, register-blocked for `registers` registers (through the
    pass manager with the backend's target but that register count)."""
    facts = replace(nncg.get_target(name), registers=registers)
    manager = PassManager(pipeline(bool(facts.vector_widths), layers, unroll), facts, verify=True)
    return nncg.emit(manager.run(import_onnx(m)), name)


def test_jam_splits_borders_and_interleaves_accumulators():
    # 12 channels = 3 vectors of 4; 3x3, pad 1 over 10 columns: columns 0 and 9 are borders.
    m = conv_model((1, 5, 6, 10), 12, (3, 3), pads=[1, 1, 1, 1])
    kernel = lowered(m, layers="Conv_0:4x3").kernels[0]
    stmts = list(walk_stmts(kernel.body))
    lets = [s for s in stmts if isinstance(s, Let)]
    # border columns: 3 accumulators each; interior 8 columns = 2 jammed blocks of 4 x 3 vectors
    assert sorted({len(let.name.split("_")) for let in lets}) == [2, 3]
    blocked = [s for s in stmts if isinstance(s, Loop) and s.var == "ow"]
    assert [loop.extent for loop in blocked] == [2]
    interior_checks = [s for s in walk_stmts(blocked[0].body) if isinstance(s, If)]
    assert all("ow" not in b.expr.vars for s in interior_checks for b in s.bounds)
    stores = [s for s in walk_stmts(blocked[0].body) if isinstance(s, Store)]
    assert len(stores) == 12 and len({s.index for s in stores}) == 12


def test_siblings_of_mixed_width_share_their_reduction():
    # 12 channels on 8/4 lanes: the 8-lane and the 4-lane accumulator run in the same loops.
    m = conv_model((1, 4, 5, 9), 12, (3, 3), pads=[1, 1, 1, 1])
    kernel = lowered(m, widths=(8, 4), layers="Conv_0:2x2").kernels[0]
    jammed = next(s for s in walk_stmts(kernel.body) if isinstance(s, Loop) and s.var == "ow")
    lanes = sorted(s.init.lanes for s in walk_stmts(jammed.body) if isinstance(s, Let))
    assert lanes == [4, 4, 8, 8]
    reductions = [s for s in walk_stmts(jammed.body) if isinstance(s, Loop) and s.var == "ci"]
    assert len(reductions) == 1


def test_a_jammed_channel_block_and_a_narrower_tail_share_their_reduction():
    # 40 channels on 16/8 lanes: a loop of 2 16-lane vectors (jammed) and an 8-lane tail, one loop over ci.
    m = conv_model((1, 4, 5, 9), 40, (3, 3), pads=[1, 1, 1, 1])
    kernel = lowered(m, widths=(16, 8), layers="Conv_0:2x3", registers=32).kernels[0]
    jammed = next(s for s in walk_stmts(kernel.body) if isinstance(s, Loop) and s.var == "ow")
    lanes = sorted(s.init.lanes for s in walk_stmts(jammed.body) if isinstance(s, Let))
    assert lanes == [8, 8, 16, 16, 16, 16]
    reductions = [s for s in walk_stmts(jammed.body) if isinstance(s, Loop) and s.var == "ci"]
    assert len(reductions) == 1


def test_cost_model_fills_the_registers_it_is_given():
    assert choose_blocks((40, 3), 16) == (3, 3)  # 9 accumulators, 6 registers left
    assert choose_blocks((40, 2), 16) == (5, 2)
    assert choose_blocks((2, 1), 16) == (2, 1)  # never more pixels than the loop has
    assert choose_blocks((40, 1), 32) == (26, 1)
    assert choose_blocks((40, 16), 16) == (2, 4)  # many channel vectors: blocks of 4
    # x86 FMA: each pixel's accumulators and broadcast input, and one weight vector
    assert choose_blocks((40, 4), 16, fused=True) == (3, 4)  # avx2's 1x1 panels: 12 accumulators
    assert choose_blocks((40, 2), 16, fused=True) == (5, 2)
    assert choose_blocks((40, 4), 32, fused=True) == (6, 4)
    assert choose_blocks((40, 1), 32, fused=True) == (15, 1)


def test_only_x86_fma_reads_its_weights_from_memory():
    assert [fma_from_memory(nncg.get_target(t)) for t in ("avx2", "avx512")] == [True, True]
    # SSE multiplies into a register of its own; NEON's multiply-add reads registers only
    assert [fma_from_memory(nncg.get_target(t)) for t in ("ssse3", "neon", "ansi-c")] == [False, False, False]


def test_layers_parameter_parses_and_rejects():
    assert parse_layers("conv1:4x2;conv_2:1x3") == {"conv1": (4, 2), "conv_2": (1, 3)}
    for bad in ("conv1", "conv1:4", "conv1:0x2", "conv1:ax2"):
        with pytest.raises(ValueError):
            parse_layers(bad)
    with pytest.raises(NncgError, match="register-block"):
        PassManager("register-block{layers=conv1:4}")
    with pytest.raises(NncgError, match="no layer named conv9; the layers are: Conv_0, Conv_0_to_y"):
        lowered(conv_model((1, 2, 4, 4), 4, (3, 3)), layers="conv9:2x2")


def conv_case(**attrs):
    shape = attrs.pop("x", (1, 6, 9, 11))
    return conv_model(shape, attrs.pop("c_out", 12), attrs.pop("kernel", (3, 3)), **attrs)


CONVS = {
    "pad1": conv_case(pads=[1, 1, 1, 1]),
    "asymmetric_pads_stride2": conv_case(pads=[0, 2, 1, 0], strides=[2, 2]),
    "dilated": conv_case(pads=[2, 2, 2, 2], dilations=[2, 2]),
    "depthwise": conv_case(c_out=6, group=6, pads=[1, 1, 1, 1]),
    "grouped": conv_case(c_out=12, group=3, pads=[1, 0, 1, 0]),
    "conv1d": conv_case(x=(1, 5, 17), kernel=(5,), pads=[2, 2]),
    "conv3d": conv_case(x=(1, 3, 4, 5, 6), kernel=(3, 3, 3), c_out=8, pads=[1, 1, 1, 1, 1, 1]),
    "20_channels": conv_case(c_out=20, pads=[1, 1, 1, 1]),
    "narrow_input": conv_case(x=(1, 6, 3, 2), pads=[1, 1, 1, 1]),
    "one_vector": conv_case(x=(1, 3, 5, 30), c_out=16, pads=[1, 1, 1, 1]),
}
BLOCKS = [(16, None), (32, None), (16, "Conv_0:1x1"), (16, "Conv_0:7x5")]  # registers, per-layer shapes


@pytest.mark.parametrize("block", BLOCKS)
@pytest.mark.parametrize("target", ["ansi-c", "ssse3", "avx512"])
@pytest.mark.parametrize("case", CONVS)
def test_blocked_conv_matches_onnxruntime(case, target, block):
    from helpers import HOST

    if target == "avx512" and "avx512f" not in HOST:
        pytest.skip("the host CPU lacks avx512f")
    compiled = compiled_for(CONVS[case], target, *block)
    check_against_onnxruntime(CONVS[case], compiled, opt="-O1")


def residual_then_pool():
    nodes = [
        helper.make_node("Conv", ["x", "w", "b"], ["c"], pads=[1, 1, 1, 1]),
        helper.make_node("Add", ["c", "x"], ["r"]),
        helper.make_node("Relu", ["r"], ["p"]),
        helper.make_node("MaxPool", ["p"], ["q"], kernel_shape=[3, 3], pads=[1, 1, 1, 1]),
        helper.make_node("Flatten", ["q"], ["f"]),
        helper.make_node("Gemm", ["f", "g"], ["y"], transB=1),
    ]
    inits = {"w": weights(8, 8, 3, 3), "b": weights(8), "g": weights(10, 8 * 7 * 9)}
    return onnx_model(nodes, inputs={"x": (1, 8, 7, 9)}, initializers=inits)


@pytest.mark.parametrize("target", ["ansi-c", "ssse3"])
def test_blocked_residual_pool_and_gemm_under_sanitizers(target):
    m = residual_then_pool()
    compiled = compiled_for(m, target, 16, None, unroll="none")
    check_against_onnxruntime(m, compiled, sanitize=True, opt="-O1")


def test_unroll_layer_budgets_name_existing_layers():
    m = conv_model((1, 2, 4, 4), 4, (3, 3))
    with pytest.raises(NncgError, match="unroll: no layer named conv9"):
        PassManager(f"{LOWER},unroll{{level=auto,layers=conv9:16}}").run(import_onnx(m))


def narrow_conv_pair(channels: int, size: int):
    """A 3x3 Conv reading the output of another (so it reads a zero halo and no pixel is a border
    pixel), `channels` channels on `size` x `size` pixels, as resnet18's layer4 at 96x96 (512, 3)."""
    nodes = [
        helper.make_node("Conv", ["x", "w0", "b0"], ["a"], name="first", pads=[1, 1, 1, 1]),
        helper.make_node("Relu", ["a"], ["r"]),
        helper.make_node("Conv", ["r", "w1", "b1"], ["y"], name="conv", pads=[1, 1, 1, 1]),
    ]
    inits = {
        "w0": weights(channels, 8, 3, 3),
        "b0": weights(channels),
        "w1": weights(channels, channels, 3, 3),
        "b1": weights(channels),
    }
    return onnx_model(nodes, inputs={"x": (1, 8, size, size)}, initializers=inits)


def test_cost_model_blocks_whole_rows_of_narrow_images():
    # avx512, 3 pixels a row of 4 channel vectors: two rows (24 accumulators and 6 broadcasts)
    assert choose_blocks((3, 4), 32, fused=True, rows=3) == (6, 4)
    assert choose_blocks((3, 2), 32, fused=True, rows=3) == (9, 2)  # all 3 rows
    assert choose_blocks((3, 4), 16, fused=True, rows=3) == (3, 4)  # avx2: one row is the fit
    assert choose_blocks((40, 4), 32, fused=True, rows=40) == (6, 4)  # wide rows: as before
    assert choose_blocks((3, 4), 32, fused=True) == (3, 4)  # no row loop: as before


def direct(target: str, block: str | None = None) -> str:
    """The default pipeline without Winograd (which takes such small convs), `block` forced."""
    pipeline = nncg.default_pipeline(nncg.get_target(target)).replace("winograd,", "")
    return pipeline.replace("register-block", f"register-block{{layers={block}}}") if block else pipeline


def test_whole_row_block_jams_rows_and_columns():
    m = narrow_conv_pair(32, 3)
    compiled = nncg.compile(m, target="avx512", pipeline=direct("avx512"))
    blocks = chosen_blocks(compiled.record.before_register_block, nncg.get_target("avx512"))
    assert blocks["conv"] == (9, 2)
    upto = direct("avx512").split(",register-block")[0] + ",register-block"
    program = PassManager(upto, nncg.get_target("avx512"), verify=True).run(import_onnx(m))
    kernel = next(k for k in program.kernels if k.name == "conv")
    loops = {s.var for s in walk_stmts(kernel.body) if isinstance(s, Loop)}
    assert not loops & {"oh", "ow"}  # all 9 pixels in one block
    assert len({s.name for s in walk_stmts(kernel.body) if isinstance(s, Let)}) == 18  # 9 pixels x 2 vectors


WHOLE_ROWS = [(32, 3, None), (64, 3, None), (24, 4, "conv:8x3"), (64, 5, "conv:10x1")]


@pytest.mark.parametrize("target", ["ansi-c", "ssse3", "avx2", "avx512", "neon"])
@pytest.mark.parametrize("channels, size, block", WHOLE_ROWS)
def test_whole_row_blocks_match_onnxruntime(target, channels, size, block):
    # the cost model's blocks of whole rows, and forced ones: two rows of 4 (the third row left over)
    # and two rows of 5 with the channel loop left around them; neon on qemu
    m = narrow_conv_pair(channels, size)
    compiled = nncg.compile(m, target=target, pipeline=direct(target, block))
    if target != "neon":
        check_against_onnxruntime(m, compiled, opt="-O1")
        return
    toolchain = TOOLCHAINS["aarch64-neon"]
    if missing_tools(toolchain):
        pytest.skip(f"{', '.join(missing_tools(toolchain))} not installed")
    report = verify_on(toolchain, m, compiled)
    assert report.ok, report.format()


def test_float_layer_of_one_vector_blocks_its_columns():
    # 16 channels: one vector on avx512, whose multiply-add broadcasts its input from memory (6
    # pixels: ONE_VECTOR_FLOAT_PIXELS), two on avx2; 8 channels: one vector on avx2 (an accumulator and
    # a broadcast each)
    for name, channels, block in (("avx512", 16, (6, 1)), ("avx2", 16, (5, 2)), ("avx2", 8, (7, 1))):
        m = narrow_conv_pair(channels, 30)
        upto = direct(name).split(",register-block")[0]
        program = PassManager(upto, nncg.get_target(name), verify=True).run(import_onnx(m))
        assert chosen_blocks(program, nncg.get_target(name))["conv"] == block
