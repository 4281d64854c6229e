"""--report: NAME.report.html is one well-formed, self-contained page (plots inline, nothing fetched) with
a row per layer, NAME.report.md has the same tables for CI logs; model names are escaped in both; the
files are byte-identical run to run and written all or nothing; a browser renders the page."""

import platform
import re
import shutil
import subprocess
import sys
import xml.etree.ElementTree as ET
from html.parser import HTMLParser
from pathlib import Path

import numpy as np
import pytest
from test_names import hostile_model

import nncg
from nncg.bench.benchmark import BenchResult, LayerTime
from nncg.bench.harness import ObjectSizes
from nncg.cli import main
from nncg.report import Measurements, ReportError, write_report
from nncg.safe_text import markdown_text
from nncg.verify import ErrorStat, VerifyReport

ROOT = Path(__file__).resolve().parent.parent
ROBOT = ROOT / "examples" / "robot.onnx"
HOSTILE_NAMES = [
    "<script>alert(1)</script>",
    "`tick` *em* _em_",
    '"><img src="http://evil.example/x.png">',
    "[link](http://evil.example)",
    "a|b</td><td>",
    "trojan\u202egnp",
    "&amp; &lt;",
    "# heading\nline",
    "~~strike~~ \\",
    "| pipe",
    "x*/ y",
    "{{ template }}",
]  # 12 distinct: one per tensor, node and graph name of hostile_model (inputs 0 and 4, outputs 5 and 6)


@pytest.fixture(scope="module")
def robot_report(tmp_path_factory):
    out = tmp_path_factory.mktemp("robot")
    compiled = nncg.compile(ROBOT, target="ssse3")
    write_report(compiled, out)
    return compiled, (out / "robot.report.html").read_text(), (out / "robot.report.md").read_text()


@pytest.fixture(scope="module")
def hostile_compiled(tmp_path_factory):
    path = tmp_path_factory.mktemp("model") / "hostile.onnx"
    path.write_bytes(hostile_model(HOSTILE_NAMES).SerializeToString())
    return path, nncg.compile(path, target="ansi-c")


def parse_xhtml(page: str) -> ET.Element:
    """The page as XML (it is written XHTML-style: every element closed, only XML's entities)."""
    assert page.startswith("<!DOCTYPE html>\n")
    return ET.fromstring(page.removeprefix("<!DOCTYPE html>\n"))


class TagBalance(HTMLParser):
    """Every start tag closed in order, as a browser's parser sees the page."""

    def __init__(self):
        super().__init__()
        self.open: list[str] = []
        self.tags: list[str] = []

    def handle_starttag(self, tag, attrs):
        self.open.append(tag)
        self.tags.append(tag)

    def handle_startendtag(self, tag, attrs):
        self.tags.append(tag)

    def handle_endtag(self, tag):
        assert self.open and self.open.pop() == tag, f"</{tag}> closes {self.open[-1:]}"


def assert_self_contained_and_balanced(page: str) -> ET.Element:
    balance = TagBalance()
    balance.feed(page)
    balance.close()
    assert balance.open == []
    assert "script" not in balance.tags and "link" not in balance.tags and "iframe" not in balance.tags
    for attribute in ("src", "href"):
        assert not re.search(rf"{attribute}\s*=\s*[\"']?\s*(https?:|//)", page, re.I)
    assert "url(" not in page and "@import" not in page
    return parse_xhtml(page)


def md_table_rows(markdown: str, header_start: str) -> list[list[str]]:
    """The cells of the Markdown table whose header starts with `header_start` (split at unescaped |)."""
    lines = markdown.splitlines()
    start = next(i for i, line in enumerate(lines) if line.startswith(header_start))
    rows = []
    for line in lines[start:]:
        if not line.startswith("|"):
            break
        rows.append([cell.strip() for cell in re.split(r"(?<!\\)\|", line)[1:-1]])
    return rows


def test_robot_page_is_well_formed_with_a_row_per_layer_and_an_inline_plot(robot_report):
    compiled, page, _ = robot_report
    root = assert_self_contained_and_balanced(page)
    images = [img.get("src") for img in root.iter("img")]
    assert images and all(src.startswith("data:image/png;base64,") for src in images)
    layers = [k.name for k in compiled.record.program.kernels]
    tables = [t for t in root.iter("table") if [th.text for th in t.iter("th")][:2] == ["#", "layer"]]
    (layer_table,) = tables
    rows = [[td.text for td in tr.iter("td")] for tr in layer_table.find("tbody")]
    assert [row[1] for row in rows] == layers
    assert [row[0] for row in rows] == [str(i) for i in range(len(layers))]
    conv1 = rows[layers.index("conv1")]
    assert conv1[2] == "Conv" and conv1[3] == "1x8x60x80" and conv1[5] == "1,036,800"
    assert "register block" in conv1[7] and "@ 0 (" in conv1[8]
    assert any("winograd" in row[7] for row in rows)


def test_robot_markdown_has_the_model_and_layer_tables(robot_report):
    compiled, _, markdown = robot_report
    rows = md_table_rows(markdown, "| # | layer |")
    assert len(rows) == 2 + len(compiled.record.program.kernels)
    assert all(len(row) == len(rows[0]) for row in rows)
    assert "| MACs per inference | 4,320,000 |" in markdown
    assert "Conv x5" in markdown


def test_robot_report_states_the_arena_and_object_sizes(robot_report):
    compiled, page, markdown = robot_report
    assert f"{compiled.arena_bytes:,} bytes" in page
    if shutil.which("cc") or shutil.which("gcc") or shutil.which("clang"):
        (sizes,) = md_table_rows(markdown, "| text | rodata |")[2:]
        assert int(sizes[0]) > 0 and int(sizes[3]) >= compiled.arena_bytes  # the arena is a static array


def test_hostile_names_are_escaped_in_html_and_markdown(hostile_compiled, tmp_path):
    _, compiled = hostile_compiled
    write_report(compiled, tmp_path)
    page = (tmp_path / "hostile.report.html").read_text()
    markdown = (tmp_path / "hostile.report.md").read_text()
    root = assert_self_contained_and_balanced(page)
    assert "<script>" not in page and "&lt;script&gt;alert(1)&lt;/script&gt;" in page
    assert "\u202e" not in page and "\\u202e" in page
    texts = {td.text for td in root.iter("td")}
    assert "<script>alert(1)</script>" in texts  # what a reader sees: the name as given
    assert "<script>" not in markdown and "\\<script\\>" in markdown
    assert "](http" not in markdown
    params = md_table_rows(markdown, "| role | ONNX name |")
    assert all(len(row) == 4 for row in params)
    in_out = [HOSTILE_NAMES[i] for i in (0, 4, 5, 6)]  # hostile_model's inputs x, z and outputs y, y2
    assert [row[1] for row in params[2:]] == [markdown_text(name) for name in in_out]


def test_report_is_byte_identical_run_to_run(hostile_compiled, tmp_path):
    path, _ = hostile_compiled
    for run in ("a", "b"):
        write_report(nncg.compile(path, target="ansi-c"), tmp_path / run)
    for name in ("hostile.report.html", "hostile.report.md"):
        assert (tmp_path / "a" / name).read_bytes() == (tmp_path / "b" / name).read_bytes()


def test_measurements_get_their_sections_and_plots(hostile_compiled, tmp_path):
    _, compiled = hostile_compiled
    stats = (ErrorStat(HOSTILE_NAMES[0], (1, 5, 6, 7), 1e-7, 2e-7),)
    verify = VerifyReport(compiled.name, "ansi-c", stats, 1e-4, 0)
    bench = BenchResult(
        compiled.name, "ansi-c", 10.0, 20.0, 30.0, 2.0, 1e-7, 2e-7, ObjectSizes(1, 2, 3, 4), compiled.macs,
        "sse", None, 0.1, 0.2,
    )  # fmt: skip
    layers = [LayerTime(k.name, 1.5 + i, 10.0, 0) for i, k in enumerate(compiled.record.program.kernels)]
    write_report(compiled, tmp_path, Measurements(verify, bench, layers))
    page = (tmp_path / "hostile.report.html").read_text()
    root = assert_self_contained_and_balanced(page)
    headings = [h.text for h in root.iter("h2")]
    assert headings[-3:] == ["Verify (against onnxruntime)", "Benchmark", "Profile"]
    assert len(list(root.iter("img"))) == 3
    assert "PASS: max rel err" in page and "2.00x" in page
    markdown = (tmp_path / "hostile.report.md").read_text()
    assert len(md_table_rows(markdown, "| layer | µs |")) == 2 + len(layers)


def test_without_a_c_compiler_the_report_says_so(hostile_compiled, tmp_path):
    _, compiled = hostile_compiled
    write_report(compiled, tmp_path, cc="no-such-cc-for-nncg")
    markdown = (tmp_path / "hostile.report.md").read_text()
    assert "not measured: C compiler" in markdown and "| text | rodata |" not in markdown


@pytest.mark.skipif(platform.machine() not in ("x86_64", "AMD64"), reason="needs a host without arm_neon.h")
def test_a_target_the_host_cannot_build_gets_no_sizes_but_a_report(hostile_compiled, tmp_path):
    path, _ = hostile_compiled
    write_report(nncg.compile(path, target="neon"), tmp_path)
    markdown = (tmp_path / "hostile.report.md").read_text()
    assert "not measured for target neon on this host: compiling hostile.c exited with status 1" in markdown


def test_report_files_are_written_all_or_nothing(hostile_compiled, tmp_path):
    _, compiled = hostile_compiled
    (tmp_path / "hostile.report.md").mkdir()
    with pytest.raises(nncg.NncgError, match="is a folder"):
        write_report(compiled, tmp_path, cc="no-such-cc-for-nncg")
    assert not (tmp_path / "hostile.report.html").exists()


def test_cli_report_writes_both_files_beside_the_c(hostile_compiled, tmp_path, capsys):
    path, _ = hostile_compiled
    assert main([str(path), "-o", str(tmp_path), "--report", "--verify"]) == 0
    names = sorted(p.name for p in tmp_path.iterdir())
    assert names == ["hostile.c", "hostile.h", "hostile.report.html", "hostile.report.md"]
    assert "hostile.report.html" in capsys.readouterr().out
    page = (tmp_path / "hostile.report.html").read_text()
    assert "Verify (against onnxruntime)" in page and "PASS: max rel err" in page


def test_cli_report_without_matplotlib_is_one_line_and_writes_nothing(hostile_compiled, tmp_path, monkeypatch, capsys):
    path, _ = hostile_compiled
    monkeypatch.setitem(sys.modules, "matplotlib", None)  # import matplotlib raises ImportError
    monkeypatch.delitem(sys.modules, "nncg.report_plot", raising=False)
    assert main([str(path), "-o", str(tmp_path / "out"), "--report"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "pip install matplotlib" in err
    assert not (tmp_path / "out").exists()
    with pytest.raises(ReportError):
        write_report(nncg.compile(path), tmp_path / "api")


CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")


@pytest.mark.skipif(CHROMIUM is None, reason="chromium is not installed (scripts/install-test-deps.sh)")
def test_chromium_renders_the_page(robot_report, tmp_path):
    import matplotlib.image

    _, page, _ = robot_report
    html = tmp_path / "robot.report.html"
    html.write_text(page)
    shot = tmp_path / "shot.png"
    command = [
        CHROMIUM, "--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
        "--disable-background-networking", "--disable-component-update", "--disable-sync",
        f"--user-data-dir={tmp_path / 'profile'}", f"--screenshot={shot}", "--window-size=1200,1600", html.as_uri(),
    ]  # fmt: skip
    subprocess.run(command, capture_output=True, timeout=180, check=True)
    pixels = matplotlib.image.imread(shot)
    assert pixels.shape[:2] == (1600, 1200)
    colours = np.unique(pixels.reshape(-1, pixels.shape[-1]), axis=0)
    assert len(colours) > 50 and pixels.std() > 0.05  # text, tables and the plot, not a blank page
