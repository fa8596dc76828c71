"""tools/compare_reports.py: the before/after of two experiments reports, on the committed report."""
import doctest
import importlib.util
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
REPORT = ROOT / "docs" / "experiments" / "report.md"


def _tool():
    spec = importlib.util.spec_from_file_location("compare_reports", ROOT / "tools" / "compare_reports.py")
    mod = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = mod  # dataclasses look their module up by name
    spec.loader.exec_module(mod)
    return mod


@pytest.fixture(scope="module")
def tool():
    return _tool()


def test_its_examples(tool):
    assert doctest.testmod(tool).failed == 0


def test_the_report_against_itself_is_equal_everywhere(tool):
    text = REPORT.read_text(encoding="utf-8")
    ch = tool.compare(text, text)
    sections = {c.section for c in ch}
    # every table of results is read: the paper's six, the hard cases, both realistic tables, the real frames
    assert len(sections) == 10, sections
    assert len(ch) > 500
    assert {c.verdict for c in ch} == {"equal"}
    # the timings and the fixed columns are not compared
    assert not any(k in c.column for c in ch for k in ("ms", "fps", "variance", "projection", "overlay"))


def _edit(text, row_start, old, new):
    lines = text.splitlines()
    i = next(i for i, ln in enumerate(lines) if ln.startswith(row_start))
    assert old in lines[i]
    lines[i] = lines[i].replace(old, new, 1)
    return "\n".join(lines)


def test_one_cell_made_worse_is_the_one_worse_change(tool):
    text = REPORT.read_text(encoding="utf-8")
    row = next(ln for ln in text.splitlines() if ln.startswith("| fast |"))
    cell = row.split("|")[3].strip()  # the full-DoF column, "7.6 (53 %, 0 %)"
    worse = _edit(text, "| fast |", f"| {cell} |", "| 99.9 (0 %, 0 %) |")
    ch = [c for c in tool.compare(text, worse) if c.verdict != "equal"]
    assert [(c.row, c.column, c.before, c.verdict) for c in ch] == [("fast · 120", "full", cell, "worse")]
    # and the other way round it is better
    assert [c.verdict for c in tool.compare(worse, text) if c.verdict != "equal"] == ["better"]


def test_directions_shares_counts_and_sizes(tool):
    head = "## S\n\n| method | mean ° | ≤ 1° | first frame found | scale found / true | fps |\n|---|---|---|---|---|---|\n"
    old = head + "| flat | 0.53 | 96 % | yes | 0.982 | 100 |\n"
    new = head + "| flat | 0.60 | 100 % | no | 1.010 | 50 |\n"
    got = {c.column: c.verdict for c in tool.compare(old, new)}
    # a larger error is worse, a larger share within a bound is better, a miss is worse, a size nearer the
    # truth is better; fps is a timing, never compared
    assert got == {"mean °": "worse", "≤ 1°": "better", "first frame found": "worse",
                   "scale found / true": "better"}


def test_command_line(tmp_path):
    import re

    old = tmp_path / "old.md"
    text = REPORT.read_text(encoding="utf-8")
    now = re.search(r"\| 1 \+ 0 \| (\d+\.\d\d) \|", text).group(1)  # the committed report's Fig. 8 first row
    earlier = f"{float(now) - 0.5:.2f}"
    old.write_text(text.replace(f"| 1 + 0 | {now} |", f"| 1 + 0 | {earlier} |"), encoding="utf-8")
    r = subprocess.run([sys.executable, str(ROOT / "tools" / "compare_reports.py"), str(old), str(REPORT)],
                       capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    assert (f"| Fig. 8 — ICP iterations (stride 3, full DoF) | 1 + 0 | posture error ° | {earlier} | {now} | worse |"
            in r.stdout)
    r = subprocess.run([sys.executable, str(ROOT / "tools" / "compare_reports.py"), str(tmp_path / "nope.md"),
                        str(REPORT)], capture_output=True, text=True)
    assert r.returncode == 2 and r.stderr.count("\n") == 1 and "nope.md" in r.stderr
    png = tmp_path / "report.png"
    png.write_bytes(b"\x89PNG\r\n\x1a\n\xff\xfe")
    r = subprocess.run([sys.executable, str(ROOT / "tools" / "compare_reports.py"), str(REPORT), str(png)],
                       capture_output=True, text=True)
    assert r.returncode == 2 and r.stderr == f"error: {png}: not a UTF-8 text file (a report.md is)\n"
