"""The segmenter's reused full-frame buffers (:class:`tracker.segment.buffers.FrameBuffers`): one segmenter
observing frame after frame gives what a fresh one gives on each frame, and never writes into an
observation its caller still holds."""
import copy
import pickle

import numpy as np
import pytest
from hypothesis import given, settings, strategies as st

from conftest import realistic_frame
from tracker.observe import backproject, hand_window, observe
from tracker.segment import Segmenter
from tracker.segment.buffers import FrameBuffers

FIELDS = ("points", "normals", "mask", "depth", "density", "stride", "frame_depth", "silhouette", "window")


def _frames(hand):
    """Kinect v1 frames (float32 depth, as the renderer and sensors give them: the frame is converted into a
    buffer too) with the hand's predicted window: two poses of one scene, the second also shifted 120 px left
    and 40 px up, so that each frame's hand lies where the others' does not."""
    out = []
    for f, shift in ((4, (0, 0)), (22, (0, 0)), (22, (-40, -120))):
        cam, depth, colour, labels = realistic_frame(hand, "kinect1", 1.0, "forearm,torso", f)
        depth = np.roll(depth, shift, (0, 1)).astype(np.float32)
        colour, labels = np.roll(colour, shift, (0, 1)), np.roll(labels, shift, (0, 1))
        hand_px = (labels >= 0) & np.isfinite(depth)
        window = hand_window(backproject(depth, cam)[hand_px], cam, 0.08)
        out.append((cam, depth, colour, window))
    return out


@pytest.fixture(scope="module")
def frames(hand):
    return _frames(hand)


def _same(a, b):
    """Whether two observations are equal to the bit (NaN where NaN), field by field."""
    for f in FIELDS:
        x, y = getattr(a, f), getattr(b, f)
        if f == "window" or x is None or y is None:
            if x != y:
                return False
            continue
        x, y = np.asarray(x), np.asarray(y)
        if x.dtype != y.dtype or x.shape != y.shape or x.tobytes() != y.tobytes():
            return False
    return True


def _fresh(frame, whole, colour):
    cam, depth, col, window = frame
    return observe(depth, cam, color=col if colour else None, window=None if whole else window, segmenter=Segmenter())


def test_a_frame_observed_again_after_others_is_observed_as_the_first_time(frames):
    """Frame A, then B elsewhere in the image (windowed and whole), then A again with one segmenter, each
    observation dropped before the next (so the next reuses its buffers): A's second observation is its
    first, bit for bit, and each is a fresh segmenter's. A buffer not cleared whole would show B's hand
    (mask, silhouette, depth) where A has none."""
    seg = Segmenter()
    for colour in (True, False):
        cam, depth, col, window = frames[0]
        first = observe(depth, cam, color=col if colour else None, window=window, segmenter=seg)
        kept = copy.deepcopy(first)
        del first
        for k, whole in ((2, False), (2, True), (1, False)):
            cam, depth, col, window = frames[k]
            ob = observe(depth, cam, color=col if colour else None, window=None if whole else window, segmenter=seg)
            assert _same(ob, _fresh(frames[k], whole, colour))
            del ob
        cam, depth, col, window = frames[0]
        again = observe(depth, cam, color=col if colour else None, window=window, segmenter=seg)
        assert again.window is not None and (again.silhouette & ~again.mask).any()  # windowed, with a band
        assert _same(again, kept)
        del again


@given(st.lists(st.tuples(st.integers(0, 2), st.booleans(), st.booleans(), st.booleans()), min_size=2, max_size=6))
@settings(max_examples=12, deadline=None)
def test_held_observations_are_never_overwritten(frames, steps):
    """Any sequence of frames (windowed or whole, colour or not), some observations kept by the caller and
    some dropped: every observation is a fresh segmenter's, and those kept are unchanged at the end (a
    buffer is handed out again only when nothing refers to it)."""
    seg = Segmenter()
    held = []
    for k, whole, colour, keep in steps:
        ob = observe(frames[k][1], frames[k][0], color=frames[k][2] if colour else None,
                     window=None if whole else frames[k][3], segmenter=seg)
        ref = _fresh(frames[k], whole, colour)
        assert _same(ob, ref)
        if keep:
            held.append((ob, ref))
        del ob
    for ob, ref in held:
        assert _same(ob, ref)


def test_a_view_keeps_its_buffer():
    """A view of a buffer (its base) holds it as the array itself does; once dropped, the buffer is handed
    out again; a copied or unpickled owner starts without buffers."""
    bufs = FrameBuffers()
    a = bufs.zeros("m", (4, 5))
    a_at = a.__array_interface__["data"][0]
    view = a[1:3]
    del a
    b = bufs.zeros("m", (4, 5))
    assert not np.shares_memory(b, view)
    del b
    c = bufs.zeros("m", (4, 5))
    assert not np.shares_memory(c, view)  # b's buffer; never the view's
    del view, c
    again = bufs.zeros("m", (4, 5))
    assert again.__array_interface__["data"][0] == a_at  # free again: reused, not a new allocation
    for other in (copy.deepcopy(bufs), pickle.loads(pickle.dumps(bufs))):
        assert other._pool == {}
