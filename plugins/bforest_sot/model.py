"""The self-organizing tree (SOT) growth engine (docs/models.md part B).

Structure of arrays, one row per segment (metamer) ever created; rows are never reused, so the
creation order is a parent-before-child order. Every per-cycle computation is vectorised over
segments, buds or shoots; Python loops run only over cycles, depth levels (basipetal pass),
pointer-jumping rounds (acropetal pass) and metamer steps (shoot construction).

Random draws, all from one ``numpy.random.Generator(PCG64(seed))`` (docs/models.md B.7):

* init: ``n_vox**3`` uniforms for ``ran`` in C order of (i, j, k) (drawn even when ran = 0;
  skipped with ``advance`` when the initial field of this seed is cached: the same stream after)
* per growth cycle c = 2 .. max_iter, in this order:

  1. one standard normal for lambda (``lambda_sd``);
  2. one standard normal per growing lateral shoot (``branch_angle_sd``);
  3. one standard normal per growing shoot (``tropism_sd``);
  4. at each metamer step k, one standard normal per shoot still active after the wall check
     (``phyllotaxis_sd``), then, only when ``heading_sd`` > 0, one more per such shoot
     (``heading_sd``, an addition to docs/models.md B.7, see B.10: trees without it keep their old draws).

  Shoots are ordered by bearing segment, the apical shoot before the lateral one. A block is
  drawn even when its sd is 0; no draw depends on ``max_iter``, so a run of length t equals the
  ``on_step`` snapshot at t of any longer run (prefix property).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from bforest_core.tree import Tree, group_by_level, remap_ids

from .kernels import advance_frames, sum_levels, turn_geometry
from .light import LightField

MODEL_VERSION = "1.0"

EMPTY, BUD, CHILD, STUB = 0, 1, 2, 3
SLOT_NAMES = {EMPTY: "EMPTY", BUD: "BUD", CHILD: "CHILD", STUB: "STUB"}


class GrowthFailure(Exception):
    """Internal: a non-ok status (turned into ``bf.SimulationFailed`` by the component)."""

    def __init__(self, status: str, message: str):
        self.status = status
        super().__init__(message)


# ------------------------------------------------------------------------------------------------
# small vector helpers
# ------------------------------------------------------------------------------------------------


def cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Row-wise cross product of (m, 3) arrays of one shape: the arithmetic of ``np.cross`` (so
    the same bits) without its axis handling, which costs more than the products for the short
    batches of a growth cycle."""
    out = np.empty(a.shape)
    a0, a1, a2 = a[:, 0], a[:, 1], a[:, 2]
    b0, b1, b2 = b[:, 0], b[:, 1], b[:, 2]
    np.subtract(a1 * b2, a2 * b1, out=out[:, 0])
    np.subtract(a2 * b0, a0 * b2, out=out[:, 1])
    np.subtract(a0 * b1, a1 * b0, out=out[:, 2])
    return out


def rotate(v: np.ndarray, k: np.ndarray, theta: np.ndarray) -> np.ndarray:
    """Right-handed rotation of rows of ``v`` about unit rows ``k`` by ``theta`` (radians)."""
    c = np.cos(theta)[:, None]
    s = np.sin(theta)[:, None]
    kdv = np.einsum("ij,ij->i", k, v)[:, None]
    return v * c + cross(k, v) * s + k * (kdv * (1.0 - c))


def _norm(v: np.ndarray) -> np.ndarray:
    """Row norms of (m, 3) ``v``: ``np.linalg.norm(v, axis=1)``'s sum in its order (the same bits)."""
    return np.sqrt(v[:, 0] * v[:, 0] + v[:, 1] * v[:, 1] + v[:, 2] * v[:, 2])


def _unit(v: np.ndarray) -> np.ndarray:
    return v / _norm(v)[:, None]


def lambda_schedule(age: float, init_lambda: float, targ_lambda: float, delay: float, transition: float) -> float:
    """Apical control at schedule age (B.5 step 1): ``init_lambda`` up to ``delay``, then a
    linear ramp over ``transition`` cycles to ``targ_lambda``."""
    if age <= delay:
        return float(init_lambda)
    return float(((delay + transition - age) * init_lambda + (age - delay) * targ_lambda) / transition)


# ------------------------------------------------------------------------------------------------
# the two passes, on a compact node set (local indices 0..m-1, children given as local ids)
# ------------------------------------------------------------------------------------------------


def accumulate(
    api_state,
    lat_state,
    api_child,
    lat_child,
    q_api,
    q_lat,
    api_stub_w,
    lat_stub_w,
    depth,
    lam,
    kappa,
    pipe_exp,
    init_width,
    levels=None,
):
    """Basipetal pass (B.5 step 3) over a compact set of m living segments.

    Slot contributions (N, Q, width): CHILD c -> (N_c, Q_c, d_c); BUD -> (1, Q_bud, -);
    STUB -> (0, 0, w); EMPTY -> (0, 0, -). ``N = 1 + N_m + N_l``, ``Q = Q_m + Q_l``,
    ``D = lam N_m (Q_m/N_m)^kappa + (1 - lam) N_l (Q_l/N_l)^kappa`` (terms with N = 0 omitted;
    D = 1 when neither slot holds a BUD or CHILD), ``d^n = sum of w^n over CHILD and STUB slots``
    or ``init_width^n`` if there is none.

    Parameters
    ----------
    api_state, lat_state : (m,) int8
        Slot states (EMPTY, BUD, CHILD, STUB).
    api_child, lat_child : (m,) int
        Local index of the child in a CHILD slot (ignored elsewhere).
    q_api, q_lat : (m,) float
        Bud exposures (read where the slot is a BUD).
    api_stub_w, lat_stub_w : (m,) float
        Stub widths (read where the slot is a STUB).
    depth : (m,) int
        Depth of each node (root 0); children have their parent's depth + 1.
    lam, kappa, pipe_exp, init_width : float

    Returns
    -------
    dict
        ``N``, ``Q``, ``D``, ``W`` (= d^pipe_exp), ``width`` (d) per node, and the slot sums
        ``Nm``, ``Qm`` (apical) and ``Nl``, ``Ql`` (lateral).
    """
    m = api_state.shape[0]
    sent = m  # sentinel row of zeros for non-CHILD slots
    a_bud = api_state == BUD
    l_bud = lat_state == BUD
    base = np.zeros((m + 1, 3))
    base[:m, 0] = a_bud.astype(float) + l_bud
    base[:m, 1] = np.where(a_bud, q_api, 0.0) + np.where(l_bud, q_lat, 0.0)
    base[:m, 2] = (
        np.where(api_state == STUB, api_stub_w, 0.0) ** pipe_exp
        + np.where(lat_state == STUB, lat_stub_w, 0.0) ** pipe_exp
    )
    base[:m, 0] += 1.0
    ac = np.where(api_state == CHILD, api_child, sent)
    lc = np.where(lat_state == CHILD, lat_child, sent)
    d0n = float(init_width) ** pipe_exp
    order, bounds = group_by_level(depth) if levels is None else levels
    V = sum_levels(base, ac, lc, order, bounds, d0n)  # level by level, deepest first (kernels.py)
    N = V[:m, 0]
    Q = V[:m, 1]
    W = V[:m, 2]
    Nm = a_bud + V[ac, 0]
    Qm = np.where(a_bud, q_api, 0.0) + V[ac, 1]
    Nl = l_bud + V[lc, 0]
    Ql = np.where(l_bud, q_lat, 0.0) + V[lc, 1]
    if kappa == 1.0:
        D = lam * Qm + (1.0 - lam) * Ql
    else:
        D = lam * np.where(Nm > 0, Nm * (Qm / np.maximum(Nm, 1.0)) ** kappa, 0.0) + (1.0 - lam) * np.where(
            Nl > 0, Nl * (Ql / np.maximum(Nl, 1.0)) ** kappa, 0.0
        )
    D = np.where((Nm + Nl) > 0, D, 1.0)
    woody = np.isin(api_state, (CHILD, STUB)) | np.isin(lat_state, (CHILD, STUB))
    width = np.where(woody, W ** (1.0 / pipe_exp), float(init_width))
    return {"N": N.copy(), "Q": Q.copy(), "D": D, "W": W.copy(), "width": width, "Nm": Nm, "Qm": Qm, "Nl": Nl, "Ql": Ql}


def _pointer_jump_rounds(parent: np.ndarray):
    """The rounds of Wyllie's pointer jumping: a list of ``(active, ancestor)`` index pairs so
    that replaying ``x[active] = op(x[active], x[ancestor])`` in order folds every path."""
    anc = parent.copy()
    act = np.flatnonzero(anc >= 0)
    rounds = []
    while act.size:
        a = anc[act]
        rounds.append((act, a))
        anc[act] = anc[a]
        act = act[anc[act] >= 0]
    return rounds


def allocate(parent, is_lateral, N, Q, D, lam, kappa, v_base, rounds=None):
    """Acropetal Borchert-Honda pass (B.5 step 4) over a compact node set.

    ``v_root = v_base``; a child c in slot sigma of s gets
    ``v_c = v_s w_sigma N_c (Q_c/N_c)^kappa / D_s`` (w_api = lam, w_lat = 1 - lam; 0 if D_s <= 0).
    Vigor is a product of these ratios along the path, folded by pointer jumping.

    Returns
    -------
    v : (m,) float
        Vigor of every node (including nodes that the caller will drop).
    rounds : list
        The pointer-jumping rounds (reusable for path folds over the same parents).
    """
    share = N * (Q / N) ** kappa if kappa != 1.0 else Q
    w = np.where(is_lateral, 1.0 - lam, lam)
    has_p = parent >= 0
    Dp = np.where(has_p, D[np.maximum(parent, 0)], 1.0)
    r = np.where(Dp > 0, w * share / np.where(Dp > 0, Dp, 1.0), 0.0)
    r[~has_p] = v_base
    if rounds is None:
        rounds = _pointer_jump_rounds(parent)
    v = r.copy()
    for act, a in rounds:
        v[act] = v[act] * v[a]
    return v, rounds


def path_any(flag: np.ndarray, rounds) -> np.ndarray:
    """True where the node or any ancestor is flagged (replays pointer-jumping rounds)."""
    f = flag.copy()
    for act, a in rounds:
        f[act] = f[act] | f[a]
    return f


# ------------------------------------------------------------------------------------------------
# state
# ------------------------------------------------------------------------------------------------

_FIELDS = {
    "start": (np.float64, 3),
    "h": (np.float64, 3),
    "u": (np.float64, 3),
    "length": (np.float64, 0),
    "width": (np.float64, 0),
    "parent": (np.int64, 0),
    "is_lateral": (np.bool_, 0),
    "order": (np.int64, 0),
    "depth": (np.int64, 0),
    "alive": (np.bool_, 0),
    "born": (np.int64, 0),
    "api_state": (np.int8, 0),
    "lat_state": (np.int8, 0),
    "api_child": (np.int64, 0),
    "lat_child": (np.int64, 0),
    "api_stub_w": (np.float64, 0),
    "lat_stub_w": (np.float64, 0),
    "twin": (np.bool_, 0),
    "short": (np.bool_, 0),
    "vcap": (np.float64, 0),  # vigor_sd: the shoot's cap factor (1 = max_grow)
    "lat_vcap": (np.float64, 0),  # ... and the one its lateral bud's shoot will have
}


class SegmentStore:
    """Growable structure-of-arrays of all segments ever created (``n`` rows in use)."""

    def __init__(self, capacity: int = 1024):
        self.n = 0
        self.cap = 0
        for name, (dt, k) in _FIELDS.items():
            setattr(self, name, np.zeros((0, k) if k else 0, dtype=dt))
        self.reserve(capacity)

    def reserve(self, total: int) -> None:
        if total <= self.cap:
            return
        cap = max(total, 2 * self.cap, 1024)
        for name, (dt, k) in _FIELDS.items():
            old = getattr(self, name)
            new = np.zeros((cap, k) if k else cap, dtype=dt)
            new[: self.n] = old[: self.n]
            setattr(self, name, new)
        self.cap = cap

    def append(self, new: slice, start, h, u, length, width, parent, is_lateral, order, born) -> None:
        """Fill the rows ``new`` (the next ones, reserved) as living metamers without children:
        an EMPTY apical slot and a lateral BUD."""
        self.start[new] = start
        self.h[new] = h
        self.u[new] = u
        self.length[new] = length
        self.width[new] = width
        self.parent[new] = parent
        self.is_lateral[new] = is_lateral
        self.order[new] = order
        self.depth[new] = self.depth[parent] + 1
        self.alive[new] = True
        self.born[new] = born
        self.api_state[new] = EMPTY
        self.lat_state[new] = BUD
        self.api_child[new] = -1
        self.lat_child[new] = -1
        self.api_stub_w[new] = 0.0
        self.lat_stub_w[new] = 0.0
        self.short[new] = False
        self.vcap[new] = 1.0
        self.lat_vcap[new] = 1.0

    @property
    def live(self) -> np.ndarray:
        """Ids of the living segments in creation (parent-before-child) order."""
        return np.flatnonzero(self.alive[: self.n])


@dataclass
class AllocationRecord:
    """Inspection record of one cycle's two passes (ids are global segment ids).

    Arrays are over the segments alive at the start of the cycle (``ids``); slot states and
    children are as *before* the drops of this cycle. ``vA_raw``/``vL_raw`` are the bud vigors
    before the ``max_grow`` cap (0 where the slot is not a BUD or D <= 0).
    """

    cycle: int
    lam: float
    ids: np.ndarray
    parent: np.ndarray
    is_lateral: np.ndarray
    api_state: np.ndarray
    lat_state: np.ndarray
    api_child: np.ndarray
    lat_child: np.ndarray
    q_api: np.ndarray
    q_lat: np.ndarray
    N: np.ndarray
    Q: np.ndarray
    D: np.ndarray
    width: np.ndarray
    v: np.ndarray
    v_base: float
    dropped: np.ndarray
    vA_raw: np.ndarray
    vL_raw: np.ndarray


@dataclass
class ShootRecord:
    """Inspection record of one cycle's shoots (one entry per growing shoot, in draw order)."""

    bearing: np.ndarray  # global id of the bearing segment
    lateral: np.ndarray  # bool
    vigor: np.ndarray  # capped bud vigor v
    planned: np.ndarray  # floor(v)
    built: np.ndarray  # metamers actually built (fewer only at the walls)
    first: np.ndarray  # global id of the first metamer (-1 if none)
    metamer_length: np.ndarray
    branch_angle: np.ndarray  # drawn branch angle (deg; NaN for apical shoots)
    target: np.ndarray  # (k, 3) unit target direction (0 if |t| = 0)
    tau: np.ndarray  # turning fraction


@dataclass
class _Basipetal:
    """Steps 2-3 of a cycle over the segments alive at its start (local index; ``ids`` global):
    bud states and exposures as before the drops, and the basipetal sums."""

    ids: np.ndarray
    lpar: np.ndarray  # local parent (-1 for the root)
    is_lat: np.ndarray
    api_state0: np.ndarray
    lat_state0: np.ndarray
    q_api: np.ndarray
    q_lat: np.ndarray
    N: np.ndarray
    Q: np.ndarray
    D: np.ndarray
    width: np.ndarray


# ------------------------------------------------------------------------------------------------
# the growth run
# ------------------------------------------------------------------------------------------------


class SOTGrowth:
    """One SOT run. ``run()`` executes cycles 1 .. max_iter; failures raise
    :class:`GrowthFailure` and leave the state in place for the partial tree."""

    def __init__(
        self,
        p: dict,
        seed: int,
        *,
        max_live_segments: int = 200_000,
        sympodial: bool = False,
        buds_per_node: int = 1,
        stem_path=(),
        on_step: Callable | None = None,
        record: bool = False,
    ):
        self.p = p
        self.seed = seed
        self.max_live = int(max_live_segments)
        self.sympodial = bool(sympodial)
        self.buds_per_node = int(buds_per_node)
        self.on_step = on_step
        self.record = record or on_step is not None
        self.rng = np.random.Generator(np.random.PCG64(seed))
        n3 = int(round(p["span"] / p["voxel_size"])) ** 3
        # draw 1; the field of a seed seen before comes from the field's cache, and the generator
        # then skips the n3 draws it was made of (PCG64 advance: the same stream after it)
        self.field = LightField(
            p["span"],
            p["voxel_size"],
            int(p["depth"]),
            p["spread"],
            p["shadow_a"],
            p["shadow_b"],
            p["ran"],
            p["vert"],
            lambda: self.rng.random(n3),
            stand_shade=p["stand_shade"],
            gap_shade=p["gap_shade"],
            gap_azimuth=p["gap_azimuth"],
            initial_key=("sot", int(seed)) if isinstance(seed, (int, np.integer)) else None,
        )
        if self.field.from_cache:
            self.rng.bit_generator.advance(n3)
        self.s = SegmentStore()
        # vigor_sd (an addition, B.10): the shoots' cap factors come from a generator of the run's
        # seed and a stream of their own, so the growth's other draws stay as they are
        self.vig_rng = _own_stream(seed, VIGOR_STREAM) if p["vigor_sd"] > 0.0 else None
        # bud_abort (an addition, B.10): which lateral buds abort, from a stream of their own too
        self.abort_rng = _own_stream(seed, ABORT_STREAM) if p["bud_abort"] > 0.0 else None
        # stem_guide (an addition, B.10): the path the stem's shoots follow, by arc length
        self.guide = _Guide(stem_path) if p["stem_guide"] > 0.0 and len(stem_path) else None
        self.stem_arc = 0.0  # length of the stem (order 0) grown so far
        self.age = 0.0
        self.cycle = 0
        self.lam = float(p["init_lambda"])
        self.created = 0
        self.last_alloc: AllocationRecord | None = None
        self.last_shoots: ShootRecord | None = None

    # -------------------------------------------------------------- cycle 1
    def _seed(self) -> None:
        p, s = self.p, self.s
        s.reserve(1)
        s.start[0] = (0.0, 0.0, 0.0)
        s.h[0] = (0.0, 0.0, 1.0)
        s.u[0] = (0.0, -1.0, 0.0)
        s.length[0] = p["node_length"]
        s.width[0] = p["init_width"]
        s.parent[0] = -1
        s.alive[0] = True
        s.born[0] = 1
        s.api_state[0] = BUD
        s.lat_state[0] = BUD
        s.api_child[0] = s.lat_child[0] = -1
        s.vcap[0] = s.lat_vcap[0] = 1.0
        s.n = 1
        self.stem_arc = float(p["node_length"])
        if self.buds_per_node > 1:
            s.reserve(self.buds_per_node)
            last = self._add_bud_nodes(
                1, np.zeros(1, np.int64), s.start[:1] + s.length[0] * s.h[:1], s.h[:1], s.u[:1], s.order[:1]
            )
            s.api_state[last] = BUD
        self.created = s.n
        self._draw_lateral_buds(0)
        self.field.cast(s.start[:1])  # falls below ground: no effect

    def _draw_lateral_buds(self, lo: int) -> None:
        """The draws of the lateral buds of the rows ``lo ..``, one per row in creation order, each
        from its own stream. vigor_sd (an addition): the cap factor exp(vigor_sd * N(0, 1)) of the
        shoot each bud will grow; bud_abort (an addition): each bud aborts (its slot left EMPTY: it
        takes no light, no vigor and never grows) with probability bud_abort."""
        s = self.s
        if self.vig_rng is not None:
            s.lat_vcap[lo : s.n] = np.exp(self.p["vigor_sd"] * self.vig_rng.standard_normal(s.n - lo))
        if self.abort_rng is not None:
            s.lat_state[lo : s.n][self.abort_rng.random(s.n - lo) < self.p["bud_abort"]] = EMPTY

    # -------------------------------------------------------------- passes on the living set
    def _compact(self):
        s = self.s
        ids = s.live
        loc = np.full(s.n, -1, dtype=np.int64)
        loc[ids] = np.arange(ids.size)
        par = s.parent[ids]
        lpar = remap_ids(par, loc)
        ac = np.where(s.api_state[ids] == CHILD, loc[np.maximum(s.api_child[ids], 0)], -1)
        lc = np.where(s.lat_state[ids] == CHILD, loc[np.maximum(s.lat_child[ids], 0)], -1)
        return ids, loc, lpar, ac, lc

    def _bud_light(self, ids):
        s = self.s
        a_bud = s.api_state[ids] == BUD
        l_bud = s.lat_state[ids] == BUD
        any_bud = np.flatnonzero(a_bud | l_bud)
        q = np.zeros(ids.size)
        if any_bud.size:
            g = ids[any_bud]
            ends = s.start[g] + s.length[g, None] * s.h[g]
            q[any_bud] = self.field.exposure(ends)
        return np.where(a_bud, q, 0.0), np.where(l_bud, q, 0.0)

    def widths(self) -> np.ndarray:
        """Width-only basipetal update of the living segments on a copy: ``(ids, width)``."""
        s = self.s
        ids, loc, lpar, ac, lc = self._compact()
        p = self.p
        z = np.zeros(ids.size)
        acc = accumulate(
            s.api_state[ids],
            s.lat_state[ids],
            ac,
            lc,
            z,
            z,
            s.api_stub_w[ids],
            s.lat_stub_w[ids],
            s.depth[ids],
            self.lam,
            1.0,
            p["pipe_exp"],
            p["init_width"],
        )
        return ids, acc["width"]

    # -------------------------------------------------------------- one growth cycle
    def _grow_cycle(self, c: int) -> None:
        """Cycle ``c``: one method per step (1 lambda; 2-3 bud light and the basipetal pass; 4
        the acropetal pass and drops; 5 bud vigor; 6 the shoots)."""
        lam = self._cycle_lambda()  # 1
        bp = self._basipetal(lam)  # 2, 3
        v, v_base, dead = self._allocate_and_drop(bp, lam)  # 4
        vA, vL = self._vigor(c, bp, lam, v, v_base, dead)  # 5
        self._grow_shoots(c, bp, dead, vA, vL)  # 6

    def _cycle_lambda(self) -> float:
        """Step 1: this cycle's apical control (schedule plus noise: the cycle's draw 1); with k
        buds per node the share of one of a node's k splits. Also lifts the stand's canopy top to
        the tree's."""
        p, s = self.p, self.s
        self.age = min(self.age + 1.0, p["delay"] + p["transition"])
        lam = lambda_schedule(self.age, p["init_lambda"], p["targ_lambda"], p["delay"], p["transition"])
        z_lam = self.rng.standard_normal()
        lam = float(np.clip(lam + p["lambda_sd"] * z_lam, 0.0, 1.0))
        self.lam = lam
        if self.buds_per_node > 1:
            # a node of k buds is k Borchert-Honda splits in a row (see _add_bud_nodes): each takes
            # lambda^(1/k), so the axis keeps the share lambda of a node that the papers' model
            # gives it and the node's lateral buds share the rest
            lam = lam ** (1.0 / self.buds_per_node)
        if p["stand_shade"] > 0.0:  # the stand's canopy grows with the tree: its top is the tree's
            live = s.live
            self.field.z_top = float((s.start[live, 2] + s.length[live] * s.h[live, 2]).max())
        return lam

    def _basipetal(self, lam: float) -> _Basipetal:
        """Steps 2-3: the exposure of every bud and the basipetal pass (bud counts N, light Q,
        the allocation denominators D, pipe-model widths, written to the store)."""
        p, s = self.p, self.s
        ids, loc, lpar, ac, lc = self._compact()
        q_api, q_lat = self._bud_light(ids)
        api_state0 = s.api_state[ids].copy()
        lat_state0 = s.lat_state[ids].copy()
        acc = accumulate(
            api_state0,
            lat_state0,
            ac,
            lc,
            q_api,
            q_lat,
            s.api_stub_w[ids],
            s.lat_stub_w[ids],
            s.depth[ids],
            lam,
            float(p["nonlinear"]),
            p["pipe_exp"],
            p["init_width"],
        )
        s.width[ids] = acc["width"]
        return _Basipetal(
            ids,
            lpar,
            s.is_lateral[ids],
            api_state0,
            lat_state0,
            q_api,
            q_lat,
            acc["N"],
            acc["Q"],
            acc["D"],
            acc["width"],
        )

    def _allocate_and_drop(self, bp: _Basipetal, lam: float):
        """Step 4: the acropetal (Borchert-Honda) pass, and the drop of under-supplied branches
        and of those below the ground (their parents' slots become stubs, they leave the light
        field). Returns ``(v, v_base, dropped)``."""
        p, s = self.p, self.s
        ids, lpar, width = bp.ids, bp.lpar, bp.width
        v_base = p["alpha0"] + p["alpha1"] * bp.Q[0]
        v, rounds = allocate(lpar, bp.is_lat, bp.N, bp.Q, bp.D, lam, float(p["nonlinear"]), v_base)
        cand = (v / bp.N <= p["drop_thresh"]) | (s.start[ids, 2] <= 0.0)
        cand[lpar < 0] = False  # the root is never dropped
        dead = path_any(cand, rounds)
        top = np.flatnonzero(dead & ~dead[np.maximum(lpar, 0)])
        if top.size:
            pg = ids[lpar[top]]
            lat_top = bp.is_lat[top]
            s.lat_state[pg[lat_top]] = STUB
            s.lat_stub_w[pg[lat_top]] = width[top[lat_top]]
            s.api_state[pg[~lat_top]] = STUB
            s.api_stub_w[pg[~lat_top]] = width[top[~lat_top]]
            gone = ids[dead]
            s.alive[gone] = False
            if self.buds_per_node > 1:  # bud nodes cast no shadow (see _add_bud_nodes)
                gone = gone[~s.twin[gone]]
            self.field.remove(s.start[gone])
        return v, v_base, dead

    def _vigor(self, c: int, bp: _Basipetal, lam: float, v, v_base: float, dead):
        """Step 5: the vigor of every apical and lateral bud, capped at ``max_grow`` (the
        uncapped values go to the inspection record). Returns ``(vA, vL)``."""
        p, s = self.p, self.s
        ids = bp.ids
        kappa = float(p["nonlinear"])
        D = bp.D
        Dpos = D > 0
        Dsafe = np.where(Dpos, D, 1.0)
        vA_raw = np.where((bp.api_state0 == BUD) & Dpos, v * lam * bp.q_api**kappa / Dsafe, 0.0)
        vL_raw = np.where((bp.lat_state0 == BUD) & Dpos, v * (1.0 - lam) * bp.q_lat**kappa / Dsafe, 0.0)
        if self.record:
            self.last_alloc = AllocationRecord(
                cycle=c,
                lam=lam,
                ids=ids,
                parent=s.parent[ids].copy(),
                is_lateral=bp.is_lat.copy(),
                api_state=bp.api_state0,
                lat_state=bp.lat_state0,
                api_child=np.where(bp.api_state0 == CHILD, s.api_child[ids], -1),
                lat_child=np.where(bp.lat_state0 == CHILD, s.lat_child[ids], -1),
                q_api=bp.q_api,
                q_lat=bp.q_lat,
                N=bp.N,
                Q=bp.Q,
                D=D,
                width=bp.width,
                v=v,
                v_base=v_base,
                dropped=dead,
                vA_raw=vA_raw,
                vL_raw=vL_raw,
            )
        mg = float(p["max_grow"])  # times each shoot's own factor (vigor_sd; 1 without it: max_grow exactly)
        return np.minimum(vA_raw, mg * s.vcap[ids]), np.minimum(vL_raw, mg * s.lat_vcap[ids])

    def _grow_shoots(self, c: int, bp: _Basipetal, dead, vA, vL) -> None:
        """Step 6: the buds that grow (an apical bud with at least one metamer, a lateral bud
        with vigor above 1; leader death and sympodial branching take apical buds away), in
        draw order (by bearing segment, apical before lateral), checked against
        ``max_live_segments`` and built."""
        p, s, rng = self.p, self.s, self.rng
        ids = bp.ids
        keep = ~dead
        may_grow = keep & ~s.short[ids]  # a short shoot's buds never grow
        grow_a = may_grow & (bp.api_state0 == BUD) & (np.floor(vA) >= 1.0)
        grow_l = may_grow & (bp.lat_state0 == BUD) & (vL > 1.0)
        if p["leader_death"] > 0.0 and c > p["death_delay"]:
            # draw 1b (an addition): a growing apical bud dies with probability leader_death; the
            # lateral buds at its node take over (with opposite buds: a fork). Drawn only when
            # the probability is positive, so trees without it keep their draws.
            ga = np.flatnonzero(grow_a)
            # the stem's own buds die at stem_death x the rate (1: as every leader's, the same draws)
            rate = np.where(s.order[ids[ga]] == 0, p["leader_death"] * p["stem_death"], p["leader_death"])
            died = ga[rng.random(ga.size) < rate]
            s.api_state[ids[died]] = EMPTY
            grow_a[died] = False
        if self.sympodial:
            s.api_state[ids[keep & (bp.api_state0 == BUD)]] = EMPTY
            grow_a[:] = False

        # shoots ordered by bearing segment, apical before lateral
        ia = np.flatnonzero(grow_a)
        il = np.flatnonzero(grow_l)
        key = np.concatenate([2 * ia, 2 * il + 1])
        srt = np.argsort(key, kind="stable")
        sl = np.concatenate([ia, il])[srt]  # local ids of bearing segments
        lateral = np.concatenate([np.zeros(ia.size, bool), np.ones(il.size, bool)])[srt]
        vig = np.concatenate([vA[ia], vL[il]])[srt]
        bearing = ids[sl]
        planned = np.floor(vig).astype(np.int64)
        short = np.zeros(bearing.size, bool)
        if p["short_shoot"] > 0.0:
            # draw 1c (an addition): a lateral shoot is a short shoot with probability
            # short_shoot: one internode that never grows on (its buds take light and vigor but
            # do not grow). Drawn only when the probability is positive, so trees without it keep
            # their draws.
            li = np.flatnonzero(lateral)
            short[li[rng.random(li.size) < p["short_shoot"]]] = True
            planned[short] = 1
        n_live = int(ids.size - np.count_nonzero(dead))
        if self.buds_per_node > 1:  # bud nodes are not segments of the tree
            n_live -= int(np.count_nonzero(s.twin[ids] & ~dead))
        if n_live + int(planned.sum()) > self.max_live:
            raise GrowthFailure(
                "too_many_segments",
                f"cycle {c} would grow {int(planned.sum())} metamers on {n_live} "
                f"live segments (max_live_segments = {self.max_live})",
            )
        self._build_shoots(c, bearing, lateral, vig, planned, short)

    def _build_shoots(self, c, bearing, lateral, vig, planned, short) -> None:
        p, s, rng = self.p, self.s, self.rng
        m = bearing.size
        # draws 2 and 3 (blocks consumed even when the sd is 0)
        z_ang = rng.standard_normal(int(np.count_nonzero(lateral)))
        z_trop = rng.standard_normal(m)
        # 6. target directions from the field after the drops, before the new shadows
        grad = self.field.gradient(s.start[bearing], p["sample_rad"]) if m else np.zeros((0, 3))
        t = p["reorient"] * grad
        eta = p["tropism"] + p["tropism_sd"] * z_trop
        if p["gap_lean"] > 0.0:  # an addition (B.10): shoots rise towards the sky of the gap, not the zenith
            lean = math.radians(p["gap_lean"])
            sky = np.r_[math.sin(lean) * self.field.gap_dir, math.cos(lean)]  # gap_dir: gap_azimuth's unit vector
            t += eta[:, None] * np.where(eta[:, None] > 0.0, sky, [0.0, 0.0, 1.0])  # a sag stays downwards
        else:
            t[:, 2] += eta
        tn = _norm(t)
        tau = np.minimum(tn, p["redir_strength"])
        that = np.where(tn[:, None] > 0, t / np.where(tn > 0, tn, 1.0)[:, None], 0.0)
        # 7. initial frames
        h = s.h[bearing].copy()
        u = s.u[bearing].copy()
        ang = np.full(m, np.nan)
        if z_ang.size:
            li = np.flatnonzero(lateral)
            ang[li] = p["branch_angle"] + p["branch_angle_sd"] * z_ang
            if p["relay_angle"] != 1.0:
                # an addition (B.10): a lateral at a node whose leader died or was shed is a relay
                # shoot and leaves at relay_angle x its angle; it draws nothing
                ang[li] *= np.where(self._leader_lost(bearing[li]), p["relay_angle"], 1.0)
            hl = _unit(rotate(h[li], u[li], np.radians(ang[li])))
            ul = rotate(u[li], hl, np.full(li.size, math.radians(p["nonplanar_twist"])))
            h[li] = hl
            u[li] = ul
        pos = s.start[bearing] + s.length[bearing, None] * s.h[bearing]
        seg_len = (
            np.where(short, p["short_length"], np.where(planned > 0, vig / np.maximum(planned, 1), 0.0))
            * p["node_length"]
        )
        order = s.order[bearing] + lateral
        stem = np.flatnonzero(order == 0) if self.guide is not None else np.empty(0, np.int64)
        if stem.size:
            # stem_guide (an addition, B.10): the stem's shoot heads for the point of the path one
            # shoot length beyond the stem's arc length, blended with its own target by stem_guide
            w = p["stem_guide"]
            g = self.guide.at(self.stem_arc + planned[stem] * seg_len[stem]) - pos[stem]
            g = (1.0 - w) * that[stem] + w * g / np.maximum(_norm(g), 1e-12)[:, None]
            that[stem] = g / np.maximum(_norm(g), 1e-12)[:, None]
            tau[stem] = (1.0 - w) * tau[stem] + w
        last = np.full(m, -1, dtype=np.int64)
        built = np.zeros(m, dtype=np.int64)
        first = np.full(m, -1, dtype=np.int64)
        stopped = np.zeros(m, dtype=bool)
        half = 0.5 * p["span"]
        total = int(planned.sum())
        s.reserve(s.n + total * self.buds_per_node)
        lo = s.n
        # the cap factor of each shoot's axis: a lateral shoot's from its bud, an apical one its bearer's
        axis_cap = np.where(lateral, s.lat_vcap[bearing], s.vcap[bearing])
        new_starts = []
        for k in range(int(planned.max()) if m else 0):  # at most floor(max_grow) but for vigor_sd's caps
            want = (planned > k) & ~stopped
            if not want.any():
                break
            q = pos[want]
            out = (
                (q[:, 0] < -half)
                | (q[:, 0] > half)
                | (q[:, 1] < -half)
                | (q[:, 1] > half)
                | (q[:, 2] < 0.0)
                | (q[:, 2] > p["span"])
            )
            wi = np.flatnonzero(want)
            stopped[wi[out]] = True
            act = wi[~out]
            z_phy = rng.standard_normal(act.size)  # draw 4: one per active shoot
            if act.size == 0:
                continue
            # (ii) partial rotation of the frame towards the target, (iii) the clone noise's bend
            # and the phyllotaxis roll: compiled loops (kernels.py), numpy's arctan2 between them
            ax, sn, cs = turn_geometry(h, that, act)
            th = np.zeros(act.size)
            ti = np.flatnonzero(sn > 1e-12)
            th[ti] = tau[act[ti]] * np.arctan2(sn[ti], cs[ti])
            bend = np.empty(0)
            if p["heading_sd"] > 0.0:
                # clone noise (an addition): each metamer of a branch bends by N(0, heading_sd)
                # about its up vector, whose phyllotaxis roll turns the bending plane from metamer
                # to metamer; the stem (order 0) stays straight, as a leader held by gravitropism
                # does. Drawn only when the sd is positive, so trees without it are unchanged.
                z_head = rng.standard_normal(act.size)
                bend = np.radians(p["heading_sd"] * z_head) * (order[act] > 0)
            phi = np.radians(p["phyllotaxis"] + p["phyllotaxis_sd"] * z_phy)
            advance_frames(h, u, act, ax, sn, th, bend, phi)
            ha, ua = h[act], u[act]
            # (iv) append the metamers
            nid = s.n + np.arange(act.size)
            new = slice(s.n, s.n + act.size)  # the rows nid, as a slice (cheaper to write)
            par = bearing[act] if k == 0 else last[act]
            s.append(new, pos[act], ha, ua, seg_len[act], p["init_width"], par, lateral[act] & (k == 0), order[act], c)
            s.vcap[new] = axis_cap[act]
            if k == 0:
                la = lateral[act]
                s.lat_state[par[la]] = CHILD
                s.lat_child[par[la]] = nid[la]
                s.api_state[par[~la]] = CHILD
                s.api_child[par[~la]] = nid[~la]
                first[act] = nid
            else:
                s.api_state[par] = CHILD
                s.api_child[par] = nid
            new_starts.append(pos[act].copy())
            pos[act] = pos[act] + seg_len[act, None] * ha
            last[act] = nid
            built[act] += 1
            s.n += act.size
            if self.buds_per_node > 1:
                last[act] = self._add_bud_nodes(c, nid, pos[act], ha, ua, order[act], axis_cap[act])
        self._draw_lateral_buds(lo)
        if stem.size:
            self.stem_arc += float((built[stem] * seg_len[stem]).sum())
        tips = last[last >= 0]
        s.api_state[tips] = BUD
        if short.any():  # a short shoot's metamer and its bud nodes never grow on
            node = first[short & (first >= 0)]
            s.short[node] = True
            for _ in range(self.buds_per_node - 1):
                node = s.api_child[node]
                s.short[node] = True
        self.created = s.n
        # 8. shadows of all new metamers, from their starts, in one batch
        if new_starts:
            self.field.cast(np.concatenate(new_starts))
        if self.record:
            self.last_shoots = ShootRecord(
                bearing=bearing,
                lateral=lateral,
                vigor=vig,
                planned=planned,
                built=built,
                first=first,
                metamer_length=seg_len,
                branch_angle=ang,
                target=that,
                tau=tau,
            )

    def _leader_lost(self, bearing: np.ndarray) -> np.ndarray:
        """Whether the node of each bearing segment has lost its leader: the apical slot at the
        end of the node (past its bud nodes) is empty (the bud died) or a stub (shed)."""
        s = self.s
        end = bearing.copy()
        for _ in range(self.buds_per_node - 1):  # walk on through the node's bud nodes
            kid = np.where(s.api_state[end] == CHILD, s.api_child[end], -1)
            on = (kid >= 0) & s.twin[np.maximum(kid, 0)]
            end = np.where(on, kid, end)
        return np.isin(s.api_state[end], (EMPTY, STUB))

    def _add_bud_nodes(self, c, nid, end, h, u, order, cap=1.0) -> np.ndarray:
        """Further lateral buds at the ends of the metamers ``nid`` (``buds_per_node`` > 1, an
        addition to the papers' model): a chain of ``buds_per_node - 1`` zero-length *bud nodes*
        on each metamer's apical slot, each holding one lateral bud whose up vector is the
        metamer's rolled by ``360 * j / buds_per_node`` degrees about the heading, so the buds
        of a node point to evenly spaced sides (2: opposite; 3 or more: a whorl). The axis goes
        on from the last bud node. Bud nodes take part in the light, allocation and pipe-model
        passes like segments (the Borchert-Honda split is applied at each of them in turn), cast
        no shadow and are folded away in the output tree. Returns the last node of each chain."""
        s = self.s
        prev = nid
        m = nid.size
        for j in range(1, self.buds_per_node):
            tid = s.n + np.arange(m)
            new = slice(s.n, s.n + m)
            s.append(
                new,
                end,
                h,
                rotate(u, h, np.full(m, 2.0 * math.pi * j / self.buds_per_node)),
                0.0,
                self.p["init_width"],
                prev,
                False,
                order,
                c,
            )
            s.twin[new] = True
            s.vcap[new] = cap
            s.api_state[prev] = CHILD
            s.api_child[prev] = tid
            s.n += m
            prev = tid
        return prev

    # -------------------------------------------------------------- driver
    def run(self, max_iter: int) -> None:
        for c in range(1, int(max_iter) + 1):
            self.cycle = c
            if c == 1:
                self._seed()
            else:
                self._grow_cycle(c)
            n_live = int(np.count_nonzero(self.s.alive[: self.s.n]))
            if c >= 5 and n_live < 10:
                raise GrowthFailure("collapsed", f"{n_live} live segments at the end of cycle {c} (< 10)")
            if self.on_step is not None:
                self.on_step(c, StepView(self))


class StepView:
    """Read-only view passed to ``on_step(cycle, view)`` after each cycle.

    Valid only during the callback (the run continues afterwards): copy what you keep.

    Attributes
    ----------
    cycle : int
    lam : float
        Apical control lambda of this cycle.
    field : LightField
        The live light field (do not modify).
    alloc : AllocationRecord or None
        The passes of this cycle (None in the seed cycle).
    shoots : ShootRecord or None
        The shoots built this cycle.
    """

    def __init__(self, run: SOTGrowth):
        self._run = run
        self.cycle = run.cycle
        self.lam = run.lam
        self.field = run.field
        self.alloc = run.last_alloc if run.cycle > 1 else None
        self.shoots = run.last_shoots if run.cycle > 1 else None
        self._tree = None

    @property
    def live_ids(self) -> np.ndarray:
        return self._run.s.live

    @property
    def store(self) -> SegmentStore:
        return self._run.s

    @property
    def n_live(self) -> int:
        return int(self.live_ids.size)

    def tree(self):
        """The output tree at this cycle (final width update applied to a copy)."""
        if self._tree is None:
            self._tree = self._run_tree()
        return self._tree

    def _run_tree(self):
        return build_tree(self._run, status="ok")


#: the stream of the shoots' cap factors (vigor_sd): a generator of its own, as the stubs'
VIGOR_STREAM = 0x716
#: the stream of the lateral buds' aborts (bud_abort): a generator of its own too
ABORT_STREAM = 0xAB0


class _Guide:
    """A polyline (points from the stem base, base first) read by arc length: :meth:`at` gives the
    point at each arc length, on the line through the last two points beyond the end."""

    def __init__(self, points):
        pts = np.asarray(points, dtype=float).reshape(-1, 3)
        step = np.linalg.norm(np.diff(pts, axis=0), axis=1)
        keep = np.r_[True, step > 1e-9]  # repeated points carry no direction
        self.pts = pts[keep]
        self.arc = np.r_[0.0, np.cumsum(step[step > 1e-9])]  # two distinct points at least (the settings' check)
        d = self.pts[-1] - self.pts[-2]
        self.end_dir = d / np.linalg.norm(d)

    def at(self, a: np.ndarray) -> np.ndarray:
        a = np.asarray(a, dtype=float)
        out = np.stack([np.interp(a, self.arc, self.pts[:, k]) for k in range(3)], axis=-1)
        beyond = np.maximum(a - self.arc[-1], 0.0)
        return out + beyond[..., None] * self.end_dir


def _own_stream(seed, key: int) -> np.random.Generator:
    """A generator of the run's seed and a stream of its own (``key``), apart from the growth's draws."""
    return np.random.default_rng(np.random.SeedSequence(int(seed), spawn_key=(key,)))


#: the stream of the stubs' draws: a generator of its own, so that stubs leave the growth's draws alone
STUB_STREAM = 0x57B


def _stubs(run: SOTGrowth):
    """The dead stubs of shed branches on the living tree (``shed_stub``, an addition; output only).

    A branch shed at a slot of a living segment (a STUB slot) leaves, with probability
    ``shed_stub``, its base: its first metamer's start and heading, broken at a uniform fraction
    in [0.1, 1] of that metamer's length, with the width the branch had when it was shed (the
    width the pipe model keeps for the slot). The two uniforms of a shed branch are drawn from a
    generator of the run's seed and its own stream, indexed by the branch's segment id, so a
    branch keeps or loses its stub alike at every cycle's output and the growth draws nothing.

    Returns ``(bearer, child, width, frac)``: the bearing segment (a metamer, bud nodes folded
    away), the shed segment, its width and the kept fraction of its length.
    """
    s = run.s
    ids = s.live
    bearer, child, width = [], [], []
    for state, kid, stub_w in ((s.lat_state, s.lat_child, s.lat_stub_w), (s.api_state, s.api_child, s.api_stub_w)):
        on = ids[(state[ids] == STUB) & (kid[ids] >= 0)]
        bearer.append(on)
        child.append(kid[on])
        width.append(stub_w[on])
    b, c, w = np.concatenate(bearer), np.concatenate(child), np.concatenate(width)
    real = (s.length[c] > 0.0) & ~s.twin[c]  # a shed bud node has no wood to leave
    b, c, w = b[real], c[real], w[real]
    u = _own_stream(run.seed, STUB_STREAM).random((s.n, 2))
    keep = u[c, 0] < run.p["shed_stub"]
    b, c, w = b[keep], c[keep], w[keep]
    for _ in range(run.buds_per_node - 1):  # a stub on a bud node sits on the node's metamer
        b = np.where(s.twin[b], s.parent[b], b)
    return b, c, w, 0.1 + 0.9 * u[c, 1]


def build_tree(run: SOTGrowth, status: str = "ok") -> Tree:
    """The output :class:`Tree` of a run's current state, after a width-only basipetal update
    (applied to a copy of the widths). Raises ``GrowthFailure('no_root')`` if nothing lives."""
    s = run.s
    if run.s.n == 0 or not s.alive[0]:
        raise GrowthFailure("no_root", "the tree has no living segments")
    ids, width = run.widths()
    par = s.parent[ids]
    ext_g = np.where(s.api_state[ids] == CHILD, s.api_child[ids], -1)
    if run.buds_per_node > 1:
        # fold the bud nodes away: a segment's parent is its nearest segment ancestor, and a
        # metamer continues into the metamer after its bud nodes (or nothing, if the axis ends)
        for _ in range(run.buds_per_node - 1):
            up = (par >= 0) & s.twin[np.maximum(par, 0)]
            par = np.where(up, s.parent[np.maximum(par, 0)], par)
            on = (ext_g >= 0) & s.twin[np.maximum(ext_g, 0)]
            nxt = np.where(s.api_state[np.maximum(ext_g, 0)] == CHILD, s.api_child[np.maximum(ext_g, 0)], -1)
            ext_g = np.where(on, nxt, ext_g)
        keep = ~s.twin[ids]
        ids, width, par, ext_g = ids[keep], width[keep], par[keep], ext_g[keep]
    loc = np.full(s.n, -1, dtype=np.int64)
    loc[ids] = np.arange(ids.size)
    parent = remap_ids(par, loc)
    ext = remap_ids(ext_g, loc)
    start, h, length, age = s.start[ids], s.h[ids], s.length[ids], run.cycle - s.born[ids]
    if run.p.get("shed_stub", 0.0) > 0.0:
        b, c, w, frac = _stubs(run)
        start = np.concatenate([start, s.start[c]])
        h = np.concatenate([h, s.h[c]])
        length = np.concatenate([length, frac * s.length[c]])
        width = np.concatenate([width, w])
        parent = np.concatenate([parent, loc[b]])
        ext = np.concatenate([ext, np.full(c.size, -1, dtype=np.int64)])
        age = np.concatenate([age, run.cycle - s.born[c]])
    settings = getattr(run, "settings", None)
    order_mode = getattr(settings, "order_mode", "growth")
    meta = {
        "model": "sot",
        "model_version": MODEL_VERSION,
        "params": dict(run.p),
        "seed": run.seed,
        "status": status,
        "cycles": int(run.cycle),
        "order_mode": order_mode,
        "units": {"length": "m", "angle": "deg"},
        "frame": "Z up, stem base at the origin",
        "segments_created": int(s.n),
    }
    tree = Tree(
        start,
        h,
        length,
        0.5 * width,
        parent,
        ext,
        topology="thickest" if order_mode == "thickest" else "source",
        extras={"age": age.astype(np.int64)},
        metadata=meta,
    )
    # C: is_lateral = starts a new branch (in "growth" mode: the first metamer of a lateral shoot)
    tree.extras["is_lateral"] = (tree.parent >= 0) & (tree.position_in_branch == 0)
    if run.p.get("prune_tips", 0.0) > 1.0:
        # a simplified QSM's view (an addition, output only): in the pipe model a shoot carrying
        # n growing tips is init_width * n^(1/pipe_exp) thick, so the shoots that carry fewer than
        # prune_tips go with all beyond them, whatever the tree's scale (the edge a hair below that
        # width, so that a shoot of exactly prune_tips tips stays whatever the rounding)
        edge = 0.5 * run.p["init_width"] * run.p["prune_tips"] ** (1.0 / run.p["pipe_exp"])
        tree = tree.pruned(edge * (1.0 - 1e-9))
    return tree
