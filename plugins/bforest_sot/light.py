"""The multiplicative shadow-propagation light field of the SOT model (docs/models.md B.6).

The field is a cube of ``n_vox**3`` voxels over x, y in [-span/2, span/2] and z in [0, span]
(Z up). Each voxel holds an exposure E in [0, 1]. A segment casts a *shadow pyramid* from the
voxel of its start point: for layers ``l = 1 .. depth-1`` below it, every voxel with
``|di|, |dj| <= floor(l * spread)`` is multiplied by ``f = 1 - a * b**(-d)``,
``d = sqrt(l**2 + di**2 + dj**2)`` (voxel units). Removing a shadow divides by the same factors.

The field is stored as ``log E`` in a flat float64 array (C order of (i, j, k)), so a batch of
shadows is added or removed with one ``np.bincount`` of ``log f``: exact, independent of the order
of operations and free of drift. The top layer (the "roof") is a mask with E = 0, never a log 0.
"""

from __future__ import annotations

from collections import OrderedDict

import numpy as np

from .kernels import add_shadows

_LOG_FLOOR = np.log(1e-12)  # factors and initial exposures are clamped to >= 1e-12

#: initial fields (padded log E0 and roof mask, read-only) by ``initial_key`` and shape: a fit grows
#: every candidate with the same model seeds, whose uniforms, and so whose initial fields, repeat
_INITIAL: OrderedDict = OrderedDict()
_INITIAL_KEEP = 4


def shadow_kernel(depth: int, spread: float, shadow_a: float, shadow_b: float):
    """Offsets and log-factors of one shadow pyramid.

    Parameters
    ----------
    depth : int
        Layers ``1 .. depth-1`` below the source voxel are shaded.
    spread : float
        Half-width of layer ``l`` is ``floor(l * spread)`` voxels.
    shadow_a, shadow_b : float
        Shadow strength ``a`` and dissipation base ``b`` of ``f = 1 - a * b**(-d)``.

    Returns
    -------
    di, dj, dk : (m,) int64
        Voxel offsets (``dk = -l``).
    log_f : (m,) float64
        ``log(max(f, 1e-12))``.
    """
    di, dj, dk = [], [], []
    for layer in range(1, int(depth)):
        half = int(np.floor(layer * spread))
        r = np.arange(-half, half + 1)
        gi, gj = np.meshgrid(r, r, indexing="ij")
        di.append(gi.ravel())
        dj.append(gj.ravel())
        dk.append(np.full(gi.size, -layer))
    if not di:
        e = np.zeros(0, dtype=np.int64)
        return e, e, e, np.zeros(0)
    di = np.concatenate(di).astype(np.int64)
    dj = np.concatenate(dj).astype(np.int64)
    dk = np.concatenate(dk).astype(np.int64)
    dist = np.sqrt(dk.astype(float) ** 2 + di**2 + dj**2)
    f = 1.0 - shadow_a * shadow_b ** (-dist)
    log_f = np.log(np.maximum(f, 1e-12))
    return di, dj, dk, log_f


class LightField:
    """Voxel exposure field with exact shadow casting and removal.

    Parameters
    ----------
    span : float
        Cube edge (m).
    voxel_size : float
        Voxel edge (m); ``n_vox = round(span / voxel_size)`` voxels per axis.
    depth, spread, shadow_a, shadow_b : shadow-pyramid parameters (see :func:`shadow_kernel`).
    ran, vert : float
        Initial exposure ``E0 = (1 - ran - vert) + ran * U + vert * k / n_vox`` below the roof.
    uniforms : (n_vox**3,) array or callable returning it, optional
        The ``U(0, 1)`` draws in C order of (i, j, k); zeros when omitted. A callable is called
        only when the initial field is not cached.
    initial_key : hashable, optional
        Names the draws (e.g. the model seed): the initial field of the same key, ``ran``, ``vert``
        and grid is reused from a small cache of the process instead of computed again (the same
        numbers; the log of ~10^6 voxels is a sixth of a typical SOT run).
    filters : sequence of callables, optional
        ``f(points) -> (m,) factors`` on the exposure at points, applied in order (the growth
        forms' ``transmission``: the shade of a stand or of a gap's neighbours).

    Notes
    -----
    ``log E`` is kept in a grid padded by the pyramid's reach (``floor((depth-1) spread)`` voxels
    on each side in x and y, ``depth-1`` below), so a batch of shadows is one ``bincount`` of
    precomputed flat offsets with no bounds test; entries that fall into the padding (off-grid
    shadow parts) are never read.
    """

    def __init__(
        self,
        span,
        voxel_size,
        depth,
        spread,
        shadow_a,
        shadow_b,
        ran=0.0,
        vert=0.0,
        uniforms=None,
        initial_key=None,
        filters=(),
    ):
        self.span = float(span)
        #: factors on the exposure of points (the growth forms' ``transmission``: a stand's or a
        #: gap's shade), applied in order; none = light from every side alike (the papers' model)
        self.filters = tuple(filters)
        self.voxel = float(voxel_size)
        self.n_vox = n = int(round(self.span / self.voxel))
        self.di, self.dj, self.dk, self.log_f = shadow_kernel(depth, spread, shadow_a, shadow_b)
        self.pad_xy = pxy = int(np.abs(self.di).max()) if self.di.size else 0
        self.pad_z = pz = int(-self.dk.min()) if self.dk.size else 0
        self.shape_pad = (n + 2 * pxy, n + 2 * pxy, n + pz)
        self._sj = n + pz
        self._si = (n + 2 * pxy) * self._sj
        self._off = self.di * self._si + self.dj * self._sj + self.dk
        self._interior = (slice(pxy, pxy + n), slice(pxy, pxy + n), slice(pz, pz + n))
        key = None if initial_key is None else (initial_key, n, float(ran), float(vert), pxy, pz)
        #: True when the initial field came from the cache (``uniforms`` was not called)
        self.from_cache = key is not None and key in _INITIAL
        if self.from_cache:
            _INITIAL.move_to_end(key)
            self._log0, self._roof = _INITIAL[key]
        else:
            if callable(uniforms):
                uniforms = uniforms()
            self._log0, self._roof = self._initial(n, ran, vert, uniforms)
            if key is not None:
                _INITIAL[key] = (self._log0, self._roof)
                while len(_INITIAL) > _INITIAL_KEEP:
                    _INITIAL.popitem(last=False)
        self._log = self._log0.copy()
        self._acc = np.zeros(self._log.shape)  # add_shadows' scratch: all zeros between casts

    def _initial(self, n, ran, vert, uniforms):
        """The padded flat log E0 and roof mask (read-only)."""
        k = np.arange(n)
        u = np.zeros(n**3) if uniforms is None else np.asarray(uniforms, dtype=np.float64)
        e0 = (1.0 - ran - vert) + ran * u.reshape(n, n, n) + vert * k[None, None, :] / n
        e0 = np.minimum(e0, 1.0)
        log0 = np.zeros(self.shape_pad)
        log0[self._interior] = np.maximum(np.log(np.maximum(e0, 1e-300)), _LOG_FLOOR)
        roof = np.zeros(self.shape_pad, dtype=bool)
        roof[self._interior][:, :, n - 1] = True
        log0, roof = log0.ravel(), roof.ravel()
        log0.flags.writeable = False
        roof.flags.writeable = False
        return log0, roof

    # ------------------------------------------------------------------ indexing
    def voxel_of(self, points: np.ndarray) -> np.ndarray:
        """(m, 3) int voxel indices (i, j, k) of points, clipped to the grid."""
        p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        ijk = np.empty(p.shape, dtype=np.int64)
        ijk[:, :2] = np.floor((p[:, :2] + 0.5 * self.span) / self.voxel)
        ijk[:, 2] = np.floor(p[:, 2] / self.voxel)
        np.clip(ijk, 0, self.n_vox - 1, out=ijk)
        return ijk

    def _flat(self, ijk: np.ndarray) -> np.ndarray:
        """Padded flat index of in-grid voxel indices."""
        return (ijk[:, 0] + self.pad_xy) * self._si + (ijk[:, 1] + self.pad_xy) * self._sj + ijk[:, 2] + self.pad_z

    def _apply(self, points, sign: float) -> None:
        if len(points) == 0 or self.log_f.size == 0:
            return
        base, cnt = np.unique(self._flat(self.voxel_of(points)), return_counts=True)
        add_shadows(self._log, self._acc, base, cnt, self._off, sign * self.log_f)

    def cast(self, points: np.ndarray) -> None:
        """Cast the shadows of segments starting at ``points`` ((m, 3), m) in one batch."""
        self._apply(points, 1.0)

    def remove(self, points: np.ndarray) -> None:
        """Remove the shadows of segments starting at ``points`` (exact inverse of :meth:`cast`)."""
        self._apply(points, -1.0)

    def rebuild(self, points: np.ndarray) -> None:
        """Reset to the initial field and cast ``points`` (e.g. all living segments)."""
        self._log = self._log0.copy()
        self.cast(points)

    # ------------------------------------------------------------------ reading
    def _grid(self, flat_pad_array: np.ndarray) -> np.ndarray:
        return flat_pad_array.reshape(self.shape_pad)[self._interior].ravel()

    @property
    def log_e(self) -> np.ndarray:
        """log E of every voxel (copy, C order of (i, j, k); the roof holds its masked value)."""
        return self._grid(self._log)

    @property
    def log_e0(self) -> np.ndarray:
        """log E0 of every voxel (copy)."""
        return self._grid(self._log0)

    @property
    def roof(self) -> np.ndarray:
        """Mask of the dark top layer over every voxel (C order of (i, j, k))."""
        return self._grid(self._roof)

    def voxel_exposure(self) -> np.ndarray:
        """Exposure of every voxel in [0, 1] (C order of (i, j, k)); the roof is 0."""
        e = np.minimum(np.exp(self.log_e), 1.0)
        e[self.roof] = 0.0
        return e

    def exposure(self, points: np.ndarray) -> np.ndarray:
        """Trilinear exposure at points over the 8 surrounding voxel centres, in [0, 1], times
        each of :attr:`filters` at the points."""
        p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        n = self.n_vox
        c = np.empty(p.shape)
        c[:, :2] = (p[:, :2] + 0.5 * self.span) / self.voxel - 0.5
        c[:, 2] = p[:, 2] / self.voxel - 0.5
        lo = np.clip(np.floor(c), 0, n - 2).astype(np.int64)
        t = np.clip(c - lo, 0.0, 1.0)
        base = self._flat(lo)
        offs = np.array([a * self._si + b * self._sj + g for a in (0, 1) for b in (0, 1) for g in (0, 1)])
        idx = base[:, None] + offs[None, :]
        vals = np.where(self._roof[idx], 0.0, np.minimum(np.exp(self._log[idx]), 1.0))
        tx, ty, tz = t[:, 0:1], t[:, 1:2], t[:, 2:3]
        wx = np.concatenate([1 - tx, tx], axis=1)
        wy = np.concatenate([1 - ty, ty], axis=1)
        wz = np.concatenate([1 - tz, tz], axis=1)
        w = (wx[:, :, None, None] * wy[:, None, :, None] * wz[:, None, None, :]).reshape(-1, 8)
        e = np.clip(np.sum(w * vals, axis=1), 0.0, 1.0)
        for factor in self.filters:
            e *= factor(p)
        return e

    def clamp_to_cube(self, points: np.ndarray) -> np.ndarray:
        """Points clipped into the cube (x, y in [-span/2, span/2], z in [0, span])."""
        h = 0.5 * self.span
        return np.clip(points, [-h, -h, 0.0], [h, h, self.span])

    def gradient(self, points: np.ndarray, r: float) -> np.ndarray:
        """Finite-difference gradient ``E(p + r e) - E(p - r e)`` per axis (no division by 2r),
        probes clamped into the cube."""
        p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        m = p.shape[0]
        probes = np.broadcast_to(p, (6, m, 3)).copy()
        for a in range(3):
            probes[2 * a, :, a] += r
            probes[2 * a + 1, :, a] -= r
        e = self.exposure(self.clamp_to_cube(probes.reshape(-1, 3))).reshape(6, m)
        return np.stack([e[0] - e[1], e[2] - e[3], e[4] - e[5]], axis=1)
