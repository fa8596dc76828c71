"""A hand of another size or other finger lengths than the model's, and its fit context derived from
the model-sized one.

A probe of :mod:`tracker.scale` needs the :class:`tracker.init.FitContext` of the hand at that size.
Building one samples the model's surface anew (~0.17 s); :func:`resized_context` derives it from the
model-sized context instead: every bone, radius and thickness of :meth:`handmodel.HandModel.scaled` is
multiplied by the same factor, so the surface samples in their nodes' frames are the same points times
the factor (:func:`resized_samples`), and limits, subspaces and finger shapes do not depend on the size.
A hand with its fingers lengthened (:func:`shaped_hand`, the bones of :func:`finger_bones`) gets its
context so too: :func:`shaped_context`, the samples stretched along the fingers (:func:`stretched_samples`).
"""
from __future__ import annotations

import copy
from dataclasses import replace

import numpy as np

from .correspond import Matcher
from .errors import TrackerError


def resized_samples(samples, hand, factor):
    """:class:`tracker.correspond.ModelSamples` of ``hand``, the hand the samples were taken on resized
    by ``factor``: the same points in their nodes' frames × ``factor`` (normals unchanged). The
    points keep their number, so they are ``factor`` × as far apart as freshly sampled ones would be;
    the costs they enter are means over the samples, which the spacing does not bias."""
    if samples is None:
        return None
    out = copy.copy(samples)
    out.hand = hand
    out.local = samples.local * float(factor)
    return out


def resized_context(ctx, hand, factor):
    """The :class:`tracker.init.FitContext` of ``hand``, ``ctx``'s hand resized by ``factor``
    (``ctx.hand.scaled(factor)``, or the model file's hand scaled to the same overall size): a new
    matcher, the surface samples resized (:func:`resized_samples`); limits, subspaces, synergies and
    finger shapes shared (none depends on the size)."""
    return replace(ctx, hand=hand, matcher=Matcher(hand, ctx.matcher.settings),
                   samples=resized_samples(ctx.samples, hand, factor),
                   score_samples=resized_samples(ctx.score_samples, hand, factor))


#: The fingers whose lengths :func:`tracker.scale.finger_scales` estimates, in :data:`tracker.sim.hands.FINGERS` order.
FINGERS = ("thumb", "index", "middle", "ring", "pinky")


def finger_bones(factors) -> dict:
    """Node name → bone factor (:meth:`handmodel.HandModel.scaled`'s ``bone_scales``) of finger length
    factors ``factors`` (finger name → factor; missing or 1: unchanged): the three bones of each
    finger's ray past its base joint (thumb: metacarpal and both phalanges), as
    :class:`tracker.sim.hands.HandShape` renders them.

    >>> finger_bones({"index": 1.1, "ring": 1.0})
    {'index2': 1.1, 'index3': 1.1, 'index_tip': 1.1}
    """
    out = {}
    for f, a in factors.items():
        if f not in FINGERS:
            raise TrackerError("finger scale", f"unknown finger {f!r} ({', '.join(FINGERS)})")
        if float(a) != 1.0:
            out.update({f"{f}2": float(a), f"{f}3": float(a), f"{f}_tip": float(a)})
    return out


def shaped_hand(base, scale, factors):
    """``base`` resized by the global ``scale`` and the finger length ``factors`` (:func:`finger_bones`)."""
    return base.scaled(float(scale), finger_bones(factors) or None)


def stretched_samples(samples, hand, bone_scales):
    """:class:`tracker.correspond.ModelSamples` of ``hand``, the hand the samples were taken on with
    the bones in ``bone_scales`` (node name → factor) lengthened: every capsule rides along its
    joint's +y towards its one child, so a sample at height y on a capsule of length L whose bone is
    × a moves to a·y on the capsule's side (0 ≤ y ≤ L) and by (a − 1)·L on its far cap; the base cap
    stays. Exact for a cylinder; on the model's tapered capsules (radii 0.6 mm apart over 3 cm) the
    side moves off the surface by a hundredth of a millimetre."""
    if samples is None:
        return None
    old = samples.hand
    local = samples.local.copy()
    for name, a in bone_scales.items():
        child = old.node_index(name)
        joint = int(old.parents[child])
        length = float(np.linalg.norm(old.rest[child, :3, 3]))
        on = samples.nodes == joint
        y = local[on, 1]
        local[on, 1] = np.where(y <= 0.0, y, np.where(y <= length, y * a, y + (a - 1.0) * length))
    out = copy.copy(samples)
    out.hand = hand
    out.local = local
    return out


def shaped_context(ctx, base, scale, factors):
    """The :class:`tracker.init.FitContext` of ``base`` resized by ``scale`` with finger length
    ``factors``, from ``ctx``, the context of ``base.scaled(scale)``: a new matcher, the surface
    samples stretched along the resized fingers (:func:`stretched_samples`); the rest shared."""
    bones = finger_bones(factors)
    if not bones:
        return ctx
    hand = shaped_hand(base, scale, factors)
    return replace(ctx, hand=hand, matcher=Matcher(hand, ctx.matcher.settings),
                   samples=stretched_samples(ctx.samples, hand, bones),
                   score_samples=stretched_samples(ctx.score_samples, hand, bones))
