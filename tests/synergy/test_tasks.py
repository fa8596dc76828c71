"""Tests of synergy.tasks: task-map files and glob labelling."""
from __future__ import annotations

import fnmatch

import pytest
from hypothesis import given
from hypothesis import strategies as st

from synergy.errors import TaskMapError
from synergy.tasks import TaskMap, glob_match, label_for, load_task_map, task_map_from_rules


def write(tmp_path, text, name="tasks.yaml"):
    p = tmp_path / name
    p.write_text(text, encoding="utf-8")
    return p


def test_list_form_first_match_wins(tmp_path):
    tm = load_task_map(write(tmp_path, """
- glob: "grasp/*.c3d"
  task: grasp
- glob: "*.c3d"
  task: general
- glob: "**/sign/**/*.csv"
  task: sign
"""))
    assert isinstance(tm, TaskMap) and tm.tasks == ["grasp", "general", "sign"]
    assert label_for("/mocap/s01/grasp/cup.c3d", tm) == "grasp"
    assert label_for("grasp/cup.c3d", tm) == "grasp"
    assert label_for("/mocap/s01/fist.c3d", tm) == "general"
    assert label_for("/m/sign/a/b/abc.csv", tm) == "sign"
    assert label_for("/m/sign/abc.csv", tm) == "sign"
    assert label_for("/m/other/abc.csv", tm) is None
    assert label_for("/m/other/abc.csv", tm, default="misc") == "misc"


def test_mapping_form(tmp_path):
    tm = load_task_map(write(tmp_path, '"s?_grasp_*.csv": grasp\n"s[0-9]_twist*": twist\n'))
    assert [r.task for r in tm.rules] == ["grasp", "twist"]
    assert label_for("data/s1_grasp_01.csv", tm) == "grasp"
    assert label_for("s3_twist.csv", tm) == "twist"
    assert label_for("sx_twist.csv", tm) is None
    assert label_for("data/s12_grasp_01.csv", tm) is None


def test_glob_with_folder_matches_whole_components():
    assert glob_match("/a/grasp/x.c3d", "grasp/*.c3d")
    assert not glob_match("/a/pregrasp/x.c3d", "grasp/*.c3d")
    assert not glob_match("/a/grasp/b/x.c3d", "grasp/*.c3d")
    assert glob_match("/abs/x.c3d", "/abs/*.c3d")
    assert not glob_match("/q/abs/x.c3d", "/abs/*.c3d")


@given(
    # "." and ".." are path components, not file names
    st.text(alphabet="ab.c_1", min_size=1, max_size=8).filter(lambda n: n not in (".", "..")),
    st.lists(st.sampled_from(["a", "b", ".", "c", "_", "1", "*", "?"]), min_size=1, max_size=6),
)
def test_basename_globs_agree_with_fnmatch(name, pattern_chars):
    pattern = "".join(pattern_chars)
    assert glob_match(f"/some/dir/{name}", pattern) == fnmatch.fnmatchcase(name, pattern)


BAD = [
    ("syntax", "- glob: [unclosed\n", "not valid YAML"),
    ("alias", "*.c3d: grasp\n", "quote globs"),
    ("empty", "", "is empty"),
    ("scalar", "grasp\n", "expected a list"),
    ("task type", "- glob: '*.c3d'\n  task: 5\n", "[0].task"),
    ("missing task", "- glob: '*.c3d'\n", "'task' is a required property"),
    ("extra field", "- glob: a\n  task: b\n  weight: 2\n", "'weight' was unexpected"),
    ("bad label", "'*.c3d': 'two words'\n", "'*.c3d'"),
    ("empty glob", "'': grasp\n", "glob"),
    ("numeric key", "1: grasp\n", "glob must be a string"),
    ("empty list", "[]\n", "non-empty"),
]


@pytest.mark.parametrize("text, fragment", [b[1:] for b in BAD], ids=[b[0] for b in BAD])
def test_bad_task_map_names_file_and_field(tmp_path, text, fragment):
    p = write(tmp_path, text)
    with pytest.raises(TaskMapError) as info:
        load_task_map(p)
    msg = str(info.value)
    assert msg.startswith(f"{p}: ") and fragment in msg and "\n" not in msg


def test_missing_file(tmp_path):
    with pytest.raises(TaskMapError, match="cannot read"):
        load_task_map(tmp_path / "nope.yaml")


def test_rules_from_python_objects():
    tm = task_map_from_rules({"*.csv": "grasp"})
    assert tm.source is None and label_for("x.csv", tm) == "grasp"
    with pytest.raises(TaskMapError):
        task_map_from_rules([{"glob": "*.csv", "task": ""}])
