"""The docs that show pipeline output cannot drift: docs/architecture.md is what
scripts/architecture_doc.py generates now, and README.md's pipeline example runs."""

import importlib.util
import re
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent


def load_script():
    spec = importlib.util.spec_from_file_location("architecture_doc", ROOT / "scripts" / "architecture_doc.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # its dataclasses look their module up there
    spec.loader.exec_module(module)
    return module


def test_architecture_doc_is_current():
    problem = load_script().check()
    assert problem is None, problem


def test_architecture_doc_states_the_pipeline_its_listings_come_from():
    script = load_script()
    doc = script.OUTPUT.read_text()
    assert script.COMMAND in doc
    assert "{{" not in doc
    for name, model in script.MODELS.items():
        assert f"| `{name}` |" in doc and f"`{model.target}`" in doc


def readme_example() -> str:
    section = (ROOT / "README.md").read_text().split("## The pipeline, for researchers", 1)[1]
    (block,) = re.findall(r"```python\n(.*?)```", section.split("\n## ", 1)[0], flags=re.S)
    return block


def test_readme_pipeline_example_runs(tmp_path, monkeypatch, capsys):
    code = readme_example()
    assert code.count('"build/"') == 1
    code = code.replace('"build/"', repr(str(tmp_path / "build")))
    monkeypatch.chdir(ROOT)  # the example names examples/ball.onnx relative to the repository
    namespace = {"__name__": "readme_example"}
    exec(compile(code, "README.md", "exec"), namespace)
    assert (tmp_path / "build" / "ball.c").is_file() and (tmp_path / "build" / "ball.h").is_file()
    printed = capsys.readouterr().out
    assert "// ----- IR after inline-constants" in printed and "// ----- IR after plan-memory" in printed
    assert namespace["pm"].pipeline.endswith(",plan-memory")
    assert namespace["compiled"].target == "ssse3"
