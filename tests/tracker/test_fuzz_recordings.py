"""tools/fuzz_recordings.py: mutants of every recording format are read or refused cleanly, and the tool
itself tells a clean refusal from a bug (the full run: ≥ 10,000 mutants per format, docs/accuracy.md)."""
import importlib.util
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("rosbags", reason="the [recordings] extra (rosbags) is not installed")

TOOL = Path(__file__).resolve().parents[2] / "tools" / "fuzz_recordings.py"


def _tool():
    spec = importlib.util.spec_from_file_location("fuzz_recordings", TOOL)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


@pytest.mark.parametrize("fmt", ["bag", "db3", "mcap", "mkv", "png"])
def test_a_few_mutants_per_format_end_read_or_refused(fmt):
    fz = _tool()
    log = []
    if fmt == "mkv" and not (fz.DEFAULT_CORPUS / fz.REAL["mkv"]).is_file():
        pytest.skip(f"no mkv seed: {fz.DEFAULT_CORPUS / fz.REAL['mkv']} (../shared/data is absent)")
    c = fz.run(fmt, fz.DEFAULT_CORPUS, 40, 0, 1, 60.0, 1024.0, 1.0, None, log=log.append)
    assert c["other"] == c["crash"] == c["hang"] == c["memory"] == 0, log
    # the mutants are neither all harmless nor all refused
    assert c["read"] > 0 and c["error"] > 0, c


def test_mutants_are_reproducible(tmp_path):
    fz = _tool()
    (tmp_path / "s").mkdir()
    sources = fz.seeds("bag", tmp_path / "s", tmp_path / "no-corpus")
    a, b = tmp_path / "a", tmp_path / "b"
    a.mkdir(), b.mkdir()
    pa, _ = fz.make_mutant("bag", sources, 3, 17, a)
    pb, _ = fz.make_mutant("bag", sources, 3, 17, b)
    assert pa.read_bytes() == pb.read_bytes() != sources[0].read_bytes()


def test_the_mutators_change_what_they_are_given():
    fz = _tool()
    rng = np.random.default_rng(0)
    text = "fps: 30\nframes: 3\n"
    assert fz.mutate_yaml(text, rng) != text
    out = fz.mutate_bytes(bytes(range(256)) * 40, np.random.default_rng(1))
    assert isinstance(out, bytes) and out != bytes(range(256)) * 40


@pytest.mark.parametrize("i, field", [(2801, "width"), (7112, "encoding")])
def test_an_mcap_with_a_damaged_message_definition_says_so(tmp_path, i, field):
    """Found by the tool (seed 0): an MCAP whose embedded Image definition lost a field decoded into
    messages without it, and the reader stopped with an AttributeError."""
    from tracker.errors import RecordingError
    from tracker.io.recording import open_recording

    fz = _tool()
    (tmp_path / "s").mkdir()
    path, _ = fz.make_mutant("mcap", fz.seeds("mcap", tmp_path / "s", tmp_path / "no-corpus"), 0, i, tmp_path)
    with pytest.raises(RecordingError, match=f"damaged message definition of sensor_msgs/msg/Image .*no '{field}'"):
        list(open_recording(path))
