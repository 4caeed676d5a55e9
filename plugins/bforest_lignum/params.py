"""Parameters and presets of the simplified stochastic LIGNUM model (docs/models.md A.3, A.4).

Every parameter has one snake_case name. The Normal ``(mean, sd)`` pairs of docs/models.md A.3 (``lr``,
``q``, ``r_env``) are flat parameters ``lr_mean``/``lr_sd``, ``q_mean``/``q_sd`` and
``r_env_mean``/``r_env_sd``. The two categorical settings of the table are integer codes so that
every parameter fits :class:`~bforest_core.interfaces.ParameterSpec`:

* ``bud_table``: 0 = ``p98``, 1 = ``s08`` (the strings are accepted by ``simulate`` too);
* ``collision``: 0 = off, 1 = on (``True``/``False`` accepted).

A preset (``sf_synthetic`` by default, ``sf_real``, ``p98``, ``s08``, ``sf_test16``) sets the
defaults; parameters passed to ``simulate`` override them.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping

from bforest_core.envelope import SHADE_MEANING, SHADE_SPEC
from bforest_core.interfaces import ParameterSpec

P = ParameterSpec

BUD_TABLES = ("p98", "s08")
PAIRS = ("lr", "q", "r_env")
PRESETS = ("sf_synthetic", "sf_real", "p98", "s08", "sf_test16")


#: name, default (the default preset's, sf_synthetic), plausible lower, upper, integer, unit, meaning
#: (the symbol of docs/models.md A.3 first), group: the style of every model's table (SOT's too)
PARAMETERS: list[ParameterSpec] = [
    P("years", 15, 7, 40, True, "iter", "[T] iterations (growth in the first T-1)", "time"),
    P("radiation", 30.0, 5, 100, False, "", "[R] full-exposure radiation (relative)", "light"),
    P("shadow_max", 10.0, 5, 80, False, "", "[S_max] one segment's shadow at the pyramid top", "light"),
    P("shadow_len", 0.55, 0.3, 1.5, False, "m", "[S_L] shadow depth", "light"),
    P("voxel_size", 0.02, 0.01, 0.05, False, "m", "[V_S] voxel edge of the shadow lattice", "light"),
    P(
        "stand_shade",
        0.0,
        0.0,
        40.0,
        False,
        "m-1",
        "[S_stand] shade of the surrounding stand per metre below the tree's top: S += S_stand (z_top - "
        "z) (0 = an open-grown tree, the papers' model)",
        "light",
    ),
    P(
        **SHADE_SPEC,
        description=f"[-] {SHADE_MEANING}: I times 1 - envelope_shade (1 - the envelope's light there); 1 = no light "
        "outside (its buds stay dormant), 0 (or no crown_envelope) = the papers' model",
        group="light",
    ),
    P(
        "r_env_mean",
        1.33,
        0.1,
        4.0,
        False,
        "m",
        "[R_env mean] mean of TN R_env: buds farther from the stem axis die (1 draw per bud per year)",
        "space",
    ),
    P("r_env_sd", 0.0, 0.0, 0.3, False, "m", "[R_env sd] sd of TN R_env", "space"),
    P(
        "lr_mean",
        0.009,
        0.0045,
        0.04,
        False,
        "",
        "[L_R mean] mean of TN L_R, radius:length of a new shoot (1 draw per shoot; the published range "
        "(docs/models.md A.3) stops at 0.0135, scanned pines' first-order branches have base "
        "radius:length 0.015-0.024, the medians)",
        "shoot",
    ),
    P("lr_sd", 0.001, 0.0, 0.003, False, "", "[L_R sd] sd of TN L_R", "shoot"),
    P(
        "q_mean",
        0.2,
        0.0,
        0.4,
        False,
        "",
        "[Q mean] mean of TN Q, apical dominance 1 - w*Q (1 draw per bud + 1 per shoot)",
        "shoot",
    ),
    P("q_sd", 0.03, 0.0, 0.05, False, "", "[Q sd] sd of TN Q", "shoot"),
    P(
        "beta_init",
        35.0,
        17.5,
        90,
        False,
        "deg",
        "[beta_init] angle of a new lateral to its parent (the published range (docs/models.md A.3) stops"
        " at 60; scanned pines' first-order branches leave the stem at 55-120 deg)",
        "angles",
    ),
    P("beta_incr", 10.0, 0, 15, False, "deg", "[Delta beta] mean yearly bending (mean of delta)", "angles"),
    P("beta_max", 95.0, 40, 105, False, "deg", "[beta_max] bending cap vs the mother segment", "angles"),
    P("zeta_sd", 5.0, 0, 10, False, "deg", "[Delta zeta] sd of delta ~ N(Delta beta, Delta zeta)", "angles"),
    P(
        "gamma_sd",
        5.0,
        0,
        10,
        False,
        "deg",
        "[Delta gamma] azimuth noise N(0, Delta gamma) of apical shoots of order > 0",
        "angles",
    ),
    P("init_rot_angle", 144.0, 0, 360, False, "deg", "[INITROTANG] g_ref turn between trunk whorls", "angles"),
    P(
        "whorl_rotation_sd",
        15.0,
        0,
        30,
        False,
        "deg",
        "[sigma_whorl] clone noise N(0, sd) added to each trunk-whorl turn",
        "angles",
    ),
    P("shed_year", 0, 0, 15, True, "iter", "[T_sh] minimum tip age for shedding", "shedding"),
    P(
        "shed_dist",
        0,
        0,
        2,
        True,
        "",
        "[SHEDDIST] order-1 shedding: 0 all, 1 uniform, 2 Poisson number of tip segments",
        "shedding",
    ),
    P("shed_mu", 2.0, 0, 6, False, "seg", "[mu_sh] Poisson mean of shed tip segments (capped at 10)", "shedding"),
    P("foliage_per_area", 1.3, 0.5, 1.5, False, "kg m-2", "[a_f] foliage per segment surface", "carbon"),
    P("root_per_foliage", 0.5, 0.0, 2.0, False, "", "[a_r] new roots per new foliage", "carbon"),
    P("root_senescence", 0.33, 0.0, 1.0, False, "yr-1", "[s_r] yearly root loss", "carbon"),
    P("sapwood_senescence", 0.07, 0.02, 0.2, False, "yr-1", "[s_s] sapwood -> heartwood per year", "carbon"),
    P("ss_start", 0, 0, 30, True, "iter", "[SSSTART] heartwood forms once age > this", "carbon"),
    P("resp_foliage", 0.2, 0.0, 1.0, False, "yr-1", "[m_f] foliage respiration rate", "carbon"),
    P("resp_sapwood", 0.024, 0.0, 0.2, False, "yr-1", "[m_s] sapwood respiration rate", "carbon"),
    P("resp_root", 0.24, 0.0, 1.0, False, "yr-1", "[m_r] root respiration rate", "carbon"),
    P("heartwood_share", 0.6, 0.6, 0.7, False, "", "[xi] r_h = sqrt(xi) r at creation", "carbon"),
    P("wood_density", 400.0, 200, 400, False, "kg m-3", "[rho] wood density", "carbon"),
    P("photo_eff", 0.001, 0.0001, 0.01, False, "kg/unit", "[p_r] production per unit light", "carbon"),
    P("fl_threshold", 0.4, 0.2, 0.4, False, "", "[a_L] light threshold of f_L", "light"),
    P("fl_min_buds", 0.0, 0.0, 0.8, False, "", "[FLMINBUDS] minimum f_L for laterals", "shoot"),
    P("min_len", 0.0, 0.0, 0.05, False, "m", "[MINLEN] shorter new shoots are discarded", "shoot"),
    P("init_len", 0.5, 0.1, 1.0, False, "m", "[INITLEN] first segment length", "shoot"),
    P("pipe_coeff", 1.0, 0.75, 1.0, False, "", "[c_p] pipe weight of lateral links", "carbon"),
    P("fol_threshold", 1e-08, 0.0, 0.0001, False, "kg", "[FOLTHR] foliage counted as none (shedding)", "shedding"),
    P(
        "wind_sd",
        0.0,
        0.0,
        40.0,
        False,
        "deg",
        "[sigma_wind] output only (an addition): sd of the bend of each piece of a branch shoot (order > "
        "0) with the shoot's end points kept, so branches wind as scanned ones do (0 = straight shoots)",
        "output",
    ),
    P(
        "year_sd",
        0.0,
        0.0,
        0.5,
        False,
        "",
        "[sigma_year] an addition: sd of the log of each year's production, the same for the whole tree (a "
        "year's weather: its shoots grow longer or shorter together, so whorls stand at uneven steps; 0 = "
        "every year alike, the papers' model)",
        "carbon",
    ),
    P("bud_table", 0, 0, 1, True, "", "[-] lateral-count table: 0 = p98, 1 = s08", "shoot"),
    P(
        "max_laterals",
        7,
        1,
        7,
        True,
        "",
        "[n_L max] an addition: most laterals one bud sets, the table's count capped (a scanned Scots pine "
        "shows 2-4 branches a whorl where the tables give vigorous shoots 5-7; 7 = the papers' model)",
        "shoot",
    ),
    P("collision", 0, 0, 1, True, "", "[-] optional collision test: 0 off, 1 on", "space"),
]

NAMES = tuple(p.name for p in PARAMETERS)

_P98 = dict(
    years=10,
    radiation=30.0,
    shadow_max=10.0,
    shadow_len=0.55,
    voxel_size=0.01,
    stand_shade=0.0,
    envelope_shade=0.0,
    r_env_mean=1.33,
    r_env_sd=0.0,
    lr_mean=0.01,
    lr_sd=0.0,
    q_mean=0.1,
    q_sd=0.0,
    beta_init=45.0,
    beta_incr=10.0,
    beta_max=95.0,
    zeta_sd=5.0,
    gamma_sd=5.0,
    init_rot_angle=144.0,
    whorl_rotation_sd=15.0,
    shed_year=0,
    shed_dist=0,
    shed_mu=2.0,
    foliage_per_area=1.3,
    root_per_foliage=0.5,
    root_senescence=0.33,
    sapwood_senescence=0.07,
    ss_start=0,
    resp_foliage=0.2,
    resp_sapwood=0.024,
    resp_root=0.24,
    heartwood_share=0.6,
    wood_density=400.0,
    photo_eff=0.001,
    fl_threshold=0.4,
    fl_min_buds=0.0,
    min_len=0.0,
    init_len=0.5,
    pipe_coeff=1.0,
    fol_threshold=1e-8,
    bud_table=0,
    max_laterals=7,
    collision=0,
    wind_sd=0.0,
    year_sd=0.0,
)
_S08 = dict(
    _P98,
    radiation=40.0,
    shadow_max=50.0,
    shadow_len=0.7,
    voxel_size=0.01,
    r_env_mean=1.2,
    foliage_per_area=0.66,
    sapwood_senescence=0.04,
    ss_start=15,
    resp_foliage=0.24,
    wood_density=200.0,
    photo_eff=0.0006,
    fl_threshold=0.2,
    fl_min_buds=0.6,
    min_len=0.02,
    pipe_coeff=0.77,
    bud_table=1,
)

PRESET_VALUES: dict[str, dict[str, float]] = {
    "p98": _P98,
    "s08": _S08,
    # SF Table 2 (8 free parameters), base set P98
    "sf_synthetic": dict(
        _P98,
        radiation=30.0,
        voxel_size=0.02,
        shadow_max=10.0,
        shadow_len=0.55,
        r_env_mean=1.33,
        r_env_sd=0.0,
        lr_mean=0.009,
        lr_sd=0.001,
        q_mean=0.2,
        q_sd=0.03,
        years=15,
        beta_init=35.0,
        beta_incr=10.0,
        beta_max=95.0,
        zeta_sd=5.0,
        gamma_sd=5.0,
        shed_year=0,
        shed_dist=0,
    ),
    # SF Fig. 4 best real fit (16 free parameters), base set S08
    "sf_real": dict(
        _S08,
        radiation=60.0,
        voxel_size=0.02,
        shadow_max=72.4,
        shadow_len=0.87,
        r_env_mean=0.83,
        r_env_sd=0.23,
        lr_mean=0.01,
        lr_sd=0.002,
        q_mean=0.11,
        q_sd=0.03,
        years=32,
        beta_init=34.6,
        beta_incr=5.5,
        beta_max=77.1,
        zeta_sd=8.9,
        gamma_sd=7.6,
        shed_year=12,
        shed_dist=2,
        shed_mu=5.2,
    ),
    # driver test_sim16.m, base set P98
    "sf_test16": dict(
        _P98,
        radiation=40.0,
        voxel_size=0.02,
        shadow_max=30.0,
        shadow_len=0.4,
        r_env_mean=1.0,
        r_env_sd=0.3,
        lr_mean=0.009,
        lr_sd=0.001,
        q_mean=0.2,
        q_sd=0.03,
        years=12,
        beta_init=35.0,
        beta_incr=2.0,
        beta_max=100.0,
        zeta_sd=5.0,
        gamma_sd=7.0,
        shed_year=7,
        shed_dist=2,
        shed_mu=3.0,
    ),
}

for _name, _vals in PRESET_VALUES.items():  # every preset sets every parameter
    assert set(_vals) == set(NAMES), (_name, set(NAMES) ^ set(_vals))


def parameter_specs(preset: str) -> list[ParameterSpec]:
    """The :class:`ParameterSpec` list of one preset: :data:`PARAMETERS` with the preset's values
    as defaults (each description starts with the symbol of docs/models.md A.3, e.g. ``"[S_L]
    shadow depth"``)."""
    if preset not in PRESET_VALUES:
        raise ValueError(f"unknown LIGNUM preset {preset!r} (choose from {', '.join(PRESETS)})")
    vals = PRESET_VALUES[preset]
    return [dataclasses.replace(p, default=vals[p.name]) for p in PARAMETERS]


def normalise_inputs(params: Mapping[str, object]) -> dict:
    """Expand ``(mean, sd)`` pairs (``lr=(0.009, 0.001)`` -> ``lr_mean``, ``lr_sd``) and map the
    categorical spellings to their integer codes (``bud_table="s08"`` -> 1, ``collision=True``
    -> 1); other values are passed through."""
    out = dict(params)
    for pair in PAIRS:  # the (mean, sd) spelling of docs/models.md A.3: lr=(0.009, 0.001)
        if pair in out:
            v = out.pop(pair)
            try:
                mean, sd = v
            except (TypeError, ValueError):
                raise ValueError(f"parameter {pair!r} must be a (mean, sd) pair, got {v!r}") from None
            for key, val in ((f"{pair}_mean", mean), (f"{pair}_sd", sd)):
                if key in out and out[key] != val:
                    raise ValueError(f"parameter {pair!r} conflicts with {key!r} = {out[key]!r}")
                out[key] = val
    bt = out.get("bud_table")
    if isinstance(bt, str):
        if bt not in BUD_TABLES:
            raise ValueError(f"parameter 'bud_table' must be one of {BUD_TABLES} or 0/1, got {bt!r}")
        out["bud_table"] = BUD_TABLES.index(bt)
    if isinstance(out.get("collision"), bool):
        out["collision"] = int(out["collision"])
    return out


def validate(p: Mapping[str, float]) -> None:
    """Raise ``ValueError`` naming the first invalid parameter of a resolved set."""

    # numbers and finiteness are checked (and integers rounded) by SSM.resolve_params
    def need(cond: bool, name: str, what: str):
        if not cond:
            raise ValueError(f"parameter {name!r} {what}, got {p[name]!r}")

    need(p["years"] >= 1, "years", "must be an integer >= 1")
    for name in ("radiation", "shadow_len", "voxel_size", "init_len", "foliage_per_area", "wood_density"):
        need(p[name] > 0, name, "must be > 0")
    for name in (
        "shadow_max",
        "photo_eff",
        "root_per_foliage",
        "resp_foliage",
        "resp_sapwood",
        "resp_root",
        "min_len",
        "fol_threshold",
        "pipe_coeff",
        "shed_mu",
        "shed_year",
        "ss_start",
        "r_env_mean",
        "q_mean",
    ):
        need(p[name] >= 0, name, "must be >= 0")
    need(p["lr_mean"] > 0, "lr_mean", "must be > 0")
    for name in ("r_env_sd", "lr_sd", "q_sd", "zeta_sd", "gamma_sd", "whorl_rotation_sd", "wind_sd", "year_sd"):
        need(p[name] >= 0, name, "is a standard deviation and must be >= 0")
    for name in ("root_senescence", "sapwood_senescence"):
        need(0 <= p[name] <= 1, name, "must lie in [0, 1]")
    need(0 <= p["heartwood_share"] < 1, "heartwood_share", "must lie in [0, 1)")
    need(0 <= p["fl_threshold"] < 1, "fl_threshold", "must lie in [0, 1)")
    need(0 <= p["fl_min_buds"] <= 1, "fl_min_buds", "must lie in [0, 1]")
    need(0 <= p["envelope_shade"] <= 1, "envelope_shade", "must lie in [0, 1]")
    need(p["shed_dist"] in (0, 1, 2), "shed_dist", "must be 0, 1 or 2")
    need(p["bud_table"] in (0, 1), "bud_table", "must be 0 (p98) or 1 (s08)")
    need(
        p["max_laterals"] >= 1 and float(p["max_laterals"]).is_integer(), "max_laterals", "must be a whole number >= 1"
    )
    need(p["collision"] in (0, 1), "collision", "must be 0 or 1")
    need(0 < p["beta_max"] <= 180, "beta_max", "must lie in (0, 180] degrees")
    need(0 <= p["beta_init"] <= 180, "beta_init", "must lie in [0, 180] degrees")
