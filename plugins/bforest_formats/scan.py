"""Synthetic laser scans of a cylinder tree: points on the cylinder surfaces, written as LAS/LAZ
(through laspy) or plain XYZ text, with the true structure kept as extra dimensions.

A user tests a QSM reconstruction method on clones whose structure is known: scan the clone,
reconstruct it, compare. Two sampling modes:

``uniform``
    Occlusion-free and direction-free: every lateral surface point is equally likely, ``density``
    points per m² on average (Poisson per cylinder). Range noise is applied along the surface
    normal.
``scanner``
    One terrestrial scanner at ``scanner`` (x, y, z in m), occlusion-free: a surface point is kept
    with probability ``cos(incidence) * (reference_range / range)²`` (capped at 1), so surfaces
    facing away from the scanner get no points, grazing ones few, far ones fewer (a
    constant-angular-step scanner's footprint grows with range²); ``density`` is the density at
    ``reference_range`` and normal incidence. Range noise is applied along the beam.

Extra dimensions of a LAS file: ``cylinder_id`` (row of the tree's cylinder table, 0-based),
``branch_id`` (0-based) and ``branch_order`` (0 = stem); in a plot's scan also ``tree_id``
(the tree's place in the plot, 0-based).
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Literal, Optional

import numpy as np
from pydantic import Field

from bforest_core.cylinders import resolve_options
from bforest_core.errors import QSMFormatError
from bforest_core.interfaces import ComponentSettings, QSMWriter
from bforest_core.provenance import provenance, provenance_line
from bforest_core.tables import format_columns

#: ASPRS class of every point: 5 = high vegetation (the points are a tree's wood)
LAS_CLASS = 5
#: extra dimensions of a LAS scan: the true structure of every point (``tree_id`` in a plot's)
EXTRA_DIMS = (("cylinder_id", np.uint32), ("branch_id", np.uint32), ("branch_order", np.uint8), ("tree_id", np.uint32))


class ScanSettings(ComponentSettings):
    density: float = Field(
        2000.0,
        gt=0,
        description="points per m² of lateral cylinder surface (scanner mode: at reference_range and normal incidence)",
    )
    mode: Literal["uniform", "scanner"] = Field(
        "uniform",
        description="uniform: every surface point equally likely; scanner: one occlusion-free scanner position",
    )
    scanner: Optional[tuple[float, float, float]] = Field(
        None, description="scanner position (m); default: 10 m from the stem base along -y, 1.5 m above it"
    )
    reference_range: float = Field(10.0, gt=0, description="range (m) at which the scanner mode has `density`")
    noise: float = Field(0.0, ge=0, description="sd (m) of Gaussian range noise")
    seed: int = Field(0, description="seed of the sampling and the noise")


def _frames(axis: np.ndarray):
    """Two unit vectors per cylinder, orthogonal to its axis and to each other."""
    helper = np.where(np.abs(axis[:, 2:3]) < 0.9, [[0.0, 0.0, 1.0]], [[1.0, 0.0, 0.0]])
    u = np.cross(axis, helper)
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    return u, np.cross(axis, u)


def scan_points(
    tree,
    density: float = 2000.0,
    mode: str = "uniform",
    scanner=None,
    reference_range: float = 10.0,
    noise: float = 0.0,
    seed: int = 0,
) -> dict[str, np.ndarray]:
    """Points on the lateral cylinder surfaces (see the module docstring for the two modes).

    Returns
    -------
    dict
        ``xyz`` (n, 3) m, ``cylinder_id`` (n,), ``branch_id`` (n,), ``branch_order`` (n,) and
        ``normal`` (n, 3): the outward surface normal at each point before noise.
    """
    s = ScanSettings(
        density=density, mode=mode, scanner=scanner, reference_range=reference_range, noise=noise, seed=seed
    )
    rng = np.random.default_rng(s.seed)
    area = 2.0 * np.pi * tree.radius * tree.length
    base = tree.start[0]
    if s.mode == "scanner":
        pos = np.asarray(s.scanner if s.scanner is not None else base + [0.0, -10.0, 1.5], float)
        # candidates at the highest density any cylinder can reach, then thinned (vectorised)
        near = np.maximum(
            np.linalg.norm(tree.start + 0.5 * tree.length[:, None] * tree.axis - pos, axis=1)
            - tree.length
            - tree.radius,
            1e-3,
        )
        boost = np.clip((s.reference_range / near) ** 2, 1.0, None)
        lam = s.density * area * boost
    else:
        lam = s.density * area
    counts = rng.poisson(lam)
    cyl = np.repeat(np.arange(tree.n), counts)
    t = rng.random(cyl.size) * tree.length[cyl]
    phi = rng.random(cyl.size) * 2.0 * np.pi
    u, v = _frames(tree.axis)
    normal = np.cos(phi)[:, None] * u[cyl] + np.sin(phi)[:, None] * v[cyl]
    xyz = tree.start[cyl] + t[:, None] * tree.axis[cyl] + tree.radius[cyl, None] * normal
    if s.mode == "scanner":
        beam = xyz - pos
        rangev = np.linalg.norm(beam, axis=1)
        beam /= rangev[:, None]
        cosinc = -np.einsum("ij,ij->i", beam, normal)
        keep_p = np.clip(cosinc, 0.0, None) * (s.reference_range / rangev) ** 2 / boost[cyl]
        keep = rng.random(cyl.size) < np.minimum(keep_p, 1.0)
        cyl, xyz, normal, beam = cyl[keep], xyz[keep], normal[keep], beam[keep]
        if s.noise:
            xyz = xyz + s.noise * rng.standard_normal(cyl.size)[:, None] * beam
    elif s.noise:
        xyz = xyz + s.noise * rng.standard_normal(cyl.size)[:, None] * normal
    return {
        "xyz": xyz,
        "cylinder_id": cyl.astype(np.uint32),
        "branch_id": tree.branch[cyl].astype(np.uint32),
        "branch_order": tree.order[cyl].astype(np.uint8),
        "normal": normal,
    }


class LASWriter(QSMWriter):
    """Synthetic laser scan as LAS 1.4 (point format 6, mm precision) or LAZ, through laspy.

    Every point is a single return (return number 1 of 1: LAS 1.4 forbids 0) of class 5, high
    vegetation; the header's generating software names Bayes Forest and a VLR (user id
    ``BayesForest``, record 1) holds the provenance as JSON: model, parameters, seed, version and
    the scan settings."""

    name = "las"
    summary = "synthetic laser scan of the cylinder surfaces (LAS/LAZ via laspy; cylinder, branch, order kept)"
    suffixes = (".las", ".laz")
    Settings = ScanSettings

    def write(self, tree, path, **options) -> Path:
        o = resolve_options(self, options)
        pts = scan_points(tree, **o.model_dump())
        return _write_las(Path(path), pts, provenance(tree, scan=o.model_dump()), provenance(tree)["software"])

    def write_plot(self, trees, path, names=None, **options) -> Path:
        """A synthetic scan of a plot: every tree scanned as :meth:`write` scans one (tree ``i``
        with the seed ``seed + i``), one LAS file with the extra dimension ``tree_id`` (the
        tree's place in ``names``, 0-based); the provenance VLR lists every tree's."""
        o = resolve_options(self, options)
        names = names or [f"tree_{i}" for i in range(len(trees))]
        scans = [scan_points(t, **{**o.model_dump(), "seed": o.seed + i}) for i, t in enumerate(trees)]
        pts = {k: np.concatenate([sc[k] for sc in scans]) for k in ("xyz", "cylinder_id", "branch_id", "branch_order")}
        pts["tree_id"] = np.repeat(np.arange(len(trees), dtype=np.uint32), [sc["xyz"].shape[0] for sc in scans])
        info = {
            "software": provenance(trees[0])["software"],
            "scan": o.model_dump(),
            "trees": [{"tree_id": i, "name": n, **provenance(t)} for i, (n, t) in enumerate(zip(names, trees))],
        }
        return _write_las(Path(path), pts, info, info["software"])


def _write_las(path: Path, pts: dict, info: dict, software: str) -> Path:
    """One LAS 1.4 (point format 6) or LAZ file of ``pts`` (``xyz`` and the extra dimensions it
    holds), with ``info`` as the provenance VLR."""
    import laspy

    if path.suffix.lower() == ".laz" and not laspy.LazBackend.detect_available():
        raise QSMFormatError(path, "writing LAZ needs a LAZ backend: pip install lazrs (or write .las)")
    extra = [(k, t) for k, t in EXTRA_DIMS if k in pts]
    header = laspy.LasHeader(point_format=6, version="1.4")
    header.add_extra_dims([laspy.ExtraBytesParams(name=k, type=t) for k, t in extra])
    xyz = pts["xyz"]
    header.offsets = np.floor(xyz.min(axis=0)) if xyz.size else np.zeros(3)
    header.scales = np.array([0.001, 0.001, 0.001])
    header.generating_software = software[:32]
    header.system_identifier = "synthetic scan (cylinder QSM)"
    text = json.dumps(info, separators=(",", ":"), allow_nan=False)
    header.vlrs.append(
        laspy.VLR(user_id="BayesForest", record_id=1, description="provenance (JSON)", record_data=text.encode("utf-8"))
    )
    las = laspy.LasData(header)
    las.x, las.y, las.z = xyz[:, 0], xyz[:, 1], xyz[:, 2]
    n = xyz.shape[0]
    las.return_number = np.ones(n, np.uint8)
    las.number_of_returns = np.ones(n, np.uint8)
    las.classification = np.full(n, LAS_CLASS, np.uint8)
    for k, _ in extra:
        las[k] = pts[k]
    las.write(str(path))
    return path


class XYZWriter(QSMWriter):
    """Synthetic laser scan as plain text: ``x y z cylinder_id branch_order branch_id``."""

    name = "xyz"
    summary = "synthetic laser scan of the cylinder surfaces as XYZ text (with cylinder, order, branch)"
    suffixes = (".xyz",)
    Settings = ScanSettings

    def write(self, tree, path, **options) -> Path:
        o = resolve_options(self, options)
        path = Path(path)
        pts = scan_points(tree, **o.model_dump())
        rows = format_columns(
            [(pts["xyz"], "%.4f"), (pts["cylinder_id"], "%d"), (pts["branch_order"], "%d"), (pts["branch_id"], "%d")],
            sep=" ",
        )
        with open(path, "w", newline="\n") as fh:
            fh.write("# x y z cylinder_id branch_order branch_id (m; synthetic scan, Bayes Forest)\n")
            fh.write(f"# {provenance_line(tree, scan=o.model_dump())}\n")
            fh.write(rows)
        return path
