"""Tree-level summary statistics as a data set, and a distance between summaries.

The structural distance compares the *distributions* of branch and segment rows; it does not see
how tall a tree is, how many branches it carries or where its crown starts. ``tree-summary``
turns a tree into one row of such statistics (:func:`bforest_core.metrics.tree_summary`, the same
code for QSMs and model trees) and ``summary`` scores a model row against the data row,
statistic by statistic, so that one objective can weigh both (``[[objective.terms]]``). A weight
sets the rate at which a fit trades a statistic for structure; ``limits`` make the trade steep
beyond a forester's limit (docs/user-guide.md section 5b).
"""

from __future__ import annotations

from typing import Literal, Optional

import numpy as np
from pydantic import Field, field_validator, model_validator

from bforest_core.interfaces import ComponentSettings, Distance, FeatureSet, RecipePart, RecipePlan
from bforest_core.metrics import (
    DETECTION_DIAMETER,
    SIGNED_UNITS,
    SIZE_WEIGHTS,
    SUMMARY_DEFAULT,
    checked_fractions,
    ruled_summary,
    summary_unit,
)

SET = "summary"
#: offset c of the log ratio |log((m + c) / (d + c))| by unit: a count of 0 is fine, a length or
#: volume near 0 does not blow up
OFFSETS = {"": 1.0, "m": 0.05, "m^3": 1e-4}


class TreeSummarySettings(ComponentSettings):
    statistics: list[str] = Field(
        list(SUMMARY_DEFAULT),
        min_length=1,
        description=(
            "statistics of bforest_core.metrics.tree_summary (height, dbh, base_diameter, crown_spread, "
            "crown_base_height, stem_length, n_whorls, n_branches_o<w>, n_all_branches_o<w>, length_o<w>, volume_o<w>, angle_o<w>, "
            "angle_iqr_o<w>, profile_n_b<k>, "
            "profile_len_b<k>)"
        ),
    )
    max_order: int = Field(3, ge=1, le=10, description="highest branch order with its own statistics")
    bands: int = Field(5, ge=1, le=50, description="height bands of the vertical profile")
    min_branch_diameter: float = Field(
        DETECTION_DIAMETER,
        ge=0,
        description=(
            "detection limit (m): branches thinner at the base are left out of the branch counts, lengths "
            "and profile, in the target and the model alike (a TLS QSM rarely resolves them); 0 counts all"
        ),
    )
    topology: Optional[Literal["source", "subtree", "thickest"]] = Field(
        None,
        description=(
            "branch rule of both trees' statistics (docs/features-and-distance.md section 1.1): None keeps each "
            "tree's own (the QSM's stored branches, the model's order_mode); 'subtree' counts and measures "
            "branches as the structural tables do"
        ),
    )
    topology_statistics: Optional[list[str]] = Field(
        None,
        description="the statistics measured by topology (default: all); the others by each tree's own branches",
    )

    @model_validator(mode="after")
    def _rule_named(self):
        if self.topology_statistics is not None and self.topology is None:
            raise ValueError(
                f"topology_statistics = {self.topology_statistics} needs a topology to measure them by "
                '(for example topology = "subtree")'
            )
        return self


class TreeSummary(FeatureSet):
    """One row of tree-level statistics (the data set ``summary``)."""

    name = "tree-summary"
    summary = "tree-level statistics: height, DBH, crown spread, crown base, branch counts, vertical profile"
    Settings = TreeSummarySettings

    def summary_rule(self) -> tuple[str | None, list[str] | None]:
        """The branch rule the statistics are measured by, and which (``topology``, ``topology_statistics``)."""
        return self.settings.topology, self.settings.topology_statistics

    def draft_recipe(self, plan: RecipePlan) -> RecipePart | None:
        """The size term's statistics: the default set, and those the growth model adds; every
        living branch counts (no detection limit), which keeps a fit from crowns of thin twigs."""
        if plan.term != "size":
            return None
        settings = [("min_branch_diameter", 0.0, None)]
        if plan.draft.size_extra:
            settings.append(("statistics", [*SUMMARY_DEFAULT, *plan.draft.size_extra], None))
        return RecipePart(self.name, settings)

    @property
    def set_names(self) -> list[str]:
        return [SET]

    def columns(self, set_name: str) -> list[str]:
        return list(self.settings.statistics)

    def _row(self, tree) -> np.ndarray:
        s = self.settings
        stats = ruled_summary(
            tree,
            s.topology,
            s.topology_statistics,
            max_order=s.max_order,
            bands=s.bands,
            min_diameter=s.min_branch_diameter,
        )
        missing = [k for k in (*s.statistics, *(s.topology_statistics or ())) if k not in stats]
        if missing:
            raise ValueError(
                f"tree-summary: unknown statistic(s) {', '.join(missing)} (known with max_order = "
                f"{s.max_order}, bands = {s.bands}: {', '.join(stats)})"
            )
        return np.array([[stats[k] for k in s.statistics]], float)

    def prepare(self, data_trees) -> None:
        for t in data_trees:
            self._row(t)  # names are checked once, at set-up, against the data tree

    def extract(self, tree) -> dict[str, np.ndarray]:
        return {SET: self._row(tree)}


class SummaryDistanceSettings(ComponentSettings):
    form: Literal["logratio", "relative"] = Field(
        "logratio",
        description=(
            "logratio: |log((m + c) / (d + c))| (symmetric; c by unit: 1 for counts, 0.05 m, 1e-4 m^3); "
            "relative: |m - d| / |d|; in either, a signed statistic (the crown offset, crown radii) by |m - d|"
        ),
    )
    weights: dict[str, float] = Field(default_factory=dict, description="weight per statistic (default 1)")
    scales: dict[str, float] = Field(
        default_factory=dict,
        description=("scale per statistic: its term is divided by it (e.g. 0.05 for height: a 5 % miss counts 1)"),
    )
    limits: dict[str, float] = Field(
        default_factory=dict,
        description=(
            "a forester's limit per statistic as a relative error (0.2: the model's value within 20 % of the "
            "tree's): beyond it the statistic's term grows steep times as fast, so a fit cannot buy structure "
            "with a size that a forester would reject; the cap bounds the plain term and the extra comes on top "
            "(a term can reach cap * (1 + steep): set [objective] penalty above what the objective can then "
            "reach; default: no limit)"
        ),
    )
    steep: float = Field(10.0, ge=0, description="how many times as fast a term grows beyond its statistic's limit")
    cap: float = Field(
        2.0, gt=0, description="largest term of one statistic before a limit's extra (a missing value counts this)"
    )

    _limits = field_validator("limits")(lambda cls, v: checked_fractions(v, "limits"))

    @field_validator("weights", "scales")
    @classmethod
    def _positive(cls, v):
        bad = {k: x for k, x in v.items() if not x > 0}
        if bad:
            raise ValueError(f"must be positive: {bad}")
        return v


def _column_means(u: np.ndarray) -> np.ndarray:
    """Mean of the finite values of each column (NaN where a column has none), without the
    warning ``np.nanmean`` gives for an all-NaN column (a tree without DBH is a normal case)."""
    ok = np.isfinite(u)
    n = ok.sum(axis=0)
    total = np.where(ok, u, 0.0).sum(axis=0)
    return np.where(n > 0, total / np.maximum(n, 1), np.nan)


class SummaryDistance(Distance):
    """Weighted mean over statistics of the per-statistic miss of the model's summary row."""

    name = "summary"
    summary = "distance between summary rows: weighted mean of per-statistic log ratios or relative errors"
    Settings = SummaryDistanceSettings

    def draft_recipe(self, plan: RecipePlan) -> RecipePart | None:
        """The size term: log ratios weighted as the growth model's recipes calibrated them (or by
        the inverse of the error a forester tolerates), with the model's limits beyond which a
        statistic's term grows ``steep`` times as fast."""
        if plan.term != "size":
            return None
        d = plan.draft
        weights = {**(d.size_weights or SIZE_WEIGHTS), **d.size_extra}
        settings = [("form", "logratio", None), ("weights", weights, None)]
        why = (
            "The headline statistics weigh as the model's recipes calibrated them."
            if d.size_weights
            else "The headline statistics weigh by the inverse of the error a forester tolerates (height 7.5 %, "
            "DBH 20 %, crown spread 25 %, crown base and first-order branches 30 %)."
        )
        reach = None
        if d.size_limits:
            cap = 2.0  # a statistic's plain term at most: the structural distance (KS) reaches 1
            limits = {k: float(f"{v:g}") for k, v in d.size_limits.items()}
            settings += [("limits", limits, None), ("steep", float(d.size_steep), None), ("cap", cap, None)]
            why += (
                f" Beyond its limit (a relative error, limits) a statistic's term grows {d.size_steep:g} times as "
                "fast: a fit trades a size for structure only as far as a forester still accepts the size."
            )
            reach = cap * (1.0 + d.size_steep)
        return RecipePart(self.name, settings, why, reach=reach)

    def __init__(self, settings=None, **kwargs):
        super().__init__(settings, **kwargs)
        self._columns: dict[str, list[str]] = {}

    def prepare(self, U_data, columns=None) -> None:
        self._columns = {k: list(v) for k, v in (columns or {}).items()}
        for k, cols in self._columns.items():
            named = set(self.settings.weights) | set(self.settings.scales) | set(self.settings.limits)
            unknown = sorted(named - set(cols))
            if unknown:
                raise ValueError(
                    f"summary distance: weights/scales/limits name statistics that set {k!r} does not have: "
                    f"{', '.join(unknown)} (it has: {', '.join(cols)})"
                )

    def per_statistic(self, u_model: np.ndarray, u_data: np.ndarray, names=None) -> dict[str, float]:
        """The (scaled, capped) term of each statistic; the model and data rows are averaged
        first when there are several."""
        u_model, u_data = np.atleast_2d(u_model), np.atleast_2d(u_data)
        names = list(names) if names is not None else [f"x{i}" for i in range(u_data.shape[1])]
        cap = self.settings.cap
        if u_model.shape[0] == 0:
            return {n: cap for n in names}
        m, d = _column_means(u_model), _column_means(u_data)
        out = {}
        for i, n in enumerate(names):
            if not np.isfinite(d[i]):
                continue  # the data tree has no value (e.g. no DBH below 1.3 m): not compared
            if not np.isfinite(m[i]):
                out[n] = cap
                continue
            apart = summary_unit(n) in SIGNED_UNITS  # a signed statistic: its difference, in its unit
            if apart:
                term = abs(m[i] - d[i])
            elif self.settings.form == "logratio":
                c = OFFSETS.get(summary_unit(n), 1.0)
                signed = np.log((max(m[i], 0.0) + c) / (max(d[i], 0.0) + c))
                term = abs(signed)
            else:
                term = abs(m[i] - d[i]) / abs(d[i]) if d[i] != 0 else (0.0 if m[i] == 0 else cap)
            scale = self.settings.scales.get(n, 1.0)
            term = min(term / scale, cap)
            if n in self.settings.limits:
                # the limit's relative error on the miss's side (as a log ratio in that form; a
                # signed statistic's limit is a difference in its unit); the extra comes after the
                # cap, so that a miss far beyond the limit still costs more than one just beyond it
                lim = self.settings.limits[n]
                if self.settings.form == "logratio" and not apart:
                    lim = abs(np.log1p(lim if signed > 0 else -lim))
                term += self.settings.steep * max(0.0, term - lim / scale)
            out[n] = float(term)
        return out

    def _mean(self, terms: dict[str, float]) -> float:
        if not terms:
            return 0.0
        w = np.array([self.settings.weights.get(k, 1.0) for k in terms])
        return float(np.dot(w, list(terms.values())) / w.sum())

    def compute(self, u_model: np.ndarray, u_data: np.ndarray) -> float:
        return self._mean(self.per_statistic(u_model, u_data))

    def compute_pair(self, set_name: str, u_model: np.ndarray, u_data: np.ndarray) -> float | None:
        return self._mean(self.per_statistic(u_model, u_data, self._columns.get(set_name)))
