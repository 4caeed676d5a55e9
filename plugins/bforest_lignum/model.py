"""Simplified stochastic LIGNUM (docs/models.md part A; Potapov et al. 2016, Silva Fennica).

One iteration is one year (A.5): ageing, respiration, receiver-only shadow and light,
photosynthesis, bud fate with apical dominance, provisional shoots with whorls, the growth
multiplier lambda of the carbon balance (pipe model), bending, finalising the shoots, secondary
growth, foliage ageing, roots and shedding.

Everything is vectorised over segments and buds; Python loops run only over years, depth/order
levels, shedding sweeps and Poisson redraw rounds.

Random draws (one ``numpy.random.Generator(PCG64(seed))``, fixed blocks, ascending segment
index; nothing is drawn at t = T, so a T-year run is a prefix of a longer one):

1. ``r_env``: one U(0,1) per bud-bearing segment (TN by inverse CDF);
2. ``q`` fate: one U per bud-bearing segment (also for buds killed in 1 -- fixed block size);
3. ``q``: one U per provisional shoot (shoot list: ascending parent, laterals in whorl order,
   then the apical shoot);
4. ``lr``: one U per provisional shoot;
5. gamma: one N(0,1) per apical shoot of the list whose parent has order > 0;
6. whorl turn noise: one N(0,1) per trunk bud with n_L >= 1 (``whorl_rotation_sd``);
7. delta: one N(0,1) per bent segment, by order level then segment index;
8. shedding: per order-1 candidate axis (``shed_dist`` 1: one U; 2: one Poisson, redrawn in
   further blocks for the axes where k > n, at most 100 rounds), by sweep then ``axis_id``.

Shoots discarded at any later point (l° <= 0, lambda solve, ground, ``min_len``, collision) have
consumed their draws; draws are never undone (futile years included).

Implementation choices where docs/models.md leaves room (all documented in docs/lignum-sizes.md):

* the shadow S is evaluated only at foliated receivers (a bare segment's light is 0 whatever S
  is, so the model is unchanged; ``LignumView.shadow`` is NaN there); every segment casts shadow;
* dead remnants bend like the rest of their axis (as in the original ``branch_bending``), except
  the axis's last segment;
* a provisional shoot with r° = 0 (a TN L_R draw of exactly 0) is discarded like l° <= 0 (guard);
* the collision option (A.9.5) hashes segment end points in 0.05 m cells; a shoot is rejected when
  its end cell holds a live segment that is not its ancestor and not its sibling, or the end of an
  earlier shoot of the same year (shoot-list order) that is not a sibling.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field

import numpy as np
from scipy.optimize import brentq
from scipy.special import ndtr, ndtri

from bforest_core.envelope import grown_in
from bforest_core.errors import SimulationFailed
from bforest_core.tree import Tree, group_by_level, remap_ids

from .shadow import q_max_of, shadow_fast, voxel_coords

FOLIATED = 1e-5  # W_f above this counts as foliated (light and P)
PF = np.array([1.0, 0.9, 0.7, 0.5, 0.3])  # foliage survival at ages 0-4, then 0
_TN_EPS = 1e-16
BUD_TABLE_ROWS = {
    0: (np.array([0.06, 0.03, 0.01, 0.005, 0.002, 0.0011, 0.0002]), np.array([7, 6, 5, 4, 3, 2, 1])),
    1: (np.array([0.0054, 0.0042, 0.003, 0.0023, 0.0017, 0.0013, 0.001]), np.array([7, 6, 5, 4, 3, 2, 1])),
}
EZ = np.array([0.0, 0.0, 1.0])
EX = np.array([1.0, 0.0, 0.0])


# ------------------------------------------------------------------------------------ helpers
def tn_inverse_cdf(u: np.ndarray, mean: float, sd: float) -> np.ndarray:
    """Truncated Normal TN(mean, sd) (>= 0) from uniforms u by the inverse CDF (docs/models.md section 1).

    ``x = m + s * ndtri(c + u (1 - c))`` with ``c = ndtr(-m/s)``, the argument clipped to
    [1e-16, 1 - 1e-16]; 0 where c rounds to 1; ``mean`` when ``sd == 0``.
    """
    u = np.asarray(u, dtype=np.float64)
    if sd == 0:
        return np.full(u.shape, float(mean))
    c = float(ndtr(-mean / sd))
    if c >= 1.0:
        return np.zeros(u.shape)
    arg = np.clip(c + u * (1.0 - c), _TN_EPS, 1.0 - _TN_EPS)
    return np.maximum(mean + sd * ndtri(arg), 0.0)


def _cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    out = np.empty(np.broadcast_shapes(a.shape, b.shape))
    out[..., 0] = a[..., 1] * b[..., 2] - a[..., 2] * b[..., 1]
    out[..., 1] = a[..., 2] * b[..., 0] - a[..., 0] * b[..., 2]
    out[..., 2] = a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0]
    return out


def rotate(v: np.ndarray, k: np.ndarray, theta) -> np.ndarray:
    """Right-handed rotation of vectors ``v`` (n, 3) about unit axes ``k`` by ``theta`` (rad)."""
    v = np.asarray(v, dtype=np.float64)
    k = np.broadcast_to(np.asarray(k, dtype=np.float64), v.shape)
    th = np.broadcast_to(np.asarray(theta, dtype=np.float64), v.shape[:-1])
    c = np.cos(th)[..., None]
    s = np.sin(th)[..., None]
    kv = np.sum(k * v, axis=-1)[..., None]
    return v * c + _cross(k, v) * s + k * kv * (1.0 - c)


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def _angle(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Angle (rad) between unit vectors, row-wise, robust near 0 and pi."""
    c = np.linalg.norm(_cross(a, b), axis=-1)
    d = np.sum(a * b, axis=-1)
    return np.arctan2(c, d)


def lateral_count(wf: np.ndarray, table: int) -> np.ndarray:
    """n_L of A.5 e3: the first row whose threshold (kg) the foliage mass exceeds, else 0."""
    thr, val = BUD_TABLE_ROWS[int(table)]
    wf = np.asarray(wf, dtype=np.float64)
    exceeds = wf[:, None] > thr[None, :]
    first = np.argmax(exceeds, axis=1)
    return np.where(exceeds.any(axis=1), val[first], 0).astype(np.int64)


def foliage_survival(age: np.ndarray) -> np.ndarray:
    """pf(age): 1, 0.9, 0.7, 0.5, 0.3 at ages 0-4, then 0."""
    age = np.asarray(age)
    return np.where(age < PF.size, PF[np.clip(age, 0, PF.size - 1)], 0.0)


def light(mid: np.ndarray, wf: np.ndarray, p: Mapping[str, float], z_top: float = 0.0, space=None):
    """Light step c of A.5 for segment midpoints ``mid`` and foliage masses ``wf``.

    Returns ``(S, I, f_L, P)``: shadow (evaluated at foliated receivers only, NaN at bare
    segments, whose light is 0 whatever S is), intercepted light max(0, R - S) (0 where not
    foliated),
    f_L = max(0, (I/R - a_L) / (1 - a_L)) and production P = p_r sum I.

    ``stand_shade`` (an addition to the papers' open-grown model) adds the shade of a stand whose
    canopy grows with the tree: S_stand (z_top - z) at a point z below the tree's current top
    ``z_top``. Trees scanned in a stand have lost their lower branches to their neighbours' shade,
    which the tree's own shadow pyramid (only ``shadow_len`` deep) cannot do.

    ``space`` (an addition: ``envelope_shade`` with the setting ``crown_envelope``) is the share of
    the light left at each midpoint by the neighbours around the crown's space (1 inside it): the
    intercepted light is multiplied by it, so a segment outside takes none.
    """
    q = q_max_of(p["shadow_len"], p["voxel_size"])
    foliated = wf > FOLIATED
    S = shadow_fast(voxel_coords(mid, p["voxel_size"]), p["shadow_max"], q, receivers=foliated)
    if p["stand_shade"] > 0.0:
        S = S + p["stand_shade"] * np.maximum(0.0, z_top - mid[:, 2])
    R = p["radiation"]
    I = np.zeros(S.shape)
    I[foliated] = np.maximum(0.0, R - S[foliated])
    if space is not None:
        I *= space
    ip = I / R
    aL = p["fl_threshold"]
    fL = np.maximum(0.0, (ip - aL) / (1.0 - aL))
    return S, I, fL, p["photo_eff"] * float(I.sum())


def depth_levels(idx: np.ndarray, depth: np.ndarray) -> list[np.ndarray]:
    """Rows ``idx`` grouped by depth (ascending index within a level)."""
    if idx.size == 0:
        return []
    order, bounds = group_by_level(depth[idx])
    s = idx[order]
    return [s[bounds[k] : bounds[k + 1]] for k in range(bounds.size - 1)]


# ------------------------------------------------------------------------------------ output
#: stream of the output-only draws (``render_pieces``), apart from the growth draws of the seed
RENDER_STREAM = 0x57494E44


#: stream of the years' production factors (``year_sd``), apart from the growth draws of the seed
YEAR_STREAM = 0x59454152


def year_factors(seed: int, years: int, sd: float) -> np.ndarray:
    """Each year's production factor exp(sd z - sd^2 / 2), z ~ N(0, 1), mean 1 (index = year;
    all ones for ``sd = 0``, which draws nothing): from a stream of its own, so the growth's draws
    are those of a tree without it."""
    if sd <= 0.0:
        return np.ones(int(years) + 1)
    z = np.random.Generator(np.random.PCG64(np.random.SeedSequence([int(seed), YEAR_STREAM]))).standard_normal(
        int(years) + 1
    )
    return np.exp(sd * z - 0.5 * sd * sd)


def render_rng(seed: int) -> np.random.Generator:
    """The generator of the output-only draws of model seed ``seed`` (independent of the growth
    stream, so trees drawn in pieces grow exactly as those drawn one cylinder per shoot)."""
    return np.random.Generator(np.random.PCG64(np.random.SeedSequence([int(seed), RENDER_STREAM])))


def render_pieces(
    start, axis, length, parent, ext, order, piece_length: float, wind_sd: float, rng: np.random.Generator
):
    """Draw every segment as ``k = ceil(length / piece_length)`` consecutive cylinders.

    A QSM draws a branch as short cylinders fitted to the scan (median 0.08-0.16 m on the
    Ruotsinkyla pines); LIGNUM grows a year's shoot as one straight segment. Here a segment of
    order > 0 winds: piece j points along ``axis + e_j - mean(e)``, with e_j normal to the axis and
    each of its two components N(0, wind_sd) (radians), so the pieces end exactly at the segment's
    end point and the growth (light, positions of the children) is unchanged; order-0 segments
    (the stem) stay straight. One draw block per call: 2 normals per piece of every segment of
    order > 0 with k >= 2, in row order.

    Returns ``(start, axis, length, parent, extension, keep)``: the pieces' table (parents and
    extensions re-indexed; a segment's children hang from its last piece) and, per piece, the row
    of its segment (``keep``, for the per-segment columns).
    """
    n = length.size
    k = np.maximum(1, np.ceil(length / piece_length - 1e-9).astype(np.int64))
    first = np.zeros(n, dtype=np.int64)
    np.cumsum(k[:-1], out=first[1:])
    last = first + k - 1
    keep = np.repeat(np.arange(n), k)
    j = np.arange(keep.size) - first[keep]  # piece number within its segment
    kk = k[keep].astype(np.float64)
    vec = axis[keep] * (length[keep] / kk)[:, None]
    wind = (order[keep] > 0) & (kk > 1)
    if wind_sd > 0 and wind.any():
        rows = np.flatnonzero(wind)
        a = axis[keep[rows]]
        # two unit normals of each axis
        helper = np.where(np.abs(a[:, 2:3]) < 0.9, EZ, EX)
        u = _unit(_cross(a, helper))
        v = _cross(a, u)
        g = rng.standard_normal((rows.size, 2)) * math.radians(wind_sd)
        e = g[:, :1] * u + g[:, 1:] * v
        seg = keep[rows]  # centre e within each segment
        sums = np.zeros((n, 3))
        np.add.at(sums, seg, e)
        e -= sums[seg] / kk[rows, None]
        vec[rows] += e * (length[seg] / kk[rows])[:, None]
    plen = np.linalg.norm(vec, axis=1)
    paxis = vec / plen[:, None]
    # piece starts: the segment's start plus the vectors of its earlier pieces
    csum = np.cumsum(vec, axis=0)
    before = csum - vec - (csum[first] - vec[first])[keep]
    pstart = start[keep] + before
    ppar = np.where(j > 0, np.arange(keep.size) - 1, -1)
    root = j == 0
    ppar[root] = remap_ids(parent[keep[root]], last)
    pext = np.where(j < kk - 1, np.arange(keep.size) + 1, -1)
    at_last = np.flatnonzero(j == kk - 1)
    has_ext = ext[keep[at_last]] >= 0
    pext[at_last[has_ext]] = first[ext[keep[at_last[has_ext]]]]
    return pstart, paxis, plen, ppar, pext, keep


# ------------------------------------------------------------------------------------ state
_FIELDS = {
    "start": (np.float64, 3),
    "axis": (np.float64, 3),
    "length": (np.float64, 0),
    "radius": (np.float64, 0),
    "hw": (np.float64, 0),
    "wf0": (np.float64, 0),
    "wf": (np.float64, 0),
    "age": (np.int64, 0),
    "order": (np.int64, 0),
    "parent": (np.int64, 0),
    "is_lat": (bool, 0),
    "depth": (np.int64, 0),
    "axis_id": (np.int64, 0),
    "has_bud": (bool, 0),
    "deleted": (bool, 0),
    "dead": (bool, 0),
    "born": (np.int64, 0),
}


class _State:
    """Structure of growable arrays (A.2); rows are never reused, deleted rows are flagged."""

    def __init__(self, cap: int = 1024):
        self.n = 0
        self.cap = cap
        for k, (dt, w) in _FIELDS.items():
            setattr(self, "_" + k, np.zeros((cap, w) if w else cap, dtype=dt))
        self._views()

    def _views(self):
        """``self.<field>``: a view of the used part of each array (refreshed when rows are
        added; plain attributes, as a hot loop reads them hundreds of thousands of times)."""
        for k in _FIELDS:
            setattr(self, k, getattr(self, "_" + k)[: self.n])

    def append(self, **cols) -> np.ndarray:
        k = len(cols["length"])
        need = self.n + k
        if need > self.cap:
            cap = max(need, 2 * self.cap)
            for f in _FIELDS:
                old = getattr(self, "_" + f)
                new = np.zeros((cap,) + old.shape[1:], dtype=old.dtype)
                new[: self.n] = old[: self.n]
                setattr(self, "_" + f, new)
            self.cap = cap
        rows = np.arange(self.n, need)
        for f in _FIELDS:
            getattr(self, "_" + f)[self.n : need] = cols[f]
        self.n = need
        self._views()
        return rows


@dataclass
class YearTrace:
    """Debug record of one growth year (filled only when ``simulate(..., trace=list)``)."""

    t: int
    P: float = 0.0
    M: float = 0.0
    lam: float = 0.0
    G_at_lam: float = 0.0
    futile: bool = False
    data: dict = field(default_factory=dict)


class LignumView:
    """Read-only view of the state after step c of year ``t`` (passed to ``on_step``).

    Attributes are copies over the live rows (in output order): ``start``, ``axis``, ``length``,
    ``radius``, ``heartwood_radius``, ``foliage``, ``age``, ``order``, ``is_dead``, ``shadow``
    (S; NaN at bare segments, where it is not needed), ``light`` (I), ``f_L``; scalars ``t``,
    ``P``, ``M``, ``root_mass``. :meth:`tree` builds the
    output table exactly as a ``years = t`` run would return it.
    """

    def __init__(self, sim: _Simulation, t: int, S, I, fL, Pv, Mv):
        st = sim.st
        live = ~st.deleted
        self.t = t
        self.P = Pv
        self.M = Mv
        self.root_mass = sim.Wr
        self.start = st.start[live].copy()
        self.axis = st.axis[live].copy()
        self.length = st.length[live].copy()
        self.radius = st.radius[live].copy()
        self.heartwood_radius = st.hw[live].copy()
        self.foliage = st.wf[live].copy()
        self.age = st.age[live].copy()
        self.order = st.order[live].copy()
        self.is_dead = st.dead[live].copy()
        self.shadow = S[live].copy()
        self.light = I[live].copy()
        self.f_L = fL[live].copy()
        self._tree = sim.to_tree("ok", t)
        for a in self.__dict__.values():
            if isinstance(a, np.ndarray):
                a.flags.writeable = False

    def tree(self) -> Tree:
        """The cylinder table of this state (as ``simulate`` with ``years = t`` returns it)."""
        return self._tree


@dataclass
class _Shoots:
    """The provisional shoots of a year (step e), one row per shoot in shoot-list order."""

    prod: np.ndarray  # the segments whose buds produced shoots
    par: np.ndarray  # parent segment
    lat: np.ndarray  # lateral (else the apical shoot)
    l0: np.ndarray  # provisional length and radius (m), before lambda
    r0: np.ndarray
    lr: np.ndarray  # radius/length ratio drawn
    dirs: np.ndarray  # unit directions


@dataclass
class _Allocation:
    """Step f: the growth multiplier and the per-segment terms of the wood demand (A.7)."""

    lam: float
    futile: bool
    levels: list  # live rows by depth
    A: np.ndarray  # cross-section areas before growth
    Ah: np.ndarray  # heartwood area after senescence
    B: np.ndarray  # pipe-model area the new shoots ask of each segment, per lambda^2
    C: np.ndarray  # area the senesced sapwood of the tips above asks


# ------------------------------------------------------------------------------------ model
class _Failed(Exception):
    def __init__(self, status, message):
        self.status = status
        self.message = message


class _Simulation:
    def __init__(self, p: dict, seed: int, settings, *, on_step: Callable | None = None, trace: list | None = None):
        self.p = p
        self.seed = seed
        #: the model's validated settings (``LignumSSM.Settings``): preset, order_mode,
        #: max_live_segments, piece_length
        self.settings = settings
        self.on_step = on_step
        self.trace = trace
        self.rng = np.random.Generator(np.random.PCG64(seed))
        self.qmax = q_max_of(p["shadow_len"], p["voxel_size"])
        self.st = _State()
        self.Wr = 0.0
        self.g_ref = 0.0  # angle of the trunk-whorl reference direction from +x (rad)
        self.year = 0
        #: the crown's space (``envelope_shade`` with the setting ``crown_envelope``), or None
        self.envelope = grown_in(settings.crown_envelope, p["envelope_shade"])

    # -------------------------------------------------------------- output
    def to_tree(self, status: str, t: int) -> Tree:
        st = self.st
        idx = np.flatnonzero(~st.deleted)
        if idx.size == 0:
            raise _Failed("no_root", "every segment was removed")
        remap = np.full(st.n, -1, dtype=np.int64)
        remap[idx] = np.arange(idx.size)
        par = st.parent[idx]
        parent_out = remap_ids(par, remap)
        ext = np.full(idx.size, -1, dtype=np.int64)
        ap = (par >= 0) & ~st.is_lat[idx]
        ext[parent_out[ap]] = np.flatnonzero(ap)
        axis = st.axis[idx]
        axis = axis / np.linalg.norm(axis, axis=1, keepdims=True)
        meta = {
            "model": "lignum",
            "preset": self.settings.preset,
            "params": dict(self.p),
            "seed": int(self.seed),
            "status": status,
            "years": int(self.p["years"]),
            "year_reached": int(t),
            "order_mode": self.settings.order_mode,
            "units": {"length": "m", "angle": "deg"},
            "frame": "right-handed, z up, stem base at the origin",
            "root_mass": float(self.Wr),
            "segments_created": int(st.n),
            "dead_segments": int(np.count_nonzero(st.dead[idx])),
        }
        extras = {
            "is_dead": st.dead[idx].copy(),
            "age": st.age[idx].copy(),
            "foliage_mass": st.wf[idx].copy(),
            "heartwood_radius": st.hw[idx].copy(),
            "is_lateral": st.is_lat[idx].copy(),
            "segment_id": idx.copy(),
            "birth_year": st.born[idx].copy(),
        }
        start, length, radius = st.start[idx], st.length[idx], st.radius[idx]
        piece = self.settings.piece_length
        if piece > 0:
            start, axis, length, parent_out, ext, keep = render_pieces(
                start,
                axis,
                length,
                parent_out,
                ext,
                st.order[idx],
                piece,
                self.p["wind_sd"],
                render_rng(self.seed),
            )
            radius = radius[keep]
            extras = {k: v[keep] for k, v in extras.items()}
            meta["pieces"] = {"piece_length": float(piece), "wind_sd": float(self.p["wind_sd"])}
        return Tree(
            start,
            axis,
            length,
            radius,
            parent_out,
            ext,
            topology="thickest" if self.settings.order_mode == "thickest" else "source",
            extras=extras,
            metadata=meta,
        )

    # -------------------------------------------------------------- run
    def run(self) -> Tree:
        try:
            t = self._run()
        except _Failed as e:
            try:
                tree = self.to_tree(e.status, self.year)
            except _Failed:
                tree = None
            raise SimulationFailed(e.status, f"year {self.year}: {e.message}", tree) from None
        return self.to_tree("ok", t)

    def _init(self):
        p = self.p
        L = p["init_len"]
        r = p["lr_mean"] * L
        wf0 = p["foliage_per_area"] * 2 * np.pi * r * L
        self.st.append(
            start=[[0.0, 0.0, 0.0]],
            axis=[[0.0, 0.0, 1.0]],
            length=[L],
            radius=[r],
            hw=[math.sqrt(p["heartwood_share"]) * r],
            wf0=[wf0],
            wf=[wf0],
            age=[0],
            order=[0],
            parent=[-1],
            is_lat=[False],
            depth=[0],
            axis_id=[0],
            has_bud=[True],
            deleted=[False],
            dead=[False],
            born=[0],
        )
        self.Wr = p["root_per_foliage"] * wf0

    def _run(self) -> int:
        p = self.p
        st = self.st
        T = int(p["years"])
        self.weather = year_factors(self.seed, T, float(p["year_sd"]))
        self._init()
        for t in range(1, T + 1):
            self.year = t
            live = ~st.deleted
            # a. ageing
            st.age[live] += 1
            # b. respiration
            sap = np.pi * (st.radius**2 - st.hw**2)
            Mv = (
                p["resp_foliage"] * float(st.wf[live].sum())
                + p["resp_root"] * self.Wr
                + p["resp_sapwood"] * p["wood_density"] * float(np.sum((st.length * sap)[live]))
            )
            # c. light (and the year's weather, ``year_sd``)
            S, I, fL, Pv = self._light(live)
            Pv *= self.weather[t]
            if self.on_step is not None:
                self.on_step(t, LignumView(self, t, S, I, fL, Pv, Mv))
            if t == T:
                return t
            # d. balance
            if Pv - Mv <= 0:
                raise _Failed("negative_balance", f"P - M = {Pv - Mv:.6g} <= 0")
            tr = YearTrace(t=t, P=Pv, M=Mv) if self.trace is not None else None
            self._grow_year(t, fL, Pv - Mv, tr)
            if tr is not None:
                self.trace.append(tr)
            # k. size cap
            n_live = int(np.count_nonzero(~st.deleted))
            if n_live > self.settings.max_live_segments:
                raise _Failed(
                    "too_many_segments",
                    f"{n_live} live segments > max_live_segments = {self.settings.max_live_segments}",
                )
        return T

    def _light(self, live):
        st = self.st
        idx = np.flatnonzero(live)
        mid = st.start[idx] + 0.5 * st.length[idx, None] * st.axis[idx]
        z_top = (
            float((st.start[idx, 2] + st.length[idx] * st.axis[idx, 2]).max()) if self.p["stand_shade"] > 0.0 else 0.0
        )
        S_l, I_l, fL_l, Pv = light(mid, st.wf[idx], self.p, z_top, self._space(idx, mid))
        S = np.zeros(st.n)
        I = np.zeros(st.n)
        fL = np.zeros(st.n)
        S[idx] = S_l
        I[idx] = I_l
        fL[idx] = fL_l
        return S, I, fL, Pv

    def _space(self, idx: np.ndarray, mid: np.ndarray):
        """The share of the light the crown's space leaves at the midpoints ``mid`` of the segments
        ``idx`` (``envelope_shade``, ``crown_envelope``), the trunk keeping a corridor of the
        envelope's margin; None without it."""
        if self.envelope is None:
            return None
        st = self.st
        trunk = idx[st.order[idx] == 0]
        trunk = trunk[np.argsort(st.depth[trunk], kind="stable")]  # base first
        stem = np.vstack([np.zeros((1, 3)), st.start[trunk] + st.length[trunk, None] * st.axis[trunk]])
        return 1.0 - self.p["envelope_shade"] * (1.0 - self.envelope.light(mid, stem))

    # -------------------------------------------------------------- one growth year (e-j)
    def _grow_year(self, t: int, fL: np.ndarray, balance: float, tr: YearTrace | None):
        """Steps e-j of year ``t``: one method per step. In a futile year (no positive lambda)
        the buds stay, nothing bends or grows but heartwood, and nothing is shed."""
        live = ~self.st.deleted
        shoots = self._buds_to_shoots(live, fL, tr)  # e
        alloc = self._allocate(live, shoots, balance, tr)  # f
        if alloc.futile:
            self.st.has_bud[shoots.prod] = True
            self._secondary(live, alloc.Ah, None, None, None, 0.0)
            self._foliage_and_roots()
        else:
            self._bend_year(live, shoots, alloc.levels, tr)  # g
            gone = self._finalise_shoots(t, shoots, alloc, live, tr)  # h
            self._secondary(live & ~gone, alloc.Ah, alloc.B, alloc.C, alloc.A, alloc.lam)  # i
            self._foliage_and_roots()
            self._shed(tr)  # j
        if tr is not None:
            self._trace_end(tr)

    def _buds_to_shoots(self, live: np.ndarray, fL: np.ndarray, tr: YearTrace | None) -> _Shoots:
        """Step e: bud fate (environment, dormancy, apical dominance), lateral counts, and the
        provisional shoots with their sizes and directions (draws 1-6)."""
        p = self.p
        st = self.st
        rng = self.rng
        bud = np.flatnonzero(live & st.has_bud)
        nb = bud.size
        renv = tn_inverse_cdf(rng.random(nb), p["r_env_mean"], p["r_env_sd"])  # draw 1
        q_fate = tn_inverse_cdf(rng.random(nb), p["q_mean"], p["q_sd"])  # draw 2
        bend_ = st.start[bud] + st.length[bud, None] * st.axis[bud]
        hdist = np.hypot(bend_[:, 0], bend_[:, 1])
        killed = hdist > renv
        st.has_bud[bud[killed]] = False
        w = st.order[bud]
        flb = fL[bud]
        dormant = (flb < 1e-5) | (1.0 - q_fate * w < 1e-5)
        active = ~killed & ~dormant
        apical_only = 1.0 - q_fate * (w + 1) < 1e-5
        nL = np.minimum(lateral_count(st.wf[bud], p["bud_table"]), int(p["max_laterals"]))
        nL[(flb < p["fl_min_buds"]) | apical_only | ~active] = 0
        if tr is not None:
            tr.data.update(
                bud=bud.copy(),
                bud_hdist=hdist,
                bud_renv=renv,
                bud_killed=killed,
                bud_active=active,
                bud_nL=nL.copy(),
                bud_fL=flb,
            )
        prod = bud[active]
        nLp = nL[active]
        st.has_bud[prod] = False
        cnt = nLp + 1
        ns = int(cnt.sum())
        grp = np.repeat(np.arange(prod.size), cnt)
        first = np.concatenate(([0], np.cumsum(cnt)[:-1])) if prod.size else np.zeros(0, np.int64)
        j = np.arange(ns) - first[grp]
        par = prod[grp]
        s_lat = j < nLp[grp]
        u_q = rng.random(ns)  # draw 3
        u_lr = rng.random(ns)  # draw 4
        qs = tn_inverse_cdf(u_q, p["q_mean"], p["q_sd"])
        lrs = tn_inverse_cdf(u_lr, p["lr_mean"], p["lr_sd"])
        wp = st.order[par]
        gmask = ~s_lat & (wp > 0)
        gam = rng.standard_normal(int(gmask.sum())) * math.radians(p["gamma_sd"])  # draw 5
        trunk_whorl = (st.order[prod] == 0) & (nLp >= 1)
        wnoise = rng.standard_normal(int(trunk_whorl.sum()))  # draw 6
        turns = math.radians(p["init_rot_angle"]) + math.radians(p["whorl_rotation_sd"]) * wnoise

        # provisional size
        fl_s = fL[par]
        l0 = np.where(s_lat, fl_s * (1.0 - qs * (wp + 1)), fl_s * (1.0 - qs * wp))
        r0 = lrs * l0

        # directions
        a_b = st.axis[prod]  # per producing bud
        dref = np.empty((prod.size, 3))
        tw = np.flatnonzero(trunk_whorl)
        if tw.size:
            ang = self.g_ref + np.concatenate(([0.0], np.cumsum(turns)[:-1]))
            dref[tw] = np.stack([np.cos(ang), np.sin(ang), np.zeros(tw.size)], axis=1)
            self.g_ref = float((self.g_ref + turns.sum()) % (2 * np.pi))
        ot = np.flatnonzero(~trunk_whorl)
        if ot.size:
            a = a_b[ot]
            vert = np.abs(np.abs(a[:, 2]) - 1.0) < 1e-5
            rax = np.where(vert[:, None], EX, EZ)
            dref[ot] = rotate(a, rax, 1.0)
        kax = _cross(a_b, dref)
        kn = np.linalg.norm(kax, axis=1)
        bad = kn < 1e-12
        if bad.any():  # numeric guard: fall back to x-hat
            alt = _cross(a_b[bad], rotate(a_b[bad], EX, 1.0))
            kax[bad] = alt
            kn[bad] = np.linalg.norm(alt, axis=1)
        kax = kax / np.maximum(kn, 1e-300)[:, None]
        lat0 = rotate(a_b, kax, math.radians(p["beta_init"]))
        dirs = np.empty((ns, 3))
        if ns:
            li = np.flatnonzero(s_lat)
            gl = grp[li]
            roll = 2 * np.pi * j[li] / np.maximum(nLp[gl], 1)
            dirs[li] = rotate(lat0[gl], a_b[gl], roll)
            ai = np.flatnonzero(~s_lat)
            dirs[ai] = st.axis[par[ai]]
            gi = np.flatnonzero(gmask)
            dirs[gi] = rotate(dirs[gi], EZ, gam)
            dirs = _unit(dirs)
        keep = (l0 > 0) & (r0 > 0)
        if tr is not None:
            tr.data.update(
                shoot_parent=par[keep].copy(),
                shoot_lat=s_lat[keep].copy(),
                shoot_dir=dirs[keep].copy(),
                shoot_parent_axis=st.axis[par[keep]].copy(),
                shoot_l0=l0[keep].copy(),
                shoot_r0=r0[keep].copy(),
            )
        return _Shoots(prod, par[keep], s_lat[keep], l0[keep], r0[keep], lrs[keep], dirs[keep])

    def _allocate(self, live: np.ndarray, shoots: _Shoots, balance: float, tr: YearTrace | None) -> _Allocation:
        """Step f: the growth multiplier lambda that spends the carbon balance on the new shoots
        and the wood the pipe model asks of the old segments (A.7); ``futile`` when even lambda = 0
        costs more than the balance."""
        p = self.p
        st = self.st
        n = st.n
        par, s_lat, l0, r0 = shoots.par, shoots.lat, shoots.l0, shoots.r0
        ns = par.size
        wf0_s = p["foliage_per_area"] * 2 * np.pi * r0 * l0
        xi = p["heartwood_share"]
        cp = p["pipe_coeff"]
        ss = np.where(st.age > p["ss_start"], p["sapwood_senescence"], 0.0)
        A = np.pi * st.radius**2
        As = np.pi * (st.radius**2 - st.hw**2)
        Ah = np.pi * st.hw**2 + ss * As
        alive_idx = np.flatnonzero(live)
        levels = depth_levels(alive_idx, st.depth)
        wlink = np.where(st.is_lat, cp, 1.0)
        # float even for a year without shoots (np.bincount of nothing is an integer array)
        B = np.bincount(par, weights=np.where(s_lat, cp, 1.0) * np.pi * r0**2 * (1 - xi), minlength=n).astype(
            np.float64, copy=False
        )
        nonroot = alive_idx[st.parent[alive_idx] >= 0]
        nchild = np.bincount(st.parent[nonroot], minlength=n)
        tip = live & (nchild == 0)
        tip[par] = False
        C = np.where(tip, (1 - ss) * As, 0.0)
        for rows in reversed(levels[1:]):
            pr = st.parent[rows]
            wl = wlink[rows]
            B += np.bincount(pr, weights=wl * B[rows], minlength=n)
            C += np.bincount(pr, weights=wl * C[rows], minlength=n)
        sumW = float(wf0_s.sum())
        sumV = float(np.sum(np.pi * r0**2 * l0))
        Lw = np.where(live, st.length, 0.0)
        rho = p["wood_density"]
        ar = p["root_per_foliage"]

        def G(lam: float) -> float:
            """G(lambda) of A.7, evaluated directly (O(n))."""
            extra = np.maximum(0.0, Ah + lam * lam * B + C - A)
            return balance - ((1 + ar) * lam * lam * sumW + rho * lam**3 * sumV + rho * float(np.dot(Lw, extra)))

        # the same function in O(log n): segment i adds L_i (base_i + lam^2 B_i) once lam^2
        # passes its threshold max(0, -base_i / B_i); prefix sums over the sorted thresholds
        base = (Ah + C - A)[alive_idx]
        Bl = B[alive_idx]
        Ll = st.length[alive_idx]
        pos = Bl > 0
        const = float(np.dot(Ll[~pos], np.maximum(0.0, base[~pos])))
        thr = np.maximum(0.0, -base[pos] / Bl[pos])
        o = np.argsort(thr, kind="stable")
        thr = thr[o]
        cLb = np.concatenate(([0.0], np.cumsum((Ll[pos] * base[pos])[o])))
        cLB = np.concatenate(([0.0], np.cumsum((Ll[pos] * Bl[pos])[o])))

        def G_fast(lam: float) -> float:
            l2 = lam * lam
            k = int(np.searchsorted(thr, l2, side="right"))
            wood = const + cLb[k] + l2 * cLB[k]
            return balance - ((1 + ar) * l2 * sumW + rho * l2 * lam * sumV + rho * wood)

        lam = 0.0
        futile = False
        if ns:
            g0 = G(0.0)
            if g0 <= 0:
                futile = True
            else:
                hi = 1.0
                while G_fast(hi) >= 0:
                    hi *= 2.0
                    if hi > 1e12:
                        raise _Failed("negative_balance", "lambda bracket failed")  # unreachable in practice
                if G_fast(0.0) <= 0:  # rounding of the prefix form at the bracket end
                    lam = brentq(G, 0.0, hi, xtol=1e-12, rtol=1e-12, maxiter=500)
                else:
                    lam = brentq(G_fast, 0.0, hi, xtol=1e-12, rtol=1e-12, maxiter=500)
        if tr is not None:
            tr.lam = lam
            tr.G_at_lam = G(lam) if ns and not futile else float("nan")
            tr.futile = futile
            tr.data.update(
                n_shoots=ns,
                B=B.copy(),
                C=C.copy(),
                Ah=Ah.copy(),
                A_before=A.copy(),
                hw_before=st.hw.copy(),
                r_before=st.radius.copy(),
                old_live=live.copy(),
                balance=balance,
                cost_terms=((1 + ar) * sumW, rho * sumV),
            )
        return _Allocation(lam, futile, levels, A, Ah, B, C)

    def _bend_year(self, live: np.ndarray, shoots: _Shoots, levels: list, tr: YearTrace | None):
        """Step g: bending of the old segments (new shoots are the last of their axes), then
        the start points moved along."""
        st = self.st
        has_next = np.zeros(st.n, dtype=bool)
        ap_old = live & ~st.is_lat
        ap_old[0] = False
        has_next[st.parent[ap_old]] = True
        has_next[shoots.par[~shoots.lat]] = True
        self._bend(live, has_next, tr)
        self._positions(levels)

    def _finalise_shoots(
        self, t: int, shoots: _Shoots, alloc: _Allocation, live: np.ndarray, tr: YearTrace | None
    ) -> np.ndarray:
        """Step h: segments that bent below the ground go (with their subtrees); the shoots get
        their final size (lambda times the provisional one) and are added unless they start on a
        removed segment, end below the ground, are shorter than ``min_len`` or collide. Returns
        the removed old segments."""
        p = self.p
        st = self.st
        n = st.n
        par, s_lat, dirs = shoots.par, shoots.lat, shoots.dirs
        ns = par.size
        L = alloc.lam * shoots.l0
        r = shoots.lr * L
        end_old = st.start + st.length[:, None] * st.axis
        below = live & (end_old[:, 2] < 0)
        gone = np.zeros(n, dtype=bool)
        if below.any():
            gone |= below
            for rows in alloc.levels[1:]:
                gone[rows] |= gone[st.parent[rows]]
            st.deleted[gone] = True
            st.has_bud[gone] = False
        sstart = end_old[par]
        send = sstart + L[:, None] * dirs
        ok = ~gone[par] & (send[:, 2] >= 0) & (L >= p["min_len"])
        collided = np.zeros(ns, dtype=bool)
        if p["collision"] and ok.any():
            collided = self._collides(par, send, ok)
            ok &= ~collided
        if tr is not None:
            tr.data.update(
                shoot_L=L.copy(), shoot_kept=ok.copy(), ground_removed=np.flatnonzero(gone), shoot_collided=collided
            )
        k = np.flatnonzero(ok)
        if k.size:
            pk = par[k]
            lat_k = s_lat[k]
            wf0_k = p["foliage_per_area"] * 2 * np.pi * r[k] * L[k]
            rows = np.arange(st.n, st.n + k.size)
            self.st.append(
                start=sstart[k],
                axis=dirs[k],
                length=L[k],
                radius=r[k],
                hw=math.sqrt(p["heartwood_share"]) * r[k],
                wf0=wf0_k,
                wf=wf0_k,
                age=np.zeros(k.size, np.int64),
                order=st.order[pk] + lat_k,
                parent=pk,
                is_lat=lat_k,
                depth=st.depth[pk] + 1,
                axis_id=np.where(lat_k, rows, st.axis_id[pk]),
                has_bud=np.ones(k.size, bool),
                deleted=np.zeros(k.size, bool),
                dead=np.zeros(k.size, bool),
                born=np.full(k.size, t, np.int64),
            )
            self.Wr += p["root_per_foliage"] * float(wf0_k.sum())
        return gone

    def _foliage_and_roots(self):
        """Step i's end: foliage ages, roots senesce."""
        st = self.st
        st.wf[:] = foliage_survival(st.age) * st.wf0
        self.Wr *= 1.0 - self.p["root_senescence"]

    def _trace_end(self, tr):
        st = self.st
        tr.data.update(
            end_radius=st.radius.copy(),
            end_hw=st.hw.copy(),
            end_wf=st.wf.copy(),
            end_wf0=st.wf0.copy(),
            end_age=st.age.copy(),
            end_deleted=st.deleted.copy(),
            end_dead=st.dead.copy(),
            end_order=st.order.copy(),
            end_axis_id=st.axis_id.copy(),
            end_parent=st.parent.copy(),
            end_is_lat=st.is_lat.copy(),
            end_start=st.start.copy(),
            end_axis=st.axis.copy(),
            end_length=st.length.copy(),
        )

    # -------------------------------------------------------------- pieces
    def _secondary(self, rows_mask, Ah, B, C, A, lam):
        """Step i for the segments in ``rows_mask`` (pre-existing, dead included)."""
        st = self.st
        m = np.flatnonzero(rows_mask)
        hw_new = np.sqrt(Ah[m] / np.pi)
        hw_new = np.maximum(st.hw[m], hw_new)
        if B is not None:
            Areq = Ah[m] + lam * lam * B[m] + C[m]
            r_new = np.where(Areq > A[m], np.sqrt(Areq / np.pi), st.radius[m])
            r_new = np.maximum(st.radius[m], r_new)
        else:
            r_new = st.radius[m]
        st.radius[m] = r_new
        st.hw[m] = np.minimum(hw_new, r_new)

    def _bend(self, live, has_next, tr):
        """A.8 bending by order level (mother axes first); descendants move later by translation."""
        p = self.p
        st = self.st
        bmax = math.radians(p["beta_max"])
        binc = math.radians(p["beta_incr"])
        zsd = math.radians(p["zeta_sd"])
        cand = live & has_next & (st.order >= 1)
        if not cand.any():
            return
        max_w = int(st.order[live].max())
        for w in range(1, max_w + 1):
            rows = np.flatnonzero(cand & (st.order == w))
            if rows.size == 0:
                continue
            af = st.axis[st.axis_id[rows]]
            k = np.stack([-af[:, 1], af[:, 0], np.zeros(rows.size)], axis=1)  # z x a_first
            kn = np.linalg.norm(k, axis=1)
            ok = kn >= 1e-9
            rows, k, kn = rows[ok], k[ok], kn[ok]
            if rows.size == 0:
                continue
            k /= kn[:, None]
            mother = st.parent[st.axis_id[rows]]
            phi = _angle(st.axis[rows], st.axis[mother])
            delta = binc + zsd * self.rng.standard_normal(rows.size)  # draw 7
            delta = np.where(phi + delta > bmax, bmax - phi, delta)
            st.axis[rows] = _unit(rotate(st.axis[rows], k, delta))

    def _positions(self, levels):
        st = self.st
        for rows in levels[1:]:
            pr = st.parent[rows]
            st.start[rows] = st.start[pr] + st.length[pr, None] * st.axis[pr]

    def _shed(self, tr):
        """A.8 shedding sweeps until nothing changes."""
        p = self.p
        st = self.st
        rng = self.rng
        n = st.n
        Tsh = p["shed_year"]
        dist = int(p["shed_dist"])
        mu = min(p["shed_mu"], 10.0)
        n_sweeps = 0
        shed_log = []
        while True:
            live = ~st.deleted
            li = np.flatnonzero(live)
            nonroot = li[st.parent[li] >= 0]
            apc = nonroot[~st.is_lat[nonroot]]
            has_ext = np.zeros(n, dtype=bool)
            has_ext[st.parent[apc]] = True
            latc = nonroot[st.is_lat[nonroot]]
            lat_on_axis = np.zeros(n, dtype=bool)
            lat_on_axis[st.axis_id[st.parent[latc]]] = True
            tip = live & ~has_ext
            cand = (
                tip
                & (st.order >= 1)
                & ~st.dead
                & (st.wf < p["fol_threshold"])
                & (st.age >= Tsh)
                & ~lat_on_axis[st.axis_id]
            )
            tips = np.flatnonzero(cand)
            if tips.size == 0:
                break
            n_sweeps += 1
            ax = st.axis_id[tips]
            o = np.argsort(ax, kind="stable")
            tips, ax = tips[o], ax[o]
            nseg = np.bincount(st.axis_id[li], minlength=n)[ax]
            kk = nseg.copy()
            o1 = np.flatnonzero(st.order[tips] == 1)
            if dist == 1 and o1.size:
                u = rng.random(o1.size)  # draw 8
                kk[o1] = np.ceil(u * nseg[o1]).astype(np.int64)
            elif dist == 2 and o1.size:
                k1 = rng.poisson(mu, o1.size)  # draw 8
                nn = nseg[o1]
                bad = np.flatnonzero(k1 > nn)
                tries = 1
                while bad.size and tries < 100:
                    k1[bad] = rng.poisson(mu, bad.size)
                    bad = bad[k1[bad] > nn[bad]]
                    tries += 1
                k1[bad] = nn[bad]
                kk[o1] = k1
            # segments of the candidate axes
            axis_k = np.full(n, -1, dtype=np.int64)
            axis_k[ax] = kk
            axis_n = np.zeros(n, dtype=np.int64)
            axis_n[ax] = nseg
            on = li[axis_k[st.axis_id[li]] >= 0]
            pos = st.depth[on] - st.depth[st.axis_id[on]]
            cut = pos >= axis_n[st.axis_id[on]] - axis_k[st.axis_id[on]]
            st.deleted[on[cut]] = True
            st.dead[on[~cut]] = True
            st.has_bud[on] = False
            shed_log.append((ax.copy(), kk.copy(), nseg.copy()))
        if tr is not None:
            tr.data["shed"] = shed_log

    def _collides(self, par, send, ok) -> np.ndarray:
        """Optional collision test (A.9.5): a 0.05 m occupancy hash of segment end points; a
        shoot is rejected when its end cell holds a live segment that is neither an ancestor
        of the shoot nor a sibling (same parent), or an earlier non-sibling shoot of this year."""
        st = self.st
        cell = 0.05
        live = np.flatnonzero(~st.deleted)
        ends = st.start[live] + st.length[live, None] * st.axis[live]
        pts = np.concatenate([ends, send])
        owner_par = np.concatenate([st.parent[live], par])
        ids = np.concatenate([live, -1 - np.arange(par.size)])  # shoots: negative ids
        c = np.floor(pts / cell).astype(np.int64)
        keyv = np.unique(c, axis=0, return_inverse=True)[1].reshape(-1)
        ks = keyv[live.size :]
        ko = keyv
        # candidate pairs (shoot s, occupant o) sharing a cell
        srt = np.argsort(ko, kind="stable")
        kos = ko[srt]
        lo = np.searchsorted(kos, ks, "left")
        hi = np.searchsorted(kos, ks, "right")
        cntp = hi - lo
        s_idx = np.repeat(np.arange(par.size), cntp)
        offs = np.arange(cntp.sum()) - np.repeat(np.cumsum(cntp) - cntp, cntp)
        occ = srt[np.repeat(lo, cntp) + offs]
        occ_id = ids[occ]
        is_shoot = occ_id < 0
        sh_j = -1 - occ_id
        # ancestors of shoot s: its parent and the parent's ancestors (tin/tout intervals)
        tin, size = self._euler(live)
        p_s = par[s_idx]
        anc = np.zeros(s_idx.size, dtype=bool)
        oi = np.flatnonzero(~is_shoot)
        o_old = occ_id[oi]
        anc[oi] = (tin[o_old] <= tin[p_s[oi]]) & (tin[p_s[oi]] < tin[o_old] + size[o_old])
        sib = owner_par[occ] == p_s
        earlier = ~is_shoot | ((sh_j < s_idx) & ok[np.where(is_shoot, sh_j, 0)])
        self_pair = is_shoot & (sh_j == s_idx)
        bad = ~anc & ~sib & ~self_pair & earlier & ok[s_idx]
        out = np.zeros(par.size, dtype=bool)
        out[s_idx[bad]] = True
        return out

    def _euler(self, live_idx):
        """Pre-order entry index and subtree size of live segments (level passes)."""
        st = self.st
        n = st.n
        levels = depth_levels(live_idx, st.depth)
        size = np.zeros(n, dtype=np.int64)
        size[live_idx] = 1
        for rows in reversed(levels[1:]):
            size += np.bincount(st.parent[rows], weights=size[rows], minlength=n).astype(np.int64)
        tin = np.zeros(n, dtype=np.int64)
        for rows in levels[1:]:
            pr = st.parent[rows]  # rows ascending -> siblings ordered by index
            o = np.lexsort((rows, pr))
            r2, p2 = rows[o], pr[o]
            csum = np.cumsum(size[r2])
            grp_start = np.r_[True, p2[1:] != p2[:-1]]
            base = np.maximum.accumulate(np.where(grp_start, np.arange(r2.size), 0))
            before = csum - size[r2] - (csum[base] - size[r2[base]])
            tin[r2] = tin[p2] + 1 + before
        return tin, size
