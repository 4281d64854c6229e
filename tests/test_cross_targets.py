"""Portability (issue 6): the generated C cross-compiled for 32-bit x86, armhf, aarch64 and riscv64 and
run natively or under qemu-user, built with clang and tcc on the host, and built bare metal for a
Cortex-M4 run in qemu-system-arm. Every run is compared with onnxruntime on the host.

A missing toolchain skips its tests when run by hand and fails them in CI (CI set), so that CI
proves scripts/install-test-deps.sh installed every one. scripts/cross_matrix.py prints the
target x model errors and the Cortex-M4 sizes as tables."""

import functools
import os
import shutil

import pytest
from cross_helpers import (
    CASES,
    CORTEX_M4_MODELS,
    CORTEX_M4_TOOLS,
    MODELS,
    TOOLCHAINS,
    format_table,
    missing_tools,
    runner,
    size_row,
    verify_on,
    verify_on_cortex_m4,
)

import nncg


def require(missing: list[str]) -> None:
    if not missing:
        return
    message = f"{', '.join(missing)} not installed (scripts/install-test-deps.sh installs it)"
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
