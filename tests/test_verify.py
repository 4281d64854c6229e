"""Tests for nncg.verify, using hand-written C stand-ins for the compiler's output."""

from __future__ import annotations

import shutil
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import onnx
import pytest
from helpers import check_against_onnxruntime, onnx_model
from onnx import helper

from nncg.errors import NncgError
from nncg.verify import (
    ErrorStat,
    VerificationError,
    VerifyReport,
    compare,
    find_c_compiler,
    random_inputs,
    run_compiled,
    verify,
)

ANSI_STRICT = ("-std=c89", "-pedantic", "-Wall", "-Wextra", "-Werror")
SSSE3_STRICT = ("-Wall", "-Wextra", "-Werror")

needs_cc = pytest.mark.skipif(not any(shutil.which(c) for c in ("cc", "gcc", "clang")), reason="no C compiler on PATH")


@dataclass(frozen=True)
class Tensor:
    name: str
    shape: tuple[int, ...]


@dataclass(frozen=True)
class FakeCompiled:
    """Stand-in for the compiler's CompiledModel with hand-written C."""

    name: str
    source: str
    header: str
    inputs: tuple[Tensor, ...]
    outputs: tuple[Tensor, ...]
    target: str = "ansi-c"
    cflags: tuple[str, ...] = ()
    strict_cflags: tuple[str, ...] = ANSI_STRICT

    def write(self, directory: str | Path) -> tuple[Path, Path]:
        c_path, h_path = Path(directory) / f"{self.name}.c", Path(directory) / f"{self.name}.h"
        c_path.write_text(self.source)
        h_path.write_text(self.header)
        return c_path, h_path


def fake(
    name: str,
    inputs: list[Tensor],
    outputs: list[Tensor],
    body: str,
    prelude: str = "",
    **kwargs: object,
) -> FakeCompiled:
    """A FakeCompiled whose header follows the contract and whose function body is `body`."""
    params = [f"const float *{t.name}" for t in inputs] + [f"float *{t.name}" for t in outputs]
    sizes = [f"#define {name.upper()}_{t.name.upper()}_SIZE {int(np.prod(t.shape))}" for t in [*inputs, *outputs]]
    guard = f"{name.upper()}_H"
    header = "\n".join(
        [
            f"#ifndef {guard}",
            f"#define {guard}",
            *sizes,
            f"void {name}({', '.join(params)});",
            "#endif",
            "",
        ]
    )
    source = f'#include <math.h>\n{prelude}#include "{name}.h"\n\nvoid {name}({", ".join(params)})\n{{\n{body}}}\n'
    return FakeCompiled(name, source, header, tuple(inputs), tuple(outputs), **kwargs)  # type: ignore[arg-type]


def checked_model(nodes: list[onnx.NodeProto], inputs: list[Tensor], outputs: list[Tensor]) -> onnx.ModelProto:
    """The model of these nodes over these tensors, validated by the ONNX checker."""
    model = onnx_model(
        nodes, inputs={t.name: t.shape for t in inputs}, outputs={t.name: t.shape for t in outputs}, opset=17
    )
    onnx.checker.check_model(model)
    return model


X, Y = Tensor("x", (1, 3, 4, 4)), Tensor("y", (1, 3, 4, 4))
RELU_MODEL = checked_model([helper.make_node("Relu", ["x"], ["y"])], [X], [Y])
RELU_BODY = "    int i;\n    for (i = 0; i < RELU_NET_X_SIZE; ++i) y[i] = x[i] > 0.0f ? x[i] : 0.0f;\n"

X1, X2, Y1, Y2 = (
    Tensor("x1", (2, 5)),
    Tensor("x2", (2, 5)),
    Tensor("y1", (2, 5)),
    Tensor("y2", (2, 5)),
)
ADD_MUL_MODEL = checked_model(
    [helper.make_node("Add", ["x1", "x2"], ["y1"]), helper.make_node("Mul", ["x1", "x2"], ["y2"])],
    [X1, X2],
    [Y1, Y2],
)
ADD_MUL_BODY = (
    "    int i;\n    for (i = 0; i < 10; ++i) {\n"
    "        y1[i] = x1[i] + x2[i];\n        y2[i] = x1[i] * x2[i];\n    }\n"
)


def relu(body: str = RELU_BODY, prelude: str = "", **kwargs: object) -> FakeCompiled:
    return fake("relu_net", [X], [Y], body, prelude, **kwargs)


@needs_cc
def test_correct_relu_passes_with_zero_error() -> None:
    report = check_against_onnxruntime(RELU_MODEL, relu())
    assert [(s.name, s.shape) for s in report.stats] == [("y", (1, 3, 4, 4))]
    assert report.stats[0].max_abs == 0.0
    assert report.format().splitlines()[-1].startswith("PASS")


@needs_cc
def test_two_inputs_two_outputs_are_passed_in_graph_order() -> None:
    compiled = fake("add_mul", [X1, X2], [Y1, Y2], ADD_MUL_BODY)
    x1, x2 = random_inputs(compiled.inputs, seed=3)
    y1, y2 = run_compiled(compiled, [x1, x2])
    np.testing.assert_array_equal(y1, x1 + x2)
    np.testing.assert_array_equal(y2, x1 * x2)
    report = check_against_onnxruntime(ADD_MUL_MODEL, compiled, seed=3)
    assert [s.name for s in report.stats] == ["y1", "y2"]
    assert all(s.max_abs == 0.0 for s in report.stats)


@needs_cc
def test_ssse3_style_target_flags_are_used() -> None:
    body = "#ifndef __SSSE3__\n#error built without the cflags of the target\n#endif\n" + RELU_BODY
    compiled = relu(body, target="ssse3", cflags=("-mssse3",), strict_cflags=SSSE3_STRICT)
    assert check_against_onnxruntime(RELU_MODEL, compiled).ok


@needs_cc
def test_wrong_implementation_fails_with_large_error() -> None:
    wrong = relu("    int i;\n    for (i = 0; i < 48; ++i) y[i] = x[i];\n")
    report = verify(RELU_MODEL, wrong)
    assert not report.ok
    assert report.stats[0].max_rel > 0.1
    assert report.format().splitlines()[-1].startswith("FAIL")
    with pytest.raises(AssertionError, match="FAIL"):
        check_against_onnxruntime(RELU_MODEL, wrong)


@needs_cc
def test_swapped_outputs_fail() -> None:
    swapped = ADD_MUL_BODY.replace("y1[i] =", "tmp =").replace("y2[i] =", "y1[i] =").replace("tmp =", "y2[i] =")
    report = verify(ADD_MUL_MODEL, fake("add_mul", [X1, X2], [Y1, Y2], swapped))
    assert not report.ok
    assert all(s.max_rel > 0.1 for s in report.stats)


@needs_cc
def test_unwritten_output_elements_are_caught() -> None:
    half = relu("    int i;\n    for (i = 0; i < 24; ++i) y[i] = x[i] > 0.0f ? x[i] : 0.0f;\n")
    report = verify(RELU_MODEL, half)
    assert not report.ok
    assert "24 NaN elements" in (report.stats[0].problem or "")
    assert "24 NaN elements" in report.format()


@needs_cc
@pytest.mark.parametrize(
    ("body", "strict", "message"),
    [
        ("    int unused;\n" + RELU_BODY, SSSE3_STRICT, "unused variable"),
        ("    // C++ comment\n" + RELU_BODY, ANSI_STRICT, r"C\+\+ style comments"),
        (
            RELU_BODY + "    { y[0] = 1.0f; int late = 0; y[1] = (float)late; }\n",
            ANSI_STRICT,
            "mixed declarations",
        ),
    ],
)
def test_warning_under_strict_flags_raises_with_compiler_message(
    body: str, strict: tuple[str, ...], message: str
) -> None:
    with pytest.raises(VerificationError, match=message) as info:
        verify(RELU_MODEL, relu(body, strict_cflags=strict))
    assert "compiling relu_net.c" in str(info.value)
    assert "-Werror" in str(info.value)


@needs_cc
def test_compiler_stderr_is_cut_to_the_first_lines() -> None:
    body = "".join(f"    int unused{i};\n" for i in range(100)) + RELU_BODY
    with pytest.raises(VerificationError, match=r"more lines\)$") as info:
        run_compiled(relu(body, strict_cflags=("-Wall", "-Wextra")), random_inputs([X]))
    assert "warned" in str(info.value)  # no -Werror, still a failure
    assert "unused variable" in str(info.value)
    assert len(str(info.value).splitlines()) == 1 + 40 + 1  # command, 40 stderr lines, cut note


@needs_cc
def test_sanitize_catches_out_of_bounds_write() -> None:
    overflow = relu("    int i;\n    for (i = 0; i <= RELU_NET_Y_SIZE; ++i) y[i] = 0.0f;\n    (void)x;\n")
    with pytest.raises(VerificationError, match="AddressSanitizer") as info:
        verify(RELU_MODEL, overflow, sanitize=True)
    assert "crashed" in str(info.value) or "exited" in str(info.value)


@needs_cc
def test_sanitize_catches_undefined_behaviour() -> None:
    body = "    int i, k = 2147483647 - (x[0] > 1000.0f);\n    k += 1;\n    y[0] = (float)k;\n" + RELU_BODY[10:]
    with pytest.raises(VerificationError, match="runtime error"):
        verify(RELU_MODEL, relu(body), sanitize=True)


@needs_cc
def test_sanitize_passes_correct_code() -> None:
    assert check_against_onnxruntime(ADD_MUL_MODEL, fake("add_mul", [X1, X2], [Y1, Y2], ADD_MUL_BODY), sanitize=True).ok


@needs_cc
def test_crashing_program_raises() -> None:
    compiled = relu("    (void)x;\n    (void)y;\n    raise(SIGABRT);\n", "#include <signal.h>\n")
    with pytest.raises(VerificationError, match="crashed with signal 6"):
        verify(RELU_MODEL, compiled)


@needs_cc
def test_workdir_keeps_model_and_harness_files(tmp_path: Path) -> None:
    (x,) = random_inputs([X], seed=1)
    (y,) = run_compiled(relu(), [x], workdir=tmp_path / "build")
    np.testing.assert_array_equal(y, np.maximum(x, 0))
    assert y.dtype == np.float32
    files = {p.name for p in (tmp_path / "build").iterdir()}
    assert {"relu_net.c", "relu_net.h", "harness.c", "harness"} <= files
    harness = (tmp_path / "build" / "harness.c").read_text()
    assert '#include "relu_net.h"' in harness
    assert "static float nncg_in0[48];" in harness and "static float nncg_out0[48];" in harness


@needs_cc
def test_wrong_input_shape_is_rejected() -> None:
    with pytest.raises(VerificationError, match="must have shape"):
        run_compiled(relu(), [np.zeros((48,), np.float32)])


def test_interface_must_match_the_graph_order() -> None:
    reordered = fake("add_mul", [X1, X2], [Y2, Y1], ADD_MUL_BODY)
    with pytest.raises(VerificationError, match="outputs"):
        verify(ADD_MUL_MODEL, reordered)


def test_random_inputs_are_deterministic_per_seed() -> None:
    specs = [X1, Tensor("w", (3,))]
    first, again, other = (
        random_inputs(specs, seed=7),
        random_inputs(specs, seed=7),
        random_inputs(specs, seed=8),
    )
    assert [a.shape for a in first] == [(2, 5), (3,)]
    assert all(a.dtype == np.float32 for a in first)
    for a, b in zip(first, again):
        np.testing.assert_array_equal(a, b)
    assert not np.array_equal(first[0], other[0])
    assert 0.3 < float(np.std(random_inputs([Tensor("big", (10000,))])[0])) < 3.0


def test_compare_is_relative_to_the_output_scale() -> None:
    ref = np.array([0.0, 100.0], np.float32)
    (stat,) = compare([np.array([1e-3, 100.0], np.float32)], [ref], ["y"])
    assert stat.name == "y" and stat.problem is None
    assert stat.max_abs == pytest.approx(1e-3)
    assert stat.max_rel == pytest.approx(1e-5)


def test_compare_flags_nan_shape_and_count_mismatches() -> None:
    ref = np.array([1.0, np.nan, 2.0], np.float32)
    (both_nan,) = compare([np.array([1.0, np.nan, 2.0], np.float32)], [ref])
    assert both_nan.problem is None and both_nan.max_abs == 0.0
    (new_nan,) = compare([np.array([np.nan, np.nan, 2.0], np.float32)], [ref])
    assert new_nan.problem is not None and "1 NaN" in new_nan.problem
    (bad_shape,) = compare([np.zeros((3, 1), np.float32)], [np.zeros((3,), np.float32)])
    assert bad_shape.problem is not None and "shape" in bad_shape.problem
    with pytest.raises(VerificationError):
        compare([ref], [ref, ref])


def test_report_table_is_aligned_and_states_tolerance() -> None:
    stats = (ErrorStat("y", (1, 10), 1.5e-7, 2e-8), ErrorStat("logits_long_name", (1,), 0.5, 0.25))
    report = VerifyReport("net", "ansi-c", stats, 1e-4, 0)
    lines = report.format().splitlines()
    header, row1, row2 = lines[1:4]
    for column in ("shape", "max abs err", "max rel err"):
        start = header.index(column)
        assert row1[start - 2 : start] == "  " and row1[start] != " "
        assert row2[start - 2 : start] == "  " and row2[start] != " "
    assert not report.ok
    assert lines[-1] == "FAIL: max rel err <= 0.0001 required"
    assert VerifyReport("net", "ansi-c", stats[:1], 1e-4, 0).format().endswith("PASS: max rel err <= 0.0001 required")


def test_find_c_compiler() -> None:
    with pytest.raises(NncgError, match="not found"):
        find_c_compiler("no-such-compiler-nncg")
    if any(shutil.which(c) for c in ("cc", "gcc", "clang")):
        found = find_c_compiler()
        assert found in ("cc", "gcc", "clang") and shutil.which(found) is not None
        assert find_c_compiler(found) == found
