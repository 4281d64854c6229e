"""Imports point one way: the IRs know nothing of the stages around them, the front end and the
lowering only of the IRs (so each declares its own op table; tests/test_op_tables.py joins them)."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

NNCG = Path(__file__).resolve().parent.parent / "nncg"

# {package: the nncg modules and packages it may import}
ALLOWED = {
    "ir": {"ir", "errors", "safe_text"},
    "lowering": {"lowering", "ir", "errors", "safe_text"},
    "frontend": {"frontend", "ir", "errors", "safe_text", "limits"},
}


def nncg_imports(path: Path) -> set[str]:
    """The top-level nncg modules or packages `path` imports (nncg.ir.graph -> "ir"), relative
    imports resolved."""
    package = path.relative_to(NNCG.parent).with_suffix("").parts[:-1]  # ("nncg", "ir")
    found = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.ImportFrom):
            base = list(package[: len(package) - node.level + 1]) if node.level else []
            names = [".".join([*base, node.module or ""]).strip(".")]
            if not node.module:  # from . import x
                names = [".".join([*base, alias.name]) for alias in node.names]
        elif isinstance(node, ast.Import):
            names = [alias.name for alias in node.names]
        else:
            continue
        found |= {name.split(".")[1] for name in names if name.startswith("nncg.")}
    return found


@pytest.mark.parametrize("package", sorted(ALLOWED))
def test_package_imports_only_downward(package: str) -> None:
    for path in sorted((NNCG / package).glob("*.py")):
        upward = nncg_imports(path) - ALLOWED[package]
        assert not upward, f"{path.relative_to(NNCG.parent)} imports nncg.{', nncg.'.join(sorted(upward))}"


def test_relative_imports_are_resolved() -> None:
    assert nncg_imports(NNCG / "lowering" / "__init__.py") >= {"ir", "errors", "lowering"}
    assert nncg_imports(NNCG / "bench" / "macs.py") == {"ir"}
