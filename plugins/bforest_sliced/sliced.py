"""The sliced (tomographic) structural distance and its permutation test.

Reference: docs/features-and-distance.md §3-§4 and §6 (GS Methods IV; SF §2.3):

    D_S(U_m, U_d) = aggregate_i K[P(U_m, a_i), P(U_d, a_i)],   i = 1 ... L

Both tables are normalised with a transform fitted on the data table, projected on L unit
directions and compared line by line with a two-sample statistic K.

Resolution (:mod:`.grid`): normalised values and directions are snapped to grids of about 1e-6
before projecting, which makes every projection exact: the same on every CPU, equal for equal
rows, blind to round-off from the tree's numbering or position.

Performance (§6): the directions are cached; the data side of a pair is projected and sorted
once (``prepare``, or the first ``compute`` with that data array); an evaluation projects the
model table on every line at once, sorts each line and evaluates KS with ``np.searchsorted``.
Lines are processed in blocks on a thread pool (NumPy releases the GIL while sorting and
searching).
"""

from __future__ import annotations

import hashlib
import math
import os
import re
import threading
import warnings
from collections import OrderedDict
from collections.abc import Mapping
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from typing import Any, Literal

import numpy as np
from pydantic import AliasChoices, Field, field_validator, model_validator

from bforest_core.interfaces import ComponentSettings, LineDistance, RecipePart, RecipePlan

from .directions import directions as _directions
from .grid import VALUE_BITS, snap
from .stats import ALIASES, ks_encoded, stat_from_labels, stat_sorted

__all__ = ["SlicedDistance", "SlicedSettings", "Normalization", "fit_normalization", "PermutationResult", "holm"]

_CIRC_RE = re.compile(r"^(sin|cos)\((.+)\)$")


# ----------------------------------------------------------------------------------------------
# normalisation (§3) and the resolution the distance sees
# ----------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Normalization:
    """A frozen per-column affine transform ``x -> (x - center) / scale``."""

    method: str
    center: np.ndarray
    scale: np.ndarray
    columns: tuple[str, ...] | None = None

    def apply(self, u: np.ndarray) -> np.ndarray:
        return (u - self.center) / self.scale

    def snapped(self, u: np.ndarray) -> np.ndarray:
        """The normalised table on the distance's grid (:data:`VALUE_BITS`), transposed to
        ``(d, n)`` and contiguous, ready to be projected."""
        return np.ascontiguousarray(snap(self.apply(u), VALUE_BITS).T)

    def to_dict(self) -> dict[str, Any]:
        return {
            "method": self.method,
            "center": self.center.tolist(),
            "scale": self.scale.tolist(),
            "columns": list(self.columns) if self.columns is not None else None,
        }


def circular_pairs(columns) -> list[tuple[int, int]]:
    """Index pairs ``(i_sin, i_cos)`` of columns named ``"sin(x)"`` and ``"cos(x)"``."""
    if not columns:
        return []
    where: dict[str, dict[str, int]] = {}
    for j, c in enumerate(columns):
        mt = _CIRC_RE.match(str(c))
        if mt:
            where.setdefault(mt.group(2), {})[mt.group(1)] = j
    return [(v["sin"], v["cos"]) for v in where.values() if "sin" in v and "cos" in v]


def fit_normalization(
    u: np.ndarray, method: str = "zscore", columns=None, set_name: str | None = None
) -> Normalization:
    """Fit the normalisation of §3 on a data table.

    Parameters
    ----------
    u : (n, d) array
        The data table.
    method : {"none", "zscore", "robust"}
        ``zscore``: mean and population sd; ``robust``: median and IQR/1.349 (numpy's default
        ``linear`` quantiles).
    columns : sequence of str, optional
        Column names; pairs ``"sin(x)"``, ``"cos(x)"`` are mean-centred and share one scale
        ``sqrt(1 - Rbar^2)`` under ``zscore`` and ``robust``.
    set_name : str, optional
        Named in warnings.

    Notes
    -----
    A scale that is zero or not finite is replaced by 1 with a ``RuntimeWarning`` naming the
    feature and the set. An empty table gives the identity.
    """
    u = np.asarray(u, dtype=np.float64)
    d = u.shape[1]
    cols = tuple(columns) if columns is not None else None
    if cols is not None and len(cols) != d:
        raise ValueError(f"set {set_name or '?'}: {len(cols)} column names for a table with {d} columns")
    center = np.zeros(d)
    scale = np.ones(d)
    if method == "none" or u.shape[0] == 0:
        return Normalization(method, center, scale, cols)
    if method == "zscore":
        center = u.mean(axis=0)
        scale = u.std(axis=0)
    elif method == "robust":
        q25, center, q75 = np.percentile(u, [25, 50, 75], axis=0)
        scale = (q75 - q25) / 1.349
    else:
        raise ValueError(f"unknown normalize {method!r} (choose none, zscore, robust)")
    for i_s, i_c in circular_pairs(cols):
        ms, mc = u[:, i_s].mean(), u[:, i_c].mean()
        center[i_s], center[i_c] = ms, mc
        s = math.sqrt(max(0.0, 1.0 - (ms * ms + mc * mc)))
        scale[i_s] = scale[i_c] = s
    bad = np.flatnonzero(~np.isfinite(scale) | (scale <= 0))
    if bad.size:
        names = [cols[j] if cols else f"column {j}" for j in bad]
        warnings.warn(
            f"sliced distance: set {set_name or '(unnamed)'}: the data table has zero or "
            f"non-finite spread in {', '.join(names)}; its scale is set to 1",
            RuntimeWarning,
            stacklevel=3,
        )
        scale = scale.copy()
        scale[bad] = 1.0
    return Normalization(method, center, scale, cols)


def holm(p: Mapping[str, float]) -> dict[str, float]:
    """Holm's step-down adjusted p-values."""
    keys = sorted(p, key=lambda k: p[k])
    K = len(keys)
    out, run = {}, 0.0
    for j, k in enumerate(keys):
        run = max(run, min(1.0, (K - j) * p[k]))
        out[k] = run
    return out


# ----------------------------------------------------------------------------------------------
# settings and per-set state
# ----------------------------------------------------------------------------------------------


#: the most projection lines (16 times the 1000 of the SF runs): each costs a sort per set and evaluation
MAX_LINES = 16384


class SlicedSettings(ComponentSettings):
    """Settings of the ``sliced`` distance (docs/features-and-distance.md §3-§4)."""

    statistic: Literal["ks", "cvm", "ad", "w1", "energy", "l1", "l2"] = "ks"
    lines: int = Field(256, ge=1, le=MAX_LINES)
    net: Literal["gp2", "sobol", "halton", "random"] = "gp2"
    seed: int = Field(0, ge=0)
    scramble: bool = False
    parity: bool = False
    aggregate: Literal["mean", "max"] = "mean"
    scale_by_sample_size: bool = Field(False, validation_alias=AliasChoices("scale_by_sample_size", "scale_by_size"))
    normalize: Literal["none", "zscore", "robust"] = "zscore"
    empty_cost: float | None = Field(None, ge=0)
    threads: int | None = Field(None, ge=1, le=256)
    block: int = Field(16, ge=1, le=4096)
    presort_memory_limit: int = Field(1 << 30, ge=0, le=1 << 30)
    return_lines: bool = False

    @field_validator("statistic", mode="before")
    @classmethod
    def _alias(cls, v):
        return ALIASES.get(v, v) if isinstance(v, str) else v

    @model_validator(mode="after")
    def _empty_cost_needed(self):
        if self.empty_cost is None and self.statistic != "ks":
            raise ValueError(
                f"empty_cost must be set for statistic '{self.statistic}': 1.0 is the "
                "maximum of unscaled KS only (docs/features-and-distance.md §4.5)"
            )
        return self


@dataclass
class _PairState:
    norm: Normalization
    A: np.ndarray  # (L, d) directions on their grid: A @ norm.snapped(u) = exact projections
    data: np.ndarray  # the raw data table (reference)
    sorted_data: np.ndarray | None = None  # (L, n) sorted projections, when within the memory limit
    digest: str = ""


@dataclass
class PermutationResult:
    """Outcome of :meth:`SlicedDistance.permutation_test` (docs/features-and-distance.md §4.6)."""

    p_value: float
    draws: int
    se: float
    cv: float
    d0: float
    alpha: float
    distinguishable: bool
    per_set: dict[str, float] = field(default_factory=dict)
    per_set_holm: dict[str, float] = field(default_factory=dict)
    per_set_d0: dict[str, float | None] = field(default_factory=dict)
    null: np.ndarray = field(default_factory=lambda: np.empty(0))

    @property
    def floor(self) -> float:
        """The distance's floor at these row counts: the median of the permutation null, what a
        model tree drawn from the same distribution as the data tree would score with the
        model's and the data's numbers of rows (sampling noise alone; nan without draws). A
        distance near its floor cannot be brought down by a better model, only by more rows."""
        return float(np.median(self.null)) if self.null.size else math.nan

    def summary(self) -> str:
        verdict = "distinguishable" if self.distinguishable else "not distinguishable"
        return (
            f"p = {self.p_value:.4f} ({self.draws} draws, SE {self.se:.4f}, CV {self.cv:.3f}); "
            f"D0 = {self.d0:.4f}; floor {self.floor:.4f} (the null's median: a tree of the data's own "
            f"distribution with these row counts); {verdict} at alpha = {self.alpha}"
        )


def _digest(a: np.ndarray) -> str:
    h = hashlib.blake2b(digest_size=16)
    h.update(str((a.shape, a.dtype.str)).encode())
    h.update(np.ascontiguousarray(a).data)
    return h.hexdigest()


def _check_finite(u: np.ndarray, what: str, set_name) -> None:
    ok = np.isfinite(u).all(axis=1)
    if not ok.all():
        bad = np.flatnonzero(~ok)
        raise ValueError(
            f"set {set_name or '(unnamed)'}: the {what} table has non-finite values in "
            f"{bad.size} row(s) (first rows {bad[:5].tolist()}); drop them first "
            "(features nan_policy = 'drop')"
        )


def _as_table(u, what: str, d: int | None = None) -> np.ndarray:
    a = np.asarray(u, dtype=np.float64)
    if a.ndim == 1:
        if a.size == 0:
            return a.reshape(0, d if d is not None else 0)
        a = a.reshape(-1, 1)
    if a.ndim != 2:
        raise ValueError(f"{what} table must be 2-D (n, d), got shape {a.shape}")
    return a


# ----------------------------------------------------------------------------------------------
# the component
# ----------------------------------------------------------------------------------------------


class SlicedDistance(LineDistance):
    """Sliced (tomographic) distance: mean (or max) over projection lines of a 1-D statistic.

    Settings
    --------
    statistic : {"ks", "cvm", "ad", "w1" (alias "wasserstein"), "energy", "l1", "l2"}
    lines : int
        Number of projection lines L (default 256, at most 16384; one line for 1-D tables).
    net : {"gp2", "sobol", "halton", "random"}
        Direction net (§4.1); ``seed``/``scramble`` for scrambled or random nets, ``parity``
        for the toolbox's Fang-Wang indexing.
    aggregate : {"mean", "max"}
    scale_by_sample_size : bool
        Sample-size-scaled statistic (alias ``scale_by_size``).
    normalize : {"zscore", "robust", "none"}
        Transform fitted on the data table of each pair and frozen (§3). Columns named
        ``sin(x)``/``cos(x)`` share one scale.
    empty_cost : float
        Distance of a pair with one empty side. Defaults to 1.0 for KS (sqrt(n/2) when scaled);
        required for every other statistic.
    threads : int
        Worker threads over line blocks (default min(8, cores), and no more than
        ``OMP_NUM_THREADS`` when that is set: the process and Dask executors set it to 1 in their
        workers, which already keep every core busy); ``block`` lines per block.
    presort_memory_limit : int
        Bytes above which the data projections are not kept sorted (recomputed per block; at
        most 1 GiB, the default).
    return_lines : bool
        Keep per-line values of the last evaluation in :attr:`last_lines`.
    """

    name = "sliced"
    summary = "sliced (tomographic) distance: KS/CvM/AD/W1/energy on quasi-random projections"
    Settings = SlicedSettings

    def draft_recipe(self, plan: RecipePlan) -> RecipePart | None:
        """The structural distance of the real-tree recipes: KS (at most 1) on 128 lines for the
        search, 256 where the candidate answers are scored."""
        if plan.term != "structure":
            return None
        return RecipePart(
            self.name,
            [("statistic", "ks", None), ("lines", 128, None)],
            select={"lines": 256},
            select_why="on 256 lines",
            reach=1.0,
        )

    _CACHE_SIZE = 16

    def __init__(self, settings=None, **kwargs):
        super().__init__(settings, **kwargs)
        self._prepared: dict[str, _PairState] = {}
        self._columns: dict[str, tuple[str, ...]] = {}
        self._cache: OrderedDict[tuple, _PairState] = OrderedDict()
        self._lock = threading.Lock()
        self._pool: ThreadPoolExecutor | None = None
        self.last_lines: dict[str | None, np.ndarray] = {}
        self.last_per_set: dict[str, float | None] = {}

    # ------------------------------------------------------------------ pickling (process pools)
    def __getstate__(self):
        st = dict(self.__dict__)
        st["_pool"] = None
        st["_lock"] = None
        st["_cache"] = OrderedDict()
        return st

    def __setstate__(self, st):
        self.__dict__.update(st)
        self._lock = threading.Lock()

    def close(self) -> None:
        """Shut the thread pool down (it is recreated on demand)."""
        if self._pool is not None:
            self._pool.shutdown(wait=True)
            self._pool = None

    @property
    def statistic(self) -> str:
        """The per-line statistic of the settings (``Distance.statistic``)."""
        return self.settings.statistic

    # ------------------------------------------------------------------ directions
    def directions(self, d: int) -> np.ndarray:
        """The cached read-only ``(lines, d)`` directions on the distance's grid (``(1, 1)`` for
        d = 1): unit vectors to about 1e-6 (:mod:`.grid`)."""
        s = self.settings
        return _directions(d, s.lines, s.net, scramble=s.scramble, seed=s.seed, parity=s.parity)

    @property
    def n_threads(self) -> int:
        t = self.settings.threads
        if t is not None:
            return t
        omp = os.environ.get("OMP_NUM_THREADS", "").strip()
        cap = int(omp) if omp.isdigit() and int(omp) >= 1 else 8
        return max(1, min(8, cap, os.cpu_count() or 1))

    def empty_cost(self, n_nonempty: int) -> float:
        """Distance of a pair whose other side is empty (§4.5)."""
        s = self.settings
        if s.empty_cost is not None:
            return float(s.empty_cost)
        if s.statistic == "ks" and s.scale_by_sample_size:
            return math.sqrt(n_nonempty / 2.0)
        return 1.0

    # ------------------------------------------------------------------ set-up
    def prepare(self, U_data: Mapping[str, np.ndarray], columns: Mapping[str, list[str]] | None = None) -> None:
        """Fit the normalisation on each data table and pre-sort its projections (once per run).

        Parameters
        ----------
        U_data : dict
            Set name -> data table ``(n_d, d)``.
        columns : dict, optional
            Set name -> column names (from ``FeatureSet.columns``); circular pairs
            ``sin(x)``/``cos(x)`` are then scaled jointly.
        """
        self._prepared = {}
        self._columns = {k: tuple(v) for k, v in (columns or {}).items()}
        for k, ud in U_data.items():
            ud = _as_table(ud, f"data set '{k}'")
            _check_finite(ud, "data", k)
            norm = fit_normalization(ud, self.settings.normalize, self._columns.get(k), set_name=k)
            self._prepared[k] = self._make_state(ud, norm, set_name=k)

    def normalizations(self) -> dict[str, dict]:
        """The frozen transforms of the prepared sets (for the run directory)."""
        return {k: st.norm.to_dict() for k, st in self._prepared.items()}

    def _make_state(self, ud: np.ndarray, norm: Normalization, digest: str = "", set_name=None) -> _PairState:
        d = ud.shape[1]
        A = self.directions(d)
        st = _PairState(norm=norm, A=A, data=ud, digest=digest)
        n = ud.shape[0]
        if n and A.shape[0] * n * 8 <= self.settings.presort_memory_limit:
            srt = np.empty((A.shape[0], n))
            udT = norm.snapped(ud)  # (d, n) contiguous: a strided operand makes BLAS ~7x slower here

            def job(lo, hi):
                blk = A[lo:hi] @ udT
                blk.sort(axis=1)
                blk += 0.0  # -0.0 -> +0.0 (bit-level label encoding of ks_encoded)
                srt[lo:hi] = blk

            self._run_blocks(A.shape[0], job)
            srt.flags.writeable = False
            st.sorted_data = srt
        return st

    def _state(self, set_name: str | None, ud: np.ndarray, columns=None) -> _PairState:
        """Prepared state of a set, or a cached one keyed by the data array's content."""
        st = self._prepared.get(set_name) if set_name is not None else None
        if st is not None and (ud is st.data or (ud.shape == st.data.shape and np.array_equal(ud, st.data))):
            return st
        dig = _digest(ud)
        cols = tuple(columns) if columns is not None else self._columns.get(set_name)
        key = (set_name if st is not None else None, dig, cols)
        with self._lock:
            hit = self._cache.get(key)
            if hit is not None:
                self._cache.move_to_end(key)
                return hit
        # a prepared set keeps its frozen transform; otherwise fit it on this data table
        _check_finite(ud, "data", set_name)
        norm = st.norm if st is not None else fit_normalization(ud, self.settings.normalize, cols, set_name)
        new = self._make_state(ud, norm, dig, set_name)
        with self._lock:
            self._cache[key] = new
            while len(self._cache) > self._CACHE_SIZE:
                self._cache.popitem(last=False)
        return new

    # ------------------------------------------------------------------ thread pool over line blocks
    def _run_blocks(self, L: int, job) -> None:
        b = self.settings.block
        bounds = [(lo, min(L, lo + b)) for lo in range(0, L, b)]
        nt = self.n_threads
        if nt <= 1 or len(bounds) <= 1:
            for lo, hi in bounds:
                job(lo, hi)
            return
        if self._pool is None:
            with self._lock:
                if self._pool is None:
                    self._pool = ThreadPoolExecutor(max_workers=nt, thread_name_prefix="bforest-sliced")
        for f in [self._pool.submit(job, lo, hi) for lo, hi in bounds]:
            f.result()

    # ------------------------------------------------------------------ evaluation
    def _line_values(self, st: _PairState, um: np.ndarray) -> np.ndarray:
        s = self.settings
        A = st.A
        L = A.shape[0]
        out = np.empty(L)
        umT = st.norm.snapped(um)  # (d, m) contiguous: see _make_state
        udT = st.norm.snapped(st.data) if st.sorted_data is None else None
        stat, scaled = s.statistic, s.scale_by_sample_size

        nd, nm = st.data.shape[0], um.shape[0]

        def job(lo, hi):
            if st.sorted_data is not None:
                X = st.sorted_data[lo:hi]
            else:
                X = A[lo:hi] @ udT
                X.sort(axis=1)
                X += 0.0
            if stat == "ks":
                D = ks_encoded(X, A=A[lo:hi], UT=umT)
                out[lo:hi] = np.sqrt(nd * nm / (nd + nm)) * D if scaled else D
            else:
                Y = A[lo:hi] @ umT
                Y.sort(axis=1)
                out[lo:hi] = stat_sorted(X, Y, stat, scaled)

        self._run_blocks(L, job)
        return out

    def line_values(self, u_model, u_data, set_name: str | None = None, columns=None) -> np.ndarray:
        """Per-line statistic values ``(L,)`` of one pair (both sides non-empty)."""
        ud = _as_table(u_data, "data")
        um = _as_table(u_model, "model", ud.shape[1])
        self._check_dims(um, ud, set_name)
        if ud.shape[0] == 0 or um.shape[0] == 0:
            raise ValueError("line_values needs both tables non-empty")
        return self._line_values(self._state(set_name, ud, columns), um)

    def _aggregate(self, vals: np.ndarray) -> float:
        return float(vals.max() if self.settings.aggregate == "max" else vals.mean())

    @staticmethod
    def _check_dims(um, ud, set_name):
        if um.shape[0] and ud.shape[0] and um.shape[1] != ud.shape[1]:
            raise ValueError(
                f"set {set_name or '(unnamed)'}: model table has {um.shape[1]} columns, data table {ud.shape[1]}"
            )

    def compute_pair(self, set_name: str | None, u_model, u_data, columns=None) -> float | None:
        """Distance of one named pair (§4.5 rules for empty sides; ``None`` = skipped)."""
        ud = _as_table(u_data, "data")
        um = _as_table(u_model, "model", ud.shape[1] if ud.ndim == 2 else None)
        self._check_dims(um, ud, set_name)
        nd, nm = ud.shape[0], um.shape[0]
        if nd == 0 and nm == 0:
            return None
        if nd == 0 or nm == 0:
            return self.empty_cost(max(nd, nm))
        _check_finite(um, "model", set_name)
        vals = self._line_values(self._state(set_name, ud, columns), um)
        if self.settings.return_lines:
            self.last_lines[set_name] = vals
        return self._aggregate(vals)

    def compute(self, u_model, u_data, columns=None) -> float:
        """Distance of one pair of ``(n, d)`` tables (data side second).

        The normalisation is fitted on ``u_data`` (or frozen by :meth:`prepare`); the data
        projections are cached by the array's content. Both sides empty gives 0.0.
        """
        v = self.compute_pair(None, u_model, u_data, columns)
        return 0.0 if v is None else v

    def compute_per_set(self, U_model, U_data) -> dict[str, float | None]:
        if set(U_model) != set(U_data):
            raise ValueError(f"model sets {sorted(U_model)} differ from data sets {sorted(U_data)}")
        out = {k: self.compute_pair(k, U_model[k], U_data[k]) for k in U_data}
        self.last_per_set = out
        return out

    def compute_sets(self, U_model, U_data, weights=None) -> float:
        """Weighted mean over the pairs that take part (§4.5).

        Parameters
        ----------
        U_model, U_data : dict
            Set name -> table; both must hold the same names.
        weights : dict, optional
            Set name -> weight >= 0 (default equal; normalised over the pairs taking part).
        """
        self._check_weights(weights, U_data)
        return self.combine(self.compute_per_set(U_model, U_data), weights)

    @staticmethod
    def _check_weights(weights, U_data):
        if weights is None:
            return
        unknown = sorted(set(weights) - set(U_data))
        if unknown:
            raise ValueError(f"weights name unknown set(s) {unknown} (sets: {sorted(U_data)})")
        bad = {k: w for k, w in weights.items() if not (np.isfinite(w) and w >= 0)}
        if bad:
            raise ValueError(f"weights must be finite and >= 0, got {bad}")

    # ------------------------------------------------------------------ permutation test (§4.6)
    def permutation_test(
        self,
        U_model,
        U_data,
        weights=None,
        *,
        seed: int = 0,
        max_draws: int = 500,
        min_draws: int = 100,
        se_max: float = 0.025,
        cv_max: float = 0.5,
        alpha: float = 0.05,
        parity: bool = False,
    ) -> PermutationResult:
        """Is the model tree distinguishable from the data tree? (docs/features-and-distance.md §4.6)

        Every pair's pooled rows are shuffled and split into ``n_d`` and ``n_m`` rows; ``D_b``
        is the weighted distance of the shuffled pairs with the same directions, statistic and
        frozen normalisation as the observed ``D0``.

        Parameters
        ----------
        U_model, U_data : dict or (n, d) array
            Tables by set name (a single pair may be given as arrays).
        weights : dict, optional
        seed : int
            Seeds the ``numpy.random.Generator`` of the shuffles.
        max_draws, min_draws, se_max, cv_max
            Stop after ``i >= min_draws`` draws once ``SE = sqrt(p(1-p)/i) <= se_max`` and
            ``CV = sqrt((1-p)/(p i)) <= cv_max`` (Efron & Tibshirani 1993, p. 211), or at
            ``max_draws``.
        alpha : float
            Level of the "distinguishable" verdict (p < alpha).
        parity : bool
            Toolbox p-value ``#{D_b > D0}/i`` (can be 0) instead of ``(1 + #{D_b >= D0})/(1 + i)``.

        Returns
        -------
        PermutationResult
            p-value, draws, SE, CV, D0, per-set p-values and their Holm adjustment.

        Notes
        -----
        Rows of one tree are not independent (siblings share a parent), so p is a screening
        measure, not an exact test. Ties ``D_b = D0`` are judged with a relative tolerance of
        1e-12 (the same distance summed in another order).
        """
        if not isinstance(U_data, Mapping):
            U_data, U_model = {"U": U_data}, {"U": U_model}
        if set(U_model) != set(U_data):
            raise ValueError(f"model sets {sorted(U_model)} differ from data sets {sorted(U_data)}")
        self._check_weights(weights, U_data)
        s = self.settings
        names = list(U_data)
        seqs = np.random.SeedSequence(seed).spawn(len(names))
        pairs = []
        for k, sq in zip(names, seqs):
            ud = _as_table(U_data[k], f"data set '{k}'")
            um = _as_table(U_model[k], f"model set '{k}'", ud.shape[1])
            self._check_dims(um, ud, k)
            nd, nm = ud.shape[0], um.shape[0]
            if nd == 0 and nm == 0:
                continue
            if nd == 0 or nm == 0:
                pairs.append(dict(name=k, const=self.empty_cost(max(nd, nm))))
                continue
            _check_finite(um, "model", k)
            st = self._state(k, ud)
            P = st.A @ st.norm.snapped(np.concatenate([ud, um]))  # (L, N), as in compute
            order = np.argsort(P, axis=1, kind="stable")
            Z = np.take_along_axis(P, order, axis=1)
            N = nd + nm
            lab0 = np.arange(N) >= nd
            d0 = self._aggregate(stat_from_labels(Z, lab0[order], nd, nm, s.statistic, s.scale_by_sample_size))
            pairs.append(dict(name=k, nd=nd, nm=nm, N=N, order=order, Z=Z, d0=d0, rng=np.random.default_rng(sq)))
        if not pairs:
            return PermutationResult(1.0, 0, 0.0, math.inf, 0.0, alpha, False)
        w = {p["name"]: (1.0 if weights is None else float(weights.get(p["name"], 1.0))) for p in pairs}
        wsum = sum(w.values())
        if wsum <= 0:
            raise ValueError("permutation_test: every pair taking part has weight 0")
        d0_set = {p["name"]: (p["d0"] if "d0" in p else p["const"]) for p in pairs}
        D0 = sum(w[k] * v for k, v in d0_set.items()) / wsum

        per_set_draws: dict[str, list[np.ndarray]] = {p["name"]: [] for p in pairs}
        totals: list[np.ndarray] = []
        done = 0
        stop = None
        while done < max_draws:
            bs = min(max_draws - done, self._perm_batch(pairs))
            tot = np.zeros(bs)
            for p in pairs:
                k = p["name"]
                if "const" in p:
                    vals = np.full(bs, p["const"])
                else:
                    vals = self._perm_batch_values(p, bs)
                per_set_draws[k].append(vals)
                tot += w[k] * vals
            totals.append(tot / wsum)
            done += bs
            stop = self._stopping_index(np.concatenate(totals), D0, min_draws, se_max, cv_max, parity)
            if stop is not None:
                break
        Db = np.concatenate(totals)
        i = stop if stop is not None else Db.size
        Db = Db[:i]
        p, se, cv = self._p_stats(Db, D0, parity)
        per_set = {}
        for k, parts in per_set_draws.items():
            v = np.concatenate(parts)[:i]
            per_set[k] = self._p_stats(v, d0_set[k], parity)[0]
        return PermutationResult(
            p_value=p,
            draws=int(i),
            se=se,
            cv=cv,
            d0=D0,
            alpha=alpha,
            distinguishable=bool(p < alpha),
            per_set=per_set,
            per_set_holm=holm(per_set),
            per_set_d0=d0_set,
            null=Db,
        )

    @staticmethod
    def _perm_batch(pairs) -> int:
        big = max((p["Z"].size for p in pairs if "Z" in p), default=1)
        return int(max(1, min(50, 4_000_000 // max(big, 1))))

    def _perm_batch_values(self, p, bs: int) -> np.ndarray:
        s = self.settings
        N, nd, nm = p["N"], p["nd"], p["nm"]
        perms = p["rng"].permuted(np.broadcast_to(np.arange(N), (bs, N)), axis=1)
        lab = np.zeros((bs, N), dtype=bool)
        lab[np.arange(bs)[:, None], perms[:, nd:]] = True  # shuffled rows that go to the model side
        vals = stat_from_labels(p["Z"], lab[:, p["order"]], nd, nm, s.statistic, s.scale_by_sample_size)
        return vals.max(axis=1) if s.aggregate == "max" else vals.mean(axis=1)

    @staticmethod
    def _exceed(Db, D0, parity):
        tol = 1e-12 * max(1.0, abs(D0))
        return (Db > D0 + tol) if parity else (Db >= D0 - tol)

    def _p_stats(self, Db, D0, parity):
        i = Db.size
        c = int(np.count_nonzero(self._exceed(Db, D0, parity)))
        p = c / i if parity else (1 + c) / (1 + i)
        se = math.sqrt(p * (1 - p) / i)
        cv = math.sqrt((1 - p) / (p * i)) if p > 0 else math.inf
        return p, se, cv

    def _stopping_index(self, Db, D0, min_draws, se_max, cv_max, parity):
        i = np.arange(1, Db.size + 1)
        c = np.cumsum(self._exceed(Db, D0, parity))
        p = c / i if parity else (1 + c) / (1 + i)
        se = np.sqrt(p * (1 - p) / i)
        with np.errstate(divide="ignore"):
            cv = np.sqrt(np.where(p > 0, (1 - p) / np.where(p > 0, p * i, 1.0), np.inf))
        ok = np.flatnonzero((i >= min_draws) & (se <= se_max) & (cv <= cv_max))
        return int(i[ok[0]]) if ok.size else None
