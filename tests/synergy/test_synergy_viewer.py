"""``synergy plot --rerun``: the hand swept from −2σ to +2σ along each PC, read back from the ``.rrd``:
every step of every PC is there, and each logged mesh is the hand at μ + s·σ along that PC."""
from __future__ import annotations

import numpy as np
import pytest
from typer.testing import CliRunner

pytest.importorskip("rerun")

from rerun.chunk import RrdReader  # noqa: E402

from handmodel import HandModel  # noqa: E402
from synergy.bundle import load_bundle  # noqa: E402
from synergy.cli import app  # noqa: E402
from synergy.viewer import read_sweep, sweep  # noqa: E402


def _meshes(path, pc):
    """Step → logged vertices of ``hands/pc<pc>/mesh``."""
    out = {}
    for ch in RrdReader(path).stream():
        if ch.entity_path.lstrip("/") == f"hands/pc{pc}/mesh" and not ch.is_static:
            rb = ch.to_record_batch()
            for step, v in zip(rb.column("sweep").to_pylist(), rb.column("Mesh3D:vertex_positions").to_pylist()):
                out[step] = np.asarray(v, float)
    return out


def test_plot_rerun_sweeps_each_pc(tmp_path):
    out = tmp_path / "syn.rrd"
    r = CliRunner().invoke(app, ["plot", "fingerfist", "--rerun", str(out), "--pcs", "2", "--steps", "5"],
                           env={"SYNERGY_PATH": ""})
    assert r.exit_code == 0, r.output
    assert not (tmp_path / "figs").exists()  # only the .rrd was asked for
    got = read_sweep(out)
    for pc in (1, 2):
        for part in ("mesh", "skeleton"):
            assert got[f"hands/pc{pc}/{part}"] == [0, 1, 2, 3, 4]
        assert got[f"sigma/pc{pc}"] == [0, 1, 2, 3, 4]
    assert "hands/pc3/mesh" not in got
    b = load_bundle("fingerfist")
    hand = HandModel.load()
    mesh = hand.mesh()
    for pc in (1, 2):
        logged = _meshes(out, pc)
        for step, s in enumerate(sweep(5)):
            th = np.zeros(hand.n_dofs)
            th[~hand.pose_mask] = b.model.posture(np.eye(pc)[pc - 1] * s)
            assert np.abs(logged[step] - mesh.pose(th)).max() < 1e-5
        # the sweep moves the hand: the fingertips of −2σ and +2σ are centimetres apart
        assert np.abs(logged[0] - logged[4]).max() > 0.02
    r = CliRunner().invoke(app, ["plot", "fingerfist", "--rerun", str(out)], env={"SYNERGY_PATH": ""})
    assert r.exit_code == 2 and "exists and is never overwritten" in r.stderr and r.stderr.count("\n") == 1
