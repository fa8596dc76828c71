"""Before/after of two experiments reports (``tracker experiments``' report.md): every result cell of
every table the two share, better, worse or equal, and a Markdown table of the cells that changed.

A change to the tracker must not make the existing experiments worse (issue 12's acceptance); this
reads the two reports' own tables, so it compares what the reports say and needs no run of its own.
Rows are matched by their leading identifying cells (scenario, mode, scene × sensor × hand scale …);
timings (ms, fps, s/frame) and the tables' fixed columns (variance, projection, the paper's figures)
are left out: they are not the tracker's accuracy, and timings depend on the machine's load.

Run: .venv/bin/python tools/compare_reports.py OLD/report.md NEW/report.md [--all]
"""
from __future__ import annotations

import argparse
import math
import re
import sys
from dataclasses import dataclass
from pathlib import Path

#: a column from this one on holds results (the columns before it name the row)
RESULT = re.compile(r"error|°|mm\b|px|found|lost|%|≤|floors|mask|size|full|hierarchical|reduced|noise|"
                    r"mean|median", re.I)
#: result columns that are not the tracker's accuracy: timings, the paper's figures, fixed properties
SKIP = re.compile(r"\bms\b|ms/|fps|s/frame|net ran|paper|variance|projection|optimum|pixels used|^size$|overlay",
                  re.I)
NUMBER = re.compile(r"[-+]?\d+(?:\.\d+)?")


@dataclass(frozen=True)
class Change:
    section: str
    row: str
    column: str
    before: str
    after: str
    verdict: str  # "better", "worse" or "equal"


def tables(text: str) -> dict:
    """``{section: (header, rows)}``: the first table under each ``## `` heading of a Markdown report.

    >>> t = tables("## A\\n\\n| mode | error ° |\\n|---|---|\\n| full | 0.65 |\\n")
    >>> t["A"]
    (['mode', 'error °'], [['full', '0.65']])
    """
    out, section, header, rows = {}, None, None, None
    for line in text.splitlines() + [""]:
        if line.startswith("## "):
            section, header = line[3:].strip(), None
        elif line.startswith("|") and section is not None and section not in out:
            cells = [c.strip() for c in line.strip().strip("|").split("|")]
            if header is None:
                header, rows = cells, []
            elif not set(line) <= set("|-: "):
                rows.append(cells)
        elif header is not None and section not in out:
            out[section] = (header, rows)
    return out


def value(cell: str, column: str) -> float:
    """A cell as a number where higher is worse (NaN: nothing to compare): the first number of the cell
    (a hard case's "2.0 (94 %, 0 %)" is its mean error), yes/no as 0/1 worse, a share "≤ …" or found
    negated, a scale's ratio as its distance from 1.

    >>> value("2.0 (94 %, 0 %)", "full"), value("96 %", "≤ 1°"), value("no", "all floors")
    (2.0, -96.0, 1.0)
    >>> round(value("0.967", "scale found / true"), 3)
    0.033
    """
    c = cell.strip().lower()
    if c in ("yes", "no"):
        return 0.0 if c == "yes" else 1.0
    m = NUMBER.search(c)
    if m is None:
        return math.nan
    x = float(m.group())
    if "/ true" in column:
        return abs(x - 1.0)
    if "≤" in column or "found" in column or "in mask" in column or "within" in column:
        return -x
    return x


def _key_columns(header) -> int:
    for i, h in enumerate(header[1:], 1):
        if RESULT.search(h):
            return i
    return 1


def _renamed(column, header):
    """``column``'s name in ``header``: itself, else the longest name it begins with (a column whose name
    was shortened, "hierarchical, Kinect v1 noise" → "hierarchical, Kinect v1"), else None.

    >>> _renamed("hierarchical, Kinect v1 noise", ["full", "hierarchical", "hierarchical, Kinect v1"])
    'hierarchical, Kinect v1'
    """
    if column in header:
        return column
    return max((h for h in header if column.startswith(h + ",") or column.startswith(h + " ")), key=len,
               default=None)


def compare(old_text: str, new_text: str) -> list:
    """Every result cell of the tables both reports hold, old against new (:class:`Change` each).

    >>> old = "## H\\n\\n| scenario | frames | full |\\n|---|---|---|\\n| fast | 120 | 8.0 (56 %, 0 %) |\\n"
    >>> [c.verdict for c in compare(old, old.replace("8.0", "7.6"))]
    ['better']
    """
    old, new = tables(old_text), tables(new_text)
    out = []
    for section, (h_old, rows_old) in old.items():
        if section not in new:
            continue
        h_new, rows_new = new[section]
        k_old, k_new = _key_columns(h_old), _key_columns(h_new)
        by_key = {tuple(r[:k_new]): dict(zip(h_new, r)) for r in rows_new}
        for r in rows_old:
            other = by_key.get(tuple(r[:k_old]))
            if other is None:
                continue
            for col, before in zip(h_old[k_old:], r[k_old:]):
                after = other.get(_renamed(col, h_new))
                if after is None or SKIP.search(col):
                    continue
                a, b = value(before, col), value(after, col)
                if math.isnan(a) or math.isnan(b):
                    continue
                verdict = "equal" if before == after or a == b else ("better" if b < a else "worse")
                out.append(Change(section, " · ".join(r[:k_old]), col, before, after, verdict))
    return out


def markdown(changes, *, old_name="before", new_name="after", every=False) -> list:
    """Lines: a count per section, then a table of the cells that got worse (with ``every``: that changed)."""
    lines = ["| section | cells | better | worse | equal |", "|---|---|---|---|---|"]
    for section in dict.fromkeys(c.section for c in changes):
        sel = [c for c in changes if c.section == section]
        n = {v: sum(c.verdict == v for c in sel) for v in ("better", "worse", "equal")}
        lines.append(f"| {section} | {len(sel)} | {n['better']} | {n['worse']} | {n['equal']} |")
    shown = [c for c in changes if c.verdict != "equal" and (every or c.verdict == "worse")]
    if shown:
        lines += ["", f"| section | row | column | {old_name} | {new_name} | |", "|---|---|---|---|---|---|"]
        lines += [f"| {c.section} | {c.row} | {c.column} | {c.before} | {c.after} | {c.verdict} |" for c in shown]
    return lines


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("old", type=Path)
    ap.add_argument("new", type=Path)
    ap.add_argument("--all", action="store_true", help="list every changed cell, not only the worse ones")
    a = ap.parse_args(argv)
    texts = []
    for path in (a.old, a.new):
        try:
            texts.append(path.read_text(encoding="utf-8"))
        except OSError as exc:
            print(f"error: {path}: {exc.strerror or exc}", file=sys.stderr)
            return 2
        except UnicodeDecodeError:
            print(f"error: {path}: not a UTF-8 text file (a report.md is)", file=sys.stderr)
            return 2
    print("\n".join(markdown(compare(*texts), old_name=str(a.old), new_name=str(a.new), every=a.all)))
    return 0


if __name__ == "__main__":
    sys.exit(main())
