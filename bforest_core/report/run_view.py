"""Everything the report reads from a run directory, read once (:class:`RunView`)."""

from __future__ import annotations

import csv
import json
from functools import cached_property
from pathlib import Path

import numpy as np

from ..errors import BayesForestError
from ..pipeline.clones import CSV_COLUMNS
from ..pipeline.store import RunFiles, RunStore

# ---------------------------------------------------------------------------------- run data
#: clones.csv header -> row key (headers carry units)
_CSV_KEYS = {v: k for k, v in CSV_COLUMNS.items()}


class RunView:
    """Lazy, cached access to everything a run directory holds (and what can be rebuilt from
    its config). Problems are collected in ``notes`` instead of raised."""

    def __init__(self, run_dir):
        self.path = Path(run_dir)
        self.store = RunStore.open(self.path)
        self.notes: list[str] = []
        self.best_tree_source = ""

    def note(self, text: str) -> None:
        if text not in self.notes:
            self.notes.append(text)

    # ----------------------------------------------------------------- config, results
    @cached_property
    def raw_config(self) -> dict:
        import tomllib

        try:
            return tomllib.loads(self.store.config_path.read_text(encoding="utf-8"))
        except Exception as exc:
            self.note(f"{RunFiles.CONFIG} could not be read: {exc}")
            return {}

    @cached_property
    def cfg(self):
        from ..config import load_config

        try:
            return load_config(self.store.config_path)
        except BayesForestError as exc:
            self.note(
                f"{RunFiles.CONFIG} does not validate with the installed plugins ({exc}); "
                "figures that need the models are skipped"
            )
            return None

    @cached_property
    def best(self) -> dict | None:
        p = self.store.best_path
        if not p.exists():
            self.note(f"no {RunFiles.BEST}: the fit has not finished (the report shows the evaluations so far)")
            return None
        return json.loads(p.read_text(encoding="utf-8"))

    @cached_property
    def evaluations(self):
        return self.store.evaluations()

    @cached_property
    def records(self) -> list[dict]:
        return self.store.log_records()

    @cached_property
    def param_specs(self) -> dict:
        """The SSM's parameter specs by name (empty when the SSM is not available)."""
        if self.cfg is None:
            return {}
        try:
            from ..config import build_component

            ssm = build_component(self.cfg, "ssm")
            return {p.name: p for p in ssm.parameters}
        except Exception:
            return {}

    @property
    def free_names(self) -> list[str]:
        if self.cfg is not None:
            return list(self.cfg.ssm.free)
        return list((self.raw_config.get("ssm") or {}).get("free", {}))

    @property
    def best_params(self) -> dict | None:
        if self.best is not None:
            return dict(self.best["params"])
        ev = self.store.best()
        return None if ev is None else dict(ev.params)

    @cached_property
    def true_params(self) -> dict[str, float]:
        """The free parameters' true values where the target was grown by the fitted model
        (``[target.generate]`` with the same ``ssm``): the generating parameters, a parameter it
        leaves out at the model's default. Empty for a QSM target or another model's tree."""
        gen = self.cfg.target.generate if self.cfg is not None else None
        if gen is None or gen.ssm != self.cfg.ssm.kind:
            return {}
        out = {}
        for name in self.free_names:
            if name in gen.params:
                out[name] = float(gen.params[name])
            elif name in self.param_specs and self.param_specs[name].default is not None:
                out[name] = float(self.param_specs[name].default)
        return out

    @property
    def best_seeds(self) -> list[int]:
        if self.best is not None and self.best.get("seeds"):
            return list(self.best["seeds"])
        from ..pipeline.seeds import model_seeds

        c = self.cfg
        return model_seeds(c.seed, c.objective.seeds, "fixed") if c is not None else [1]

    # ----------------------------------------------------------------- target and data sets
    @cached_property
    def target(self):
        """The :class:`~bforest_core.pipeline.target.Target` rebuilt from the config (or None)."""
        if self.cfg is None:
            return None
        from ..pipeline.target import build_target

        try:
            return build_target(self.cfg)
        except Exception as exc:  # a moved QSM file must not stop the report
            self.note(
                f"the target could not be rebuilt from the config ({type(exc).__name__}: {exc}); "
                "using the run's saved copies"
            )
            return None

    @cached_property
    def U_data(self) -> dict[str, np.ndarray]:
        p = self.store.target_sets_path
        if p.exists():
            with np.load(p) as z:
                return {k: np.asarray(z[k]) for k in z.files}
        if self.target is not None:
            return dict(self.target.U)
        self.note(f"no {RunFiles.TARGET_SETS} and the target could not be rebuilt: data-set figures skipped")
        return {}

    @cached_property
    def columns(self) -> dict[str, list[str]]:
        if self.target is not None:
            return dict(self.target.columns)
        if self.cfg is not None and self.U_data:
            try:
                from ..pipeline.target import feature_set_for

                fs = feature_set_for(self.cfg, "target")
                return {k: list(fs.columns(k)) for k in self.U_data}
            except Exception:
                pass
        return {k: [f"x{i}" for i in range(v.shape[1])] for k, v in self.U_data.items()}

    def _read_tree(self, p: Path):
        if not p.exists():
            return None
        try:
            from ..io import read_tree

            return read_tree(p)
        except Exception as exc:
            self.note(f"{p.name} could not be read ({type(exc).__name__}: {exc})")
            return None

    @cached_property
    def target_tree(self):
        if self.target is not None:
            return self.target.trees[0]
        t = self._read_tree(self.store.target_tree_path)
        if t is None:
            self.note(
                f"the target tree is not available (no {RunFiles.TARGET_TREE} and no readable target in the config)"
            )
        return t

    @cached_property
    def crown_space(self):
        """The crown's space drawn over the target and its clones, and its name in the legend:
        the envelope the model grew the clones in (``SSM.crown_space`` at the best parameters),
        else the one measured from the target (``metrics.crown_envelope``), or (None, "")."""
        if self.cfg is not None and self.best_params is not None:
            try:
                from ..config import build_component

                space = build_component(self.cfg, "ssm").crown_space(self.best_params)
            except Exception as exc:  # a model that cannot say must not stop the report
                self.note(f"the model's crown space could not be read ({type(exc).__name__}: {exc})")
                space = None
            if space is not None:
                return space, "the crown's space the clones grew in"
        if self.target_tree is None:
            return None, ""
        from ..metrics import crown_envelope

        try:
            return crown_envelope(self.target_tree), "the target's crown space (not used by this model)"
        except ValueError:  # a target without a crown
            return None, ""

    @cached_property
    def best_tree(self):
        """The best-fit tree: regrown from the best parameters and the first model seed (exactly
        the tree ``finish_fit`` scored and wrote), else read from ``best_tree.txt``.

        Regrowing comes first because the text file rounds coordinates (to ~1e-8 m), which can
        move segment angles of near-vertical cylinders and so the distance in the 4th digit.
        """
        if self.cfg is not None and self.best_params is not None:
            try:
                from ..pipeline.scoring import grow_tree

                tree = grow_tree(self.cfg, self.best_params, int(self.best_seeds[0]))
                self.best_tree_source = "regrown"
                return tree
            except Exception as exc:
                self.note(
                    f"the best-fit tree could not be regrown ({type(exc).__name__}: {exc}); using {RunFiles.BEST_TREE}"
                )
        t = self._read_tree(self.store.best_tree_path)
        if t is not None:
            self.best_tree_source = RunFiles.BEST_TREE
        return t

    @cached_property
    def worker_parts(self):
        """(features, distance) built exactly as the fit's workers build them
        (:func:`~bforest_core.pipeline.scoring.build_scoring`), or None."""
        if self.cfg is None or not self.U_data:
            return None
        from ..config import section_settings
        from ..pipeline.scoring import build_scoring

        if self.target is not None:
            fs_settings = self.target.feature_settings
        else:
            fs_settings = section_settings(self.cfg, "features")
        try:
            scoring = build_scoring(self.cfg, self.U_data, self.columns, fs_settings)
        except Exception as exc:
            self.note(f"the feature set and distance could not be set up ({type(exc).__name__}: {exc})")
            return None
        return scoring.features, scoring.distance

    @cached_property
    def U_model(self) -> dict[str, np.ndarray] | None:
        if self.worker_parts is None or self.best_tree is None:
            return None
        try:
            return self.worker_parts[0].extract(self.best_tree)
        except Exception as exc:
            self.note(f"data sets of the best-fit tree could not be extracted ({type(exc).__name__}: {exc})")
            return None

    @cached_property
    def target_metrics(self) -> dict | None:
        if self.best is not None and self.best.get("target_metrics"):
            return self.best["target_metrics"]
        if self.target_tree is not None:
            from ..metrics import classical_metrics

            return classical_metrics(self.target_tree)
        return None

    @cached_property
    def model_metrics(self) -> dict | None:
        if self.best is not None and self.best.get("model_metrics"):
            return self.best["model_metrics"]
        if self.best_tree is not None:
            from ..metrics import classical_metrics

            return classical_metrics(self.best_tree)
        return None

    # ----------------------------------------------------------------- clones
    @cached_property
    def clone_rows(self) -> list[dict]:
        p = self.store.clones_dir() / RunFiles.CLONE_TABLE
        if not p.exists():
            return []
        rows = []
        with open(p, newline="") as fh:
            for r in csv.DictReader(fh):
                out = {}
                for k, v in r.items():
                    k = _CSV_KEYS.get(k, k)
                    if k in ("status", "file"):
                        out[k] = v
                        continue
                    try:
                        out[k] = float(v) if v not in ("", None) else float("nan")
                    except ValueError:
                        out[k] = v
                rows.append(out)
        return rows

    def clone_trees(self, k: int) -> list[tuple[str, object]]:
        """The first ``k`` clones grown ok, read from their files: ``(label, tree)`` with the
        label ``"clone <i>\nD = <distance>"``; a file that cannot be read is a note."""
        from ..io import read_tree

        shown = []
        for r in self.clone_rows:
            if len(shown) >= k:
                break
            f = r.get("file")
            if r.get("status") != "ok" or not f or not (self.store.clones_dir() / f).exists():
                continue
            try:
                t = read_tree(self.store.clones_dir() / f)
            except Exception as exc:
                self.note(f"clone file {f} could not be read ({type(exc).__name__}: {exc})")
                continue
            d = r.get("distance")
            shown.append(
                (f"clone {int(r['index'])}" + (f"\nD = {d:.3f}" if d is not None and np.isfinite(d) else ""), t)
            )
        return shown

    @cached_property
    def clone_summary(self) -> dict | None:
        p = self.store.clones_dir() / RunFiles.CLONE_SUMMARY
        if not p.exists():
            return None
        return json.loads(p.read_text(encoding="utf-8"))
