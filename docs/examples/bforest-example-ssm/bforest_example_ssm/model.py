"""A stochastic bracketed L-system tree, interpreted by a vectorised 3-D turtle.

Grammar (one rewriting step = one growth unit; ``k`` = ``whorl_size``, ``o`` = branch order)::

    axiom:  A(0)
    A(o) -> I(o) [ &(beta) /(psi_1) A(o+1) ] ... [ &(beta) /(psi_k) A(o+1) ] /(phi) A(o)
            each bracketed lateral kept with probability ``lateral_prob``, only while o < max_order
            (and, on the trunk, only from step ``bare_steps`` on: a clear bole)
    I(o) -> I(o)                                   (internodes never grow again)

``A`` is an apex, ``I`` an internode of length ``internode_length * length_decay**o``, ``&``
pitches a lateral down from its mother axis by the branch angle ``beta``, ``/`` rolls it to the
azimuth ``psi_j = phase + 2 pi j / k`` around the mother axis, and ``/(phi)`` rolls the
continuing apex by the divergence (phyllotaxis) angle so successive whorls are offset. Before
drawing an internode the turtle deviates its heading by a random angle (normal, sd
``angle_sd``) in a random direction and bends it towards the vertical by ``tropism``
(negative: drooping). Radii follow the pipe model: ``r**e`` of a cylinder is the sum of
``r**e`` of its children, every tip having ``tip_radius``.

The string is never materialised: every step rewrites all apices at once as numpy arrays
(position, heading, roll reference, order, mother row), so the only Python loop is over the
``iterations`` rewriting steps.
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np
from pydantic import Field

from bforest_core import SSM, ComponentSettings, ParameterSpec, SimulationFailed, Tree
from bforest_core.tree import subtree_sum

__all__ = ["LSystemSSM", "LSystemSettings", "PARAMETERS", "grow"]

_DEG = np.pi / 180.0
_UP = np.array([0.0, 0.0, 1.0])

PARAMETERS: tuple[ParameterSpec, ...] = (
    ParameterSpec(
        "iterations",
        6,
        1,
        10,
        integer=True,
        unit="",
        description="rewriting steps; every apex grows one internode per step",
        group="growth",
    ),
    ParameterSpec(
        "internode_length",
        0.4,
        0.05,
        1.5,
        unit="m",
        description="internode length of the trunk (order 0)",
        group="growth",
    ),
    ParameterSpec(
        "length_decay", 0.65, 0.3, 1.0, unit="", description="internode length factor per branch order", group="growth"
    ),
    ParameterSpec(
        "branch_angle",
        50.0,
        10.0,
        90.0,
        unit="deg",
        description="angle between a lateral and its mother axis",
        group="geometry",
    ),
    ParameterSpec(
        "divergence",
        137.5,
        0.0,
        180.0,
        unit="deg",
        description="roll of the apex between successive whorls (phyllotaxis)",
        group="geometry",
    ),
    ParameterSpec(
        "bare_steps",
        1,
        0,
        5,
        integer=True,
        unit="",
        description="first rewriting steps in which the trunk makes no whorl (clear bole)",
        group="branching",
    ),
    ParameterSpec(
        "whorl_size", 3, 1, 6, integer=True, unit="", description="lateral buds per whorl", group="branching"
    ),
    ParameterSpec(
        "lateral_prob",
        0.8,
        0.0,
        1.0,
        unit="",
        description="probability that a lateral bud grows (stochastic branching)",
        group="branching",
    ),
    ParameterSpec(
        "max_order",
        3,
        1,
        4,
        integer=True,
        unit="",
        description="highest branch order that is produced",
        group="branching",
    ),
    ParameterSpec(
        "angle_sd",
        4.0,
        0.0,
        30.0,
        unit="deg",
        description="sd of the random deviation of headings and branch angles",
        group="geometry",
    ),
    ParameterSpec(
        "tropism",
        0.25,
        -0.5,
        0.5,
        unit="",
        description="pull of every internode towards the vertical (negative: drooping)",
        group="geometry",
    ),
    ParameterSpec("tip_radius", 0.004, 0.001, 0.02, unit="m", description="radius of a shoot tip", group="radius"),
    ParameterSpec(
        "pipe_exponent",
        2.5,
        1.5,
        3.5,
        unit="",
        description="pipe-model exponent e: r**e = sum of the children's r**e",
        group="radius",
    ),
)


class LSystemSettings(ComponentSettings):
    """Settings of the L-system model (not fitted; set in the ``[ssm]`` section)."""

    max_segments: int = Field(
        20000, ge=1, description="cap on the number of internodes; larger trees fail with status 'too_many_segments'"
    )


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v, axis=1, keepdims=True)


def _perpendicular(h: np.ndarray, ref: np.ndarray) -> np.ndarray:
    """``ref`` made perpendicular to the unit rows of ``h`` and normalised (another reference
    where ``ref`` is parallel to ``h``)."""
    u = ref - np.sum(ref * h, axis=1, keepdims=True) * h
    nrm = np.linalg.norm(u, axis=1)
    bad = nrm < 1e-9
    if bad.any():
        hb = h[bad]
        alt = np.where(np.abs(hb[:, :1]) < 0.9, [[1.0, 0.0, 0.0]], [[0.0, 1.0, 0.0]])
        u[bad] = alt - np.sum(alt * hb, axis=1, keepdims=True) * hb
        nrm[bad] = np.linalg.norm(u[bad], axis=1)
    return u / nrm[:, None]


def grow(p: Mapping[str, float], rng: np.random.Generator, max_segments: int = 20000) -> dict[str, np.ndarray]:
    """Rewrite the axiom ``iterations`` times and interpret the result with the turtle.

    Parameters
    ----------
    p : mapping
        Resolved parameters (every name of :data:`PARAMETERS`).
    rng : numpy.random.Generator
        The only source of randomness.
    max_segments : int
        Cap on the number of internodes.

    Returns
    -------
    dict
        ``start``, ``axis`` (n, 3), ``length``, ``radius`` (n,), ``parent``, ``extension``
        (n,) int64 and ``order`` (n,) of the internodes, rows in growth order (parents first).

    Raises
    ------
    SimulationFailed
        ``too_many_segments`` when the tree would exceed ``max_segments`` internodes.
    """
    n_iter = int(p["iterations"])
    k = int(p["whorl_size"])
    max_order = int(p["max_order"])
    bare = int(p["bare_steps"])
    lat_p = float(p["lateral_prob"])
    sd = float(p["angle_sd"]) * _DEG
    beta0 = float(p["branch_angle"]) * _DEG
    div = float(p["divergence"]) * _DEG
    trop = float(p["tropism"])
    l0, decay = float(p["internode_length"]), float(p["length_decay"])

    # apex state, one row per apex
    pos = np.zeros((1, 3))
    head = _UP[None, :].copy()
    left = np.array([[1.0, 0.0, 0.0]])
    order = np.zeros(1, dtype=np.int64)
    mother = np.full(1, -1, dtype=np.int64)  # row of the internode the apex sits on
    cont = np.zeros(1, dtype=bool)  # apex continues its mother's axis (extension)
    phase = rng.uniform(0.0, 2 * np.pi, 1)
    chunks = []
    n = 0
    whorl = 2 * np.pi / k * np.arange(k)
    for it in range(n_iter):
        m = order.shape[0]
        if n + m > max_segments:
            raise SimulationFailed(
                "too_many_segments",
                f"step {it + 1} of {n_iter} would make {n + m} internodes (max_segments = {max_segments})",
            )
        # random deviation of the heading, then tropism towards the vertical
        dev = np.clip(rng.normal(0.0, 1.0, m) * sd, -80 * _DEG, 80 * _DEG)
        turn = rng.uniform(0.0, 2 * np.pi, m)
        side = np.cos(turn)[:, None] * left + np.sin(turn)[:, None] * np.cross(head, left)
        head = _unit(head + np.tan(dev)[:, None] * side)
        head = _unit(head + trop * _UP)
        left = _perpendicular(head, left)
        length = l0 * decay**order
        rows = n + np.arange(m)
        end = pos + head * length[:, None]
        chunks.append((pos, head, length, mother, cont, order))
        n += m
        # the whorl: k lateral buds, each kept with probability lateral_prob (buds made in the
        # last step would never grow an internode, so they are not made)
        lat = None
        if it < n_iter - 1 and lat_p > 0:
            can = (order < max_order) & ((order > 0) | (it >= bare))
            keep = can[:, None] & (rng.random((m, k)) < lat_p)
            beta = np.clip(beta0 + sd * rng.normal(0.0, 1.0, (m, k)), 1 * _DEG, 179 * _DEG)
            ii, jj = np.nonzero(keep)
            if ii.size:
                b = beta[ii, jj][:, None]
                psi = (phase[ii] + whorl[jj])[:, None]
                h, l = head[ii], left[ii]
                d = np.cos(b) * h + np.sin(b) * (np.cos(psi) * l + np.sin(psi) * np.cross(h, l))
                d = _unit(d)
                lat = (end[ii], d, _perpendicular(d, h), order[ii] + 1, rows[ii], rng.uniform(0.0, 2 * np.pi, ii.size))
        # the continuing apices (rolled by the divergence angle), then the new laterals
        pos, mother, cont, phase = end, rows, np.ones(m, dtype=bool), phase + div
        if lat is not None:
            pos = np.concatenate([pos, lat[0]])
            head = np.concatenate([head, lat[1]])
            left = np.concatenate([left, lat[2]])
            order = np.concatenate([order, lat[3]])
            mother = np.concatenate([mother, lat[4]])
            cont = np.concatenate([cont, np.zeros(lat[4].size, dtype=bool)])
            phase = np.concatenate([phase, lat[5]])

    start, axis, length, parent, is_cont, order = (np.concatenate(c) for c in zip(*chunks))
    extension = np.full(n, -1, dtype=np.int64)
    ext_rows = np.flatnonzero(is_cont)
    extension[parent[ext_rows]] = ext_rows
    # pipe model: r**e = (number of tips in the subtree) * tip_radius**e
    n_children = np.bincount(parent[1:], minlength=n)
    tips = subtree_sum(parent, (n_children == 0).astype(np.float64))
    radius = float(p["tip_radius"]) * tips ** (1.0 / float(p["pipe_exponent"]))
    return dict(start=start, axis=axis, length=length, radius=radius, parent=parent, extension=extension, order=order)


class LSystemSSM(SSM):
    """Stochastic bracketed L-system: whorls of laterals, phyllotaxis, tropism, pipe-model radii.

    Examples
    --------
    >>> import bforest_core as bf
    >>> ssm = bf.component("ssm", "lsystem")
    >>> tree = ssm.simulate({"iterations": 5, "branch_angle": 40.0}, seed=1)
    >>> tree.metadata["model"]
    'lsystem'
    """

    name = "lsystem"
    summary = "stochastic bracketed L-system tree (example third-party plugin)"
    Settings = LSystemSettings

    @property
    def parameters(self) -> list[ParameterSpec]:
        return list(PARAMETERS)

    def simulate(self, params: Mapping[str, float], seed: int) -> Tree:
        """Grow one tree.

        Parameters
        ----------
        params : mapping
            Parameter values by name (see :data:`PARAMETERS`); missing names take their
            defaults, unknown names raise ``ValueError``.
        seed : int
            Seeds the model's single ``numpy.random.Generator``.

        Returns
        -------
        Tree
            Growth topology: the apical child of every internode is its extension.

        Raises
        ------
        SimulationFailed
            ``too_many_segments`` above the ``max_segments`` setting.
        """
        p = self.resolve_params(params)
        rng = np.random.default_rng(seed)
        a = grow(p, rng, self.settings.max_segments)
        return Tree(
            a["start"],
            a["axis"],
            a["length"],
            a["radius"],
            a["parent"],
            a["extension"],
            metadata={
                "model": self.name,
                "params": p,
                "seed": int(seed),
                "status": "ok",
                "n_segments": int(a["length"].shape[0]),
                "units": "m",
            },
        )
