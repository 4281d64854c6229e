"""ArgMax/ArgMin outputs are int32 in the C (ONNX's are int64; C89 has no guaranteed 64-bit type):
the signature, the header, the verify and benchmark harnesses and the Cortex-M4 print path carry
them as int32, and they are compared with onnxruntime's int64 indices exactly."""

from __future__ import annotations

import shutil
import subprocess

import numpy as np
import pytest
from helpers import onnx_model, skip_unless_host_runs
from onnx import helper
from test_norm_reduce_ops import arg_model

import nncg
from nncg.bench.harness import CompiledHarness
from nncg.verify import compare, random_inputs, reference_outputs, run_compiled

needs_cc = pytest.mark.skipif(shutil.which("cc") is None, reason="no C compiler on PATH")
STRICT_C89 = ("-std=c89", "-pedantic", "-Wall", "-Wextra", "-Werror")


def _model(op: str = "ArgMax"):
    return arg_model(op, (2, 7, 3, 5), axis=1, keepdims=0)


def test_header_and_signature_say_int32_indices():
    compiled = nncg.compile(_model(), name="classes")
    (spec,) = compiled.outputs
    assert spec.dtype == "int32" and compiled.inputs[0].dtype == "float32"
    assert "/* output 'y': int32[2,3,5], row-major as in ONNX; indices (ArgMax/ArgMin), int32 where ONNX" in (
        compiled.header
    )
    assert "C89 has no guaranteed 64-bit type" in compiled.header
    assert "void classes(const float *x, nncg_int32 *y);" in compiled.header
    assert "#ifndef NNCG_INT32_DEFINED" in compiled.header
    # The .c takes nncg_int32 from the header, not a second typedef (an error in C89).
    assert "typedef" not in compiled.source


def test_float_models_have_no_integer_types_in_the_header():
    relu = onnx_model([helper.make_node("Relu", ["x"], ["y"])], inputs={"x": (2, 7)}, outputs={"y": (2, 7)})
    compiled = nncg.compile(relu)
    assert compiled.outputs[0].dtype == "float32"
    assert "nncg_int32" not in compiled.header and "limits.h" not in compiled.header


@needs_cc
@pytest.mark.parametrize("target", ("ansi-c", "avx2"))
@pytest.mark.parametrize("op", ("ArgMax", "ArgMin"))
def test_indices_are_int32_and_equal_onnxruntime(op, target, tmp_path):
    skip_unless_host_runs(target)
    model = _model(op)
    compiled = nncg.compile(model, target=target)
    inputs = random_inputs(compiled.inputs, 3)
    (out,) = run_compiled(compiled, inputs, workdir=tmp_path)
    (ref,) = reference_outputs(model, compiled.inputs, inputs)
    assert out.dtype == np.int32 and ref.dtype == np.int64
    np.testing.assert_array_equal(out, ref)


@needs_cc
def test_two_models_headers_with_indices_compile_together(tmp_path):
    """The guarded typedef lets a program include the headers of two models with int32 outputs."""
    for name in ("first", "second"):
        compiled = nncg.compile(_model(), name=name)
        compiled.write(tmp_path)
        subprocess.run(["cc", *STRICT_C89, "-c", f"{name}.c"], cwd=tmp_path, check=True)
    main = '#include "first.h"\n#include "second.h"\nint main(void) { nncg_int32 y[30]; (void)y; return 0; }\n'
    (tmp_path / "main.c").write_text(main)
    subprocess.run(["cc", *STRICT_C89, "-c", "main.c"], cwd=tmp_path, check=True)


def test_compare_needs_equal_indices():
    ref = np.array([[1, 4], [0, 2]], np.int64)
    (same,) = compare([ref.astype(np.int32)], [ref])
    assert same.problem is None and same.max_abs == 0 and same.indices
    (off,) = compare([np.array([[1, 4], [0, 3]], np.int32)], [ref])
    assert off.problem == "1 of 4 indices differ from the reference" and off.max_abs == 1 and off.max_rel == np.inf
    (floats,) = compare([ref.astype(np.float32)], [ref])
    assert floats.problem == "float32 output where the reference is int64"


@needs_cc
def test_benchmark_harness_reads_int32_outputs(tmp_path):
    model = _model()
    compiled = nncg.compile(model)
    inputs = random_inputs(compiled.inputs, 5)
    harness = CompiledHarness(compiled, tmp_path, "cc", inputs)
    try:
        assert harness.run(2) > 0
        (out,) = harness.outputs()
    finally:
        harness.close()
    assert out.dtype == np.int32
    np.testing.assert_array_equal(out, reference_outputs(model, compiled.inputs, inputs)[0])


def test_cortex_m4_prints_int32_indices(tmp_path):
    from cross_helpers import CORTEX_M4_TOOLS, run_cortex_m4

    if any(shutil.which(tool) is None for tool in CORTEX_M4_TOOLS):
        pytest.skip("the Cortex-M4 toolchain is not installed")
    model = _model("ArgMin")
    compiled = nncg.compile(model)
    inputs = random_inputs(compiled.inputs, 7)
    result = run_cortex_m4(compiled, inputs, tmp_path)
    assert result.outputs[0].dtype == np.int32
    np.testing.assert_array_equal(result.outputs[0], reference_outputs(model, compiled.inputs, inputs)[0])


@needs_cc
def test_per_layer_verification_compares_the_indices_too():
    from nncg.verify_layers import verify_per_layer

    report = verify_per_layer(_model("ArgMin"), "ansi-c")
    assert report.ok
    assert [(layer.stat.name, layer.stat.indices) for layer in report.layers] == [("t", False), ("y", True)]
