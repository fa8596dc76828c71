"""The README's Python example runs as written, on the recording `make demo` makes (here: a short
synthetic one at the same path), and prints the true hand's index fingertip."""
import contextlib
import io
import os
import re
from pathlib import Path

import numpy as np

from handmodel.model import HandModel
from tracker import TRACKING_HAND
from tracker.sim.synthesize import synthesize

README = Path(__file__).resolve().parents[1] / "README.md"


def readme_example() -> str:
    text = README.read_text(encoding="utf-8")
    section = text.split("\n## Python\n", 1)[1].split("\n## ", 1)[0]
    blocks = re.findall(r"```python\n(.*?)```", section, re.S)
    assert len(blocks) == 1, "the README's Python section holds one example"
    return blocks[0]


def test_readme_example_runs_and_prints_the_true_index_tip(tmp_path):
    code = readme_example()
    assert len(code.strip().splitlines()) <= 15
    hand = HandModel.load(TRACKING_HAND)
    rec = tmp_path / "out" / "demo" / "recording"
    synthesize("grasp-back", "kinect1", "none", rec, frames=4, hand=hand)
    truth = np.loadtxt(rec / "truth.csv", delimiter=",", skiprows=1, usecols=range(2, 28), ndmin=2)
    out = io.StringIO()
    cwd = os.getcwd()
    try:
        os.chdir(tmp_path)
        with contextlib.redirect_stdout(out):
            exec(compile(code, "README.md", "exec"), {"__name__": "readme_example"})
    finally:
        os.chdir(cwd)
    lines = out.getvalue().strip().splitlines()
    assert len(lines) == 4, lines  # every frame found
    for line in lines:
        index = int(line.split()[0])
        tip = np.array([float(v) for v in line.split("[", 1)[1].rstrip("]").split()])
        true_tip = hand.keypoints(truth[index])[8]
        assert np.linalg.norm(tip - true_tip) < 0.02, (line, true_tip)
