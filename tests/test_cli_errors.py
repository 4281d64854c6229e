"""Malformed options and file-system failures: the command line prints one line and exits 2 leaving the
output folder as it was, the Python API raises NncgError; the files are written all or nothing."""

import errno
import io
import os
import shutil
import stat
import subprocess
import tempfile
from dataclasses import replace
from pathlib import Path

import pytest
from helpers import NNCG_CLI, nncg_onnx

import nncg
from nncg import cli, host_cpu
from nncg.errors import NncgError
from nncg.verify import build_model, random_inputs

ROOT = Path(__file__).resolve().parent.parent
BALL = ROOT / "examples" / "ball.onnx"
NAME_MAX = os.pathconf(tempfile.gettempdir(), "PC_NAME_MAX")  # bytes of a file name where tmp_path is


def snapshot(folder: Path) -> dict:
    """Every entry under `folder` (hidden ones too): a file's bytes, mode and mtime; a folder's mode."""
    entries = {}
    for path in sorted(folder.rglob("*")):
        info = path.lstat()
        if stat.S_ISDIR(info.st_mode):
            entries[str(path.relative_to(folder))] = ("dir", info.st_mode)
        else:
            entries[str(path.relative_to(folder))] = (path.read_bytes(), info.st_mode, info.st_mtime_ns)
    return entries


def assert_one_error_line(result, pattern: str = ""):
    assert result.returncode == 2, result.stdout + result.stderr
    assert "Traceback" not in result.stderr and result.stdout == ""
    lines = result.stderr.splitlines()
    assert len(lines) == 1 and lines[0].startswith("nncg-onnx: error: "), result.stderr
    assert pattern in lines[0], lines[0]


def old_files(folder: Path, *names: str) -> None:
    """Files from an earlier run (other bytes, an old mtime) that a failed run must leave alone."""
    folder.mkdir(parents=True, exist_ok=True)
    for name in names:
        (folder / name).write_text(f"old {name}\n")
        os.utime(folder / name, ns=(1_000_000_000, 1_000_000_000))


# --- options -------------------------------------------------------------------------------------

MALFORMED_OPTIONS = {
    "input-shape without =": (["--input-shape", "x"], "argument --input-shape: 'x' is not NAME=DIMx"),
    "input-shape without name": (["--input-shape", "1x3"], "'1x3' is not NAME=DIMx"),
    "input-shape empty name": (["--input-shape", "=1x3"], "'=1x3' is not NAME=DIMx"),
    "input-shape no dims": (["--input-shape", "x="], "'x=' is not NAME=DIMx"),
    "input-shape zero dim": (["--input-shape", "x=0x3x8x8"], "every dimension must be a whole number from 1"),
    "input-shape negative dim": (["--input-shape", "x=-1x3x8x8"], "every dimension must be a whole number from 1"),
    "input-shape empty dim": (["--input-shape", "x=1xx3"], "every dimension must be a whole number from 1"),
    "input-shape trailing x": (["--input-shape", "x=1x3x"], "every dimension must be a whole number from 1"),
    "input-shape beyond int64": (["--input-shape", f"x={2**63}x3"], "every dimension must be a whole number from 1"),
    "input-shape words": (["--input-shape", "x=onextwo"], "every dimension must be a whole number from 1"),
    "input-shape given twice": (
        ["--input-shape", "image=1x3x32x32", "--input-shape", "image=1x3x16x16"],
        "--input-shape gives input 'image' twice",
    ),
    "unknown target": (["--target", "sse9"], "argument --target: invalid choice: 'sse9'"),
    "code-budget not a number": (["--code-budget", "many"], "argument --code-budget: 'many' is not a whole number"),
    "code-budget negative": (["--code-budget", "-1"], "'-1' is not a whole number >= 0"),
    "code-budget fraction": (["--code-budget", "1.5"], "'1.5' is not a whole number >= 0"),
    "cpu not a number": (["--cpu", "first"], "argument --cpu: 'first' is not a whole number"),
    "tolerance not a number": (["--tolerance", "tight"], "argument --tolerance: invalid float value"),
    "bad weights choice": (["--weights", "rom"], "argument --weights: invalid choice: 'rom'"),
    "unknown option": (["--optimise"], "unrecognized arguments: --optimise"),
    "missing value": (["--name"], "argument --name: expected one argument"),
    "empty name": (["--name", ""], "argument --name: must not be empty"),
    "empty output folder": (["-o", ""], "argument -o/--output-dir: must not be empty"),
    "control characters": (["--target", "x\x1b[2J\u202e"], r"'x\x1b[2J\u202e'"),
}


@pytest.mark.parametrize("case", MALFORMED_OPTIONS)
def test_malformed_option_is_one_line_and_writes_nothing(tmp_path, case):
    options, message = MALFORMED_OPTIONS[case]
    old_files(tmp_path / "out", "ball.c")
    before = snapshot(tmp_path)
    # -o first: an option missing its value must be the last argument.
    result = nncg_onnx(BALL, "-o", tmp_path / "out", *options)
    assert_one_error_line(result, message)
    if case != "input-shape given twice":  # argparse's errors point to --help
        assert result.stderr.rstrip().endswith("(see nncg-onnx --help)")
    assert snapshot(tmp_path) == before


def unreadable_model(tmp_path: Path) -> Path:
    """A model file this process cannot read: root reads any file whatever its mode, but not
    /proc/self/mem at offset 0 (EIO)."""
    if os.geteuid() != 0:
        model = tmp_path / "secret.onnx"
        shutil.copy(BALL, model)
        model.chmod(0)
        return model
    if not os.path.isfile("/proc/self/mem"):
        pytest.skip("as root no file is unreadable by its mode, and there is no /proc/self/mem")
    return Path("/proc/self/mem")


def bad_model_paths(tmp_path: Path) -> dict:
    (tmp_path / "a_file").write_text("x")
    (tmp_path / "models.onnx").mkdir()
    return {
        "missing model": (tmp_path / "absent.onnx", "does not exist"),
        "model path a folder": (tmp_path / "models.onnx", "is not a file"),
        "model below a file": (tmp_path / "a_file" / "ball.onnx", "does not exist"),
        "unreadable model": (unreadable_model(tmp_path), "cannot read model file"),
    }


@pytest.mark.parametrize("case", ["missing model", "model path a folder", "model below a file", "unreadable model"])
def test_bad_model_path_is_one_line(tmp_path, case):
    model, message = bad_model_paths(tmp_path)[case]
    before = snapshot(tmp_path)
    assert_one_error_line(nncg_onnx(model, "-o", tmp_path / "out"), message)
    assert snapshot(tmp_path) == before


# --- the output folder ---------------------------------------------------------------------------


def output_folder_cases(tmp_path: Path) -> dict:
    """-o and --name that cannot work, each with what the message must say."""
    (tmp_path / "a_file").write_text("not a folder\n")
    old_files(tmp_path / "out", "ball.c")
    (tmp_path / "out" / "ball.h").mkdir()
    (tmp_path / "out" / "ball.h" / "keep.txt").write_text("mine\n")
    old_files(tmp_path / "proj", "CMakeLists.txt")
    stem = tmp_path / "long" / ("m" * (NAME_MAX - 5) + ".onnx")  # the longest model file name: NAME.weights is too long
    stem.parent.mkdir()
    shutil.copy(BALL, stem)
    return {
        "-o an existing file": ([BALL, "-o", tmp_path / "a_file"], "a_file' exists and is not a folder"),
        "-o below a file": ([BALL, "-o", tmp_path / "a_file" / "build"], "is not a folder, so the output folder"),
        "-o a device": ([BALL, "-o", "/dev/full"], "'/dev/full' exists and is not a folder"),
        "NAME.h a folder": ([BALL, "-o", tmp_path / "out"], "ball.h' is a folder: remove it or choose another"),
        "long --name": ([BALL, "--name", "n" * NAME_MAX, "-o", tmp_path / "new"], f"more than the {NAME_MAX} this"),
        "long model stem": (
            [stem, "--weights", "bin", "--unroll", "none", "-o", tmp_path / "new" / "deeper"],
            f".weights' is {NAME_MAX + 3} bytes, more than the {NAME_MAX} this file system allows: choose a shorter",
        ),
        "CMakeLists.txt not NNCG's": ([BALL, "--cmake", "-o", tmp_path / "proj"], "was not written by NNCG"),
    }


OUTPUT_CASES = [
    "-o an existing file",
    "-o below a file",
    "-o a device",
    "NAME.h a folder",
    "long --name",
    "long model stem",
    "CMakeLists.txt not NNCG's",
]


@pytest.mark.parametrize("case", OUTPUT_CASES)
def test_output_folder_problem_is_one_line_and_changes_nothing(tmp_path, case):
    args, message = output_folder_cases(tmp_path)[case]
    before = snapshot(tmp_path)
    assert_one_error_line(nncg_onnx(*args), message)
    assert snapshot(tmp_path) == before


def test_only_the_final_name_length_matters(tmp_path):
    """Temporaries have short names: a NAME.c of exactly the file system's limit is written."""
    name = "n" * (NAME_MAX - 2)
    result = nncg_onnx(BALL, "--name", name, "-o", tmp_path)
    assert result.returncode == 0, result.stderr
    assert sorted(p.name for p in tmp_path.iterdir()) == [f"{name}.c", f"{name}.h"]


def in_mount_namespace(setup: str, args: list, after: str = "") -> subprocess.CompletedProcess:
    """Runs the shell commands `setup` (mounts), nncg-onnx ARGS, then `after`, in a private mount
    namespace (the mounts vanish with it); skips where mounting is not allowed."""
    if not shutil.which("unshare") or subprocess.run(["unshare", "--mount", "true"], capture_output=True).returncode:
        pytest.skip("needs unshare --mount (root with CAP_SYS_ADMIN) to mount a read-only or full file system")
    script = f'{setup} || exit 99\n"$@"\nstatus=$?\n{after}\nexit $status'
    command = ["unshare", "--mount", "--propagation", "private", "sh", "-c", script, "sh"]
    result = subprocess.run([*command, *NNCG_CLI, *map(str, args)], capture_output=True, text=True, cwd=ROOT)
    if result.returncode == 99:
        pytest.skip(f"cannot mount here: {result.stderr.strip()}")
    return result


def test_read_only_file_system_is_one_line_and_changes_nothing(tmp_path):
    out = tmp_path / "out"
    old_files(out, "ball.c", "ball.h")
    before = snapshot(tmp_path)
    read_only = f"mount --bind '{out}' '{out}' && mount -o remount,bind,ro '{out}'"
    for target in (out, out / "sub"):
        result = in_mount_namespace(read_only, [BALL, "-o", target])
        assert_one_error_line(result, "Read-only file system (choose another -o)")
    assert snapshot(tmp_path) == before  # the folder that was under the mount


@pytest.mark.parametrize("folder", [".", "new/deeper"])
def test_full_file_system_is_one_line_and_changes_nothing(tmp_path, folder):
    """A 32 KiB tmpfs holding an earlier run's files, where ball.c (~60 KB) does not fit. The tmpfs
    vanishes with the namespace, so its files are copied out (cp -a keeps modes and mtimes)."""
    before, after, full = tmp_path / "before", tmp_path / "after", tmp_path / "full"
    old_files(before, "ball.c", "ball.h")
    full.mkdir()
    after.mkdir()
    setup = f"mount -t tmpfs -o size=32k tmpfs '{full}' && cp -a '{before}/.' '{full}/'"
    result = in_mount_namespace(setup, [BALL, "-o", full / folder], after=f"cp -a '{full}/.' '{after}/'")
    assert_one_error_line(result, "No space left on device (free some space or choose another -o)")
    assert snapshot(after) == snapshot(before)


@pytest.mark.parametrize("umask", [0o022, 0o077])
def test_files_get_the_usual_mode_under_the_umask(tmp_path, umask):
    old_files(tmp_path, "ball.c")
    (tmp_path / "ball.c").chmod(0o600)
    result = nncg_onnx(BALL, "--cmake", "--weights", "bin", "--unroll", "none", "-o", tmp_path, umask=umask)
    assert result.returncode == 0, result.stderr
    modes = {p.name: stat.S_IMODE(p.stat().st_mode) for p in tmp_path.iterdir()}
    assert modes == dict.fromkeys(["ball.c", "ball.h", "ball.weights", "CMakeLists.txt"], 0o666 & ~umask)


def test_wrote_line_shows_paths_escaped(tmp_path):
    out = tmp_path / "out\x1b[2J\u202e"
    result = nncg_onnx(BALL, "-o", out)
    assert result.returncode == 0, result.stderr
    (line,) = result.stdout.splitlines()
    assert line.startswith("wrote ") and "out\\x1b[2J\\u202e/ball.c (" in line and "\x1b" not in line
    assert sorted(p.name for p in out.iterdir()) == ["ball.c", "ball.h"]


# --- the command line's error paths, in process --------------------------------------------------


@pytest.mark.parametrize(
    "error, status, line",
    [
        (RuntimeError("boom\n\x1b[31mred"), 3, "nncg-onnx: internal error: RuntimeError: boom\\n\\x1b[31mred (a bug"),
        (PermissionError(errno.EACCES, "Permission denied", "tune.json"), 2, "nncg-onnx: error: [Errno 13]"),
    ],
)
def test_unexpected_errors_are_one_escaped_line(monkeypatch, capsys, error, status, line):
    def failing_run(args):
        raise error

    monkeypatch.setattr(cli, "run", failing_run)
    assert cli.main([str(BALL)]) == status
    (printed,) = capsys.readouterr().err.splitlines()
    assert printed.startswith(line) and "\x1b" not in printed


@pytest.mark.parametrize("option", ["--verify", "--benchmark", "--profile", "--tune"])
def test_running_code_this_cpu_lacks_the_isa_for_is_refused_before_writing(monkeypatch, capsys, tmp_path, option):
    """On a core without AVX-512, --target avx512 code would stop on an illegal instruction after the
    files were written: the run is refused first, naming the missing flag and the targets that run."""
    monkeypatch.setattr(host_cpu, "cpu_flags", lambda: frozenset({"sse2", "ssse3", "avx2", "fma"}))
    out = tmp_path / "out"
    assert cli.main([str(BALL), "--target", "avx512", option, "-o", str(out)]) == 2
    (printed,) = capsys.readouterr().err.splitlines()
    assert "this CPU lacks avx512f, which --target avx512 code needs" in printed
    assert printed.endswith("or a target this one runs: ansi-c, ssse3, avx2")
    assert not out.exists()


def test_the_api_refuses_to_run_code_this_cpu_lacks_the_isa_for(monkeypatch, tmp_path):
    monkeypatch.setattr(host_cpu, "cpu_flags", lambda: frozenset({"sse2", "ssse3"}))
    compiled = nncg.compile(str(BALL), target="avx2")
    built = build_model(compiled, tmp_path)  # building is fine: only running the code is refused
    with pytest.raises(NncgError, match="this CPU lacks avx2 and fma, which --target avx2 code needs"):
        built.run(random_inputs(compiled.inputs))


# --- the Python API ------------------------------------------------------------------------------

BAD_ARGUMENTS = {
    "model an int": (
        dict(model=5),
        "model must be a file path, bytes, an onnx.ModelProto, a torch.nn.Module or a keras.Model; got int 5",
    ),
    "model a list": (dict(model=["ball.onnx"]), "model must be"),
    "model path with NUL": (dict(model="ball\0.onnx"), "model must be a non-empty path without NUL"),
    "target a list": (dict(target=["ssse3"]), "target must be a non-empty str; got list"),
    "unknown target": (dict(target="sse9"), "unknown target 'sse9'"),
    "unroll negative": (dict(unroll=-1), "unroll must be"),
    "unroll a bool": (dict(unroll=True), "unroll must be"),
    "unroll a float": (dict(unroll=1.5), "unroll must be"),
    "name an int": (dict(name=123), "name must be a non-empty str or None; got int 123"),
    "name empty": (dict(name=""), "name must be a non-empty str or None"),
    "input_shapes a list": (dict(input_shapes=[("image", (1, 3, 32, 32))]), "input_shapes must be a dict"),
    "input_shapes a str shape": (dict(input_shapes={"image": "1x3x32x32"}), "input_shapes['image'] must be a tuple"),
    "input_shapes a zero dim": (
        dict(input_shapes={"image": (1, 0, 32, 32)}),
        "must be a tuple of ints from 1 to 2**63-1",
    ),
    "input_shapes a bool dim": (dict(input_shapes={"image": (True, 3)}), "must be a tuple of ints from 1 to 2**63-1"),
    "input_shapes beyond int64": (dict(input_shapes={"image": (2**63, 3)}), "ints from 1 to 2**63-1"),
    "input_shapes an int key": (dict(input_shapes={0: (1, 3)}), "keyed by input name (str); got int 0"),
    "pipeline an int": (dict(pipeline=5), "pipeline must be a non-empty str or None"),
    "print_ir_after_all an int": (dict(print_ir_after_all=5), "print_ir_after_all must be a writable text stream"),
    "print_ir_after_all binary": (dict(print_ir_after_all=io.BytesIO()), "must be a writable text stream"),
    "print_ir_after_all closed": (dict(print_ir_after_all=io.StringIO()), "must be an open, writable text stream"),
    "verify_ir a str": (dict(verify_ir="yes"), "verify_ir must be True or False; got str 'yes'"),
    "profile a str": (dict(profile="no"), "profile must be True or False"),
    "weights unknown": (dict(weights="rom"), "weights must be one of auto, embed, bin; got str 'rom'"),
    "weights an int": (dict(weights=5), "weights must be one of auto, embed, bin"),
    "code_budget a str": (dict(code_budget="many"), "code_budget must be an int >= 0 (0: no cap) or None"),
    "code_budget negative": (dict(code_budget=-3), "code_budget must be an int >= 0"),
    "code_budget a bool": (dict(code_budget=True), "code_budget must be an int >= 0"),
}


@pytest.mark.parametrize("case", BAD_ARGUMENTS)
def test_compile_rejects_bad_arguments_with_nncg_error(case):
    arguments, message = BAD_ARGUMENTS[case]
    arguments = {"model": BALL, **arguments}
    if case == "print_ir_after_all closed":
        arguments["print_ir_after_all"].close()
    with pytest.raises(NncgError) as raised:
        nncg.compile(**arguments)
    assert message in str(raised.value)


def test_compile_takes_every_documented_model_form():
    data = BALL.read_bytes()
    sources = {nncg.compile(model).source for model in (data, bytearray(data), memoryview(data))}
    assert len(sources) == 1


@pytest.mark.parametrize(
    "directory, cmake, message",
    [
        (5, False, "directory must be a path (str or os.PathLike); got int 5"),
        (None, False, "directory must be a path"),
        (b"build", False, "directory must be a path"),
        ("", False, "directory must be a non-empty path"),
        ("build", "yes", "cmake must be True or False"),
    ],
)
def test_write_rejects_bad_arguments_with_nncg_error(tmp_path, monkeypatch, directory, cmake, message):
    monkeypatch.chdir(tmp_path)
    compiled = nncg.compile(BALL)
    with pytest.raises(NncgError, match=message.replace("(", r"\(").replace(")", r"\)")):
        compiled.write(directory, cmake=cmake)
    assert list(tmp_path.iterdir()) == []


@pytest.fixture(scope="module")
def three_files():
    """A model written as NAME.c, NAME.h and NAME.weights."""
    return nncg.compile(BALL, unroll=None, weights="bin")


def fail_on_call(monkeypatch, name: str, call: int, error: OSError):
    """os.`name` raises `error` at its `call`-th call (counted from 1) and works otherwise."""
    original, calls = getattr(os, name), []

    def failing(*args, **kwargs):
        calls.append(args)
        if len(calls) == call:
            raise error
        return original(*args, **kwargs)

    monkeypatch.setattr(os, name, failing)


def refuse_links(*args, **kwargs):
    """os.link on a file system without hard links (FAT, some network file systems)."""
    raise OSError(errno.EPERM, "Operation not permitted")


@pytest.mark.parametrize("links", [True, False], ids=["hard links", "no hard links"])
@pytest.mark.parametrize("existing", [True, False], ids=["replacing files", "new folder"])
def test_a_failed_swap_puts_back_every_replaced_file(tmp_path, monkeypatch, three_files, links, existing):
    """The third rename fails after two files were replaced: both are put back (the same files: bytes,
    modes, mtimes), no temporary is left, and a folder created for the files is removed."""
    out = tmp_path / "build" if existing else tmp_path / "new" / "build"
    if existing:
        old_files(out, "ball.c", "ball.h", "ball.weights")
        (out / "ball.h").chmod(0o640)
    before = snapshot(tmp_path)
    if not links:
        monkeypatch.setattr(os, "link", refuse_links)
    renames = 3 if links or not existing else 5  # without links, two renames move the old files aside first
    fail_on_call(monkeypatch, "replace", renames, OSError(errno.EIO, "Input/output error"))
    with pytest.raises(NncgError, match=r"cannot replace '.*ball.weights': Input/output error \(check the output"):
        three_files.write(out)
    monkeypatch.undo()
    assert snapshot(tmp_path) == before


def test_a_full_disk_while_staging_leaves_nothing(tmp_path, monkeypatch, three_files):
    out = tmp_path / "build"
    old_files(out, "ball.c")
    before = snapshot(tmp_path)
    fail_on_call(monkeypatch, "write", 2, OSError(errno.ENOSPC, "No space left on device"))
    with pytest.raises(NncgError, match=r"cannot write '.*ball.h': No space left on device \(free some space"):
        three_files.write(out)
    monkeypatch.undo()
    assert snapshot(tmp_path) == before


def test_permission_denied_says_choose_a_writable_folder(tmp_path, monkeypatch, three_files):
    fail_on_call(monkeypatch, "open", 1, PermissionError(errno.EACCES, "Permission denied"))
    with pytest.raises(NncgError, match=r"cannot write '.*ball.c': Permission denied \(choose a writable -o\)"):
        three_files.write(tmp_path / "build")
    monkeypatch.undo()
    assert list(tmp_path.iterdir()) == []


def test_write_refuses_a_name_that_is_not_a_plain_file_name(tmp_path, three_files):
    with pytest.raises(NncgError, match=r"'\.\./ball\.c' is not a plain file name"):
        replace(three_files, name="../ball").write(tmp_path / "build")
    assert list(tmp_path.iterdir()) == []


def test_write_replaces_a_whole_earlier_set(tmp_path, three_files):
    old_files(tmp_path, "ball.c", "ball.h", "ball.weights", "notes.txt")
    paths = three_files.write(tmp_path)
    assert [p.name for p in paths] == ["ball.c", "ball.h", "ball.weights"]
    assert (tmp_path / "ball.c").read_text() == three_files.source
    assert (tmp_path / "ball.weights").read_bytes() == three_files.weights
    assert sorted(p.name for p in tmp_path.iterdir()) == ["ball.c", "ball.h", "ball.weights", "notes.txt"]
