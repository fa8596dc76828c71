"""Task labels for recording files, assigned by glob rules from a task-map file.

A task map (YAML, ``data_schema/task-map.schema.json``) is a list of ``{glob, task}``
rules or a mapping ``glob: task``; the first matching rule wins. A glob without ``/``
matches the file name; a glob with ``/`` matches the trailing path components, and
``**`` spans any number of folders.

Examples
--------
>>> tm = task_map_from_rules([{"glob": "grasp/*.c3d", "task": "grasp"}, {"glob": "*.c3d", "task": "general"}])
>>> label_for("/data/s1/grasp/cup.c3d", tm), label_for("/data/s1/fist.c3d", tm)
('grasp', 'general')
>>> print(label_for("notes.txt", tm))
None
"""
from __future__ import annotations

import json
import os
import re
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path, PurePosixPath

import jsonschema

from handmodel.fileio import MAX_YAML_BYTES, parse_yaml, read_limited, schema_path
from synergy.errors import TaskMapError

__all__ = ["TaskRule", "TaskMap", "load_task_map", "task_map_from_rules", "label_for", "glob_match"]


@dataclass(frozen=True)
class TaskRule:
    glob: str
    task: str


@dataclass(frozen=True)
class TaskMap:
    """Ordered rules; ``source`` is the file they came from (or ``None``)."""

    rules: tuple[TaskRule, ...]
    source: str | None = None

    @property
    def tasks(self) -> list[str]:
        """Distinct task labels in rule order."""
        return list(dict.fromkeys(r.task for r in self.rules))


@lru_cache(maxsize=1)
def _validator():
    with open(schema_path("task-map"), encoding="utf-8") as fh:
        schema = json.load(fh)
    return jsonschema.Draft202012Validator(schema)


def _field(path, nested: bool = False) -> str:
    out = ""
    for p in path:
        out += f"[{p}]" if isinstance(p, int) else (f".{p}" if out or nested else str(p))
    return out if out or nested else "task map"


def task_map_from_rules(doc, source: str | os.PathLike | None = None) -> TaskMap:
    """Validate a parsed task map (list of rules or mapping) and build a :class:`TaskMap`."""
    where = None if source is None else str(source)
    if not isinstance(doc, (list, dict)):
        what = "empty" if doc is None else f"a {type(doc).__name__}"
        raise TaskMapError(where, f"is {what}; expected a list of {{glob, task}} rules or a mapping glob: task")
    if isinstance(doc, dict):
        bad = [k for k in doc if not isinstance(k, str)]
        if bad:
            raise TaskMapError(where, f"{bad[0]!r}: glob must be a string (quote it in YAML)")
    errors = sorted(_validator().iter_errors(doc), key=lambda e: (list(e.absolute_path), e.message))
    if errors:
        err = errors[0]
        if "propertyNames" in err.relative_schema_path:
            field = f"glob {err.instance!r}"
        elif isinstance(doc, dict) and err.absolute_path:
            field = repr(err.absolute_path[0]) + _field(list(err.absolute_path)[1:], nested=True)
        else:
            field = _field(err.absolute_path)
        raise TaskMapError(where, f"{field}: {err.message}")
    if isinstance(doc, dict):
        rules = tuple(TaskRule(g, t) for g, t in doc.items())
    else:
        rules = tuple(TaskRule(r["glob"], r["task"]) for r in doc)
    for r in rules:
        try:
            _compile(r.glob)
        except re.error as exc:
            raise TaskMapError(where, f"{r.glob}: bad glob ({exc})") from None
    return TaskMap(rules, where)


def load_task_map(path: str | os.PathLike) -> TaskMap:
    """Read and validate a task-map YAML file (bad file → :class:`TaskMapError`).

    Read through :func:`handmodel.fileio.parse_yaml`: UTF-8 only, size-limited, no aliases (an
    unquoted glob ``*.c3d`` is an alias in YAML, hence the hint in that message).
    """
    path = Path(path)
    data = read_limited(path, MAX_YAML_BYTES, _CannotRead)
    return task_map_from_rules(parse_yaml(data, path, TaskMapError), path)


class _CannotRead(TaskMapError):
    def __init__(self, where, reason):
        super().__init__(where, reason if reason.startswith("cannot read") else f"cannot read ({reason})")


@lru_cache(maxsize=256)
def _compile(glob: str) -> re.Pattern:
    parts = glob.strip("/").split("/")
    rx = []
    for i, part in enumerate(parts):
        if part == "**":
            rx.append(".*" if i == len(parts) - 1 else "(?:[^/]+/)*")
            continue
        rx.append(_part_regex(part) + ("/" if i < len(parts) - 1 else ""))
    body = "".join(rx)
    anchor = "^/" if glob.startswith("/") else "(?:^|/)"
    return re.compile(anchor + body + "$")


def _part_regex(part: str) -> str:
    out, i = [], 0
    while i < len(part):
        c = part[i]
        if c == "*":
            out.append("[^/]*")
        elif c == "?":
            out.append("[^/]")
        elif c == "[":
            j = part.find("]", i + 2)
            if j < 0:
                out.append(re.escape(c))
            else:
                body = part[i + 1 : j]
                if body.startswith("!"):
                    body = "^" + body[1:]
                out.append(f"[{body}]")
                i = j
        else:
            out.append(re.escape(c))
        i += 1
    return "".join(out)


def glob_match(path: str | os.PathLike, glob: str) -> bool:
    """Whether ``path`` matches ``glob`` (see the module docstring for the rules)."""
    p = PurePosixPath(Path(path).as_posix()).as_posix()
    return _compile(glob).search(p) is not None


def label_for(path: str | os.PathLike, task_map: TaskMap, default: str | None = None) -> str | None:
    """Task of ``path``: the first matching rule's task, else ``default``."""
    for rule in task_map.rules:
        if glob_match(path, rule.glob):
            return rule.task
    return default
