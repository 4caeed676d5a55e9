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

from collections.abc import Mapping
from dataclasses import dataclass

from bforest_core.interfaces import ParameterSpec

BUD_TABLES = ("p98", "s08")
PAIRS = ("lr", "q", "r_env")
PRESETS = ("sf_synthetic", "sf_real", "p98", "s08", "sf_test16")


@dataclass(frozen=True)
class _Par:
    name: str
    symbol: str
    unit: str
    lower: float
    upper: float
    integer: bool
    description: str
    group: str


# name, symbol, unit, plausible lower, upper, integer, meaning, group
_TABLE = [
    _Par("years", "T", "iter", 7, 40, True, "iterations (growth in the first T-1)", "time"),
    _Par("radiation", "R", "", 5, 100, False, "full-exposure radiation (relative)", "light"),
    _Par("shadow_max", "S_max", "", 5, 80, False, "one segment's shadow at the pyramid top", "light"),
    _Par("shadow_len", "S_L", "m", 0.3, 1.5, False, "shadow depth", "light"),
    _Par("voxel_size", "V_S", "m", 0.01, 0.05, False, "voxel edge of the shadow lattice", "light"),
    _Par(
        "stand_shade",
        "S_stand",
        "m-1",
        0.0,
        40.0,
        False,
        "shade of the surrounding stand per metre below the tree's top: S += S_stand (z_top - z) "
        "(0 = an open-grown tree, the papers' model)",
        "light",
    ),
    _Par(
        "r_env_mean",
        "R_env mean",
        "m",
        0.1,
        4.0,
        False,
        "mean of TN R_env: buds farther from the stem axis die (1 draw per bud per year)",
        "space",
    ),
    _Par("r_env_sd", "R_env sd", "m", 0.0, 0.3, False, "sd of TN R_env", "space"),
    _Par(
        "lr_mean",
        "L_R mean",
        "",
        0.0045,
        0.04,
        False,
        "mean of TN L_R, radius:length of a new shoot (1 draw per shoot; the published range (docs/models.md A.3) stops at "
        "0.0135, scanned pines' first-order branches have base radius:length 0.015-0.024, the medians)",
        "shoot",
    ),
    _Par("lr_sd", "L_R sd", "", 0.0, 0.003, False, "sd of TN L_R", "shoot"),
    _Par(
        "q_mean",
        "Q mean",
        "",
        0.0,
        0.4,
        False,
        "mean of TN Q, apical dominance 1 - w*Q (1 draw per bud + 1 per shoot)",
        "shoot",
    ),
    _Par("q_sd", "Q sd", "", 0.0, 0.05, False, "sd of TN Q", "shoot"),
    _Par(
        "beta_init",
        "beta_init",
        "deg",
        17.5,
        90,
        False,
        "angle of a new lateral to its parent (the published range (docs/models.md A.3) stops at 60; scanned pines' first-order branches leave the stem at 55-120 deg)",
        "angles",
    ),
    _Par("beta_incr", "Delta beta", "deg", 0, 15, False, "mean yearly bending (mean of delta)", "angles"),
    _Par("beta_max", "beta_max", "deg", 40, 105, False, "bending cap vs the mother segment", "angles"),
    _Par("zeta_sd", "Delta zeta", "deg", 0, 10, False, "sd of delta ~ N(Delta beta, Delta zeta)", "angles"),
    _Par(
        "gamma_sd",
        "Delta gamma",
        "deg",
        0,
        10,
        False,
        "azimuth noise N(0, Delta gamma) of apical shoots of order > 0",
        "angles",
    ),
    _Par("init_rot_angle", "INITROTANG", "deg", 0, 360, False, "g_ref turn between trunk whorls", "angles"),
    _Par(
        "whorl_rotation_sd",
        "sigma_whorl",
        "deg",
        0,
        30,
        False,
        "clone noise N(0, sd) added to each trunk-whorl turn",
        "angles",
    ),
    _Par("shed_year", "T_sh", "iter", 0, 15, True, "minimum tip age for shedding", "shedding"),
    _Par(
        "shed_dist",
        "SHEDDIST",
        "",
        0,
        2,
        True,
        "order-1 shedding: 0 all, 1 uniform, 2 Poisson number of tip segments",
        "shedding",
    ),
    _Par("shed_mu", "mu_sh", "seg", 0, 6, False, "Poisson mean of shed tip segments (capped at 10)", "shedding"),
    _Par("foliage_per_area", "a_f", "kg m-2", 0.5, 1.5, False, "foliage per segment surface", "carbon"),
    _Par("root_per_foliage", "a_r", "", 0.0, 2.0, False, "new roots per new foliage", "carbon"),
    _Par("root_senescence", "s_r", "yr-1", 0.0, 1.0, False, "yearly root loss", "carbon"),
    _Par("sapwood_senescence", "s_s", "yr-1", 0.02, 0.2, False, "sapwood -> heartwood per year", "carbon"),
    _Par("ss_start", "SSSTART", "iter", 0, 30, True, "heartwood forms once age > this", "carbon"),
    _Par("resp_foliage", "m_f", "yr-1", 0.0, 1.0, False, "foliage respiration rate", "carbon"),
    _Par("resp_sapwood", "m_s", "yr-1", 0.0, 0.2, False, "sapwood respiration rate", "carbon"),
    _Par("resp_root", "m_r", "yr-1", 0.0, 1.0, False, "root respiration rate", "carbon"),
    _Par("heartwood_share", "xi", "", 0.6, 0.7, False, "r_h = sqrt(xi) r at creation", "carbon"),
    _Par("wood_density", "rho", "kg m-3", 200, 400, False, "wood density", "carbon"),
    _Par("photo_eff", "p_r", "kg/unit", 1e-4, 1e-2, False, "production per unit light", "carbon"),
    _Par("fl_threshold", "a_L", "", 0.2, 0.4, False, "light threshold of f_L", "light"),
    _Par("fl_min_buds", "FLMINBUDS", "", 0.0, 0.8, False, "minimum f_L for laterals", "shoot"),
    _Par("min_len", "MINLEN", "m", 0.0, 0.05, False, "shorter new shoots are discarded", "shoot"),
    _Par("init_len", "INITLEN", "m", 0.1, 1.0, False, "first segment length", "shoot"),
    _Par("pipe_coeff", "c_p", "", 0.75, 1.0, False, "pipe weight of lateral links", "carbon"),
    _Par("fol_threshold", "FOLTHR", "kg", 0.0, 1e-4, False, "foliage counted as none (shedding)", "shedding"),
    _Par(
        "piece_length",
        "l_piece",
        "m",
        0.0,
        0.5,
        False,
        "output only (an addition): each shoot is drawn as pieces at most this long, as a scan's "
        "QSM draws a branch as short cylinders; the growth is unchanged (0 = one cylinder per shoot)",
        "output",
    ),
    _Par(
        "wind_sd",
        "sigma_wind",
        "deg",
        0.0,
        40.0,
        False,
        "output only (an addition): sd of the bend of each piece of a branch shoot (order > 0) "
        "with the shoot's end points kept, so branches wind as scanned ones do (0 = straight shoots)",
        "output",
    ),
    _Par("bud_table", "-", "", 0, 1, True, "lateral-count table: 0 = p98, 1 = s08", "shoot"),
    _Par("collision", "-", "", 0, 1, True, "optional collision test: 0 off, 1 on", "space"),
]

NAMES = tuple(p.name for p in _TABLE)
SYMBOLS = {p.name: p.symbol for p in _TABLE}

_P98 = dict(
    years=10,
    radiation=30.0,
    shadow_max=10.0,
    shadow_len=0.55,
    voxel_size=0.01,
    stand_shade=0.0,
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
    collision=0,
    piece_length=0.0,
    wind_sd=0.0,
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
    """The :class:`ParameterSpec` list of one preset (defaults = the preset's values).

    The description starts with the symbol of docs/models.md A.3, e.g. ``"[S_L] shadow depth"``.
    """
    if preset not in PRESET_VALUES:
        raise ValueError(f"unknown LIGNUM preset {preset!r} (choose from {', '.join(PRESETS)})")
    vals = PRESET_VALUES[preset]
    return [
        ParameterSpec(
            name=p.name,
            default=vals[p.name],
            lower=p.lower,
            upper=p.upper,
            integer=p.integer,
            unit=p.unit,
            description=f"[{p.symbol}] {p.description}",
            group=p.group,
        )
        for p in _TABLE
    ]


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
    need(p["piece_length"] >= 0, "piece_length", "must be >= 0 (0 = one cylinder per shoot)")
    for name in ("r_env_sd", "lr_sd", "q_sd", "zeta_sd", "gamma_sd", "whorl_rotation_sd", "wind_sd"):
        need(p[name] >= 0, name, "is a standard deviation and must be >= 0")
    for name in ("root_senescence", "sapwood_senescence"):
        need(0 <= p[name] <= 1, name, "must lie in [0, 1]")
    need(0 <= p["heartwood_share"] < 1, "heartwood_share", "must lie in [0, 1)")
    need(0 <= p["fl_threshold"] < 1, "fl_threshold", "must lie in [0, 1)")
    need(0 <= p["fl_min_buds"] <= 1, "fl_min_buds", "must lie in [0, 1]")
    need(p["shed_dist"] in (0, 1, 2), "shed_dist", "must be 0, 1 or 2")
    need(p["bud_table"] in (0, 1), "bud_table", "must be 0 (p98) or 1 (s08)")
    need(p["collision"] in (0, 1), "collision", "must be 0 or 1")
    need(0 < p["beta_max"] <= 180, "beta_max", "must lie in (0, 180] degrees")
    need(0 <= p["beta_init"] <= 180, "beta_init", "must lie in [0, 180] degrees")
