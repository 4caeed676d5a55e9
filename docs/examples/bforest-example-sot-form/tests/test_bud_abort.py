"""The example growth form: conformant, and lateral buds that abort at the rate asked for."""

from __future__ import annotations

import hashlib

import numpy as np
import pytest

import bforest_core as bf
from bforest_core.testing import ssm_checks

example = pytest.importorskip(
    "bforest_example_sot_form",
    reason="the example growth form is not installed (python3 dev.py env, or pip install -e "
    "docs/examples/bforest-example-sot-form)",
)
SOTBudAbort = example.SOTBudAbort

#: a tree whose lateral buds all break: no noise, no light-seeking, no tropism, vigorous buds
HAND = {
    "max_iter": 8,
    "phyllotaxis": 90.0,
    "branch_angle_sd": 0.0,
    "phyllotaxis_sd": 0.0,
    "tropism": 0.0,
    "reorient": 0.0,
    "ran": 0.0,
    "init_lambda": 0.5,
    "targ_lambda": 0.5,
    "alpha0": 3.0,
    "max_grow": 4.0,
    "drop_thresh": 0.05,
    "branch_angle": 65.0,
}


@pytest.mark.parametrize(
    "check", ssm_checks(SOTBudAbort, params={"max_iter": 8, "bud_abort": 0.3}, registered=True), ids=str
)
def test_conformance(check):
    check()


def _same(a, b):
    return all(np.array_equal(getattr(a, k), getattr(b, k)) for k in ("start", "axis", "length", "radius", "parent"))


def _lateral_share(t):
    """(nodes, share): the cylinders an axis grows on from, and the share of them bearing a lateral."""
    kid = np.flatnonzero(t.parent >= 0)
    own = t.branch[kid] == t.branch[t.parent[kid]]
    goes_on = np.zeros(t.n, bool)
    goes_on[t.parent[kid[own]]] = True
    bears = np.zeros(t.n, bool)
    bears[t.parent[kid[~own]]] = True
    return int(goes_on.sum()), float((bears & goes_on).sum() / goes_on.sum())


def test_aborted_buds_leave_nodes_without_a_branch():
    ssm = SOTBudAbort()
    n, share = _lateral_share(ssm.simulate(HAND, 1))
    assert n > 100 and share == 1.0  # without aborts every node an axis grows on from bears a branch
    for q in (0.3, 0.5, 0.8):  # about 1 - bud_abort of the nodes bear one
        counts = [_lateral_share(ssm.simulate({**HAND, "bud_abort": q}, s)) for s in (1, 2, 3)]
        nodes = sum(c for c, _ in counts)
        share = sum(c * f for c, f in counts) / nodes
        assert abs(share - (1.0 - q)) < 3.0 * np.sqrt(q * (1.0 - q) / nodes), (q, share, nodes)
    # a stream of its own: a probability too small to abort any bud leaves SOT's tree, draw for draw
    sot = bf.component("ssm", "sot")
    assert _same(sot.simulate(HAND, 1), ssm.simulate({**HAND, "bud_abort": 1e-12}, 1))
    assert _same(sot.simulate(HAND, 1), ssm.simulate(HAND, 1))
    with pytest.raises(ValueError, match="bud_abort"):
        ssm.simulate({**HAND, "bud_abort": 1.0}, 1)


def _digest(t):
    h = hashlib.sha256()
    for a in (t.start, t.axis, t.length, t.radius, t.parent, t.extension):
        h.update(np.ascontiguousarray(a).tobytes())
    return t.n, h.hexdigest()[:16]


@pytest.mark.parametrize(
    "settings, params, seed, expected",
    [
        ({}, {"max_iter": 14, "bud_abort": 0.3}, 1, (565, "d0b0d3aaa17e3408")),
        ({"buds_per_node": 2}, {**HAND, "bud_abort": 0.5}, 1, (177, "171d4ce9f5957e78")),
        (
            {},
            {"max_iter": 14, "bud_abort": 0.3, "leader_death": 0.2, "short_shoot": 0.3, "heading_sd": 10.0},
            2,
            (128, "a0fb26ea8a4b6c5d"),
        ),
    ],
)
def test_the_trees_of_the_former_option_bit_for_bit(settings, params, seed, expected):
    """Recorded with SOT's own bud_abort option before it moved here (commit 8999313)."""
    assert _digest(SOTBudAbort(**settings).simulate(params, seed)) == expected
