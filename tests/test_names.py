"""Outside text is hostile: names from a model, --name, --input-shape keys and paths never reach the
generated C, a comment, CMakeLists.txt or a terminal unescaped, and identifiers never collide with the
generated API or with what standard and intrinsics headers define."""

import re
import shutil
import subprocess

import numpy as np
import onnx
import pytest
from cross_helpers import TOOLCHAINS, missing_tools, verify_on
from helpers import check_against_onnxruntime, nncg_onnx
from onnx import TensorProto, helper, numpy_helper
from test_x86_targets import TARGETS

import nncg
from nncg.ir.c_names import (
    MAX_LENGTH,
    Namespace,
    buffer_name,
    c_identifier,
    is_reserved,
    layer_name,
    program_name,
)
from nncg.safe_text import c_comment, comment_name, escaped, shown, terminal_line
from nncg.tools import run_tool

HOSTILE = [
    "x*/ int EVIL = 1; /*",
    'y\n#include "/etc/passwd"\n',
    "%s%n%x",
    "back\\slash\\",
    "trojan\u202egnp.exe\u2066",
    "esc\x1b[31mred\rcr\x00nul",
    "tri??/graph??=",
    "\u200bzero\ufeffwidth\u2028line",
    "n" * 5000,
    "",
]
# Names that collide with the generated API (for --name m), math.h, stdio.h, the intrinsics headers,
# C and C++ keywords, the portability macros.
COLLIDING = [
    "arena", "weights", "HUGE_VAL", "M_H", "M_ARENA_BYTES", "m_run", "m", "M", "EOF", "errno", "stdin",
    "exp", "free", "index", "class", "int", "float32x4_t", "vaddq_f32", "NNCG_ALIGNED", "nncg_now", "start",
    "_m128", "__m128", "INFINITY", "M_PI", "NULL", "size_t", "x_SIZE", "M_X_SIZE", "min", "max",
]  # fmt: skip
SAFE_ASCII = re.compile(r"[\x20-\x7e]*")


def is_identifier(ident: str) -> bool:
    return re.fullmatch(r"[A-Za-z][A-Za-z0-9_]*", ident) is not None


# ---------------------------------------------------------------------------- the text helpers


@pytest.mark.parametrize("text", HOSTILE + COLLIDING)
def test_comment_text_cannot_end_the_comment_or_the_line(text):
    safe = c_comment(text)
    assert SAFE_ASCII.fullmatch(safe)
    assert "*/" not in safe and "/*" not in safe and "??" not in safe
    quoted = comment_name(text)
    assert len(quoted) <= 82 and "*/" not in quoted and "??" not in quoted and SAFE_ASCII.fullmatch(quoted)


def test_escaping_keeps_distinct_texts_distinct():
    texts = ["a\nb", "a\\nb", "a\\\nb", "a\x1bb", "a\\x1bb", "\u202e", "\\u202e"]
    assert len({escaped(t) for t in texts}) == len(texts)


@pytest.mark.parametrize("text", HOSTILE)
def test_terminal_lines_have_no_control_or_bidi_characters(text):
    line = terminal_line(f"error: '{text}'")
    assert "\n" not in line and "\r" not in line and "\x1b" not in line
    assert not re.search("[\u202a-\u202e\u2066-\u2069\u200b\u2028\ufeff\x00]", line)
    assert len(shown(text)) <= 82


def test_error_messages_are_one_printable_line():
    error = nncg.NncgError("node 'a\nb\x1b[2J\u202e' is bad")
    assert str(error) == "node 'a\\nb\\x1b[2J\\u202e' is bad"


# ---------------------------------------------------------------------------- identifiers


@pytest.mark.parametrize("name", HOSTILE + COLLIDING + ["3d", "/layer1/layer1.0/conv1/Conv", "model/act/Relu;bn"])
def test_identifiers_are_valid_unreserved_short_and_stable(name):
    ident = c_identifier(name)
    assert is_identifier(ident) and not is_reserved(ident) and len(ident) <= MAX_LENGTH
    assert c_identifier(ident) == ident
    assert program_name(program_name(name)) == program_name(name)
    assert layer_name(layer_name(name)) == layer_name(name)


@pytest.mark.parametrize(
    "name", ["HUGE_VAL", "EOF", "errno", "exp", "free", "class", "float32x4_t", "vaddq_f32", "M_PI", "_x", "E2BIG"]
)
def test_header_names_are_reserved(name):
    assert is_reserved(name)


def test_program_names_keep_the_api_clear_of_header_macros():
    assert program_name("robot") == "robot" and program_name("m") == "m"
    for name in ("HUGE_VAL", "NNCG_ALIGNED", "SIG", "arena", "int"):
        renamed = program_name(name)
        assert renamed != name and is_identifier(renamed)


def test_buffers_never_take_an_api_name():
    for name in ("m", "M", "m_run", "M_H", "M_ARENA_BYTES", "m_conv1", "arena", "weights", "nncg_now"):
        ident = buffer_name(name, "m")
        assert not ident.lower().startswith("m_") and ident.lower() != "m" and not ident.lower().startswith("nncg")
    assert buffer_name("t_x", "t") != "t_x" and not buffer_name("t_x", "t").startswith("t_")


def test_long_names_are_capped_with_a_hash_so_they_stay_distinct():
    a, b = c_identifier("n" * 100 + "a"), c_identifier("n" * 100 + "b")
    assert a != b and len(a) <= MAX_LENGTH and len(b) <= MAX_LENGTH


def test_layers_never_take_an_api_suffix():
    for name in ("run", "RUN", "arena", "weights_ok", "h", "x_size", "profile_count"):
        assert layer_name(name).lower() not in ("run", "arena", "weights_ok", "h", "profile_count")
        assert not layer_name(name).lower().endswith("_size")


def test_namespace_is_case_insensitive():
    names = Namespace()
    assert [names.claim(n) for n in ("a", "A", "a_1", "a")] == ["a", "A_1", "a_1_1", "a_2"]


# ---------------------------------------------------------------------------- whole models


def hostile_model(names: list[str]) -> onnx.ModelProto:
    """Input -> Conv -> Sigmoid (a kernel calling exp) -> Add of a second input -> two outputs, every
    tensor and node named from `names` (cycled)."""
    it = iter(names * 3)
    x, w, c, s, z, y, y2 = (next(it) for _ in range(7))
    rng = np.random.default_rng(0)
    inits = [numpy_helper.from_array(rng.standard_normal((5, 3, 3, 3)).astype(np.float32), w)]
    nodes = [
        helper.make_node("Conv", [x, w], [c], name=next(it), pads=[1, 1, 1, 1]),
        helper.make_node("Sigmoid", [c], [s], name=next(it)),
        helper.make_node("Add", [s, z], [y], name=next(it)),
        helper.make_node("Relu", [c], [y2], name=next(it)),
    ]
    graph = helper.make_graph(
        nodes,
        next(it),
        [helper.make_tensor_value_info(x, TensorProto.FLOAT, [1, 3, 6, 7]),
         helper.make_tensor_value_info(z, TensorProto.FLOAT, [1, 5, 6, 7])],
        [helper.make_tensor_value_info(y, TensorProto.FLOAT, [1, 5, 6, 7]),
         helper.make_tensor_value_info(y2, TensorProto.FLOAT, [1, 5, 6, 7])],
        inits,
    )  # fmt: skip
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 13)])
    onnx.checker.check_model(model)
    return model


NAME_SETS = {
    "hostile": [n + str(i) for i, n in enumerate(HOSTILE)],
    "colliding": COLLIDING,
}
DIRECTIVE = re.compile(r"#(if|ifdef|ifndef|elif|else|endif|define \w+|include [<\"][\w.]+[>\"])")


def assert_safe_files(compiled) -> None:
    """Printable ASCII only; outside comments, nothing a name could have injected."""
    for text in (compiled.source, compiled.header):
        assert SAFE_ASCII.fullmatch(text.replace("\n", "")), "generated text is not printable ASCII"
        code = re.sub(r"/\*.*?\*/", "", text, flags=re.S)
        assert "/*" not in code and "*/" not in code
        assert "EVIL = 1" not in code and "passwd" not in code
        directives = [line.strip() for line in code.splitlines() if line.lstrip().startswith("#")]
        assert all(DIRECTIVE.match(d) for d in directives), directives


@pytest.mark.parametrize("names", NAME_SETS, ids=str)
@pytest.mark.parametrize("target", ["ansi-c", "ssse3", *TARGETS])
@pytest.mark.parametrize("name", ["m", "HUGE_VAL", "NNCG_ALIGNED", "M"])
def test_hostile_and_colliding_names_build_strictly_and_match_onnxruntime(names, target, name):
    model = hostile_model(NAME_SETS[names])
    compiled = nncg.compile(model, target=target, name=name)
    assert_safe_files(compiled)
    assert is_identifier(compiled.name)
    check_against_onnxruntime(model, compiled, sanitize=target == "ansi-c" and name == "m")


@pytest.mark.parametrize("names", NAME_SETS, ids=str)
def test_hostile_names_in_weights_file_and_profile_builds(names, tmp_path):
    model = hostile_model(NAME_SETS[names])
    compiled = nncg.compile(model, target="ssse3", name="m", weights="bin", unroll="none")
    assert compiled.weights is not None
    check_against_onnxruntime(model, compiled)
    profiled = nncg.compile(model, target="ansi-c", name="m", profile=True)
    layers = re.search(r"m_profile_layers\[\d+\] = \{(.*)\};", profiled.source).group(1)
    assert all(is_identifier(layer) for layer in re.findall(r'"([^"]*)"', layers))
    profiled.write(tmp_path)
    strict = ["-std=c99", "-Wall", "-Wextra", "-Werror"]
    run_tool(["cc", "-c", *strict, tmp_path / "m.c", "-o", tmp_path / "m.o"], "compiling the profile build")


@pytest.mark.parametrize("names", NAME_SETS, ids=str)
def test_header_builds_after_every_standard_header_in_c_and_cpp(names, tmp_path):
    compiled = nncg.compile(hostile_model(NAME_SETS[names]), target="ssse3", name="m")
    compiled.write(tmp_path)
    includes = "assert ctype errno float limits locale math setjmp signal stdarg stddef stdio stdlib string time"
    program = (
        "".join(f"#include <{h}.h>\n" for h in includes.split()) + '#include "m.h"\nint main(void) { return 0; }\n'
    )
    (tmp_path / "main.c").write_text(program)
    flags = ["-Wall", "-Wextra", "-Werror", "-Wbidi-chars=any", "-fsyntax-only", f"-I{tmp_path}"]
    for cc, std in (("gcc", "-std=c89"), ("gcc", "-std=gnu11"), ("g++", "-std=c++17")):
        if shutil.which(cc) is None:
            continue
        lang = ["-x", "c++"] if cc == "g++" else []
        run_tool([cc, std, *flags, *lang, tmp_path / "main.c"], f"checking main.c with {cc} {std}")
    run_tool(["gcc", "-c", "-mssse3", *flags[:4], tmp_path / "m.c", "-o", tmp_path / "m.o"], "compiling m.c")


@pytest.mark.parametrize("toolchain", ["aarch64-neon", "armhf-neon"])
def test_colliding_names_on_neon(toolchain):
    """arm_neon.h's intrinsics and types (vaddq_f32, float32x4_t) are reserved on every target."""
    if missing_tools(TOOLCHAINS[toolchain]):
        pytest.skip(f"missing {', '.join(missing_tools(TOOLCHAINS[toolchain]))}")
    model = hostile_model(NAME_SETS["colliding"])
    report = verify_on(TOOLCHAINS[toolchain], model, nncg.compile(model, target="neon", name="m"))
    assert report.ok, report.format()


# ---------------------------------------------------------------------------- the command line


def test_input_shape_key_and_cmake_stay_inside_their_comments(tmp_path):
    key = "x*/ int EVIL; /*\n#include <stdio.h>\u202e"
    model = hostile_model([key, *NAME_SETS["colliding"]])
    model.graph.input[0].type.tensor_type.shape.dim[0].dim_param = "batch"
    path = tmp_path / "evil.onnx"
    onnx.save(model, path)
    out = tmp_path / "out"
    result = nncg_onnx(path, "-o", out, "--cmake", "--input-shape", f"{key}=1x3x6x7", "--name", "m\n)add_x(")
    assert result.returncode == 0, result.stderr
    first = (out / "m_add_x.c").read_text().splitlines()[0]
    assert first.endswith(" */") and first.count("*/") == 1 and SAFE_ASCII.fullmatch(first)
    assert "input-shape=x*\\/ int EVIL; /\\*\\n#include <stdio.h>\\u202e=1x3x6x7" in first
    cmake = (out / "CMakeLists.txt").read_text()
    assert SAFE_ASCII.fullmatch(cmake.replace("\n", ""))
    commands = ("#", " ", "cmake_", "project(", "add_", "target_", "if(", "endif", "set(")
    assert all(line == "" or line.startswith(commands) for line in cmake.splitlines())
    assert SAFE_ASCII.fullmatch(result.stdout.replace("\n", ""))
    if shutil.which("cmake"):
        configured = subprocess.run(["cmake", "-S", out, "-B", tmp_path / "cm"], capture_output=True, text=True)
        assert configured.returncode == 0, configured.stderr


@pytest.mark.parametrize("name", HOSTILE[:8])
def test_errors_quote_hostile_names_on_one_printable_line(tmp_path, name):
    graph = helper.make_graph(
        [helper.make_node("NotAnOp", ["x"], ["y"], name=name)],
        "g",
        [helper.make_tensor_value_info("x", TensorProto.FLOAT, [1, 2])],
        [helper.make_tensor_value_info("y", TensorProto.FLOAT, [1, 2])],
    )
    path = tmp_path / "bad.onnx"
    onnx.save(helper.make_model(graph, opset_imports=[helper.make_opsetid("", 13)]), path)
    result = nncg_onnx(path, "-o", tmp_path / "out")
    assert result.returncode == 2 and result.stdout == ""
    assert len(result.stderr.splitlines()) == 1 and result.stderr.endswith("\n")
    assert not re.search("[\x00-\x08\x0b-\x1f\x7f\u202a-\u202e\u2066-\u2069\u200b\u2028\ufeff]", result.stderr)
    assert not (tmp_path / "out").exists()


def test_ir_printout_and_verify_report_are_printable(tmp_path):
    path = tmp_path / "hostile.onnx"
    onnx.save(hostile_model(NAME_SETS["hostile"]), path)
    result = nncg_onnx(path, "-o", tmp_path / "out", "--verify", "--print-ir-after-all", "--name", "m")
    assert result.returncode == 0, result.stderr
    assert "PASS" in result.stdout and "// ----- IR after lower" in result.stderr
    for text in (result.stdout, result.stderr):
        assert not re.search("[\x00-\x08\x0b-\x1f\x7f\u202a-\u202e\u2066-\u2069\u200b\u2028\ufeff]", text)
    assert max(len(line) for line in result.stdout.splitlines()) < 400
