"""The static memory plan: lifetimes, reuse, in-place, and the reentrant NAME_run with a caller's arena."""

from dataclasses import replace
from pathlib import Path

import numpy as np
import onnx
import pytest
from onnx import TensorProto, helper, numpy_helper
from test_vectorize_pixels import accumulate
from test_x86_targets import TARGETS as X86_TARGETS

import nncg
from nncg.frontend import load_model
from nncg.ir.graph import Activation
from nncg.ir.loops import Affine, Binary, Buffer, Const, Kernel, Load, Loop, Program, Store
from nncg.ir.ops import IR_OPS
from nncg.ir.target import Target
from nncg.lowering.band_plan import overwriting_layers
from nncg.passes.plan_memory import kernel_access, lifetimes, plan_memory
from nncg.passes.vectorize import vectorize
from nncg.tools import run_tool
from nncg.verify import find_c_compiler, random_inputs, reference_outputs

EXAMPLES = Path(__file__).parent.parent / "examples"
MODELS = Path(__file__).parent.parent / "benchmarks" / "models"


def copy_kernel(name, src, dst, n, fn=lambda x: x):
    body = (Loop("i", n, (Store(dst, Affine.of("i"), fn(Load(src, Affine.of("i")))),), parallel=True),)
    return Kernel(name, "Test", body)


def reverse_kernel(name, src, dst, n):
    """Reads element n-1-i for element i: not elementwise, so never in place."""
    index = Affine.of("i") * -1 + (n - 1)
    return Kernel(name, "Test", (Loop("i", n, (Store(dst, Affine.of("i"), Load(src, index)),), parallel=True),))


def chain_program(kernels, sizes):
    buffers = [Buffer("x", 64, "input"), Buffer("y", 64, "output")]
    buffers += [Buffer(name, size, "internal") for name, size in sizes.items()]
    return Program("p", tuple(buffers), tuple(kernels))


def test_lifetimes_span_first_to_last_touching_kernel():
    program = chain_program(
        [copy_kernel("k0", "x", "a", 64), copy_kernel("k1", "a", "b", 64), copy_kernel("k2", "b", "y", 64)],
        {"a": 64, "b": 64},
    )
    assert lifetimes(program) == {"a": (0, 1), "b": (1, 2)}
    access = kernel_access(program.kernels[1])
    assert access.reads == {"a"} and access.writes == {"b"}


def test_chain_reuses_memory_and_elementwise_runs_in_place():
    relu = lambda x: Binary("max", x, Const.splat(0.0))  # noqa: E731
    kernels = [
        reverse_kernel("k0", "x", "a", 64),
        copy_kernel("k1", "a", "b", 64, relu),  # elementwise: b takes a's memory (renamed to a)
        reverse_kernel("k2", "b", "c", 64),
        reverse_kernel("k3", "c", "d", 64),
        reverse_kernel("k4", "d", "y", 64),
    ]
    planned = plan_memory(chain_program(kernels, {"a": 64, "b": 64, "c": 64, "d": 64}))
    names = [b.name for b in planned.role("internal")]
    assert names == ["a", "c", "d"]  # b was merged into a
    assert kernel_access(planned.kernels[1]).writes == {"a"} and kernel_access(planned.kernels[2]).reads == {"a"}
    offsets = {b.name: b.offset for b in planned.role("internal")}
    # a (k0-k2) and c (k2-k3) overlap in time, c and d too; a and d do not: two slots suffice.
    assert offsets["a"] != offsets["c"] and offsets["c"] != offsets["d"] and offsets["a"] == offsets["d"]
    assert planned.arena.floats == 128 and planned.arena.activation_floats == 256


def test_not_elementwise_is_never_in_place():
    kernels = [copy_kernel("k0", "x", "a", 64), reverse_kernel("k1", "a", "b", 64), copy_kernel("k2", "b", "y", 64)]
    planned = plan_memory(chain_program(kernels, {"a": 64, "b": 64}))
    offsets = {b.name: b.offset for b in planned.role("internal")}
    assert set(offsets) == {"a", "b"} and offsets["a"] != offsets["b"]


def test_a_kernel_storing_elements_twice_is_never_in_place():
    """An overlapped vector tail stores some elements twice: in place, the second store would read
    an element the first already overwrote. vectorize marks such kernels; plan-memory obeys."""
    relu = lambda x: Binary("max", x, Const.splat(0.0))  # noqa: E731
    overlapping = replace(copy_kernel("k1", "a", "b", 64, relu), overlapping_stores=True)
    kernels = [reverse_kernel("k0", "x", "a", 64), overlapping, reverse_kernel("k2", "b", "y", 64)]
    planned = plan_memory(chain_program(kernels, {"a": 64, "b": 64}))
    assert [b.name for b in planned.role("internal")] == ["a", "b"]
    marked = vectorize(chain_program([Kernel("k", "Conv", (accumulate(20, 0, 20),))], {}), Target("t", (8, 4)))
    assert marked.kernels[0].overlapping_stores


def test_offsets_are_aligned_and_no_reuse_lays_out_back_to_back():
    kernels = [copy_kernel("k0", "x", "a", 5), reverse_kernel("k1", "a", "b", 5), copy_kernel("k2", "b", "y", 5)]
    program = chain_program(kernels, {"a": 5, "b": 5})
    planned = plan_memory(program, align=64)
    assert [b.offset for b in planned.role("internal")] == [0, 16] and planned.arena.floats == 32
    assert [b.offset for b in plan_memory(program, align=16).role("internal")] == [0, 8]
    alone = plan_memory(program, reuse=False)
    assert [b.offset for b in alone.role("internal")] == [0, 16]


def program_of(model, target, unroll):
    from nncg.frontend import import_onnx
    from nncg.passes import PassManager, default_pipeline

    facts = nncg.get_target(target)
    return PassManager(default_pipeline(facts, unroll), facts).run(import_onnx(model))


@pytest.mark.parametrize(
    "model",
    [EXAMPLES / "ball.onnx", EXAMPLES / "robot.onnx", MODELS / "resnet8.onnx", MODELS / "dscnn.onnx"],
    ids=lambda p: p.stem,
)
def test_no_kernel_sees_overlapping_buffers(model):
    """The plan's safety property on real networks: buffers one kernel touches never overlap."""
    program = program_of(model, "ssse3", "none")
    internal = {b.name: b for b in program.role("internal")}
    for kernel in program.kernels:
        spans = sorted(
            (internal[n].offset, internal[n].offset + internal[n].size)
            for n in kernel_access(kernel).touched
            if n in internal
        )
        for (_, end), (start, _) in zip(spans, spans[1:]):
            assert end <= start, f"{kernel.name} sees overlapping buffers"
    assert all(b.offset + b.size <= program.arena.floats for b in internal.values())
    assert program.arena.floats < program.arena.activation_floats


REENTRANT_MAIN = r"""
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include "{name}.h"

/* Runs the model three ways: NAME (static arena), NAME_run with a heap arena that is only
   float-aligned (offset by 4 bytes), and NAME_run with two arenas interleaved; prints the outputs. */
int main(void)
{{
    static float in[{name_upper}_{input_upper}_SIZE], out[3][{name_upper}_{output_upper}_SIZE];
    unsigned char *block = malloc({name_upper}_ARENA_BYTES + 68);
    unsigned char *other = malloc({name_upper}_ARENA_BYTES + 64);
    size_t i;
    if (fread(in, sizeof in, 1, stdin) != 1 || !block || !other) return 1;
    memset(block, 0xff, {name_upper}_ARENA_BYTES + 68); /* NaN garbage: the model must not read it */
    memset(other, 0xff, {name_upper}_ARENA_BYTES + 64);
    {name}(in, out[0]);
    {name}_run(in, out[1], block + 4);
    {name}_run(in, out[2], other);
    {name}_run(in, out[2], block + 4);
    for (i = 0; i < 3; ++i) fwrite(out[i], sizeof out[i], 1, stdout);
    free(block);
    free(other);
    return 0;
}}
"""


@pytest.mark.parametrize("target", ["ansi-c", "ssse3"])
def test_run_with_callers_arena_matches_onnxruntime(tmp_path, target):
    model = EXAMPLES / "ball.onnx"
    compiled = nncg.compile(model, target=target)
    compiled.write(tmp_path)
    (inp,), (out,) = compiled.inputs, compiled.outputs
    main = REENTRANT_MAIN.format(
        name=compiled.name,
        name_upper=compiled.name.upper(),
        input_upper=inp.c_name.upper(),
        output_upper=out.c_name.upper(),
    )
    (tmp_path / "main.c").write_text(main)
    cc = find_c_compiler()
    sanitizers = ["-fsanitize=address,undefined", "-fno-sanitize-recover=all"]
    flags = ["-O1", "-g", *sanitizers, *compiled.cflags, *compiled.strict_cflags]
    run_tool([cc, *flags, "main.c", f"{compiled.name}.c", "-o", "main", "-lm"], "building main", cwd=tmp_path)
    (x,) = random_inputs(compiled.inputs, seed=3)
    run = run_tool([tmp_path / "main"], "running main", stdin=x.tobytes(), text=False)
    outs = np.frombuffer(run.stdout, dtype=np.float32).reshape(3, *out.shape)
    (ref,) = reference_outputs(load_model(model), compiled.inputs, [x])
    for result in outs:
        np.testing.assert_allclose(result, ref, rtol=1e-5, atol=1e-6)
    assert compiled.arena_bytes < compiled.activation_bytes
    assert f"#define {compiled.name.upper()}_ARENA_BYTES {compiled.arena_bytes}" in compiled.header


def gemm_model(k, n):
    from onnx import TensorProto, helper, numpy_helper

    w = (np.random.default_rng(0).standard_normal((k, n)) / np.sqrt(k)).astype(np.float32)
    graph = helper.make_graph(
        [helper.make_node("Gemm", ["x", "w"], ["y"])],
        "gemm",
        [helper.make_tensor_value_info("x", TensorProto.FLOAT, [1, k])],
        [helper.make_tensor_value_info("y", TensorProto.FLOAT, [1, n])],
        [numpy_helper.from_array(w, "w")],
    )
    m = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 13)])
    m.ir_version = 8
    return m


@pytest.mark.parametrize("target", ["ansi-c", "ssse3", *X86_TARGETS])
def test_weights_in_a_binary_file_match_onnxruntime(target):
    import zlib

    from helpers import check_against_onnxruntime

    compiled = nncg.compile(EXAMPLES / "robot.onnx", target=target, unroll=None, weights="bin")
    assert compiled.weights is not None and "static NNCG_ALIGNED const float" not in compiled.source
    macro = compiled.name.upper()
    assert f"#define {macro}_WEIGHTS_BYTES {len(compiled.weights)}\n" in compiled.header
    assert f"#define {macro}_WEIGHTS_CRC32 0x{zlib.crc32(compiled.weights):08x}UL" in compiled.header
    check_against_onnxruntime(load_model(EXAMPLES / "robot.onnx"), compiled, sanitize=True, opt="-O1")


@pytest.mark.parametrize("target", ["ansi-c", "ssse3", *X86_TARGETS])
def test_conv_network_with_weights_in_a_file_matches_onnxruntime(target):
    """Default unrolling and register blocking read the blob's arrays at constant offsets from the
    aligned pointer (issue 15: a blob must run as fast as embedded weights, and as correctly)."""
    from helpers import check_against_onnxruntime

    compiled = nncg.compile(MODELS / "resnet8.onnx", target=target, weights="bin")
    assert compiled.weights is not None
    check_against_onnxruntime(load_model(MODELS / "resnet8.onnx"), compiled, opt="-O2")


def test_weights_header_states_the_contract_the_code_relies_on():
    """The blob's alignment, read-only use and no aliasing are stated in the header; the .c promises
    the alignment to the compiler (guarded, so C89 compilers take it) and checks it in NAME_weights_ok."""
    compiled = nncg.compile(EXAMPLES / "robot.onnx", target="ansi-c", unroll=None, weights="bin")
    macro, name = compiled.name.upper(), compiled.name
    header = " ".join(compiled.header.split())
    assert f"#define {macro}_WEIGHTS_ALIGN 64" in compiled.header
    assert f"`weights` is {macro}_WEIGHTS_ALIGN-byte aligned. malloc's alignment is not enough" in header
    assert "it is read only: the model never writes it, and nothing may write it while the model runs" in header
    assert "it overlaps none of the inputs, outputs and arena" in header
    assert f"{name}_weights_ok(weights) returns 1 when `weights` is aligned" in header
    assert "__builtin_assume_aligned((p), (n))" in compiled.source
    assert f"(const float *)NNCG_ASSUME_ALIGNED(weights, {macro}_WEIGHTS_ALIGN);" in compiled.source
    assert f"% {macro}_WEIGHTS_ALIGN != 0" in compiled.source
    embedded = nncg.compile(EXAMPLES / "robot.onnx", target="ansi-c", unroll=None, weights="embed")
    assert "WEIGHTS_ALIGN" not in embedded.header and "NNCG_ASSUME_ALIGNED" not in embedded.source


WEIGHTS_OK_MAIN = """\
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include "{name}.h"

int main(void)
{{
    unsigned char *raw = (unsigned char *)malloc({macro}_WEIGHTS_BYTES + 2 * {macro}_WEIGHTS_ALIGN);
    unsigned char *aligned, *file;
    FILE *f = fopen("{name}.weights", "rb");
    size_t got;
    if (raw == NULL || f == NULL) return 2;
    file = (unsigned char *)malloc({macro}_WEIGHTS_BYTES);
    if (file == NULL) return 2;
    got = fread(file, 1, {macro}_WEIGHTS_BYTES, f);
    fclose(f);
    if (got != {macro}_WEIGHTS_BYTES) return 2;
    aligned = raw + ({macro}_WEIGHTS_ALIGN - (size_t)raw % {macro}_WEIGHTS_ALIGN);
    memcpy(aligned, file, {macro}_WEIGHTS_BYTES);
    printf("aligned %d\\n", {name}_weights_ok(aligned));
    memcpy(aligned + 4, file, {macro}_WEIGHTS_BYTES);
    printf("misaligned %d\\n", {name}_weights_ok(aligned + 4));
    memcpy(aligned, file, {macro}_WEIGHTS_BYTES);
    aligned[7] ^= 1;
    printf("corrupt %d\\n", {name}_weights_ok(aligned));
    printf("null %d\\n", {name}_weights_ok(NULL));
    free(file);
    free(raw);
    return 0;
}}
"""


def test_weights_ok_refuses_a_misaligned_or_corrupt_blob(tmp_path):
    """A blob at a float-aligned but not NAME_WEIGHTS_ALIGN-aligned address fails the check, as the
    header documents: the code assumes the alignment. Built as strict C89 (the guard on the builtin)."""
    compiled = nncg.compile(EXAMPLES / "robot.onnx", target="ansi-c", unroll=None, weights="bin")
    compiled.write(tmp_path)
    (tmp_path / "main.c").write_text(WEIGHTS_OK_MAIN.format(name=compiled.name, macro=compiled.name.upper()))
    cc = find_c_compiler()
    flags = [*compiled.strict_cflags, "-O2"]
    run_tool([cc, *flags, f"{compiled.name}.c", "main.c", "-o", "main", "-lm"], "compiling", cwd=tmp_path)
    out = run_tool([str(tmp_path / "main")], "running", cwd=tmp_path).stdout
    assert out.split("\n")[:4] == ["aligned 1", "misaligned 0", "corrupt 0", "null 0"]


def test_large_weights_go_to_a_file_by_default():
    """auto: 1024 x 1100 floats (4.3 MiB) exceed the threshold; --weights embed keeps them in the C."""
    from helpers import check_against_onnxruntime

    m = gemm_model(1024, 1100)
    compiled = nncg.compile(m, target="ssse3", unroll=None)
    assert compiled.weights is not None and len(compiled.weights) >= 1024 * 1100 * 4
    check_against_onnxruntime(m, compiled)
    small = nncg.compile(gemm_model(64, 10), target="ssse3", unroll=None)
    assert small.weights is None and "static NNCG_ALIGNED const float" in small.source


def _two_branch_model(op: str, channels: int) -> onnx.ModelProto:
    """x -> Conv -> MaxPool (p) and x -> Conv -> MaxPool (q), then `op` on p (and q), then a Conv: p
    and q die at `op`, so plan-memory may compute it in place."""
    rng = np.random.default_rng(0)
    weight = lambda name: numpy_helper.from_array(rng.standard_normal((channels, channels, 3, 3), np.float32), name)  # noqa: E731
    conv = lambda x, w, y: helper.make_node("Conv", [x, w], [y], pads=[1] * 4)  # noqa: E731
    pool = lambda x, y: helper.make_node("MaxPool", [x], [y], kernel_shape=[3, 3], pads=[1] * 4)  # noqa: E731
    nodes = [conv("x", "w1", "a"), pool("a", "p"), conv("x", "w2", "b"), pool("b", "q")]
    constants = [weight("w1"), weight("w2"), weight("w3")]
    if op in ("Add", "Sub", "Mul", "Div", "Max", "Min", "Sum"):
        nodes.append(helper.make_node(op, ["p", "q"], ["r"]))
    elif op == "Where":
        condition = rng.random((channels, 8, 8)) > 0.5
        constants.append(numpy_helper.from_array(condition, "condition"))
        nodes.append(helper.make_node(op, ["condition", "p", "q"], ["r"]))
    else:
        inputs = ["p", "slope"] if op == "PRelu" else ["p"]
        if op == "PRelu":
            constants.append(numpy_helper.from_array(rng.standard_normal((channels, 1, 1), np.float32), "slope"))
        nodes += [helper.make_node(op, inputs, ["r0"]), helper.make_node("Add", ["r0", "q"], ["r"])]
    nodes.append(conv("r", "w3", "y"))
    value = lambda name: helper.make_tensor_value_info(name, TensorProto.FLOAT, [1, channels, 8, 8])  # noqa: E731
    graph = helper.make_graph(nodes, "g", [value("x")], [value("y")], constants)
    return helper.make_model(graph, opset_imports=[helper.make_opsetid("", 18)])


# Every float op the IR marks elementwise that ONNX spells the same, and one that is not elementwise.
CONTRACT_OPS = sorted(
    op
    for op, record in IR_OPS.items()
    if record.elementwise and record.attrs in (None, Activation) and op not in ("PowPerElement", "Pow", "Gelu", "Silu")
) + ["Softmax"]


@pytest.mark.parametrize("target", ["ansi-c", "avx2"])
@pytest.mark.parametrize("op", CONTRACT_OPS)
def test_band_planner_counts_in_place_layers_as_plan_memory_places_them(op, target):
    """The band planner prices memory before lowering, from IR_OPS' `elementwise`; plan-memory decides
    in place from the kernels' accesses. Where they disagree the budget and balanced figures are off."""
    for channels in (16, 5):  # 5: vector tails
        compiled = nncg.compile(_two_branch_model(op, channels).SerializeToString(), target=target)
        graph = compiled.record.lowered
        shared = overwriting_layers(graph)
        kept = {b.name for b in compiled.record.program.role("internal")}
        for i, node in enumerate(graph.nodes):
            if not graph.is_graph_output(node.outputs[0]):
                in_place = (
                    f"t_{node.outputs[0]}" not in kept
                )  # its buffer renamed to the input it overwrites (context.py)
                assert (i in shared) == in_place, (node.op, channels)
