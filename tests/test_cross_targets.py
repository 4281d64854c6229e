"""Portability (issue 6): the generated C cross-compiled for 32-bit x86, armhf, aarch64 and riscv64 and
run natively or under qemu-user, built with clang and tcc on the host, and built bare metal for a
Cortex-M4 run in qemu-system-arm; the neon target's C run on armhf (with and without VFPv4's fused
multiply-add) and aarch64, and cross-compiled with clang. Every run is compared with onnxruntime on
the host.

A missing toolchain skips its tests when run by hand and fails them in CI (CI set), so that CI
proves scripts/install-test-deps.sh installed every one. scripts/cross_matrix.py prints the
target x model errors and the Cortex-M4 sizes as tables."""

import functools
import os
import shutil

import numpy as np
import pytest
from cross_helpers import (
    CASES,
    CLANG_NEON_FLAGS,
    CORTEX_M4_INT8_MODELS,
    CORTEX_M4_MIN_INT8_MODELS,
    CORTEX_M4_MIN_MODELS,
    CORTEX_M4_MODELS,
    CORTEX_M4_TOOLS,
    MODELS,
    NEON_TOOLCHAINS,
    TOOLCHAINS,
    clang_cross_problem,
    compile_with_clang,
    format_table,
    missing_tools,
    quantized_model,
    runner,
    size_row,
    verify_int8_on_cortex_m4,
    verify_on,
    verify_on_cortex_m4,
)
from helpers import onnx_model
from onnx import helper
from test_ops import conv_model
from test_x86_targets import HOOKS

import nncg


def require(missing: list[str]) -> None:
    if missing:
        skip_unless_ci(f"{', '.join(missing)} not installed (scripts/install-test-deps.sh installs it)")


def skip_unless_ci(message: str) -> None:
    if os.environ.get("CI"):
        pytest.fail(f"{message}: CI must run every target", pytrace=False)
    pytest.skip(message)


@pytest.fixture(scope="session")
def compiled_model():
    """nncg.compile(model, target), once per session (the ansi-c file is the same for every toolchain)."""

    @functools.cache
    def compile_once(model: str, target: str):
        return nncg.compile(MODELS[model], target=target)

    return compile_once


@pytest.mark.parametrize("toolchain, model", CASES, ids=[f"{tc}-{m}" for tc, m in CASES])
def test_model_matches_onnxruntime_on_target(toolchain, model, compiled_model):
    tc = TOOLCHAINS[toolchain]
    require(missing_tools(tc))
    report = verify_on(tc, model, compiled_model(model, tc.target))
    print(f"{toolchain} (run {' '.join(runner(tc)) or 'natively'})\n{report.format()}")
    assert report.ok, report.format()


@pytest.mark.parametrize("model", CORTEX_M4_MODELS)
def test_model_matches_onnxruntime_on_cortex_m4(model, compiled_model, tmp_path):
    require([tool for tool in CORTEX_M4_TOOLS if shutil.which(tool) is None])
    compiled = compiled_model(model, "ansi-c")
    report, result = verify_on_cortex_m4(model, compiled, tmp_path)
    print(f"{report.format()}\n{format_table({model: size_row(result, compiled.arena_bytes)})}")
    assert report.ok, report.format()
    # The static arena is RAM, and the stack's deepest use stayed inside the stack (no overflow).
    assert result.model_sizes["bss"] >= compiled.arena_bytes
    assert 0 < result.stack_bytes < result.image_sizes["stack"]


@pytest.mark.parametrize("toolchain", ["aarch64-neon", "armhf-neon"])
@pytest.mark.parametrize("model", ["robot", "mobilenet_v1_025"])
def test_neon_at_min_memory_matches_onnxruntime(toolchain, model):
    tc = TOOLCHAINS[toolchain]
    require(missing_tools(tc))
    report = verify_on(tc, model, nncg.compile(MODELS[model], target="neon", memory="min"))
    assert report.ok, report.format()


RAM_MARGIN = 512  # bytes beyond what the first build measured (section alignment)


def only_the_ram(measured) -> dict[str, int]:
    """build_cortex_m4's ram and stack for a program whose first build measured `measured`: RAM for
    just the data and bss (the arena, the test program's buffers), the stack it used and a margin."""
    stack = measured.stack_bytes + RAM_MARGIN
    return {"ram": measured.image_sizes["data"] + measured.image_sizes["bss"] + stack + RAM_MARGIN, "stack": stack}


@pytest.mark.parametrize("model", CORTEX_M4_MIN_MODELS)
def test_min_memory_model_runs_in_only_the_ram_its_plan_needs(model, tmp_path):
    """At --memory min, linked with only_the_ram after a first run, and run again."""
    require([tool for tool in CORTEX_M4_TOOLS if shutil.which(tool) is None])
    compiled = nncg.compile(MODELS[model], target="ansi-c", memory="min")
    _, measured = verify_on_cortex_m4(model, compiled, tmp_path)
    memory = only_the_ram(measured)
    report, result = verify_on_cortex_m4(model, compiled, tmp_path, **memory)
    table = format_table({model: size_row(result, compiled.arena_bytes)})
    print(f"{report.format()}\nRAM {memory['ram']} bytes: {table}")
    assert report.ok, report.format()
    if model != "ball":  # ball's tensors are smaller than the program's stack
        assert memory["ram"] < nncg.compile(MODELS[model], target="ansi-c").arena_bytes  # below the speed arena alone


@pytest.mark.parametrize("model", CORTEX_M4_MIN_INT8_MODELS)
def test_int8_min_memory_model_runs_in_only_the_ram_its_plan_needs(model, tmp_path):
    """The int8 model (quantised as tests/test_int8.py does) at --memory min, linked with only_the_ram
    after a first run and run again: the same bits as onnxruntime on the QDQ model."""
    require([tool for tool in CORTEX_M4_TOOLS if shutil.which(tool) is None])
    qdq = quantized_model(model)
    compiled = nncg.compile(qdq, target="ansi-c", memory="min", verify_ir=True)
    _, measured = verify_int8_on_cortex_m4(qdq, compiled, tmp_path)
    memory = only_the_ram(measured)
    comparison, result = verify_int8_on_cortex_m4(qdq, compiled, tmp_path, **memory)
    speed_arena = nncg.compile(qdq, target="ansi-c").arena_bytes
    row = {**size_row(result, compiled.arena_bytes), "speed arena": speed_arena}
    print(f"{model} int8 on cortex-m4: {comparison}\nRAM {memory['ram']} bytes: {format_table({model: row})}")
    assert comparison.max_steps == 0 and comparison.identical == 1.0, comparison
    assert compiled.arena_bytes < speed_arena
    if model != "ball":  # ball's tensors are smaller than the program's stack
        assert memory["ram"] < speed_arena  # the whole program's RAM below the speed arena alone


@pytest.mark.parametrize("model", CORTEX_M4_INT8_MODELS)
def test_int8_model_matches_onnxruntime_on_cortex_m4(model, tmp_path):
    """The int8 C (strict C89) on the Cortex-M4's FPU rounds as onnxruntime's x86 kernels: uint8
    activations give the same bits (as tests/test_int8.py asserts on the host)."""
    require([tool for tool in CORTEX_M4_TOOLS if shutil.which(tool) is None])
    qdq = quantized_model(model)
    compiled = nncg.compile(qdq, target="ansi-c", verify_ir=True)
    comparison, result = verify_int8_on_cortex_m4(qdq, compiled, tmp_path)
    print(f"{model} int8 on cortex-m4: {comparison}\n{format_table({model: size_row(result, compiled.arena_bytes)})}")
    assert comparison.max_steps <= 1 and comparison.identical == 1.0, comparison
    assert result.model_sizes["bss"] >= compiled.arena_bytes
    assert 0 < result.stack_bytes < result.image_sizes["stack"]


def divide_by_tensor():
    """x / (d * d + 1): a vector division by a computed tensor (8 contiguous floats: two vectors)."""
    nodes = [
        helper.make_node("Mul", ["d", "d"], ["s"]),
        helper.make_node("Add", ["s", "one"], ["t"]),
        helper.make_node("Div", ["x", "t"], ["y"]),
    ]
    return onnx_model(nodes, inputs={"x": (1, 4, 5, 8), "d": (1, 4, 5, 8)}, initializers={"one": np.float32(1.0)})


def gemv():
    """A classifier at batch 1, 131 x 110 (56 KiB of weights, beyond L1): 5 panels of 5 vectors, each
    read in 2 reduction streams, and a rest of 10 columns (2 vectors and a tail of 2)."""
    rng = np.random.default_rng(0)
    w = rng.standard_normal((131, 110)).astype(np.float32)
    b = rng.standard_normal(110).astype(np.float32)
    node = helper.make_node("Gemm", ["x", "w", "b"], ["y"])
    return onnx_model([node], inputs={"x": (1, 131)}, initializers={"w": w, "b": b})


# The x86 targets' vector hooks (20 channels: five NEON vectors), 21 channels for a scalar tail
# next to the vectors (a longer tail becomes an overlapping vector), and a division.
NEON_HOOKS = {
    **HOOKS,
    "vectors_and_tail": conv_model((1, 3, 6, 7), 21, (3, 3), pads=[1, 1, 1, 1]),
    "overlapped_tail": conv_model((1, 3, 6, 7), 22, (3, 3), pads=[1, 1, 1, 1]),
    "div": divide_by_tensor(),
    "gemv": gemv(),
}
# What each case must print: the hook's intrinsic or helper.
NEON_PRINTS = {
    "fma_and_tail": ["nncg_vfmaq_f32("],
    "select": ["vbslq_f32(vcgtq_f32("],
    "max": ["vmaxq_f32("],
    "lane_wise_call": ["nncg_vsigmoidq_f32(", "nncg_vdivq_f32("],
    "vectors_and_tail": ["nncg_vfmaq_f32(", "float acc"],
    "overlapped_tail": ["nncg_vfmaq_f32("],
    "div": ["nncg_vdivq_f32(vld1q_f32("],
    "gemv": ["acc_seg1_4 = nncg_vfmaq_f32(acc_seg1_4, vdupq_n_f32(x["],
}


@pytest.mark.parametrize("toolchain", NEON_TOOLCHAINS)
@pytest.mark.parametrize("case", NEON_HOOKS)
def test_neon_vector_hooks_match_onnxruntime(case, toolchain):
    tc = TOOLCHAINS[toolchain]
    require(missing_tools(tc))
    m = NEON_HOOKS[case]
    for unroll in (None, 2):
        compiled = nncg.compile(m, target="neon", unroll=unroll, verify_ir=True)
        for text in NEON_PRINTS[case]:
            assert text in compiled.source, (text, unroll)
        report = verify_on(tc, m, compiled)
        assert report.ok, report.format()


@pytest.mark.parametrize("target", CLANG_NEON_FLAGS)
def test_neon_source_compiles_with_clang(target, compiled_model, tmp_path):
    """clang's arm_neon.h differs from gcc's (vld1q_f32 and others are macros): the paper's networks
    and every hook's file build with its strict flags."""
    flags = CLANG_NEON_FLAGS[target]
    problem = clang_cross_problem(flags)
    if problem:
        skip_unless_ci(problem)
    sources = [compiled_model(name, "neon") for name in ("ball", "pedestrian", "robot")]
    sources += [nncg.compile(m, target="neon") for m in NEON_HOOKS.values()]
    for i, compiled in enumerate(sources):
        compile_with_clang(flags, compiled, tmp_path / str(i))
