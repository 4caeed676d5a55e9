"""The self-organizing tree (SOT) growth engine (docs/models.md part B): the papers' growth cycle.

Structure of arrays, one row per segment (metamer) ever created; rows are never reused, so the
creation order is a parent-before-child order. Every per-cycle computation is vectorised over
segments, buds or shoots; Python loops run only over cycles, depth levels (basipetal pass),
pointer-jumping rounds (acropetal pass) and metamer steps (shoot construction).

The additions to the papers' model are growth forms (:mod:`bforest_sot.forms`): the cycle calls
the hooks of those that act on a run and holds no form's branch.

Random draws of the cycle, all from one ``numpy.random.Generator(PCG64(seed))`` (docs/models.md B.7):

* init: ``n_vox**3`` uniforms for ``ran`` in C order of (i, j, k) (drawn even when ran = 0;
  skipped with ``advance`` when the initial field of this seed is cached: the same stream after)
* per growth cycle c = 2 .. max_iter, in this order:

  1. one standard normal for lambda (``lambda_sd``);
  2. one standard normal per growing lateral shoot (``branch_angle_sd``);
  3. one standard normal per growing shoot (``tropism_sd``);
  4. at each metamer step k, one standard normal per shoot still active after the wall check
     (``phyllotaxis_sd``).

  Shoots are ordered by bearing segment, the apical shoot before the lateral one. A block is
  drawn even when its sd is 0; no draw depends on ``max_iter``, so a run of length t equals the
  ``on_step`` snapshot at t of any longer run (prefix property). A form that draws from this
  generator (``GROWTH_STREAM``) draws at its hook: dying leaders after draw 1, short shoots
  before draw 2, winding after each draw 4 (docs/models.md B.10); other forms draw from streams
  of their own.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from bforest_core.errors import SimulationFailed
from bforest_core.tree import Tree, group_by_level, remap_ids

from .forms.base import HOOKS, form_generator, overrides
from .kernels import advance_frames, sum_levels, turn_geometry
from .light import LightField

MODEL_VERSION = "1.0"

EMPTY, BUD, CHILD, STUB = 0, 1, 2, 3


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
    STUB -> (0, 0, w); EMPTY -> (0, 0, -). ``N = 1 + N_m + N_l``, ``Q = Q_m + Q_l``, ``D`` of
    :func:`_denominators`, ``d^n = sum of w^n over CHILD and STUB slots`` or ``init_width^n`` if
    there is none. Arguments, each (m,): the slot states (EMPTY, BUD, CHILD, STUB), the local index
    of the child in a CHILD slot, the bud exposures (read at a BUD), the stub widths (read at a
    STUB), each node's depth (root 0); then the floats lam, kappa, pipe_exp and init_width.

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
    N, Q, W = V[:m, 0], V[:m, 1], V[:m, 2]
    Nm = a_bud + V[ac, 0]
    Qm = np.where(a_bud, q_api, 0.0) + V[ac, 1]
    Nl = l_bud + V[lc, 0]
    Ql = np.where(l_bud, q_lat, 0.0) + V[lc, 1]
    D = _denominators(Nm, Qm, Nl, Ql, lam, kappa)
    woody = np.isin(api_state, (CHILD, STUB)) | np.isin(lat_state, (CHILD, STUB))
    width = np.where(woody, W ** (1.0 / pipe_exp), float(init_width))
    return {"N": N.copy(), "Q": Q.copy(), "D": D, "W": W.copy(), "width": width, "Nm": Nm, "Qm": Qm, "Nl": Nl, "Ql": Ql}


def _denominators(Nm, Qm, Nl, Ql, lam, kappa):
    """``D = lam N_m (Q_m/N_m)^kappa + (1 - lam) N_l (Q_l/N_l)^kappa`` (terms with N = 0 omitted;
    D = 1 when neither slot holds a BUD or CHILD)."""
    if kappa == 1.0:
        D = lam * Qm + (1.0 - lam) * Ql
    else:
        D = lam * np.where(Nm > 0, Nm * (Qm / np.maximum(Nm, 1.0)) ** kappa, 0.0) + (1.0 - lam) * np.where(
            Nl > 0, Nl * (Ql / np.maximum(Nl, 1.0)) ** kappa, 0.0
        )
    return np.where((Nm + Nl) > 0, D, 1.0)


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
    # a zero-length node holding one more lateral bud (forms.buds): no wood, so it casts no
    # shadow, is no segment of the tree (max_live_segments) and is folded away in the output
    "bud_node": (np.bool_, 0),
    # a segment whose buds never grow on (a short shoot's, forms.short_shoots)
    "dormant": (np.bool_, 0),
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
        self.dormant[new] = False

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


@dataclass
class BudChoice:
    """Which buds of the segments alive at a cycle's start (``ids``) grow this cycle: an apical
    bud with at least one metamer of vigor (``grow_a``), a lateral one with vigor above 1
    (``grow_l``), on segments not dropped (``keep``) and not dormant. ``select_buds`` hooks may
    change ``grow_a`` and ``grow_l`` in place."""

    ids: np.ndarray
    keep: np.ndarray
    api_state0: np.ndarray
    grow_a: np.ndarray
    grow_l: np.ndarray


class Shoots:
    """One cycle's growing shoots, in draw order (by bearing segment, apical before lateral): what
    the forms' shoot hooks see and change, and the inspection record of the cycle's shoots
    (``StepView.shoots``).

    Made with ``bearing`` (global id of the bearing segment), ``lateral`` (bool), ``vigor`` (capped
    bud vigor v) and ``planned`` (floor(v) metamers); before the ``shape_shoots`` hooks the growth
    adds ``order``, the frames ``h`` and ``u``, ``branch_angle`` (drawn, deg; NaN for apical shoots),
    the start ``pos``, ``metamer_length``, the unit ``target`` direction (0 if |t| = 0) and the
    turning share ``tau``; as it builds them ``first`` (global id of the first metamer, -1 if
    none), ``last`` (the node each axis goes on from), ``built`` (metamers built: fewer than
    planned only at the walls) and ``stopped``.
    """

    def __init__(self, bearing: np.ndarray, lateral: np.ndarray, vigor: np.ndarray, planned: np.ndarray):
        self.bearing, self.lateral, self.vigor, self.planned = bearing, lateral, vigor, planned


# ------------------------------------------------------------------------------------------------
# the growth run
# ------------------------------------------------------------------------------------------------


class SOTGrowth:
    """One SOT run: the papers' growth cycle (docs/models.md B.5), with hooks for the growth forms.

    ``run()`` executes cycles 1 .. max_iter; failures raise :class:`GrowthFailure` and leave the
    state in place for the partial tree. ``settings`` is the model's validated settings object
    (``SOT.Settings``), ``forms`` the growth-form classes (:mod:`bforest_sot.forms`): those that
    act on this run are made once, each with its generator, and their hooks are called in order;
    ``model`` the component's name (a model with forms of its own has another).
    """

    def __init__(
        self, p: dict, seed: int, settings, forms=(), *, model="sot", on_step: Callable | None = None, record=False
    ):
        self.p = p
        self.model = model  # the component's name, for the output's metadata
        self.seed = seed
        self.settings = settings
        self.max_live = int(settings.max_live_segments)
        self.on_step = on_step
        self.record = record or on_step is not None
        self.rng = np.random.Generator(np.random.PCG64(seed))
        self.forms = [f(self, form_generator(f, seed, self.rng)) for f in forms if f.acts(p, settings)]
        self.hooks = {h: [getattr(f, h) for f in self.forms if overrides(f, h)] for h in HOOKS}
        self.rows_per_metamer = 1 + sum(f.extra_rows for f in self.forms)
        self.field = self._light_field()
        self.s = SegmentStore()
        self.age = 0.0
        self.cycle = 0
        self.lam = float(p["init_lambda"])
        self.created = 0
        self.last_alloc: AllocationRecord | None = None
        self.last_shoots: Shoots | None = None

    def _light_field(self) -> LightField:
        """Draw 1: the initial field's uniforms; the field of a seed seen before comes from the
        field's cache, and the generator then skips the n3 draws it was made of (PCG64 advance:
        the same stream after it)."""
        p, seed = self.p, self.seed
        n3 = int(round(p["span"] / p["voxel_size"])) ** 3
        field = LightField(
            p["span"],
            p["voxel_size"],
            int(p["depth"]),
            p["spread"],
            p["shadow_a"],
            p["shadow_b"],
            p["ran"],
            p["vert"],
            lambda: self.rng.random(n3),
            initial_key=("sot", int(seed)) if isinstance(seed, (int, np.integer)) else None,
            filters=tuple(self.hooks["transmission"]),
        )
        if field.from_cache:
            self.rng.bit_generator.advance(n3)
        return field

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
        s.n = 1
        for hook in self.hooks["seeded"]:
            hook()
        self._rows_made(0)
        self.field.cast(s.start[:1])  # falls below ground: no effect

    def _rows_made(self, lo: int) -> None:
        self.created = self.s.n
        for hook in self.hooks["rows_made"]:
            hook(lo)

    def node_rows(self, rows: np.ndarray):
        """Yield ``rows`` and then, step by step, the bud nodes of their nodes (the rows that
        follow a metamer on its apical slot, forms.buds), as arrays of row ids."""
        s = self.s
        while rows.size:
            yield rows
            kid = np.where(s.api_state[rows] == CHILD, s.api_child[rows], -1)
            rows = kid[(kid >= 0) & s.bud_node[np.maximum(kid, 0)]]

    # -------------------------------------------------------------- passes on the living set
    def _compact(self):
        s = self.s
        ids = s.live
        loc = np.full(s.n, -1, dtype=np.int64)
        loc[ids] = np.arange(ids.size)
        lpar = remap_ids(s.parent[ids], loc)
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
        lam = self._cycle_lambda(c)  # 1
        bp = self._basipetal(lam)  # 2, 3
        v, v_base, dead = self._allocate_and_drop(bp, lam)  # 4
        vA, vL = self._vigor(c, bp, lam, v, v_base, dead)  # 5
        self._grow_shoots(c, bp, dead, vA, vL)  # 6

    def _cycle_lambda(self, c: int) -> float:
        """Step 1: this cycle's apical control (schedule plus noise: the cycle's draw 1), then
        the forms' ``begin_cycle`` and ``cycle_lambda`` hooks (k buds per node: the share of one
        of a node's k splits)."""
        p = self.p
        self.age = min(self.age + 1.0, p["delay"] + p["transition"])
        lam = lambda_schedule(self.age, p["init_lambda"], p["targ_lambda"], p["delay"], p["transition"])
        z_lam = self.rng.standard_normal()
        lam = float(np.clip(lam + p["lambda_sd"] * z_lam, 0.0, 1.0))
        self.lam = lam
        for hook in self.hooks["begin_cycle"]:
            hook(c)
        for hook in self.hooks["cycle_lambda"]:
            lam = hook(lam)
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
        field; bud nodes cast no shadow). Returns ``(v, v_base, dropped)``."""
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
            gone = gone[~s.bud_node[gone]]
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
        mg = float(p["max_grow"])
        return np.minimum(vA_raw, mg), np.minimum(vL_raw, mg)

    def _grow_shoots(self, c: int, bp: _Basipetal, dead, vA, vL) -> None:
        """Step 6: the buds that grow (the forms' ``select_buds`` hooks may take some away), the
        shoots in draw order (the ``plan_shoots`` hooks may change their metamers), checked
        against ``max_live_segments`` and built."""
        s, ids = self.s, bp.ids
        keep = ~dead
        may_grow = keep & ~s.dormant[ids]
        grow_a = may_grow & (bp.api_state0 == BUD) & (np.floor(vA) >= 1.0)
        grow_l = may_grow & (bp.lat_state0 == BUD) & (vL > 1.0)
        buds = BudChoice(ids, keep, bp.api_state0, grow_a, grow_l)
        for hook in self.hooks["select_buds"]:
            hook(c, buds)
        shoots = _in_draw_order(ids, buds.grow_a, buds.grow_l, vA, vL)
        for hook in self.hooks["plan_shoots"]:
            hook(c, shoots)
        # bud nodes are not segments of the tree
        n_live = int(ids.size - np.count_nonzero(dead) - np.count_nonzero(s.bud_node[ids] & ~dead))
        total = int(shoots.planned.sum())
        if n_live + total > self.max_live:
            raise GrowthFailure(
                "too_many_segments",
                f"cycle {c} would grow {total} metamers on {n_live} "
                f"live segments (max_live_segments = {self.max_live})",
            )
        self._build_shoots(c, shoots)

    def _build_shoots(self, c: int, sh: Shoots) -> None:
        """Steps 6-8 for the shoots ``sh``: targets and frames, the forms' ``shape_shoots``, the
        metamers step by step, then the new tips become buds and the new shadows fall."""
        s = self.s
        self._frames(sh)
        for hook in self.hooks["shape_shoots"]:
            hook(sh)
        m = sh.bearing.size
        sh.last = np.full(m, -1, dtype=np.int64)
        sh.built = np.zeros(m, dtype=np.int64)
        sh.first = np.full(m, -1, dtype=np.int64)
        sh.stopped = np.zeros(m, dtype=bool)
        sh.starts = []  # the new metamers' starts, for their shadows
        s.reserve(s.n + int(sh.planned.sum()) * self.rows_per_metamer)
        lo = s.n
        for k in range(int(sh.planned.max()) if m else 0):
            if not self._metamer_step(c, k, sh):
                break
        self._rows_made(lo)
        s.api_state[sh.last[sh.last >= 0]] = BUD
        for hook in self.hooks["shoots_built"]:
            hook(sh)
        self.created = s.n
        if sh.starts:  # 8. shadows of all new metamers, from their starts, in one batch
            self.field.cast(np.concatenate(sh.starts))
        if self.record:
            self.last_shoots = sh

    def _frames(self, sh: Shoots) -> None:
        """Draws 2 and 3 (blocks consumed even when the sd is 0), the target directions from the
        field after the drops and before the new shadows (6), the initial frames (7), the shoots'
        starts and metamer lengths."""
        p, s, rng = self.p, self.s, self.rng
        bearing, lateral = sh.bearing, sh.lateral
        m = bearing.size
        z_ang = rng.standard_normal(int(np.count_nonzero(lateral)))
        z_trop = rng.standard_normal(m)
        grad = self.field.gradient(s.start[bearing], p["sample_rad"]) if m else np.zeros((0, 3))
        t = p["reorient"] * grad
        t[:, 2] += p["tropism"] + p["tropism_sd"] * z_trop
        tn = _norm(t)
        sh.tau = np.minimum(tn, p["redir_strength"])
        sh.target = np.where(tn[:, None] > 0, t / np.where(tn > 0, tn, 1.0)[:, None], 0.0)
        sh.h, sh.u = s.h[bearing].copy(), s.u[bearing].copy()
        sh.branch_angle = np.full(m, np.nan)
        if z_ang.size:
            li = np.flatnonzero(lateral)
            sh.branch_angle[li] = p["branch_angle"] + p["branch_angle_sd"] * z_ang
            hl = _unit(rotate(sh.h[li], sh.u[li], np.radians(sh.branch_angle[li])))
            sh.u[li] = rotate(sh.u[li], hl, np.full(li.size, math.radians(p["nonplanar_twist"])))
            sh.h[li] = hl
        sh.pos = s.start[bearing] + s.length[bearing, None] * s.h[bearing]
        sh.metamer_length = np.where(sh.planned > 0, sh.vigor / np.maximum(sh.planned, 1), 0.0) * p["node_length"]
        sh.order = s.order[bearing] + lateral

    def _metamer_step(self, c: int, k: int, sh: Shoots) -> bool:
        """Metamer ``k`` of every shoot that plans one and has not met a wall: draw 4, the turn
        towards the target, the forms' bends and the phyllotaxis roll (compiled loops,
        kernels.py, numpy's arctan2 between them), the new rows. False when none is left."""
        p = self.p
        want = (sh.planned > k) & ~sh.stopped
        if not want.any():
            return False
        half = 0.5 * p["span"]
        q = sh.pos[want]
        out = (q[:, 0] < -half) | (q[:, 0] > half) | (q[:, 1] < -half) | (q[:, 1] > half)
        out |= (q[:, 2] < 0.0) | (q[:, 2] > p["span"])
        wi = np.flatnonzero(want)
        sh.stopped[wi[out]] = True
        act = wi[~out]
        z_phy = self.rng.standard_normal(act.size)  # draw 4: one per active shoot
        if act.size == 0:
            return True
        ax, sn, cs = turn_geometry(sh.h, sh.target, act)
        th = np.zeros(act.size)
        ti = np.flatnonzero(sn > 1e-12)
        th[ti] = sh.tau[act[ti]] * np.arctan2(sn[ti], cs[ti])
        bends = [hook(sh, act) for hook in self.hooks["bend"]]
        bend = functools.reduce(np.add, bends) if bends else np.empty(0)
        phi = np.radians(p["phyllotaxis"] + p["phyllotaxis_sd"] * z_phy)
        advance_frames(sh.h, sh.u, act, ax, sn, th, bend, phi)
        self._append_metamers(c, k, sh, act)
        return True

    def _append_metamers(self, c: int, k: int, sh: Shoots, act: np.ndarray) -> None:
        """The rows of the metamers ``k`` of the shoots ``act``, linked into their bearers' slots,
        and the forms' ``metamers_added`` hooks (bud nodes after them)."""
        p, s = self.p, self.s
        ha, ua = sh.h[act], sh.u[act]
        nid = s.n + np.arange(act.size)
        new = slice(s.n, s.n + act.size)  # the rows nid, as a slice (cheaper to write)
        par = sh.bearing[act] if k == 0 else sh.last[act]
        s.append(
            new,
            sh.pos[act],
            ha,
            ua,
            sh.metamer_length[act],
            p["init_width"],
            par,
            sh.lateral[act] & (k == 0),
            sh.order[act],
            c,
        )
        if k == 0:
            la = sh.lateral[act]
            s.lat_state[par[la]] = CHILD
            s.lat_child[par[la]] = nid[la]
            s.api_state[par[~la]] = CHILD
            s.api_child[par[~la]] = nid[~la]
            sh.first[act] = nid
        else:
            s.api_state[par] = CHILD
            s.api_child[par] = nid
        sh.starts.append(sh.pos[act].copy())
        sh.pos[act] = sh.pos[act] + sh.metamer_length[act, None] * ha
        sh.last[act] = nid
        sh.built[act] += 1
        s.n += act.size
        for hook in self.hooks["metamers_added"]:
            sh.last[act] = hook(c, sh.last[act], sh.pos[act], ha, ua, sh.order[act])

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


def _in_draw_order(ids, grow_a, grow_l, vA, vL) -> Shoots:
    """The shoots of the growing buds ordered by bearing segment, apical before lateral."""
    ia = np.flatnonzero(grow_a)
    il = np.flatnonzero(grow_l)
    key = np.concatenate([2 * ia, 2 * il + 1])
    srt = np.argsort(key, kind="stable")
    sl = np.concatenate([ia, il])[srt]  # local ids of bearing segments
    lateral = np.concatenate([np.zeros(ia.size, bool), np.ones(il.size, bool)])[srt]
    vig = np.concatenate([vA[ia], vL[il]])[srt]
    return Shoots(ids[sl], lateral, vig, np.floor(vig).astype(np.int64))


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
    shoots : Shoots or None
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
            self._tree = build_tree(self._run, status="ok")
        return self._tree


# ------------------------------------------------------------------------------------------------
# the output tree
# ------------------------------------------------------------------------------------------------


def grow(run: SOTGrowth) -> Tree:
    """Run to ``max_iter`` and return the output tree; a failure raises ``SimulationFailed``
    carrying the partial tree (widths updated), when there is one."""
    try:
        run.run(run.p["max_iter"])
    except GrowthFailure as e:
        try:
            partial = build_tree(run, status=e.status)
        except GrowthFailure:
            partial = None
        raise SimulationFailed(e.status, str(e), partial) from None
    try:
        return build_tree(run, status="ok")
    except GrowthFailure as e:  # pragma: no cover - the root is never dropped
        raise SimulationFailed(e.status, str(e), None) from None


def _fold_bud_nodes(s: SegmentStore, par: np.ndarray, ext: np.ndarray):
    """A segment's parent is its nearest segment ancestor, and a metamer continues into the
    metamer after its bud nodes (or nothing, if the axis ends): the links with bud nodes folded
    away (unchanged without bud nodes)."""
    while True:
        up = (par >= 0) & s.bud_node[np.maximum(par, 0)]
        on = (ext >= 0) & s.bud_node[np.maximum(ext, 0)]
        if not (up.any() or on.any()):
            return par, ext
        par = np.where(up, s.parent[np.maximum(par, 0)], par)
        nxt = np.where(s.api_state[np.maximum(ext, 0)] == CHILD, s.api_child[np.maximum(ext, 0)], -1)
        ext = np.where(on, nxt, ext)


def build_tree(run: SOTGrowth, status: str = "ok") -> Tree:
    """The output :class:`Tree` of a run's current state, after a width-only basipetal update
    (applied to a copy of the widths). Raises ``GrowthFailure('no_root')`` if nothing lives."""
    s = run.s
    if run.s.n == 0 or not s.alive[0]:
        raise GrowthFailure("no_root", "the tree has no living segments")
    ids, width = run.widths()
    par, ext_g = _fold_bud_nodes(s, s.parent[ids], np.where(s.api_state[ids] == CHILD, s.api_child[ids], -1))
    keep = ~s.bud_node[ids]
    ids, width, par, ext_g = ids[keep], width[keep], par[keep], ext_g[keep]
    loc = np.full(s.n, -1, dtype=np.int64)
    loc[ids] = np.arange(ids.size)
    order_mode = run.settings.order_mode
    meta = {
        "model": run.model,
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
        s.start[ids],
        s.h[ids],
        s.length[ids],
        0.5 * width,
        remap_ids(par, loc),
        remap_ids(ext_g, loc),
        topology="thickest" if order_mode == "thickest" else "source",
        extras={"age": (run.cycle - s.born[ids]).astype(np.int64)},
        metadata=meta,
    )
    # C: is_lateral = starts a new branch (in "growth" mode: the first metamer of a lateral shoot)
    tree.extras["is_lateral"] = (tree.parent >= 0) & (tree.position_in_branch == 0)
    return tree
