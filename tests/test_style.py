"""The tree stays ruff-clean and ruff-formatted (the rules are in pyproject.toml)."""

import shutil
import subprocess
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
LINTED = ("nncg", "tests", "examples", "scripts", "benchmarks")
FORMATTED = LINTED


def ruff(*args: str) -> subprocess.CompletedProcess:
    executable = shutil.which("ruff")
    if executable is None:
        pytest.fail("ruff is not installed: pip install '.[test]'")
    return subprocess.run([executable, *args], cwd=ROOT, capture_output=True, text=True)


def test_ruff_check_is_clean():
    result = ruff("check", *LINTED)
    assert result.returncode == 0, result.stdout + result.stderr


def test_ruff_format_leaves_the_files_unchanged():
    result = ruff("format", "--check", *FORMATTED)
    assert result.returncode == 0, result.stdout + result.stderr
