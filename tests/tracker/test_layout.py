"""The package layout (issue 37 item 8): recording I/O under tracker/io with no import circle at module
level (a reader never imports the dispatcher that imports it), and command modules that share helpers
through tracker.cli_common rather than importing each other's private ones."""
import ast
from pathlib import Path

import tracker

SRC = Path(tracker.__file__).resolve().parent


def _imports(path: Path, package: str, top_level_only: bool) -> set[str]:
    """The tracker modules ``path`` imports (``from .x import`` resolved against ``package``)."""
    tree = ast.parse(path.read_text())
    nodes = tree.body if top_level_only else list(ast.walk(tree))
    out = set()
    for node in nodes:
        if isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")[:len(package.split(".")) - node.level + 1]
                mod = ".".join(base + ([node.module] if node.module else []))
            else:
                mod = node.module or ""
            if mod.startswith("tracker"):
                out.add(mod)
                out.update(f"{mod}.{a.name}" for a in node.names)
        elif isinstance(node, ast.Import):
            out.update(a.name for a in node.names if a.name.startswith("tracker"))
    return out


def _graph(files, top_level_only=True):
    names = {f"tracker.{'.'.join(f.relative_to(SRC).with_suffix('').parts)}": f for f in files}
    return {m: {d for d in _imports(f, m.rsplit(".", 1)[0], top_level_only) if d in names and d != m}
            for m, f in names.items()}


def _cycle(graph):
    state, stack = {}, []

    def visit(m):
        state[m] = 1
        stack.append(m)
        for d in sorted(graph[m]):
            if state.get(d) == 1:
                return stack[stack.index(d):] + [d]
            if d not in state and (c := visit(d)):
                return c
        state[m] = 2
        stack.pop()
        return None

    for m in sorted(graph):
        if m not in state and (c := visit(m)):
            return c
    return None


def test_recording_io_has_no_import_circle():
    g = _graph(sorted((SRC / "io").glob("*.py")))
    assert {"tracker.io.bags", "tracker.io.mkv", "tracker.io.files", "tracker.io.folder"} <= set(g)
    assert _cycle(g) is None, _cycle(g)
    # the readers import their base, never the dispatcher nor the public face
    for reader in ("tracker.io.bags", "tracker.io.mkv"):
        assert not g[reader] & {"tracker.io.files", "tracker.io.recording", "tracker.io.folder"}, g[reader]


def test_command_modules_take_no_private_helpers_from_each_other():
    cli = [SRC / "cli.py", SRC / "track_cli.py", SRC / "live_cli.py", SRC / "eval_cli.py", SRC / "sim" / "cli.py"]
    mods = {"tracker.cli", "tracker.track_cli", "tracker.live_cli", "tracker.eval_cli", "tracker.sim.cli"}
    for f in cli:
        package = "tracker.sim" if f.parent.name == "sim" else "tracker"
        deps = _imports(f, package, top_level_only=False)
        private = sorted(d for d in deps if d.rsplit(".", 1)[0] in mods and d.rsplit(".", 1)[1].startswith("_"))
        assert not private, (f.name, private)
    # the helpers they share are public names of one small module
    from tracker.cli_common import check_not_inputs, progress_bar, segmenter_from_options  # noqa: F401


def test_the_lazy_names_still_resolve():
    from tracker.io.cameras import Camera as C
    from tracker.io.recording import Recording as R, open_recording as o

    assert tracker.Camera is C and tracker.Recording is R and tracker.open_recording is o
    assert tracker.preset("kinect1").width == 640


def test_the_tracking_file_and_the_batch_each_have_one_home():
    from tracker import batch, run
    from tracker.io import tracking_file

    assert tracker.read_tracking is tracking_file.read_tracking and tracker.tracked_hand is tracking_file.tracked_hand
    assert tracker.write_keypoints is tracking_file.write_keypoints and tracker.run_job is run.run_job
    # the one-recording pipeline uses the format and is used by the batch; it offers neither again
    for name in ("read_tracking", "parse_tracking", "read_keypoints", "tracked_hand", "keypoints_table",
                 "summary_row", "batch_jobs", "track_many", "SUMMARY_COLUMNS"):
        assert not hasattr(run, name), name
    assert batch.track_many.__module__ == "tracker.batch"
