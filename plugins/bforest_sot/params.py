"""Parameters of the SOT model (docs/models.md B.3, calibrated defaults of B.4, clone noise of E).

Groups I-V follow the *proposal* of docs/models.md B.3 (I initial growth, limits, pipe model; II environment;
III apical dominance; IV shadow propagation; V angles/branching); the geometry constants
``node_length``, ``voxel_size`` and ``span`` are in group ``"fixed"``.
Ranges of the clone-noise sds are project choices (docs/models.md E gives only their defaults).
This table holds the papers' model; each growth form declares its own parameters in its module
(:mod:`bforest_sot.forms`), and :func:`model_parameters` lists them together, group by group.
"""

from __future__ import annotations

import functools
from collections.abc import Mapping

from bforest_core.interfaces import ParameterSpec

from .forms.base import check_forms

P = ParameterSpec

PARAMETERS: list[ParameterSpec] = [
    # ---- I: initial growth, limits, pipe model
    P("max_iter", 18, 8, 30, True, "cycles", "growth cycles including the seed cycle", "I"),
    P("alpha0", 1.0, 0.0, 5.0, False, "internode", "base vigor offset: v_base = alpha0 + alpha1 * Q_base", "I"),
    P("alpha1", 1.5, 0.5, 3.0, False, "internode", "vigor per unit of light collected by the tree", "I"),
    P(
        "max_grow",
        3.0,
        2.0,
        20.0,
        False,
        "internode",
        "vigor cap of a bud; a shoot has floor(v) <= floor(max_grow) metamers per cycle",
        "I",
    ),
    P(
        "drop_thresh",
        0.2,
        0.05,
        0.5,
        False,
        "internode",
        "a branch is shed when its vigor per distal element v/N falls to this value",
        "I",
    ),
    P("init_width", 0.02, 0.01, 0.04, False, "m", "diameter of a terminal segment", "I"),
    P("pipe_exp", 2.6, 2.0, 3.0, False, "", "pipe-model exponent n: d^n = sum of children's d_i^n", "I"),
    P(
        "nonlinear",
        1.0,
        0.5,
        2.0,
        False,
        "",
        "light exponent kappa of the Borchert-Honda allocation (1 = linear BH; docs/models.md B.3 groups it I/III)",
        "I",
    ),
    # ---- II: environment
    P("reorient", 0.4, 0.0, 1.0, False, "", "weight xi of the light gradient in the shoot target direction", "II"),
    P("redir_strength", 0.4, 0.0, 1.0, False, "", "cap of the fraction of the angle turned per metamer", "II"),
    P("tropism", 0.02, -0.1, 0.3, False, "", "vertical tropism eta (positive = upwards)", "II"),
    P("sample_rad", 0.32, 0.1, 0.6, False, "m", "probe distance of the light-gradient estimate", "II"),
    P("ran", 0.05, 0.0, 0.2, False, "", "initial exposure noise: E0 += ran * U(0, 1) per voxel", "II"),
    P("vert", 0.0, 0.0, 0.3, False, "", "vertical gradient of the initial exposure", "II"),
    # ---- III: apical dominance
    P("init_lambda", 0.65, 0.35, 0.9, False, "", "apical control lambda up to `delay` cycles", "III"),
    P("targ_lambda", 0.51, 0.35, 0.9, False, "", "apical control lambda after delay + transition", "III"),
    P("delay", 7.0, 0.0, 20.0, False, "cycles", "cycles at init_lambda", "III"),
    P("transition", 7.0, 1.0, 20.0, False, "cycles", "cycles of the linear ramp from init to targ lambda", "III"),
    P("lambda_sd", 0.0, 0.0, 0.05, False, "", "clone noise: lambda(c) + N(0, sd) per cycle, clipped to [0, 1]", "III"),
    # ---- IV: shadow propagation
    P("depth", 6, 2, 10, True, "voxels", "shadow pyramid depth q_max (layers 1 .. depth-1 are shaded)", "IV"),
    P("spread", 1.0, 0.5, 2.0, False, "", "half-width of shadow layer l is floor(l * spread) voxels", "IV"),
    P("shadow_a", 0.5, 0.1, 0.9, False, "", "shadow strength a (< shadow_b): f = 1 - a * b^-d", "IV"),
    P("shadow_b", 2.0, 1.1, 10.0, False, "", "shadow dissipation base b (> 1)", "IV"),
    # ---- V: angles and branching
    P("branch_angle", 65.0, 20.0, 120.0, False, "deg", "lateral shoot turn about the parent's up vector", "V"),
    P("phyllotaxis", 137.52, 90.0, 180.0, False, "deg", "roll of the up vector about the heading per metamer", "V"),
    P("nonplanar_twist", 90.0, 0.0, 180.0, False, "deg", "roll of a lateral shoot's up vector about its heading", "V"),
    P("branch_angle_sd", 5.0, 0.0, 40.0, False, "deg", "clone noise: sd of the branch angle, per lateral shoot", "V"),
    P("phyllotaxis_sd", 10.0, 0.0, 30.0, False, "deg", "clone noise: sd of the phyllotaxis angle, per metamer", "V"),
    P("tropism_sd", 0.0, 0.0, 0.05, False, "", "clone noise: sd of the tropism, per shoot", "V"),
    # ---- fixed geometry (GS)
    P(
        "node_length",
        0.2,
        0.05,
        0.6,
        False,
        "m",
        "internode length (1 node unit of vigor; one lateral bud per "
        "internode, so it sets how many branches a metre of stem can carry); GS: 0.2 m; down to 0.05 m for a "
        "pine's dense branching, up to 0.6 m for trees of 18-20 m",
        "fixed",
    ),
    P(
        "voxel_size",
        0.2,
        0.2,
        0.5,
        False,
        "m",
        "light voxel edge; GS: 0.2 m; coarser for large trees, "
        "whose internodes are longer (the field's cost grows with (span / voxel_size)^3)",
        "fixed",
    ),
    P(
        "span",
        12.0,
        12.0,
        30.0,
        False,
        "m",
        "edge of the world cube (tree at the XY centre, Z up); GS: 12 m, larger for trees taller than about 11 m",
        "fixed",
    ),
]

#: the groups in the order the model lists its parameters (a form's go after the model's of its group)
GROUPS = ("I", "II", "III", "IV", "V", "fixed")


@functools.cache
def model_parameters(forms: tuple) -> tuple[ParameterSpec, ...]:
    """The parameters of the model with the growth forms ``forms``: the papers' table and each
    form's parameters, group by group (within a group the papers' first, then the forms' in order)."""
    check_forms(forms, PARAMETERS)
    extra = [p for form in forms for p in form.parameters]
    return tuple(sorted(PARAMETERS + extra, key=lambda p: GROUPS.index(p.group) if p.group in GROUPS else len(GROUPS)))


def validate(p: Mapping[str, float], forms=()) -> None:
    """Raise ``ValueError`` naming the first invalid parameter of a resolved parameter dict (the
    papers' parameters first, then each form's ``check``)."""

    # numbers and finiteness are checked (and integers rounded) by SSM.resolve_params
    def need(ok: bool, name: str, rule: str):
        if not ok:
            raise ValueError(f"invalid SOT parameter {name!r} = {p[name]!r}: must be {rule}")

    need(p["max_iter"] >= 1, "max_iter", ">= 1")
    need(p["depth"] >= 2, "depth", "an integer >= 2")
    need(p["shadow_b"] > 1, "shadow_b", "> 1")
    need(0 <= p["shadow_a"] < p["shadow_b"], "shadow_a", f"in [0, shadow_b = {p['shadow_b']!r})")
    need(p["spread"] >= 0, "spread", ">= 0")
    need(p["ran"] >= 0, "ran", ">= 0")
    need(p["vert"] >= 0, "vert", ">= 0")
    need(p["ran"] + p["vert"] <= 1, "ran", f"such that ran + vert <= 1 (vert = {p['vert']!r})")
    for name in (
        "node_length",
        "voxel_size",
        "span",
        "init_width",
        "sample_rad",
        "max_grow",
        "pipe_exp",
        "nonlinear",
        "transition",
    ):
        need(p[name] > 0, name, "> 0")
    need(round(p["span"] / p["voxel_size"]) >= 2, "voxel_size", f"<= span / 2 (span = {p['span']!r})")
    for name in ("alpha0", "alpha1", "delay"):
        need(p[name] >= 0, name, ">= 0")
    for name in ("init_lambda", "targ_lambda", "redir_strength"):
        need(0 <= p[name] <= 1, name, "in [0, 1]")
    for name in ("branch_angle_sd", "phyllotaxis_sd", "lambda_sd", "tropism_sd"):
        need(p[name] >= 0, name, ">= 0 (a standard deviation)")
    for form in forms:
        form.check(p, need)
