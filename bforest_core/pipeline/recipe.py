"""``bforest init``: a commented, ready-to-run recipe for one measured tree.

The tree is measured (:func:`bforest_core.metrics.measure_tree`); every registered growth model
that writes recipes drafts its part (:meth:`bforest_core.interfaces.SSM.draft_recipe`: settings,
fixed values and bounds, each with what in the tree set it, its model seeds and budget, the size
term's balance); this module picks the model that suits the tree best (or the one asked for),
asks the recipe's other plugins (``config.RECIPE_KINDS``: the structural tables and distance, the
size term's, the search) for their parts (``draft_recipe`` of each, a :class:`RecipePart`) and
assembles the whole: it names no plugin and no plugin's setting.
"""

from __future__ import annotations

import dataclasses
import math
import os
import textwrap
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..config import RECIPE_KINDS
from ..errors import ConfigError
from ..interfaces import RecipeDraft, RecipePart, RecipePlan
from ..io import read_qsm
from ..metrics import SELECT_SIZES, TreeMeasures, measure_tree
from ..registry import component, discover
from ..samples import is_sample


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


def _toml(v) -> str:
    """A plugin's value as TOML that reads back as the same value (floats by their shortest repr)."""
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, str):
        return f'"{v}"'
    if isinstance(v, (list, tuple)):
        return "[" + ", ".join(_toml(x) for x in v) + "]"
    if isinstance(v, dict):
        return "{ " + ", ".join(f"{k} = {_toml(x)}" for k, x in v.items()) + " }"
    return repr(v)


def _section(part: RecipePart) -> list[str]:
    """A plugin's part as the lines of its section: its kind and settings, each with its comment."""
    return [f'kind = "{part.kind}"'] + [_line(f"{k} = {_toml(v)}", c) for k, v, c in part.settings]


def _inline(part: RecipePart) -> str:
    """A plugin's part as an inline table (a term's ``features``/``distance``)."""
    return _toml({"kind": part.kind, **{k: v for k, v, _ in part.settings}})


def _comment(*texts: str) -> list[str]:
    return [f"# {s}" for text in texts for s in textwrap.wrap(text, 96)]


#: the parts of a recipe written by plugins: (``RECIPE_KINDS`` key, component kind, term)
PARTS = (
    ("features", "features", "structure"),
    ("distance", "distance", "structure"),
    ("size.features", "features", "size"),
    ("size.distance", "distance", "size"),
    ("optimizer", "optimizer", "search"),
)


def recipe_parts(draft: RecipeDraft, measures: TreeMeasures, start: bool = False) -> dict[str, RecipePart]:
    """Each recipe plugin's part for the growth model's ``draft``, by ``RECIPE_KINDS`` key
    (``start``: the search refines draws of an amortised estimator's posterior)."""
    plan = {"draft": draft, "measures": measures, "dim": len(draft.free), "start": start}
    out = {}
    for key, kind, term in PARTS:
        name = RECIPE_KINDS[key]
        part = component(kind, name).draft_recipe(RecipePlan(term, **plan))
        if part is None:
            raise ConfigError(f"the {kind} plugin {name!r} writes no part of a recipe for the {term} ({key})")
        out[key] = part
    return out


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


def write_recipe(
    qsm: str | Path,
    out: str | Path,
    model: str | None = None,
    start: str | None = None,
    how: str | None = None,
    crown_space: bool = True,
) -> Recipe:
    """Measure the tree in ``qsm`` and write its recipe to ``out`` (an existing file is never
    replaced: the caller checks). Raises ``ConfigError`` naming the file for a tree that cannot
    be fitted. ``qsm`` may be ``sample:NAME``, which the recipe keeps as it is.

    ``start``: the ``[start] estimator`` the recipe's search starts from (an amortised
    estimator's file as the recipe names it, or ``"shipped"``;
    :func:`~.amortised.write_amortised_recipe`): the search is short (:data:`AMORTISED_BUDGET`).
    ``how``: how the model was chosen, as the recipe says it. ``crown_space``: a decurrent or
    one-sided crown grows in its crown's space (the default; False for ``bforest init
    --open-world``, and the recipe notes that it could, :data:`CROWN_SPACE_NOTE`)."""
    out = Path(out)
    how = how or ("asked for" if model else "the one that suits the tree best")
    tree = read_qsm(qsm)
    # the recipe names the tree relative to itself (a sample by its name: it is where the user fetched it)
    rel = str(qsm) if is_sample(qsm) else os.path.relpath(Path(qsm).resolve(), out.resolve().parent)
    qsm = Path(qsm)
    try:
        m = measure_tree(tree)
    except ValueError as e:
        raise ConfigError(f"{qsm}: cannot be fitted: {e}") from None
    form = m.wood_shaped()
    if not crown_space:  # not asked for: no growth model writes a crown's space it is not given
        m = dataclasses.replace(m, envelope=None)
    drafts = draft_recipes(m, model)
    if not drafts:
        raise ConfigError("no installed growth model writes recipes (bforest plugins lists them)")
    name, draft = drafts[0]
    if draft.suits <= 0.0:
        raise ConfigError(f"{qsm}: {name} cannot grow this tree: {draft.why}")
    if not crown_space and form is not None:
        draft = dataclasses.replace(draft, notes=[*draft.notes, f"{form}: {CROWN_SPACE_NOTE}"])
    if start is not None:
        draft = dataclasses.replace(draft, **AMORTISED_BUDGET, select_sizes=SELECT_SIZES, search_why=AMORTISED_WHY)
    text = render(qsm, rel, name, draft, m, [(n, d.suits, d.why) for n, d in drafts], how, start)
    out.write_text(text, encoding="utf-8")
    return Recipe(name, draft, m, text, [(n, d.suits, d.why) for n, d in drafts])


#: what ``init`` says of a decurrent or one-sided crown grown into an open world (``--open-world``)
CROWN_SPACE_NOTE = (
    "the clones grow into an open world: their crowns lie about their stems where this tree's lies to "
    "one side; `bforest init` without --open-world (or --amortised, whose estimator learnt the open world) "
    "grows them in this tree's crown space (crown_envelope, docs/growth-forms.md)"
)


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
        f"the crown's offset from its stem (at its centre's height, by wood volume): "
        f"{math.hypot(*m.crown_side):.2f} crown radii towards "
        f"{math.degrees(math.atan2(m.crown_side[1], m.crown_side[0])):.0f} deg"
        + (" (one-sided)" if m.one_sided else ""),
    ]


#: the weight of the structural term and of the size term: they weigh alike
TERM_WEIGHT = 2.0
#: ``[objective] penalty`` of a recipe whose size term is bounded (or twice what the objective can
#: then reach, if more): the default 1.0 lies below what a grown tree can reach, and failed growths
#: would win
LIMITS_PENALTY = 12.0


#: the budget of a recipe whose search refines an amortised estimator's posterior (``bforest init
#: --amortised``): one model seed an evaluation, 576 evaluations (the search plugin plans the
#: refinement: ``RecipePlan.start``) and the answer among 8 points on 16 held-out sets: 704 growths,
#: under a fifth of the pine recipes' 4 128 (examples/real/pine_sot.toml)
#: (16 sets, not 8: a LIGNUM point's held-out distance varies 3-5 times as much from set to set as a
#: SOT point's, and on 8 sets two candidates 0.0001 apart decided a pine's answer; 2026-12-07)
AMORTISED_BUDGET = dict(seeds=1, max_evaluations=576, select_top=8, select_sets=16)
AMORTISED_WHY = (
    "The estimator's posterior already holds the region a long search would find, so the search only "
    "refines it: 704 growths in all, under a fifth of the pine recipes' 4 128."
)


def _select_text(d: RecipeDraft, parts: dict[str, RecipePart]) -> str:
    """The comment above ``[select]``: how the answer is chosen."""
    text = (
        f"The answer is chosen on model seeds the search never used: the {d.select_top} best distinct points "
        f"are each grown again with {d.select_sets} sets of held-out seeds"
    )
    sizes = (
        " Candidates whose held-out trees keep, on average, within four fifths of a forester's tolerance of the "
        "tree's height, DBH, crown spread, crown base and first-order branches (sizes) come first: the "
        "search's own distance, on one model seed, misjudges sizes whose mean the held-out trees measure "
        "within a tenth (SOT) to a third (LIGNUM) of the tolerance."
        if d.select_sizes
        else ""
    )
    if not d.select_tables:
        return text + "; the lowest held-out distance is the answer." + sizes
    judged = " ".join(w for w in (parts["features"].select_why, parts["distance"].select_why) if w)
    return (
        text + f", and scored on the tables a clone is judged by: {judged}, with the size term (the search's "
        "own tables are a smoother objective that ranks the candidates otherwise). The lowest is the answer." + sizes
    )


def render(
    qsm: Path, rel: str, name: str, d: RecipeDraft, m: TreeMeasures, choices, how: str, start: str | None = None
) -> str:
    """The recipe's TOML text, every choice commented (``start``: the estimator the search starts from)."""
    parts = recipe_parts(d, m, start is not None)
    return "\n".join(
        _head(qsm, name, d, m, choices, how)
        + ["seed = 1", "", "[target]", f'qsm = "{rel}"', ""]
        + _ssm_section(name, d)
        + _terms(d, parts)
        + _search(d, parts, start)
        + ["[executor]", 'kind = "process"', "workers = 2", "", "[clones]", "count = 30", ""]
    )


def _head(qsm: Path, name: str, d: RecipeDraft, m: TreeMeasures, choices, how: str) -> list[str]:
    """The recipe's opening comment: how to run it, what the tree measured, which model (``how`` it
    was chosen) and why."""
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
    return L + [f"# Note: {note}." for note in d.notes]


def _ssm_section(name: str, d: RecipeDraft) -> list[str]:
    """The growth model's section: its settings, fixed values and search box, as it drafted them;
    a setting that is a table of its own (a dict) follows as ``[ssm.NAME]``."""
    L = ["[ssm]", f'kind = "{name}"']
    L += [_line(f"{k} = {_value(v)}", c) for k, v, c in d.settings if not isinstance(v, dict)]
    L += [_line(f"fixed.{k} = {_value(v)}", c) for k, v, c in d.fixed]
    for k, lo, hi, c in d.free:
        by = f', scaled_by = "{d.scaled[k]}"' if k in d.scaled else ""
        L.append(_line(f"free.{k} = {{ lower = {_value(lo)}, upper = {_value(hi)}{by} }}", c))
    for k, v, c in d.settings:
        if isinstance(v, dict):
            L += ["", *_comment(c or ""), f"[ssm.{k}]", *(f"{kk} = {_rows(vv)}" for kk, vv in v.items())]
    return L + [""]


def _rows(v) -> str:
    """A value as TOML; a table of rows (a list of lists) one row a line."""
    if isinstance(v, (list, tuple)) and len(v) > 1 and all(isinstance(x, (list, tuple)) for x in v):
        return "[\n" + "".join(f"    {_toml(x)},\n" for x in v) + "]"
    return _toml(v)


def _terms(d: RecipeDraft, parts: dict[str, RecipePart]) -> list[str]:
    """The objective's two terms, weighing alike: the structural tables and distance, and the size term."""
    structure, size = parts["distance"], parts["size.distance"]
    L = _comment(
        "Two terms: the structural distance on the tree's tables (how branches look; "
        f"{parts['features'].why}) and a size term on tree-level statistics (how large the tree is, where the "
        "crown starts, how many branches it has), which the structural distance cannot see."
    )
    L += ["[features]", *_section(parts["features"]), "", "[distance]", *_section(structure), "", "[objective]"]
    L.append(
        _line(
            f"seeds = {d.seeds}",
            f"the mean over {d.seeds} model seeds: clones vary, the fit must not chase one"
            if d.seeds > 1
            else "one model seed an evaluation: the seeds' luck is taken out where the answer is chosen ([select])",
        )
    )
    L.append(_line(f"timeout = {d.timeout:.1f}", "seconds one growth may take: a safety net far above a normal growth"))
    L.append(_line(f"structure_weight = {TERM_WEIGHT!r}", "structure and size weigh alike"))
    if size.reach is not None and structure.reach is not None:
        # the most the objective can reach: the weighted mean of the terms' reaches; a failed growth scores above
        reach = (TERM_WEIGHT * structure.reach + TERM_WEIGHT * size.reach) / (2.0 * TERM_WEIGHT)
        penalty = max(LIMITS_PENALTY, float(math.ceil(2.0 * reach)))
        L.append(_line(f"penalty = {penalty!r}", f"a failed growth scores above the {reach:g} a grown tree can reach"))
    L += ["", *_comment(size.why, d.size_why if d.size_extra else "")]
    L += ["[[objective.terms]]", 'name = "size"', f"weight = {TERM_WEIGHT!r}"]
    return L + [f"features = {_inline(parts['size.features'])}", f"distance = {_inline(size)}", ""]


def _search(d: RecipeDraft, parts: dict[str, RecipePart], start: str | None = None) -> list[str]:
    """The search (the optimiser's part), where it starts, its budget and how the answer is chosen."""
    L = []
    if start is not None:
        L += _comment(
            "The search starts from an amortised estimator's posterior for this tree (bforest train, bforest "
            "posterior): its first points are draws of it."
        )
        L += ["[start]", f'estimator = "{start}"', ""]
    L += [*_comment(parts["optimizer"].why, d.search_why), "[optimizer]", *_section(parts["optimizer"]), ""]
    L += ["[stop]", f"max_evaluations = {d.max_evaluations}"]
    L.append(
        _line(
            f"wall_time = {d.wall_time:.1f}",
            "seconds: a safety net only; the search stops on its budget, so the answer is the same on any machine",
        )
    )
    L += ["", *_comment(_select_text(d, parts)), "[select]", f"top = {d.select_top}", f"sets = {d.select_sets}"]
    if d.select_tables:
        L += [f"{key} = {_toml(parts[key].select)}" for key in ("features", "distance") if parts[key].select]
    if d.select_sizes:
        L.append(f"sizes = {_toml(d.select_sizes)}")
    return L + [""]
