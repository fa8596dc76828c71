"""The synthetic renderer against an independent ray caster and point–triangle distances."""
from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest
from scipy import ndimage
from scipy.spatial import cKDTree

from tracker.errors import TrackerError
from tracker.observe import backproject
from tracker.sim.motions import make_motion
from tracker.sim.raycast import raycast
from tracker.sim.render import CLUTTER_LABELS, Clutter, DepthRenderer, render


def kinect_camera():
    """The kinect1 preset if tracker.io.cameras exists, else the same intrinsics by hand."""
    try:
        from tracker.io.cameras import preset

        return preset("kinect1")
    except ImportError:
        return SimpleNamespace(width=640, height=480, fx=580.0, fy=580.0, cx=319.5, cy=239.5, name="kinect1")


def back_project_points(depth, cam):
    """Camera-frame points of all valid pixels and their (v, u): the camera's own back-projection when it
    has one (tracker.io.cameras), else x = (u − cx)·z/fx, y = (v − cy)·z/fy (integer pixel centres)."""
    v, u = np.nonzero(np.isfinite(depth))
    if hasattr(cam, "backproject"):
        return np.asarray(backproject(depth, cam), float)[v, u], v, u
    z = depth[v, u].astype(float)
    return np.stack([(u - cam.cx) * z / cam.fx, (v - cam.cy) * z / cam.fy, z], 1), v, u


# ----------------------------------------------------------------------------- independent references
def closest_on_triangles(p, a, b, c):
    """Closest points on triangles (a, b, c) to points p, all (N, 3) (Ericson, Real-Time Collision Detection 5.1.5)."""
    dot = lambda x, y: np.einsum("ij,ij->i", x, y)  # noqa: E731
    ab, ac, ap = b - a, c - a, p - a
    d1, d2 = dot(ab, ap), dot(ac, ap)
    bp = p - b
    d3, d4 = dot(ab, bp), dot(ac, bp)
    cp = p - c
    d5, d6 = dot(ab, cp), dot(ac, cp)
    va, vb, vc = d3 * d6 - d5 * d4, d5 * d2 - d1 * d6, d1 * d4 - d3 * d2
    den = va + vb + vc
    den = np.where(den == 0, 1e-300, den)
    out = a + ab * (vb / den)[:, None] + ac * (vc / den)[:, None]  # inside the face
    with np.errstate(divide="ignore", invalid="ignore"):
        cases = [  # later entries win: the order reverses Ericson's early returns
            (va <= 0) & (d4 - d3 >= 0) & (d5 - d6 >= 0), b + (c - b) * ((d4 - d3) / ((d4 - d3) + (d5 - d6)))[:, None],
        ]
        cases += [(vb <= 0) & (d2 >= 0) & (d6 <= 0), a + ac * (d2 / (d2 - d6))[:, None]]
        cases += [(d6 >= 0) & (d5 <= d6), c]
        cases += [(vc <= 0) & (d1 >= 0) & (d3 <= 0), a + ab * (d1 / (d1 - d3))[:, None]]
        cases += [(d3 >= 0) & (d4 <= d3), b]
        cases += [(d1 <= 0) & (d2 <= 0), a]
    for i in range(0, len(cases), 2):
        out = np.where(cases[i][:, None], cases[i + 1], out)
    return out


def distance_to_mesh(points, V, F, faces_allowed=None):
    """Unsigned distance of each point to the nearest allowed triangle within 1 mm of it (inf beyond)."""
    if faces_allowed is None:
        faces_allowed = np.ones(len(F), bool)
    tris = np.flatnonzero(faces_allowed)
    T = V[F]
    cen = T[tris].mean(1)
    rad = np.linalg.norm(T[tris] - cen[:, None], axis=2).max(1)
    lists = cKDTree(points).query_ball_point(cen, rad + 1e-3)  # points near each triangle
    ti = np.repeat(tris, [len(x) for x in lists])
    pi = np.concatenate([np.asarray(x, int) for x in lists]) if len(ti) else np.zeros(0, int)
    dist = np.full(len(points), np.inf)
    cp = closest_on_triangles(points[pi], T[ti, 0], T[ti, 1], T[ti, 2])
    np.minimum.at(dist, pi, np.linalg.norm(points[pi] - cp, axis=1))
    return dist


def test_closest_on_triangles_reference():
    """The reference distance itself: against brute-force dense sampling of one triangle."""
    rng = np.random.default_rng(3)
    a, b, c = rng.normal(size=(3, 3))
    p = rng.normal(size=(200, 3)) * 2
    cp = closest_on_triangles(p, *(np.broadcast_to(x, p.shape) for x in (a, b, c)))
    s, t = np.meshgrid(np.linspace(0, 1, 301), np.linspace(0, 1, 301))
    m = s + t <= 1
    S = a + np.outer(s[m], b - a) + np.outer(t[m], c - a)
    brute = np.sqrt(((p[:, None] - S[None]) ** 2).sum(-1)).min(1)
    assert np.all(np.linalg.norm(p - cp, axis=1) <= brute + 1e-12)
    assert np.allclose(np.linalg.norm(p - cp, axis=1), brute, atol=5e-3)


# ----------------------------------------------------------------------------- scenes
@pytest.fixture(scope="module")
def cam():
    return kinect_camera()


@pytest.fixture(scope="module")
def mesh(hand):
    return hand.mesh()


@pytest.fixture(scope="module")
def scenes(hand):
    """Three frames: closing fist (palm), grasp from the back, a strongly rotated random posture."""
    a = make_motion("open-close", hand=hand, frames=20).theta[12]
    b = make_motion("grasp-back", hand=hand, frames=45).theta[40]
    c = make_motion("random", hand=hand, frames=40, seed=4).theta[33].copy()
    c[3:6] += (0.9, -0.6, 0.4)
    return [a, b, c]


@pytest.fixture(scope="module")
def rendered(hand, cam, scenes):
    r = DepthRenderer(hand, cam)
    return [r.render(th) for th in scenes]


@pytest.fixture(scope="module")
def cast(mesh, cam, scenes):
    return [raycast(mesh.pose(th), mesh.faces, cam) for th in scenes]


def test_renderer_lbs_equals_mesh_pose(hand, cam, mesh, scenes):
    r = DepthRenderer(hand, cam)
    for th in scenes:
        assert np.allclose(r.pose(th), mesh.pose(th), atol=1e-12)


def test_depth_matches_ray_casting(rendered, cast):
    for r, (zc, _) in zip(rendered, cast):
        both = np.isfinite(r.depth) & np.isfinite(zc)
        assert both.sum() > 1500
        err = np.abs(r.depth[both] - zc[both])
        assert err.max() < 0.5e-3, f"max depth difference {err.max() * 1e3:.3f} mm"
        assert np.median(err) < 1e-6  # float32 rounding, not a different surface


def test_silhouettes_match_ray_casting_up_to_one_pixel(rendered, cast):
    ring = np.ones((3, 3), bool)
    for r, (zc, _) in zip(rendered, cast):
        a, b = np.isfinite(r.depth), np.isfinite(zc)
        diff = a ^ b
        border = ndimage.binary_dilation(b, ring) & ~ndimage.binary_erosion(b, ring)
        assert not (diff & ~border).any(), "silhouette differs away from the one-pixel border"
        assert diff.sum() <= 0.01 * b.sum()


def test_back_projected_points_lie_on_the_posed_mesh(rendered, mesh, cam, scenes):
    for r, th in zip(rendered, scenes):
        P, _, _ = back_project_points(r.depth, cam)
        d = distance_to_mesh(P, mesh.pose(th), mesh.faces)
        assert d.max() < 0.5e-3, f"max distance {d.max() * 1e3:.3f} mm"


def test_labels_are_segments_of_the_visible_triangles(rendered, cast, mesh, cam, scenes):
    face_seg = mesh.segment[mesh.faces[:, 0]]
    for r, (zc, fc), th in zip(rendered, cast, scenes):
        assert set(np.unique(r.labels)) <= set(range(-1, 16))
        assert ((r.labels >= 0) == np.isfinite(r.depth)).all()
        P, v, u = back_project_points(r.depth, cam)
        lab = r.labels[v, u]
        V = mesh.pose(th)
        for s in np.unique(lab):
            sel = lab == s
            d = distance_to_mesh(P[sel], V, mesh.faces, face_seg == s)
            assert d.max() < 0.5e-3, f"segment {s}: {d.max() * 1e3:.3f} mm off its triangles"
        both = (r.labels >= 0) & (fc >= 0)
        assert np.mean(face_seg[fc[both]] == r.labels[both]) > 0.995


def test_one_segment_moves_its_label(hand, cam, scenes):
    """Labels follow the geometry: flexing the index finger moves its labelled pixels."""
    th = scenes[0].copy()
    th[6:] = 0.0
    a = render(hand, th, cam).labels
    th[hand.dof_index("index1_flex")] = -1.2
    b = render(hand, th, cam).labels
    idx = [i for i, s in enumerate(hand.segments) if hand.node_names[s.joint].startswith("index")]
    assert np.isin(a, idx).sum() != np.isin(b, idx).sum()
    assert (np.isin(a, idx) != np.isin(b, idx)).sum() > 50


def test_hand_behind_camera_renders_nothing(hand, cam, scenes):
    th = scenes[0].copy()
    th[2] = -0.8
    r = render(hand, th, cam)
    assert np.isnan(r.depth).all() and (r.labels == -1).all()


def test_color_and_incidence(hand, cam, scenes):
    r = render(hand, scenes[0], cam, color=True, incidence=True)
    assert r.color.shape == (cam.height, cam.width, 3) and r.color.dtype == np.uint8
    hand_px = np.isfinite(r.depth)
    skin = r.color[hand_px].astype(float)
    assert (skin[:, 0] > skin[:, 2]).mean() > 0.99  # skin is red-dominant, background is not
    assert not (r.color[~hand_px] == r.color[hand_px][0]).all(-1).any()
    c = r.cos_incidence[hand_px]
    assert np.all((c >= 0) & (c <= 1)) and np.median(c) > 0.5
    assert np.isnan(r.cos_incidence[~hand_px]).all()


def test_clutter_forearm_and_table(hand, cam, scenes):
    th = scenes[0]
    plain = render(hand, th, cam)
    r = render(hand, th, cam, clutter="forearm,table", color=True)
    assert np.isfinite(r.depth).all()  # the table fills the view at 45°
    hand_px = plain.labels >= 0
    forearm = (r.face >= DepthRenderer(hand, cam).n_faces)
    # the hand is unchanged where it is not behind the forearm (thicker than the palm at the wrist)
    kept = r.labels >= 0
    assert np.array_equal(r.hand_mask, kept)
    assert not (kept & ~hand_px).any()
    assert (forearm[hand_px & ~kept]).all() and (hand_px & ~kept).sum() < 0.1 * hand_px.sum()
    assert np.array_equal(r.depth[kept], plain.depth[kept])
    assert forearm.sum() > 500 and (r.labels[forearm] == CLUTTER_LABELS["forearm"]).all()
    assert (r.labels[r.face == -2] == CLUTTER_LABELS["table"]).all()
    assert (r.face == -2).sum() > 0.5 * r.face.size
    # the forearm continues below the wrist (fingers point up in the image)
    assert np.nonzero(forearm)[0].mean() > np.nonzero(hand_px)[0].mean()
    with pytest.raises(TrackerError):
        Clutter.parse("forearm,sofa")
    assert Clutter.parse("none") is None


def test_wall_plane_depth_is_exact(hand, cam, scenes):
    th = scenes[0].copy()
    th[2] = -1.0  # hand behind the camera: only the plane
    wall = Clutter(forearm=False, table=True, table_point=(0.0, 0.0, 1.2), table_normal=(0.0, 0.0, -1.0))
    r = render(hand, th, cam, clutter=wall)
    assert np.allclose(r.depth, 1.2, atol=1e-6)


def test_bad_input(hand, cam):
    with pytest.raises(Exception) as e:
        render(hand, np.zeros(7), cam)
    assert "26" in str(e.value) or "theta" in str(e.value)
    with pytest.raises(TrackerError):
        render(hand, np.zeros(26), SimpleNamespace(width=10))


# ----------------------------------------------------------------------------- synthesis → recording
def _recording_module():
    return pytest.importorskip("tracker.io.recording", reason="tracker.io.recording is not there yet")


def test_synthesize_round_trip(tmp_path, hand, cam):
    rec = _recording_module()
    from tracker.sim.synthesize import synthesize

    out = tmp_path / "rec"
    rep = synthesize("open-close", cam, "kinect1", out, fps=30, seed=3, frames=4, hand=hand)
    assert rep.frames == 4 and rep.hand_pixels > 1000 and 0.5 < rep.valid_fraction <= 1.0
    R = rec.Recording.open(out)
    frames = list(R)
    assert len(frames) == 4
    truth = make_motion("open-close", hand=hand, frames=4, fps=30).theta
    scale = float(R.camera.depth_scale)
    # the same seed gives the same noisy frames
    from tracker.sim.noise import NoiseModel

    r = DepthRenderer(hand, cam)
    for i, f in enumerate(frames):
        th = np.asarray(f.truth, float)
        assert np.allclose(th, truth[i], atol=1e-9)
        rr = r.render(truth[i], incidence=True)
        exp = NoiseModel.preset("kinect1").apply(rr.depth, cam, np.random.default_rng([3, i]), rr.cos_incidence)
        got = np.asarray(f.depth, float)
        assert np.array_equal(np.isfinite(got), np.isfinite(exp))
        ok = np.isfinite(exp)
        assert np.abs(got[ok] - exp[ok]).max() <= scale / 2 + 1e-6


def test_synthesize_noise_free_color(tmp_path, hand, cam):
    rec = _recording_module()
    from tracker.sim.synthesize import synthesize

    out = tmp_path / "rec2"
    synthesize("grasp-back", cam, "none", out, frames=2, hand=hand, color=True, clutter="forearm")
    R = rec.Recording.open(out)
    f = next(iter(R))
    assert f.color is not None and f.color.shape == (cam.height, cam.width, 3)
    exp = render(hand, make_motion("grasp-back", hand=hand, frames=2).theta[0], cam, clutter="forearm").depth
    got = np.asarray(f.depth, float)
    ok = np.isfinite(exp)
    assert np.array_equal(np.isfinite(got), ok)
    scale = float(R.camera.depth_scale)
    assert np.abs(got[ok] - exp[ok]).max() <= scale / 2 + 1e-6


def test_synthesize_bad_input(tmp_path, hand, cam):
    _recording_module()
    from tracker.sim.synthesize import synthesize

    with pytest.raises(TrackerError):
        synthesize("no-such-motion", cam, "kinect1", tmp_path / "x", hand=hand)
    with pytest.raises(TrackerError):
        synthesize("still", cam, "kinect9", tmp_path / "y", hand=hand, frames=1)


# ----------------------------------------------------------------------------- CLI
def _app():
    import typer

    from tracker.sim.cli import register

    app = typer.Typer(pretty_exceptions_enable=False)

    @app.callback()
    def main():
        pass

    register(app)
    return app


def test_cli_list_and_bad_input(tmp_path):
    from typer.testing import CliRunner

    from handmodel.errors import ToolkitError

    runner = CliRunner()
    r = runner.invoke(_app(), ["synth", "--list"])
    assert r.exit_code == 0 and "grasp-back" in r.output and "kinect1" in r.output
    r = runner.invoke(_app(), ["synth", "--motion", "still"])  # no -o
    assert isinstance(r.exception, ToolkitError) and "-o" in str(r.exception)
    r = runner.invoke(_app(), ["synth", "--motion", "nope", "-o", str(tmp_path / "r")])
    assert isinstance(r.exception, ToolkitError)
    r = runner.invoke(_app(), ["synth", "--noise", "kinect9", "-o", str(tmp_path / "r")])
    assert isinstance(r.exception, ToolkitError) and "kinect9" in str(r.exception)
    r = runner.invoke(_app(), ["synth", "--clutter", "sofa", "-o", str(tmp_path / "r")])
    assert isinstance(r.exception, ToolkitError)
    r = runner.invoke(_app(), ["synth", "--frames", "0", "-o", str(tmp_path / "r")])
    assert isinstance(r.exception, ToolkitError)
    assert not (tmp_path / "r").exists()


def test_cli_synth_writes_a_recording(tmp_path):
    rec = _recording_module()
    pytest.importorskip("tracker.io.cameras")
    from typer.testing import CliRunner

    out = tmp_path / "rec"
    r = CliRunner().invoke(_app(), ["synth", "--motion", "grasp-back", "--camera", "kinect1", "--noise", "kinect1",
                                    "--frames", "3", "--seed", "1", "-o", str(out)])
    assert r.exit_code == 0, r.output
    assert "hand pixels" in r.output
    R = rec.Recording.open(out)
    assert len(list(R)) == 3
