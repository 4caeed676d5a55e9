"""The crown's space (bforest_core/envelope.py) and the crown's offset from its stem (metrics.crown_offset),
on hand-built trees whose answers are known."""

from __future__ import annotations

import math

import numpy as np
import pytest

import bforest_core as bf
from bforest_core.envelope import BANDS, SECTORS, CrownEnvelope, stem_at
from bforest_core.metrics import (
    crown_base_height,
    crown_envelope,
    crown_offset,
    crown_spread,
    measure_tree,
    tree_summary,
)


def _tree(axes) -> bf.Tree:
    """Cylinders of 0.25 m along straight axes ``(parent axis, its cylinder, start, end, radius)``:
    the stem first (parent None), each axis starting at a point of its parent axis."""
    start, axis, length, radius, parent, first = [], [], [], [], [], []
    for par, at, a, b, r in axes:
        a, b = np.asarray(a, float), np.asarray(b, float)
        n = max(1, round(np.linalg.norm(b - a) / 0.25))
        first.append(len(start))
        for k in range(n):
            start.append(a + (b - a) * k / n)
            axis.append((b - a) / np.linalg.norm(b - a))
            length.append(np.linalg.norm(b - a) / n)
            radius.append(r)
            parent.append(len(start) - 2 if k else (-1 if par is None else first[par] + at))
    return bf.Tree(
        np.array(start), np.array(axis), np.array(length), np.array(radius), np.array(parent), topology="thickest"
    )


def one_sided_tree(lean: float = 0.0) -> bf.Tree:
    """A 10 m stem of 40 cylinders (4 m upright, then leaning ``lean`` m towards +x over its last
    6 m) and three level branches: 3 m towards +x at 4 m, 2 m towards +y at 6 m, 1 m towards -x at
    8 m, each from the stem at its height."""
    stem = [(None, 0, (0, 0, 0), (0, 0, 4), 0.1), (0, 15, (0, 0, 4), (lean, 0, 10), 0.08)]

    def on(z):  # the stem's cylinder and point at height z
        if z <= 4:
            return 0, int(z / 0.25) - 1, np.array([0.0, 0.0, z])
        return 1, int((z - 4) / 0.25) - 1, np.array([lean * (z - 4) / 6, 0.0, z])

    branches = []
    for z, d in ((4.0, (3, 0, 0)), (6.0, (0, 2, 0)), (8.0, (-1, 0, 0))):
        a, k, p = on(z)
        branches.append((a, k, p, p + d, 0.02))
    return _tree(stem + branches)


def test_the_envelope_of_a_hand_built_tree_has_its_known_extent():
    t = one_sided_tree()
    assert crown_base_height(t) == pytest.approx(4.0)  # the lowest branch's base
    e = crown_envelope(t, margin=0.5)
    assert (e.base, e.top, e.margin) == (pytest.approx(4.0), pytest.approx(10.0), 0.5)
    assert e.reach.shape == (BANDS, SECTORS) and np.allclose(e.stem, 0.0)
    band = lambda z: int((z - 4.0) / (6.0 / BANDS))  # noqa: E731
    sector = lambda deg: int((deg + 180.0) / (360.0 / SECTORS)) % SECTORS  # noqa: E731
    known = {(band(4.0), sector(0.0)): 3.0, (band(6.0), sector(90.0)): 2.0, (band(8.0), sector(180.0)): 1.0}
    for (b, s), r in np.ndenumerate(e.reach):
        assert r == pytest.approx(known.get((b, s), 0.0), abs=1e-9), (b, s)  # elsewhere only the stem
    # every point of the tree lies in its own envelope, in full light
    pts = np.concatenate([t.start, t.end])
    assert e.contains(pts).all() and (e.light(pts) == 1.0).all()
    # the light falls across the margin: beyond a branch's tip, beside the stem; no lid above the
    # top (the top band's reach holds: beside the stem, not 2 m out)
    probe = np.array(
        [[2.9, 0, 4.1], [3.25, 0, 4.1], [3.6, 0, 4.1], [0, 0.3, 4.1], [0.1, 0.6, 4.1], [0, 0, 10.25], [0, 0, 12.0]]
    )
    assert e.light(probe) == pytest.approx([1.0, 0.5, 0.0, 0.4, 0.0, 1.0, 1.0])
    assert e.contains(probe).tolist() == [True, True, False, True, False, True, True]
    assert e.light([[0, 2.0, 12.0]]) == pytest.approx([0.0])
    # below the crown base, the crown's widest reach in each direction: 3 m towards +x, 2 m towards +y
    low = np.array([[2.9, 0, 2.0], [0, 1.9, 1.0], [0, 2.6, 1.0], [-1.2, 0, 3.0], [0.0, -0.2, 3.0]])
    assert e.light(low) == pytest.approx([1.0, 1.0, 0.0, 0.6, 0.6])
    # the stem's own corridor: a point 0.2 m from a grower's stem is lit as within the margin
    assert e.light([[0.0, -0.2, 7.0]]) == pytest.approx([0.6])
    assert e.light([[1.0, -0.2, 7.0]]) == pytest.approx([0.0])
    assert e.light([[1.0, -0.2, 7.0]], stem=[[0, 0, 0], [1.0, 0, 10]])[0] > 0.0
    # ... up to the margin above its top, and not above the envelope's top
    assert e.light([[0.0, -2.0, 5.0], [0.0, -2.0, 5.3], [0.0, -2.0, 5.6]], stem=[[0, 0, 0], [0, -2, 5]]) == (
        pytest.approx([1.0, 0.4, 0.0])
    )
    assert e.light([[0.0, -2.0, 10.5]], stem=[[0, 0, 0], [0, -2, 12]])[0] == 0.0
    # its outline at 4.1 m: 3.5 m towards +x, the margin elsewhere
    ring = e.outline(4.1)
    assert np.hypot(*ring.T).max() == pytest.approx(3.5) and np.hypot(*ring.T).min() == pytest.approx(0.5)
    # a setting holds it to the cm and reads back
    back = CrownEnvelope.from_setting(e.setting())
    assert np.array_equal(back.reach, np.round(e.reach, 2)) and back.base == pytest.approx(4.0)
    # the default margin: a tenth of the crown radius
    assert crown_envelope(t).margin == pytest.approx(0.1 * 0.5 * crown_spread(t))


def test_the_side_of_a_hand_built_tree_is_its_reach_in_each_direction_over_its_widest():
    e = crown_envelope(one_sided_tree(), margin=0.5)
    half = 180.0 / SECTORS  # a sector's middle lies half a sector past its first azimuth
    at = lambda z, deg, r=1.0: [r * math.cos(math.radians(deg)), r * math.sin(math.radians(deg)), z]  # noqa: E731
    # the band of the 3 m branch towards +x: all of it in the middle of its sector, half at the
    # sector's edge (linear between the middles), none behind it; the same at any distance
    pts = [at(4.1, half), at(4.1, 0.0), at(4.1, 2 * half), at(4.1, 180.0), at(4.1, half, 2.5), at(4.1, -half)]
    assert e.side(pts) == pytest.approx([1.0, 0.5, 0.5, 0.0, 1.0, 0.0])
    # the band of the 1 m branch towards -x; the band of no branch (only the stem): open all round
    assert e.side([at(8.1, -180.0 + half), at(8.1, 90.0)]) == pytest.approx([1.0, 0.0])
    b = int((7.0 - 4.0) / (6.0 / BANDS))
    assert e.reach[b].max() == 0.0 and e.side([at(7.0, 30.0)]) == pytest.approx([1.0])
    # below the crown base, the widest reach of each sector: 3 m towards +x, 2 m towards +y
    assert e.side([at(2.0, half), at(2.0, 90.0 + half)]) == pytest.approx([1.0, 2.0 / 3.0])


def test_a_leaning_stem_carries_its_crown_and_is_measured_at_each_height():
    t = one_sided_tree(lean=3.0)
    e = crown_envelope(t, margin=0.2)
    z = 4.0 + 6.0 * np.arange(BANDS + 1) / BANDS
    assert e.stem[:, 0] == pytest.approx(np.maximum(z - 4.0, 0.0) / 2.0)  # the stem at each band edge
    assert np.allclose(stem_at(t, [2.0, 7.0, 12.0]), [[0, 0, 2.0], [1.5, 0, 7.0], [3.0, 0, 10.0]])
    # the +y branch at 6 m (the stem 1 m over) reaches 2 m from the stem, not from the base
    b = int(2.0 / (6.0 / BANDS))
    assert e.reach[b].max() == pytest.approx(2.0, abs=0.02)
    assert e.contains(np.concatenate([t.start, t.end])).all()
    assert not e.contains([[0.0, 0.0, 9.0]])[0]  # the upright line over the stem base, 2.5 m from the stem


def test_the_crown_offset_of_a_hand_built_one_sided_tree():
    # branches of 3, 2 and 1 m at 4, 6 and 8 m (radius 2 cm): the volume-weighted centre of their
    # cylinders lies at (3 * 1.5 - 1 * 0.5, 2 * 1) / 6 m = (0.667, 0.333) m from the upright stem;
    # the crown radius is half the crown spread (its 36 spokes: 3, 2 and 1 m)
    t = one_sided_tree()
    radius = 0.5 * crown_spread(t)
    assert radius == pytest.approx(6.0 / 36.0)
    assert crown_offset(t) == pytest.approx(np.array([4.0 / 6.0, 2.0 / 6.0]) / radius)
    # the same crown on a stem leaning 3 m over its upper 6 m: the centre's height is
    # (3 * 4 + 2 * 6 + 1 * 8) / 6 = 5.33 m, where the stem stands 0.667 m over: the crown lies there
    leant = one_sided_tree(lean=3.0)
    zc = 32.0 / 6.0
    dx = 3.0 * (zc - 4.0) / 6.0
    base = np.array([4.0 / 6.0 + (3 * 0.0 + 2 * 1.0 + 1 * 2.0) / 6.0, 2.0 / 6.0])  # branches ride the stem
    assert crown_offset(leant) == pytest.approx((base - [dx, 0.0]) / (0.5 * crown_spread(leant)))
    m = measure_tree(t)
    assert m.crown_side == pytest.approx(tuple(np.round(crown_offset(t), 4)))
    # the tree summary holds it (the size term's crown_offset_x and _y)
    row = tree_summary(t)
    assert (row["crown_offset_x"], row["crown_offset_y"]) == pytest.approx((4.0 / 6.0 / radius, 2.0 / 6.0 / radius))
    assert m.one_sided and m.envelope["base"] == pytest.approx(4.0)


def test_a_bad_envelope_setting_is_refused_naming_what_is_wrong():
    good = crown_envelope(one_sided_tree(), margin=0.5).setting()
    for change, says in (
        ({"margin": -1.0}, "margin"),
        ({"top": 1.0}, "base and top"),
        ({"reach": [[1.0, 2.0]]}, "reach"),
        ({"stem": [[0.0, 0.0]]}, "stem"),
        ({"reach": [[math.nan] * 16] * 8}, "reach: holds a value that is not finite"),
        ({"extra": 1}, "unknown extra"),
    ):
        with pytest.raises(ValueError, match=says):
            CrownEnvelope.from_setting({**good, **change})
    with pytest.raises(ValueError, match="missing reach"):
        CrownEnvelope.from_setting({k: v for k, v in good.items() if k != "reach"})
    with pytest.raises(bf.ConfigError, match="crown_envelope"):
        bf.component("ssm", "sot", crown_envelope={**good, "margin": -1.0})


def test_the_report_draws_the_crowns_space_beside_the_tree(tmp_path):
    from bforest_core.report.trees import clones_figure, envelope_lines

    t = one_sided_tree()
    e = crown_envelope(t, margin=0.5)
    (side,) = envelope_lines(e, "xz")
    # side view: from the ground to the top's margin, 3.5 m towards +x (the 3 m branch and the
    # margin), 1.5 m towards -x (the 1 m branch); below the crown base the widest reaches
    assert side[:, 1].min() == pytest.approx(0.0) and side[:, 1].max() == pytest.approx(10.5)
    assert side[:, 0].max() == pytest.approx(3.5, abs=0.01) and side[:, 0].min() == pytest.approx(-1.5, abs=0.01)
    top = np.concatenate(envelope_lines(e, "xy"))
    assert top[:, 0].max() == pytest.approx(3.5, abs=0.05) and top[:, 1].max() == pytest.approx(2.5, abs=0.05)
    # the 1 m branch's sector towards -x reaches from -180 to -157.5 deg: its arc dips below y = -0.5
    assert top[:, 1].min() == pytest.approx(-1.5 * math.sin(math.radians(22.5)), abs=0.02)
    path = clones_figure(t, [("clone 0", t)], tmp_path / "space.png", envelope=e)
    assert path.stat().st_size > 10_000
