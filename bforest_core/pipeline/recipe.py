"""``bforest init``: a commented, ready-to-run recipe for one measured tree.

The tree is measured (:func:`bforest_core.metrics.measure_tree`); every registered growth model
that writes recipes drafts its part (:meth:`bforest_core.interfaces.SSM.draft_recipe`: settings,
fixed values and bounds, each with what in the tree set it); this module picks the model that
suits the tree best (or the one asked for) and writes the whole recipe around it: the sets, the
size term, the robust search of the real-tree recipes (docs/validation.md section 4) and the
answer chosen on held-out seeds.
"""

from __future__ import annotations

import dataclasses
import math
import os
import textwrap
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import ConfigError
from ..interfaces import RecipeDraft
from ..io import read_qsm
from ..metrics import SIZE_WEIGHTS, SUMMARY_DEFAULT, TreeMeasures, measure_tree
from ..registry import component, discover
from ..samples import is_sample
from .target import SUMMARY_KIND


@dataclass
class Recipe:
    """A written recipe: the model, its draft, what the tree measured and the TOML text."""

    model: str
    draft: RecipeDraft
    measures: TreeMeasures
    text: str
    choices: list  # (model, suits, why) of every model that drafted one


def _value(v) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, str):
        return f'"{v}"'
    if isinstance(v, float):
        return f"{v:g}" if v != int(v) or abs(v) >= 1e6 else f"{v:.1f}"
    if isinstance(v, (list, tuple)):
        return "[" + ", ".join(_value(x) for x in v) + "]"
    return str(v)


def _line(left: str, comment: str | None, width: int = 52) -> str:
    return f"{left:<{width}} # {comment}" if comment else left


def draft_recipes(measures: TreeMeasures, model: str | None = None) -> list[tuple[str, RecipeDraft]]:
    """Drafts of every registered growth model that writes recipes (or only ``model``),
    best suited first."""
    names = [model] if model else discover().names("ssm")
    out = []
    for name in names:
        ssm = component("ssm", name)
        draft = ssm.draft_recipe(measures)
        if draft is None:
            if model:
                raise ConfigError(
                    f"--model {model}: this growth model writes no recipes (bforest init "
                    "knows the models whose plugin drafts one)"
                )
            continue
        draft.free = [
            (k, lo, hi, c) if k in draft.scaled else _within(ssm.parameter_spec(k), lo, hi, c)
            for k, lo, hi, c in draft.free
        ]
        draft.fixed = [(k, _clip(ssm.parameter_spec(k), v), c) for k, v, c in draft.fixed]
        out.append((name, draft))
    return sorted(out, key=lambda nd: -nd[1].suits)


@dataclass
class RecipeBox:
    """The search box ``bforest init`` writes for a tree, resolved to absolute bounds."""

    names: list
    lower: np.ndarray
    upper: np.ndarray
    integer: np.ndarray
    fixed: dict  # parameter -> value
    settings: dict  # the model's settings


def recipe_box(model: str, measures: TreeMeasures) -> RecipeBox:
    """The box of ``model``'s recipe for a tree of these measures, as a fit resolves it: bounds
    scaled by a measure (``scaled_by``) multiplied by it and kept within the model's range
    (:func:`~.target.scale_bounds`), with the recipe's fixed values and settings."""
    from .target import scale_bounds

    (_, d), *_ = draft_recipes(measures, model)
    ssm = component("ssm", model)
    names, lo, hi, integer = [], [], [], []
    for k, a, b, _ in d.free:
        spec = ssm.parameter_spec(k)
        if k in d.scaled:
            _, new = scale_bounds({"lower": a, "upper": b}, float(getattr(measures, d.scaled[k])), spec)
            a, b = new["lower"], new["upper"]
        names.append(k)
        lo.append(float(a))
        hi.append(float(b))
        integer.append(bool(spec.integer))
    return RecipeBox(
        names,
        np.array(lo),
        np.array(hi),
        np.array(integer, bool),
        {k: v for k, v, _ in d.fixed},
        {k: v for k, v, _ in d.settings},
    )


def _clip(spec, v):
    """A fixed value within the parameter's allowed range."""
    return (int if spec.integer else float)(min(max(v, spec.lower), spec.upper))


def _within(spec, lo, hi, comment):
    """Bounds clipped to the parameter's allowed range (the whole range if nothing is left)."""
    cast = int if spec.integer else float
    a, b = max(lo, spec.lower), min(hi, spec.upper)
    if a >= b:
        a, b = spec.lower, spec.upper
    return spec.name, cast(a), cast(b), comment


def write_recipe(qsm: str | Path, out: str | Path, model: str | None = None, amortised=None) -> Recipe:
    """Measure the tree in ``qsm`` and write its recipe to ``out`` (an existing file is never
    replaced: the caller checks). Raises ``ConfigError`` naming the file for a tree that cannot
    be fitted. ``qsm`` may be ``sample:NAME``, which the recipe keeps as it is.

    ``amortised``: an estimator's file (``bforest train``; ``"shipped"``, the one shipped for the
    model): the recipe's search starts from its posterior for the tree and is short
    (:data:`AMORTISED_SEARCH`); the model is the estimator's unless ``model`` says otherwise."""
    out = Path(out)
    start, how = None, "asked for" if model else "the one that suits the tree best"
    if amortised is not None:
        from .amortised import SHIPPED, checked_header, estimator_for

        path = estimator_for(model) if amortised == SHIPPED else Path(amortised)
        header, _ = checked_header(path)
        if model is not None and model != header["model"]:
            raise ConfigError(f"--amortised {amortised}: an estimator of {header['model']}, not of --model {model}")
        model, how = header["model"], how if model else "the estimator's"
        start = amortised if amortised == SHIPPED else os.path.relpath(path.resolve(), out.resolve().parent)
    tree = read_qsm(qsm)
    # the recipe names the tree relative to itself (a sample by its name: it is where the user fetched it)
    rel = str(qsm) if is_sample(qsm) else os.path.relpath(Path(qsm).resolve(), out.resolve().parent)
    qsm = Path(qsm)
    try:
        m = measure_tree(tree)
    except ValueError as e:
        raise ConfigError(f"{qsm}: cannot be fitted: {e}") from None
    drafts = draft_recipes(m, model)
    if not drafts:
        raise ConfigError("no installed growth model writes recipes (bforest plugins lists them)")
    name, draft = drafts[0]
    if draft.suits <= 0.0:
        raise ConfigError(f"{qsm}: {name} cannot grow this tree: {draft.why}")
    if start is not None:
        draft = dataclasses.replace(draft, **AMORTISED_SEARCH, search_why=AMORTISED_WHY)
    text = render(qsm, rel, name, draft, m, [(n, d.suits, d.why) for n, d in drafts], how, start)
    out.write_text(text, encoding="utf-8")
    return Recipe(name, draft, m, text, [(n, d.suits, d.why) for n, d in drafts])


def not_chosen(name: str, suits: float, chosen: str, chosen_suits: float, why: str) -> str:
    """Why a model was not taken, with how well each suits the tree (0-1)."""
    return f"not {name} (how well it suits the tree, 0-1: {suits:.1f}; {chosen} {chosen_suits:.1f}): {why}"


def measured_lines(m: TreeMeasures) -> list[str]:
    """What the tree measured, one line each (printed by ``bforest init`` and written in the recipe)."""
    form = "decurrent (the stem divides into limbs)" if m.decurrent else "excurrent (a leader to the top)"
    return [
        f"height {m.height:.2f} m, DBH {100 * m.dbh:.1f} cm, crown spread {m.crown_spread:.2f} m",
        f"crown base {m.crown_base_height:.2f} m, crown length {m.crown_length:.2f} m, "
        f"{m.n_branches_o1} first-order branches (one per {m.branch_spacing:.2f} m of crown), orders to {m.max_order}",
        f"first-order branch angles {m.beta_q10:.0f} / {m.beta_q50:.0f} / {m.beta_q90:.0f} deg (10 / 50 / 90 %), "
        f"longest limb {m.longest_limb:.2f} m, thinnest branch {100 * m.thinnest_branch:.1f} cm; "
        f"branches turn {m.branch_turn:.0f} deg from cylinder to cylinder (median)",
        f"crown form: {form}; the three largest limbs hold {m.limb_ratio:.2f} x the stem's wood in the crown",
        f"crown centre {m.crown_offset:.2f} m from the stem base towards azimuth {m.crown_azimuth:.0f} deg, "
        "counter-clockwise from the file's +x axis "
        f"({m.crown_offset / max(0.5 * m.crown_spread, 1e-9):.2f} crown radii); "
        f"the stem's upper half leans {m.stem_lean:.0f} deg",
    ]


#: the weight of the structural term and of the size term: they weigh alike
TERM_WEIGHT = 2.0
#: the summary distance's cap of one statistic's term, written with limits: the size term then
#: reaches at most cap * (1 + steep), the structural distance (KS) 1
SIZE_CAP = 2.0
#: the tables the candidate answers are scored on (``[select] features``/``distance``) when the
#: draft's ``select_tables`` is set: the first-order segments and branches as sets of their own on
#: 256 lines, the tables a clone is judged by (docs/validation.md), where the search pools S0,1 and
#: B1,2 on 128 lines for a smoother objective
SELECT_SETS = ("S1", "B1")
SELECT_LINES = 256
#: ``[objective] penalty`` of a recipe whose size term has limits (or twice what the objective can
#: then reach, if more): the default 1.0 lies below what a grown tree can reach, and failed growths
#: would win
LIMITS_PENALTY = 12.0


#: the search of a recipe that starts from an amortised estimator's posterior (``bforest init
#: --amortised``): one model seed an evaluation, 640 evaluations (two lq-CMA-ES runs of 16 from
#: the best distinct of 32 posterior draws, grown together) and the answer among 8 points on 8
#: held-out sets: 704 growths, under a fifth of the pine recipes' 4 128 (examples/real/pine_sot.toml)
AMORTISED_SEARCH = dict(
    seeds=1,
    evaluations=640,
    starts=2,
    population=16,
    init_design=32,
    finalists=2,
    grow_together=True,
    select_top=8,
    select_sets=8,
)
AMORTISED_WHY = (
    "The estimator's posterior already holds the region a long search would find, so the search only "
    "refines it: 704 growths in all, under a fifth of the pine recipes' 4 128."
)


def _search_text(d: RecipeDraft, amortised: bool = False) -> str:
    """The comment above ``[optimizer]``: what the search does."""
    if amortised:
        return (
            f"A short refinement of the estimator's posterior ([start]): {d.init_design} draws of it for this tree, "
            f"then {d.starts} lq-CMA-ES runs of {d.population} points a generation from the best distinct ones, "
            "taking their turns together."
        )
    if d.grow_together:
        return (
            f"A search that does not hinge on one trajectory: {d.init_design} Sobol' points over the box, then "
            f"{d.starts} lq-CMA-ES runs of {d.population} points a generation from the best distinct ones, "
            "each to the end of the budget, taking their turns together (their points go to the workers as "
            "one batch); a run that converges restarts with a doubled population."
        )
    return (
        f"A search that does not hinge on one trajectory: {d.init_design} Sobol' points over the box, "
        f"{d.starts} lq-CMA-ES runs from the best distinct ones raced by successive halving, each "
        "restarting with a doubled population once it converges."
    )


def _select_text(d: RecipeDraft) -> str:
    """The comment above ``[select]``: how the answer is chosen."""
    text = (
        f"The answer is chosen on model seeds the search never used: the {d.select_top} best distinct points "
        f"are each grown again with {d.select_sets} sets of held-out seeds"
    )
    if not d.select_tables:
        return text + "; the lowest held-out distance is the answer."
    return (
        text + f", and scored on the tables a clone is judged by: {' and '.join(SELECT_SETS)} as sets of their "
        f"own on {SELECT_LINES} lines, with the size term (the search pools its tables on fewer lines, a smoother "
        "objective that ranks the candidates otherwise). The lowest is the answer."
    )


def render(
    qsm: Path, rel: str, name: str, d: RecipeDraft, m: TreeMeasures, choices, how: str, start: str | None = None
) -> str:
    """The recipe's TOML text, every choice commented."""
    L = [
        f"# Recipe written by `bforest init {qsm.name}` for {qsm.name}: fit {name} to it and grow clones.",
        "#",
        "#   bforest fit THIS.toml -o runs/NAME",
        "#   bforest clones runs/NAME -n 30",
        "#",
        "# What the tree measured:",
    ]
    L += [f"#   {s}" for s in measured_lines(m)]
    L += [
        "#",
        f"# Model: {name} ({how}): {d.why}.",
    ]
    for n, suits, why in choices:
        if n != name:
            line = not_chosen(n, suits, name, d.suits, why)
            L.append(f"# {line[0].upper()}{line[1:]}.")
    for note in d.notes:
        L.append(f"# Note: {note}.")
    # the most the objective can reach: the weighted mean of the structure (KS, at most 1) and the
    # size term (at most cap * (1 + steep)); a failed growth scores above
    reach = (TERM_WEIGHT * 1.0 + TERM_WEIGHT * SIZE_CAP * (1.0 + d.size_steep)) / (2.0 * TERM_WEIGHT)
    penalty = max(LIMITS_PENALTY, float(math.ceil(2.0 * reach)))
    L += ["seed = 1", "", "[target]", f'qsm = "{rel}"', "", "[ssm]", f'kind = "{name}"']
    for k, v, c in d.settings:
        L.append(_line(f"{k} = {_value(v)}", c))
    for k, v, c in d.fixed:
        L.append(_line(f"fixed.{k} = {_value(v)}", c))
    for k, lo, hi, c in d.free:
        by = f', scaled_by = "{d.scaled[k]}"' if k in d.scaled else ""
        L.append(_line(f"free.{k} = {{ lower = {_value(lo)}, upper = {_value(hi)}{by} }}", c))
    L += [
        "",
        "# Two terms: the structural distance on branch and segment tables (how branches look) and a",
        "# summary term on tree-level statistics (how large the tree is, where the crown starts, how many",
        "# branches it has), which the structural distance cannot see.",
        "[features]",
        'kind = "branch-segment"',
        'sets = ["S0,1", "B1,2"]',
        "",
        "[distance]",
        'kind = "sliced"',
        'statistic = "ks"',
        "lines = 128",
        "",
        "[objective]",
        _line(
            f"seeds = {d.seeds}",
            f"the mean over {d.seeds} model seeds: clones vary, the fit must not chase one"
            if d.seeds > 1
            else "one model seed an evaluation: the seeds' luck is taken out where the answer is chosen ([select])",
        ),
        _line(f"timeout = {d.timeout:.1f}", "seconds one growth may take: a safety net far above a normal growth"),
        _line(f"structure_weight = {TERM_WEIGHT!r}", "structure and size weigh alike"),
        *(
            [
                _line(
                    f"penalty = {penalty!r}",
                    f"a failed growth scores above the {reach:g} a grown tree can reach (the size term's limits)",
                )
            ]
            if d.size_limits
            else []
        ),
        "",
        (
            "# The headline statistics weigh as the model's recipes calibrated them."
            if d.size_weights
            else "# The headline statistics weigh by the inverse of the error a forester tolerates (height 7.5 %,\n"
            "# DBH 20 %, crown spread 25 %, crown base and first-order branches 30 %)."
        ),
        *(f"# {s}" for s in textwrap.wrap(d.size_why if d.size_extra else "", 96)),
        *(
            f"# {s}"
            for s in textwrap.wrap(
                (
                    f"Beyond its limit (a relative error, limits) a statistic's term grows {d.size_steep:g} times "
                    "as fast: a fit trades a size for structure only as far as a forester still accepts the size."
                )
                if d.size_limits
                else "",
                96,
            )
        ),
        "[[objective.terms]]",
        'name = "size"',
        f"weight = {TERM_WEIGHT!r}",
        f'features = {{ kind = "{SUMMARY_KIND}", min_branch_diameter = 0.0'
        + (
            ", statistics = [" + ", ".join(f'"{k}"' for k in (*SUMMARY_DEFAULT, *d.size_extra)) + "]"
            if d.size_extra
            else ""
        )
        + " }",
        'distance = { kind = "summary", form = "logratio", weights = { '
        + ", ".join(f"{k} = {v}" for k, v in {**(d.size_weights or SIZE_WEIGHTS), **d.size_extra}.items())
        + " }"
        + (
            ", limits = { " + ", ".join(f"{k} = {v:g}" for k, v in d.size_limits.items()) + " }"
            f", steep = {float(d.size_steep)!r}, cap = {SIZE_CAP!r}"
            if d.size_limits
            else ""
        )
        + " }",
        "",
        *(
            [
                "# The search starts from an amortised estimator's posterior for this tree (bforest train, bforest",
                "# posterior): its first points are draws of it.",
                "[start]",
                f'estimator = "{start}"',
                "",
            ]
            if start is not None
            else []
        ),
        *(f"# {s}" for s in textwrap.wrap(_search_text(d, start is not None), 96)),
        *(f"# {s}" for s in textwrap.wrap(d.search_why, 96)),
        "[optimizer]",
        'kind = "cma"',
        f"population = {d.population}",
        "restarts = 4",
        "sigma0 = 0.15",
        'surrogate = "lq"',
        "surrogate_batch = 2",
        f"init_design = {d.init_design}",
        f"starts = {d.starts}",
        *([f"finalists = {d.finalists}"] if d.finalists != 1 else []),
        *(["grow_together = true"] if d.grow_together else []),
        "",
        "[stop]",
        f"max_evaluations = {d.evaluations}",
        _line(
            f"wall_time = {d.wall_time:.1f}",
            "seconds: a safety net only; the search stops on its budget, so the answer is the same on any machine",
        ),
        "",
        *(f"# {s}" for s in textwrap.wrap(_select_text(d), 96)),
        "[select]",
        f"top = {d.select_top}",
        f"sets = {d.select_sets}",
        *(
            [
                "features = { sets = [" + ", ".join(f'"{k}"' for k in SELECT_SETS) + "] }",
                f"distance = {{ lines = {SELECT_LINES} }}",
            ]
            if d.select_tables
            else []
        ),
        "",
        "[executor]",
        'kind = "process"',
        "workers = 2",
        "",
        "[clones]",
        "count = 30",
        "",
    ]
    return "\n".join(L)
