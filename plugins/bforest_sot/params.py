"""Parameters of the SOT model (docs/models.md B.3, calibrated defaults of B.4, clone noise of E).

Groups I-V follow the *proposal* of docs/models.md B.3 (I initial growth, limits, pipe model; II environment;
III apical dominance; IV shadow propagation; V angles/branching); the geometry constants
``node_length``, ``voxel_size`` and ``span`` are in group ``"fixed"`` with ``lower == upper``.
Ranges of the clone-noise sds are project choices (docs/models.md E gives only their defaults).
"""

from __future__ import annotations

from collections.abc import Mapping

from bforest_core.interfaces import ParameterSpec

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
        "vigor_sd",
        0.0,
        0.0,
        1.0,
        False,
        "",
        "an addition: sd of the log of a shoot's own vigor cap: each lateral shoot caps at max_grow x "
        "exp(vigor_sd x N(0, 1)) and its axis keeps that cap (axes of one age differ in vigor: "
        "long limbs and weak branches); the stem keeps max_grow; 0 = the papers' model (no draws)",
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
    P(
        "stand_shade",
        0.0,
        0.0,
        2.0,
        False,
        "1/m",
        "extinction of the surrounding stand's canopy: exposure "
        "times exp(-stand_shade * depth below the tree's top); 0 = open-grown (the papers' model)",
        "II",
    ),
    P(
        "gap_shade",
        0.0,
        0.0,
        5.0,
        False,
        "1/m",
        "an addition: extinction of the neighbours' shade on one side of the tree: exposure times "
        "exp(-gap_shade * distance behind the stem base, away from gap_azimuth), so the crown grows "
        "into the gap and the stem leans towards it; 0 = no gap (the papers' model)",
        "II",
    ),
    P(
        "gap_azimuth",
        0.0,
        -180.0,
        180.0,
        False,
        "deg",
        "an addition: direction of the open side (gap_shade), counterclockwise from +x in the tree's frame",
        "II",
    ),
    P(
        "gap_lean",
        0.0,
        0.0,
        80.0,
        False,
        "deg",
        "an addition: an upward tropism's direction tilted from the zenith by this angle towards gap_azimuth "
        "(the brightest sky of a tree at a gap), so shoots and the stem lean into the gap; a sag (tropism < 0) "
        "stays downwards; 0 = upright (the papers' model)",
        "II",
    ),
    P(
        "stem_guide",
        0.0,
        0.0,
        1.0,
        False,
        "",
        "an addition: how far the stem's (order 0) shoots are steered along the setting stem_path, the "
        "stem of the measured tree (a guide curve, as TreeSketch grows the self-organizing tree along strokes): each "
        "cycle's stem shoot heads for the point of the path one shoot length beyond its own arc length; "
        "1 = the stem follows the path, 0 (or no stem_path) = the papers' model",
        "II",
    ),
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
    P(
        "heading_sd",
        0.0,
        0.0,
        90.0,
        False,
        "deg",
        "clone noise (an addition): sd of a bend of each branch metamer "
        "about its up vector, so that branches wind as scanned ones do (the stem stays straight); 0 = smooth axes",
        "V",
    ),
    P(
        "bud_abort",
        0.0,
        0.0,
        0.95,
        False,
        "",
        "an addition: probability that a lateral bud aborts as its metamer forms (it takes no light or vigor and "
        "never grows): internodes as short as a broadleaf's shoots with fewer branches than buds, as most axillary "
        "buds of broadleaved trees never break; 0 = the papers' model (no draws)",
        "V",
    ),
    P(
        "leader_death",
        0.0,
        0.0,
        1.0,
        False,
        "",
        "an addition: probability per cycle that a growing apical bud "
        "dies (terminal flowering, frost, damage), so the lateral buds below it take over; with opposite buds a "
        "fork (sympodial growth of many broadleaved trees; 1 = every shoot forks); 0 = the papers' model (no draws)",
        "V",
    ),
    P(
        "stem_death",
        1.0,
        0.0,
        1.0,
        False,
        "",
        "an addition: the stem's (order 0) apical buds die at stem_death x leader_death; 1 = as every "
        "leader's, 0 = a monopodial trunk whose branches fork (Scarrone's architectural model)",
        "V",
    ),
    P(
        "relay_angle",
        1.0,
        0.0,
        1.0,
        False,
        "",
        "an addition: a lateral shoot at a node whose leader died or was shed (a relay shoot: sympodial "
        "substitution growth) leaves at relay_angle x its branch angle, so the shoots that take over rise "
        "as the lost leader did and a fork's arms diverge narrowly; 1 = as every lateral (the papers' model)",
        "V",
    ),
    P(
        "death_delay",
        0.0,
        0.0,
        30.0,
        False,
        "cycles",
        "an addition: apical buds die (leader_death) from cycle death_delay + 1 on, e.g. from the onset of flowering",
        "V",
    ),
    P(
        "short_shoot",
        0.0,
        0.0,
        1.0,
        False,
        "",
        "an addition: probability that a lateral shoot is a short shoot (one internode, short_length x node_length, whose "
        "buds never grow: the spurs and short shoots of broadleaved trees); 0 = the papers' model (no draws)",
        "V",
    ),
    P(
        "short_length",
        1.0,
        0.1,
        1.0,
        False,
        "",
        "an addition: a short shoot's internode as a share of node_length (short shoots have compressed "
        "internodes); 1 = one internode of node_length",
        "V",
    ),
    P(
        "shed_stub",
        0.0,
        0.0,
        1.0,
        False,
        "",
        "an addition (output only): probability that a shed branch leaves a dead stub, its base broken "
        "somewhere along its first internode, with the width it had when shed (natural pruning); "
        "0 = the papers' model",
        "V",
    ),
    P(
        "prune_tips",
        0.0,
        0.0,
        50.0,
        False,
        "tips",
        "an addition (output only): the tree drawn as a simplified QSM draws it: a shoot thinner than "
        "init_width * prune_tips^(1/pipe_exp) (in the pipe model, one carrying fewer than prune_tips growing "
        "tips) is left out with all beyond it; at most 1 = the papers' model",
        "V",
    ),
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

INTEGER_NAMES = tuple(p.name for p in PARAMETERS if p.integer)


def validate(p: Mapping[str, float]) -> None:
    """Raise ``ValueError`` naming the first invalid parameter of a resolved parameter dict."""

    # numbers and finiteness are checked (and integers rounded) by SSM.resolve_params
    def need(ok: bool, name: str, rule: str):
        if not ok:
            raise ValueError(f"invalid SOT parameter {name!r} = {p[name]!r}: must be {rule}")

    need(p["max_iter"] >= 1, "max_iter", ">= 1")
    need(p["depth"] >= 2, "depth", "an integer >= 2")
    need(p["shadow_b"] > 1, "shadow_b", "> 1")
    need(0 <= p["shadow_a"] < p["shadow_b"], "shadow_a", f"in [0, shadow_b = {p['shadow_b']!r})")
    need(p["spread"] >= 0, "spread", ">= 0")
    need(p["gap_shade"] >= 0, "gap_shade", ">= 0")
    need(0 <= p["gap_lean"] < 90, "gap_lean", "in [0, 90) degrees")
    need(0 <= p["stem_death"] <= 1, "stem_death", "in [0, 1]")
    need(0 <= p["stem_guide"] <= 1, "stem_guide", "in [0, 1]")
    need(0 <= p["shed_stub"] <= 1, "shed_stub", "in [0, 1]")
    need(p["prune_tips"] >= 0, "prune_tips", ">= 0")
    need(p["vigor_sd"] >= 0, "vigor_sd", ">= 0 (a standard deviation)")
    need(0 <= p["bud_abort"] < 1, "bud_abort", "in [0, 1) (a probability; 1 would leave no lateral bud)")
    need(0 < p["short_length"] <= 1, "short_length", "in (0, 1] (a share of node_length)")
    need(0 <= p["relay_angle"] <= 1, "relay_angle", "in [0, 1] (a share of the branch angle)")
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
