"""``bforest report DIR``: figures and a summary of a run directory.

Writes ``DIR/figures/*.png``, ``DIR/report.md`` and a self-contained ``DIR/report.html`` (the
figures inline as base64). Everything is read from the run directory (``config.toml``,
``evaluations.sqlite``, ``best.json``, ``target_sets.npz``, ``best_tree.txt``, ``clones/``); what
is missing (an interrupted fit, no clones yet, a distance without projection lines) is skipped
and the report says so. A figure that fails never stops the report (unless ``strict``).

Figures:

* ``trees.png``: target and best fit in XZ, YZ and XY (GigaScience Fig. 2/6);
* ``set_<set>.png``: data (QSM, blue) against model (SSM, red) for every fitted set (Fig. 3);
* ``lines_<set>.png``: ECDFs on the worst-fitting projection lines with the KS gap;
* ``convergence.png``, ``parameters.png``: the optimiser's progress and where it searched;
* ``chain.png``, ``corner.png``: MCMC trace and posterior (emcee runs);
* ``clones.png``, ``clone_metrics.png``: clones beside the target and their metric
  distributions (Fig. 5);
* ``profile_<param>.png``: made by ``bforest profile`` (Fig. 4), included when present.
"""
from __future__ import annotations

import base64
import csv
import datetime as _dt
import html as _html
import json
import re
import time
from collections import Counter
from dataclasses import dataclass, field
from functools import cached_property
from pathlib import Path

import numpy as np

from .errors import BayesForestError
from .store import RunStore

__all__ = ["write_report", "RunView", "slug"]

_METRIC_ROWS = (("height", "height (m)", "d_h"), ("girth", "girth (m)", "d_g"),
                ("crown_spread", "crown spread (m)", "d_c"), ("dbh", "DBH at 1.3 m (m)", None))


def slug(text: str) -> str:
    """A file-name-safe version of a set or parameter name (``"S0,1"`` -> ``"S0-1"``)."""
    s = re.sub(r"[^A-Za-z0-9_.-]+", "-", str(text)).strip("-")
    return s or "x"


def _fmt(v, digits: int = 4) -> str:
    if v is None:
        return "–"
    if isinstance(v, bool):
        return str(v)
    if isinstance(v, (int, np.integer)):
        return str(int(v))
    if isinstance(v, (float, np.floating)):
        if not np.isfinite(v):
            return "–" if np.isnan(v) else str(v)
        if v != 0 and (abs(v) >= 1e5 or abs(v) < 1e-3):
            return f"{v:.{digits - 1}e}"
        return f"{v:.{digits}g}"
    return str(v)


def _seconds(s) -> str:
    if s is None or not np.isfinite(s):
        return "–"
    s = float(s)
    if s < 120:
        return f"{s:.1f} s"
    if s < 7200:
        return f"{s / 60:.1f} min"
    return f"{s / 3600:.2f} h"


# ---------------------------------------------------------------------------------- document
@dataclass
class _Doc:
    """A tiny document model rendered to both Markdown and HTML."""

    blocks: list = field(default_factory=list)

    def h(self, level: int, text: str):
        self.blocks.append(("h", level, text))

    def p(self, text: str):
        self.blocks.append(("p", text))

    def items(self, items: list[str]):
        if items:
            self.blocks.append(("list", list(items)))

    def table(self, header: list[str], rows: list[list]):
        self.blocks.append(("table", header, [[_fmt(c) if not isinstance(c, str) else c for c in r] for r in rows]))

    def fig(self, rel: str, caption: str):
        self.blocks.append(("fig", rel, caption))

    def code(self, text: str):
        self.blocks.append(("code", text))

    # ----------------------------------------------------------------- markdown
    def markdown(self) -> str:
        out = []
        for b in self.blocks:
            kind = b[0]
            if kind == "h":
                out.append("#" * b[1] + " " + b[2])
            elif kind == "p":
                out.append(b[1])
            elif kind == "list":
                out.append("\n".join(f"- {x}" for x in b[1]))
            elif kind == "table":
                header, rows = b[1], b[2]
                esc = lambda c: str(c).replace("|", "\\|").replace("\n", " ")
                lines = ["| " + " | ".join(esc(c) for c in header) + " |",
                         "|" + "|".join("---" for _ in header) + "|"]
                lines += ["| " + " | ".join(esc(c) for c in r) + " |" for r in rows]
                out.append("\n".join(lines))
            elif kind == "fig":
                out.append(f"![{b[2]}]({b[1]})\n\n*{b[2]}*")
            elif kind == "code":
                out.append("```\n" + b[1] + "\n```")
        return "\n\n".join(out) + "\n"

    # ----------------------------------------------------------------- html
    @staticmethod
    def _inline(text: str) -> str:
        t = _html.escape(text)
        t = re.sub(r"`([^`]+)`", r"<code>\1</code>", t)
        t = re.sub(r"\*\*([^*]+)\*\*", r"<b>\1</b>", t)
        return t

    def html(self, base: Path, title: str, inline_images: bool = True) -> str:
        parts = []
        for b in self.blocks:
            kind = b[0]
            if kind == "h":
                parts.append(f"<h{b[1]}>{self._inline(b[2])}</h{b[1]}>")
            elif kind == "p":
                parts.append(f"<p>{self._inline(b[1])}</p>")
            elif kind == "list":
                parts.append("<ul>" + "".join(f"<li>{self._inline(x)}</li>" for x in b[1]) + "</ul>")
            elif kind == "table":
                head = "".join(f"<th>{self._inline(str(c))}</th>" for c in b[1])
                body = "".join("<tr>" + "".join(f"<td>{self._inline(str(c))}</td>" for c in r) + "</tr>"
                               for r in b[2])
                parts.append(f"<table><thead><tr>{head}</tr></thead><tbody>{body}</tbody></table>")
            elif kind == "fig":
                src = b[1]
                p = base / b[1]
                if inline_images and p.exists():
                    src = "data:image/png;base64," + base64.b64encode(p.read_bytes()).decode("ascii")
                parts.append(f'<figure><img src="{src}" alt="{_html.escape(b[2])}">'
                             f"<figcaption>{self._inline(b[2])}</figcaption></figure>")
            elif kind == "code":
                parts.append(f"<pre>{_html.escape(b[1])}</pre>")
        style = ("body{font-family:system-ui,-apple-system,Segoe UI,Helvetica,Arial,sans-serif;max-width:1200px;"
                 "margin:2em auto;padding:0 1em;color:#222;line-height:1.45}"
                 "table{border-collapse:collapse;margin:0.6em 0}th,td{border:1px solid #ccc;padding:3px 8px;"
                 "text-align:left;font-size:0.92em}th{background:#f2f2f2}"
                 "img{max-width:100%;border:1px solid #eee}figure{margin:1em 0}"
                 "figcaption{font-size:0.9em;color:#555}code,pre{background:#f6f6f6;padding:1px 3px}"
                 "h1{border-bottom:2px solid #ddd}h2{border-bottom:1px solid #eee;margin-top:1.6em}")
        return (f"<!DOCTYPE html>\n<html lang=\"en\"><head><meta charset=\"utf-8\"><title>{_html.escape(title)}"
                f"</title><style>{style}</style></head><body>\n" + "\n".join(parts) + "\n</body></html>\n")


# ---------------------------------------------------------------------------------- run data
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
            self.note(f"config.toml could not be read: {exc}")
            return {}

    @cached_property
    def cfg(self):
        from .config import load_config
        try:
            return load_config(self.store.config_path)
        except BayesForestError as exc:
            self.note(f"config.toml does not validate with the installed plugins ({exc}); "
                      "figures that need the models are skipped")
            return None

    @cached_property
    def best(self) -> dict | None:
        p = self.path / "best.json"
        if not p.exists():
            self.note("no best.json: the fit has not finished (the report shows the evaluations so far)")
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
            from .config import ssm_settings
            from .registry import component
            ssm = component("ssm", self.cfg.ssm.kind, **ssm_settings(self.cfg))
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

    @property
    def best_seeds(self) -> list[int]:
        if self.best is not None and self.best.get("seeds"):
            return list(self.best["seeds"])
        from .objective import model_seeds
        c = self.cfg
        return model_seeds(c.seed, c.objective.seeds, "fixed") if c is not None else [1]

    # ----------------------------------------------------------------- target and data sets
    @cached_property
    def target(self):
        """The :class:`~bforest_core.objective.Target` rebuilt from the config (or None)."""
        if self.cfg is None:
            return None
        from .objective import build_target
        try:
            return build_target(self.cfg)
        except Exception as exc:  # a moved QSM file must not stop the report
            self.note(f"the target could not be rebuilt from the config ({type(exc).__name__}: {exc}); "
                      "using the run's saved copies")
            return None

    @cached_property
    def U_data(self) -> dict[str, np.ndarray]:
        p = self.path / "target_sets.npz"
        if p.exists():
            with np.load(p) as z:
                return {k: np.asarray(z[k]) for k in z.files}
        if self.target is not None:
            return dict(self.target.U)
        self.note("no target_sets.npz and the target could not be rebuilt: data-set figures skipped")
        return {}

    @cached_property
    def columns(self) -> dict[str, list[str]]:
        if self.target is not None:
            return dict(self.target.columns)
        if self.cfg is not None and self.U_data:
            try:
                from .objective import feature_set_for
                fs = feature_set_for(self.cfg, "target")
                return {k: list(fs.columns(k)) for k in self.U_data}
            except Exception:
                pass
        return {k: [f"x{i}" for i in range(v.shape[1])] for k, v in self.U_data.items()}

    def _read_tree(self, name: str):
        p = self.path / name
        if not p.exists():
            return None
        try:
            from .io import read_qsm
            t = read_qsm(p)
            return t[0] if isinstance(t, list) else t
        except Exception as exc:
            self.note(f"{name} could not be read ({type(exc).__name__}: {exc})")
            return None

    @cached_property
    def target_tree(self):
        if self.target is not None:
            return self.target.trees[0]
        t = self._read_tree("target.txt")
        if t is None:
            self.note("the target tree is not available (no target.txt and no readable target in the config)")
        return t

    @cached_property
    def best_tree(self):
        """The best-fit tree: regrown from the best parameters and the first model seed (exactly
        the tree ``finish_fit`` scored and wrote), else read from ``best_tree.txt``.

        Regrowing comes first because the text file rounds coordinates (to ~1e-8 m), which can
        move segment angles of near-vertical cylinders and so the distance in the 4th digit.
        """
        if self.cfg is not None and self.best_params is not None:
            try:
                from .config import ssm_settings
                from .registry import component
                ssm = component("ssm", self.cfg.ssm.kind, **ssm_settings(self.cfg))
                tree = ssm.simulate(self.best_params, int(self.best_seeds[0]))
                self.best_tree_source = "regrown"
                return tree
            except Exception as exc:
                self.note(f"the best-fit tree could not be regrown ({type(exc).__name__}: {exc}); "
                          "using best_tree.txt")
        t = self._read_tree("best_tree.txt")
        if t is not None:
            self.best_tree_source = "best_tree.txt"
        return t

    @cached_property
    def worker_parts(self):
        """(features, distance) built exactly as the fit's workers build them (``init_worker``),
        or None."""
        if self.cfg is None or not self.U_data:
            return None
        from . import objective
        from .config import config_to_dict, section_settings
        if self.target is not None:
            fs_settings = self.target.feature_settings
        else:
            fs_settings = section_settings(self.cfg, "features")
        saved = dict(objective._CTX)
        try:
            objective.init_worker(config_to_dict(self.cfg), self.U_data, self.columns, fs_settings)
            return objective._CTX["features"], objective._CTX["distance"]
        except Exception as exc:
            self.note(f"the feature set and distance could not be set up ({type(exc).__name__}: {exc})")
            return None
        finally:
            objective._CTX.clear()
            objective._CTX.update(saved)

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
            from .metrics import classical_metrics
            return classical_metrics(self.target_tree)
        return None

    @cached_property
    def model_metrics(self) -> dict | None:
        if self.best is not None and self.best.get("model_metrics"):
            return self.best["model_metrics"]
        if self.best_tree is not None:
            from .metrics import classical_metrics
            return classical_metrics(self.best_tree)
        return None

    # ----------------------------------------------------------------- clones
    @cached_property
    def clone_rows(self) -> list[dict]:
        p = self.path / "clones" / "clones.csv"
        if not p.exists():
            return []
        rows = []
        with open(p, newline="") as fh:
            for r in csv.DictReader(fh):
                out = {}
                for k, v in r.items():
                    if k in ("status", "file"):
                        out[k] = v
                        continue
                    try:
                        out[k] = float(v) if v not in ("", None) else float("nan")
                    except ValueError:
                        out[k] = v
                rows.append(out)
        return rows

    @cached_property
    def clone_summary(self) -> dict | None:
        p = self.path / "clones" / "summary.json"
        if not p.exists():
            return None
        return json.loads(p.read_text(encoding="utf-8"))


# ---------------------------------------------------------------------------------- figures
class _Figures:
    def __init__(self, view: RunView, strict: bool):
        self.v = view
        self.strict = strict
        self.dir = view.path / "figures"
        self.dir.mkdir(exist_ok=True)
        self.made: dict[str, list[tuple[str, str]]] = {}

    def run(self, section: str, name: str, fn, *args, **kw):
        """Call a figure function; record (relative path, caption) or a note on failure."""
        try:
            res = fn(*args, **kw)
        except Exception as exc:
            if self.strict:
                raise
            self.v.note(f"figure '{name}' failed: {type(exc).__name__}: {exc}")
            return None
        if res:
            for path, caption in res:
                self.made.setdefault(section, []).append((Path(path).relative_to(self.v.path).as_posix(), caption))
        return res


def _fig_trees(v: RunView):
    from .plotting import tree_comparison_figure
    trees = {}
    if v.target_tree is not None:
        trees["target (QSM)" if v.cfg is None or v.cfg.target.qsm else "target"] = v.target_tree
    if v.best_tree is not None:
        trees["best fit"] = v.best_tree
    if not trees:
        v.note("trees figure skipped: neither the target nor the best-fit tree is available")
        return []
    p = tree_comparison_figure(trees, v.path / "figures" / "trees.png",
                               title="Target and best-fit tree (line width ∝ radius, colour = branch order)")
    cap = "Target and best-fit tree in the side views XZ, YZ and the top view XY, on one scale"
    if v.best_tree_source == "regrown":
        cap += " (best fit grown with the best parameters and the first model seed)"
    return [(p, cap)]


def _distance_view(dist, name: str, um: np.ndarray, ud: np.ndarray):
    """Tables in the distance's own units and its per-line values, when it exposes them.

    Uses the frozen per-set normalisation of a prepared sliced distance
    (``normalizations()[set] = {"center", "scale"}``) and its per-line statistic
    (``line_values(u_model, u_data, set_name)``); a distance without them is shown in raw units
    with the KS statistic computed per line by the figure.

    Returns ``(um, ud, line_values or None, statistic, normalised)``.
    """
    stat = str(getattr(getattr(dist, "settings", None), "statistic", "ks"))
    lines = None
    fn = getattr(dist, "line_values", None)
    if callable(fn):
        try:
            lines = np.asarray(fn(um, ud, set_name=name), float).reshape(-1)
        except (TypeError, ValueError, NotImplementedError):
            lines = None
    normalised = False
    norms = getattr(dist, "normalizations", None)
    if callable(norms):
        try:
            nd = norms().get(name)
        except Exception:
            nd = None
        if nd and nd.get("method", "none") != "none":
            c = np.asarray(nd["center"], float)
            sc = np.asarray(nd["scale"], float)
            if c.shape == (ud.shape[1],) and sc.shape == (ud.shape[1],):
                um, ud, normalised = (um - c) / sc, (ud - c) / sc, True
    return um, ud, lines, stat, normalised


def _fig_sets(v: RunView):
    from .plotting import set_scatter_figure, worst_lines_figure
    out = []
    if not v.U_data:
        return out
    Um = v.U_model
    if Um is None:
        v.note("data-set figures show the data only: the best-fit tree's data sets are not available")
    dist = v.worker_parts[1] if v.worker_parts is not None else None
    per_set = (v.best or {}).get("per_set", {})
    for name, ud in v.U_data.items():
        um = Um.get(name, np.empty((0, ud.shape[1]))) if Um is not None else np.empty((0, ud.shape[1]))
        cols = v.columns.get(name) or [f"x{i}" for i in range(ud.shape[1])]
        D = per_set.get(name)
        title = f"data set {name}: data (target) vs best-fit model (SSM)" + (f", D = {D:.4f}" if D is not None else "")
        p = set_scatter_figure(ud, um, cols, v.path / "figures" / f"set_{slug(name)}.png", title=title)
        out.append((p, f"Set {name}: every pair of variates, data blue, model red (angles in degrees)"))
        if dist is None or um.shape[0] == 0 or ud.shape[0] == 0:
            continue
        try:
            A = np.asarray(dist.directions(ud.shape[1]), float)
        except NotImplementedError:
            v.note(f"worst-lines figures skipped: distance '{dist.name}' does not project on lines")
            dist = None
            continue
        um2, ud2, lines, stat, normalised = _distance_view(dist, name, um, ud)
        p = worst_lines_figure(um2, ud2, A, cols, v.path / "figures" / f"lines_{slug(name)}.png",
                               line_values=lines, statistic=stat, normalised=normalised,
                               title=f"data set {name}: the worst-fitting projection lines")
        out.append((p, f"Set {name}: per-line statistic over all {A.shape[0]} lines and the ECDFs of data "
                       "(blue) and model (red) on the worst lines, KS gap in black"))
    return out


def _fig_convergence(v: RunView):
    from .plotting import convergence_figure, parameter_scatter_figure
    evs = v.evaluations
    if not evs:
        v.note("no evaluations logged: convergence figures skipped")
        return []
    d = np.array([e.distance for e in evs], float)
    st = [e.status for e in evs]
    out = [(convergence_figure(d, v.path / "figures" / "convergence.png", statuses=st, records=v.records,
                               title=f"Convergence ({(v.best or {}).get('optimizer') or _cfg_kind(v, 'optimizer')})"),
            "Distance of every evaluation and the best so far; per-generation best and mean when the "
            "optimiser logs generations")]
    names = [n for n in v.free_names if all(n in e.params for e in evs)]
    ok = [e for e in evs if e.ok]
    if names and ok:
        X = np.array([[e.params[n] for n in names] for e in ok], float)
        bounds = {}
        if v.cfg is not None:
            bounds = {n: (v.cfg.ssm.free[n].lower, v.cfg.ssm.free[n].upper) for n in names}
        out.append((parameter_scatter_figure(names, X, [e.distance for e in ok],
                                             v.path / "figures" / "parameters.png", best=v.best_params,
                                             bounds=bounds, units={n: s.unit for n, s in v.param_specs.items()},
                                             title="Where the optimiser searched"),
                    "Distance against each free parameter over the successful evaluations (colour: "
                    "evaluation number; star: best fit; x-range: the bounds)"))
    return out


def mcmc_chain(diag: dict, names: list[str]):
    """``(chain (steps, walkers, p), distances (steps, walkers) or None, burn_in, names)`` from an
    MCMC optimiser's diagnostics (the ``emcee`` optimiser stores ``chain``, ``distances``,
    ``burn_in`` and ``names``), or None when they hold no chain."""
    if not isinstance(diag, dict) or diag.get("chain") is None:
        return None
    try:
        chain = np.asarray(diag["chain"], float)
    except (TypeError, ValueError):
        return None
    names = list(diag.get("names") or names)
    if chain.ndim == 2 and chain.shape[1] == len(names):
        chain = chain[:, None, :]
    if chain.ndim != 3 or chain.shape[0] == 0 or chain.shape[1] == 0:
        return None
    if chain.shape[2] != len(names):
        names = [f"p{i}" for i in range(chain.shape[2])]
    dist = diag.get("distances")
    if dist is not None:
        try:
            dist = np.asarray(dist, float)
        except (TypeError, ValueError):
            dist = None
        if dist is not None and dist.shape != chain.shape[:2]:
            dist = None
    burn = diag.get("burn_in")
    burn = int(burn) if burn is not None else chain.shape[0] // 2
    burn = min(max(burn, 0), chain.shape[0] - 1)
    return chain, dist, burn, names


def _fig_mcmc(v: RunView):
    from .plotting import chain_figure, corner_figure
    diag = v.store.read_diagnostics()
    names = v.free_names
    got = mcmc_chain(diag, names)
    if got is None:
        return []
    chain, dist, burn, names = got
    out = [(chain_figure(chain, names, v.path / "figures" / "chain.png", burn_in=burn, distances=dist,
                         title="MCMC chain"),
            f"Trace of every walker per parameter ({chain.shape[1]} walkers, {chain.shape[0]} steps; "
            f"burn-in of {burn} steps shaded)")]
    samples = chain[burn:].reshape(-1, chain.shape[2])
    truths = [v.best_params.get(n) for n in names] if v.best_params else None
    truths = truths if truths and all(t is not None for t in truths) else None
    bounds = None
    if v.cfg is not None and all(n in v.cfg.ssm.free for n in names):
        bounds = [(v.cfg.ssm.free[n].lower, v.cfg.ssm.free[n].upper) for n in names]
    out.append((corner_figure(samples, names, v.path / "figures" / "corner.png", truths=truths, bounds=bounds,
                              title=f"Posterior ({samples.shape[0]} samples after burn-in)"),
                "Posterior marginals (16/50/84 % quantiles) and pairwise densities (39 %/86 % contours); "
                "red: the best evaluation"))
    return out


def _fig_clones(v: RunView):
    from .plotting import clone_metrics_figure, clones_figure
    rows = v.clone_rows
    ok = [r for r in rows if r.get("status") == "ok"]
    if not ok:
        return []
    out = []
    k = v.cfg.report.clones_in_figure if v.cfg is not None else 6
    shown = []
    from .io import read_qsm
    for r in ok:
        if len(shown) >= k:
            break
        f = r.get("file")
        if not f or not (v.path / "clones" / f).exists():
            continue
        try:
            t = read_qsm(v.path / "clones" / f)
            t = t[0] if isinstance(t, list) else t
        except Exception as exc:
            v.note(f"clone file {f} could not be read ({type(exc).__name__}: {exc})")
            continue
        d = r.get("distance")
        shown.append((f"clone {int(r['index'])}" + (f"\nD = {d:.3f}" if d is not None and np.isfinite(d) else ""), t))
    if shown and v.target_tree is not None:
        out.append((clones_figure(v.target_tree, shown, v.path / "figures" / "clones.png",
                                  title=f"Target and {len(shown)} morphological clones of the best fit"),
                    f"The target and {len(shown)} clones (the best-fit model with fresh seeds) on one scale, "
                    "side view XZ and top view XY"))
    keys = ("height", "girth", "crown_spread", "distance", "d_h", "d_g", "d_c", "n_cylinders")
    values = {k: np.array([r.get(k, np.nan) for r in ok], float) for k in keys}
    tm = dict(v.target_metrics or {})
    if v.target_tree is not None:
        tm["n_cylinders"] = v.target_tree.n
    bm = dict(v.model_metrics or {})
    if v.best is not None:
        bm["distance"] = v.best.get("distance")
        bm.update((v.best.get("relative_errors") or {}))
    if v.best_tree is not None:
        bm["n_cylinders"] = v.best_tree.n
    out.append((clone_metrics_figure(values, v.path / "figures" / "clone_metrics.png", target=tm, best=bm,
                                     title=f"Classical metrics of {len(ok)} clones"),
                "Distributions over the clones: height, girth, crown spread, structural distance and the "
                "relative errors d_h, d_g, d_c; black: target, red dashed: best-fit tree"))
    return out


def _cfg_kind(v: RunView, section: str) -> str:
    if v.cfg is not None:
        return getattr(v.cfg, section).kind
    return str((v.raw_config.get(section) or {}).get("kind", "?"))


# ---------------------------------------------------------------------------------- sections
def _settings_text(d: dict) -> str:
    items = []
    for k, val in d.items():
        if k in ("kind", "fixed", "free"):
            continue
        items.append(f"{k}={json.dumps(val, default=str)}")
    return ", ".join(items) if items else "defaults"


def _section_summary(doc: _Doc, v: RunView):
    evs = v.evaluations
    b = v.best
    kind = _cfg_kind(v, "ssm")
    if b is not None:
        doc.p(f"SSM **{kind}** fitted with **{b.get('optimizer', _cfg_kind(v, 'optimizer'))}**: best distance "
              f"**{_fmt(b.get('distance'))}** after {b.get('n_evaluations', len(evs))} evaluations "
              f"({b.get('stop_reason', '')}); run time {_seconds(b.get('seconds'))}.")
    else:
        best = v.store.best()
        doc.p(f"SSM **{kind}**: the fit has not finished; {len(evs)} evaluations logged"
              + (f", best distance so far **{_fmt(best.distance)}**." if best is not None else "."))


def _section_target(doc: _Doc, v: RunView):
    doc.h(2, "Target")
    t = v.raw_config.get("target", {})
    if v.cfg is not None:
        tc = v.cfg.target
        if tc.qsm:
            src = f"QSM file `{tc.qsm}`" + (f" (reader {tc.reader})" if tc.reader else "") + \
                  (f", reconstruction {tc.select}" if tc.select is not None else "")
        else:
            g = tc.generate
            src = f"generated by SSM `{g.ssm}` with seed {g.seed}, parameters {json.dumps(g.params)}"
        if tc.topology:
            src += f"; topology rule {tc.topology}"
    else:
        src = json.dumps(t)
    doc.p(f"Source: {src}.")
    tree = v.target_tree
    tm = v.target_metrics or {}
    rows = []
    if tree is not None:
        rows += [["cylinders", tree.n], ["branches", f"{tree.n_branches} (topology {tree.topology})"],
                 ["maximum branch order", tree.max_order]]
        if tree.added.any():
            rows.append(["added (gap-filling) cylinders", int(tree.added.sum())])
        rows.append(["wood volume (m³)", tree.volume])
    for key, label, _ in _METRIC_ROWS:
        if key in tm:
            rows.append([label, tm[key]])
    if rows:
        doc.table(["property", "value"], rows)
    if v.U_data:
        doc.p("Structural data sets of the target (rows = data points):")
        doc.table(["set", "rows", "columns"],
                  [[k, u.shape[0], ", ".join(v.columns.get(k, []))] for k, u in v.U_data.items()])


def _section_model(doc: _Doc, v: RunView):
    doc.h(2, "Model and method")
    raw = v.raw_config
    rows = []
    for section in ("ssm", "features", "distance", "optimizer", "executor"):
        sec = raw.get(section) or {}
        rows.append([section, f"`{sec.get('kind', '?')}`", _settings_text(sec)])
    doc.table(["component", "kind", "settings"], rows)
    obj = raw.get("objective", {})
    stop = raw.get("stop", {})
    doc.items([f"objective: {_settings_text(obj)}", f"stop: {_settings_text(stop)}",
               f"run seed: {raw.get('seed', 1)}"])


def _section_parameters(doc: _Doc, v: RunView):
    doc.h(2, "Parameters")
    specs = v.param_specs
    ssm_raw = v.raw_config.get("ssm", {})
    fixed, free = ssm_raw.get("fixed", {}) or {}, ssm_raw.get("free", {}) or {}
    best = v.best_params or {}
    rows, warn = [], []
    for name, fp in free.items():
        lo, hi = fp.get("lower"), fp.get("upper")
        b = best.get(name)
        s = specs.get(name)
        flag = ""
        if b is not None and lo is not None and hi is not None and hi > lo:
            rel = (b - lo) / (hi - lo)
            if rel < 0.01 or rel > 0.99:
                flag = " (at a bound)"
                warn.append(name)
        rows.append([name, "free", lo, hi, (_fmt(b) + flag) if b is not None else "–",
                     s.unit if s else "", s.description if s else ""])
    for name, val in fixed.items():
        s = specs.get(name)
        rows.append([name, "fixed", "", "", val, s.unit if s else "", s.description if s else ""])
    doc.table(["parameter", "role", "lower", "upper", "best", "unit", "description"], rows)
    others = [p for n, p in specs.items() if n not in free and n not in fixed]
    if others:
        doc.p("Other parameters at the model's defaults: " +
              ", ".join(f"{p.name} = {_fmt(p.default)}" for p in others) + ".")
    if warn:
        doc.p(f"Note: the best value of {', '.join(warn)} lies within 1 % of a bound; the optimum may be "
              "outside the search box (consider widening it).")


def _section_fit(doc: _Doc, v: RunView, figs: _Figures):
    doc.h(2, "Fit result")
    b = v.best
    if b is None:
        doc.p("No best fit yet (the fit has not finished).")
    else:
        weights = {}
        if v.cfg is not None and v.cfg.objective.weights:
            weights = dict(v.cfg.objective.weights)
        best_ev = next((e for e in v.evaluations if e.idx == b.get("evaluation")), None) or v.store.best()
        n_rows = best_ev.n_rows if best_ev is not None else {}
        rows = []
        per_set = b.get("per_set") or {}
        order = [k for k in v.U_data if k in per_set] + [k for k in per_set if k not in v.U_data]
        for name, d in ((k, per_set[k]) for k in order):
            rows.append([name, weights.get(name, 1.0), d if d is not None else "skipped",
                         v.U_data[name].shape[0] if name in v.U_data else "–",
                         n_rows.get(name, v.U_model[name].shape[0] if v.U_model and name in v.U_model else "–")])
        doc.p(f"Best distance **{_fmt(b.get('distance'))}** (evaluation {b.get('evaluation', '–')}, "
              f"model seeds {b.get('seeds')}). Distance per data set:")
        doc.table(["set", "weight", "distance", "data rows", "model rows"], rows)
        if v.cfg is not None:
            ds = v.raw_config.get("distance", {})
            doc.p(f"Distance `{ds.get('kind')}` ({_settings_text(ds)}); every number here uses these settings.")
    tm, mm = v.target_metrics, v.model_metrics
    if tm and mm:
        from .metrics import relative_errors
        rel = (b or {}).get("relative_errors") or relative_errors(tm, mm)
        rows = []
        for key, label, ek in _METRIC_ROWS:
            if key in tm or key in mm:
                rows.append([label, tm.get(key), mm.get(key), rel.get(ek) if ek else None])
        doc.p("Classical metrics (best-fit tree grown with the first model seed):")
        doc.table(["metric", "target", "best fit", "relative error"], rows)
    for rel_path, cap in figs.made.get("trees", []):
        doc.fig(rel_path, cap)
    if figs.made.get("sets"):
        doc.h(3, "Data sets: data against model")
        for rel_path, cap in figs.made["sets"]:
            doc.fig(rel_path, cap)


def _section_optimizer(doc: _Doc, v: RunView, figs: _Figures):
    doc.h(2, "Optimiser")
    b = v.best or {}
    kind = b.get("optimizer") or _cfg_kind(v, "optimizer")
    recs = v.records
    items = [f"optimiser `{kind}` ({_settings_text(v.raw_config.get('optimizer', {}))})"]
    if b.get("stop_reason"):
        items.append(f"stopped: {b['stop_reason']}")
    if recs:
        last = recs[-1]
        items.append(f"{len(recs)} log records (generations/iterations); last: "
                     + ", ".join(f"{k} = {_fmt(val)}" for k, val in last.items()
                                 if isinstance(val, (int, float)) or val is None))
    doc.items(items)
    diag = v.store.read_diagnostics()
    scal = [[k, _fmt(val) if not isinstance(val, str) else val] for k, val in diag.items()
            if isinstance(val, (int, float, str, bool)) or val is None]
    arr = []
    for k, val in diag.items():
        if isinstance(val, (list, tuple, np.ndarray)) and k != "names":
            try:
                arr.append([k, f"array of shape {np.shape(np.asarray(val, float))}"])
            except (TypeError, ValueError):
                arr.append([k, ", ".join(str(x) for x in val)[:200]])
    if scal or arr:
        doc.p("Diagnostics reported by the optimiser:")
        doc.table(["diagnostic", "value"], scal + arr)
    post = diag.get("posterior")
    if isinstance(post, dict) and post:
        tau = diag.get("autocorr_time") if isinstance(diag.get("autocorr_time"), dict) else {}
        rows = [[n, q.get("median"), q.get("p2.5"), q.get("p16"), q.get("p84"), q.get("p97.5"), q.get("mean"),
                 q.get("std"), tau.get(n)] for n, q in post.items() if isinstance(q, dict)]
        doc.p("Posterior summaries after burn-in" + (" (autocorrelation estimates reliable)"
              if diag.get("autocorr_reliable") else " (chain too short for reliable autocorrelation times: "
              "treat the intervals as rough)") + ":")
        doc.table(["parameter", "median", "2.5 %", "16 %", "84 %", "97.5 %", "mean", "sd", "autocorr. time"], rows)
    for rel_path, cap in figs.made.get("convergence", []) + figs.made.get("mcmc", []):
        doc.fig(rel_path, cap)


def _section_evaluations(doc: _Doc, v: RunView):
    doc.h(2, "Evaluations and run time")
    evs = v.evaluations
    if not evs:
        doc.p("No evaluations logged.")
        return
    counts = Counter(e.status for e in evs)
    example = {}
    for e in evs:
        if e.status != "ok" and e.status not in example and e.message:
            example[e.status] = e.message[:160]
    rows = [[s, n, f"{100.0 * n / len(evs):.1f} %", example.get(s, "")] for s, n in counts.most_common()]
    doc.p(f"{len(evs)} evaluations; {counts.get('ok', 0)} ok, {len(evs) - counts.get('ok', 0)} failed.")
    doc.table(["status", "evaluations", "share", "example message"], rows)
    secs = np.array([e.seconds for e in evs], float)
    workers = {e.worker for e in evs if e.worker}
    elapsed = (v.best or {}).get("seconds")
    if elapsed is None:
        elapsed = v.store.get_meta("elapsed")
    created = v.store.get_meta("created")
    rows = [["wall time of the fit", _seconds(elapsed)],
            ["simulation + features + distance, total", _seconds(secs.sum())],
            ["per evaluation: median / mean / max", f"{np.median(secs):.3g} / {secs.mean():.3g} / "
                                                    f"{secs.max():.3g} s"],
            ["workers used", len(workers) or "–"]]
    if elapsed:
        rows.append(["parallel efficiency (busy time / (wall × workers))",
                     f"{100 * secs.sum() / (float(elapsed) * max(1, len(workers))):.0f} %"])
    if created:
        rows.append(["run created", _dt.datetime.fromtimestamp(float(created)).strftime("%Y-%m-%d %H:%M:%S")])
    doc.table(["", "value"], rows)


def _section_clones(doc: _Doc, v: RunView, figs: _Figures):
    doc.h(2, "Clones")
    rows = v.clone_rows
    if not rows:
        doc.p("No clones yet: grow them with `bforest clones " + str(v.path) + "` (the report is updated "
              "afterwards).")
        return
    ok = [r for r in rows if r.get("status") == "ok"]
    failed = Counter(r.get("status") for r in rows if r.get("status") != "ok")
    doc.p(f"{len(ok)} of {len(rows)} clones grown"
          + (f" ({', '.join(f'{n} {s}' for s, n in failed.items())})" if failed else "") + ".")
    tm = v.target_metrics or {}
    table = []
    for key, label in (("distance", "distance D"), ("height", "height (m)"), ("girth", "girth (m)"),
                       ("crown_spread", "crown spread (m)"), ("d_h", "d_h"), ("d_g", "d_g"), ("d_c", "d_c")):
        x = np.array([r.get(key, np.nan) for r in ok], float)
        x = x[np.isfinite(x)]
        if not x.size:
            continue
        table.append([label, np.mean(x), np.std(x, ddof=1) if x.size > 1 else 0.0, np.median(x), np.min(x),
                      np.max(x), tm.get(key) if key in tm else ((v.best or {}).get("distance") if key == "distance" else None)])
    if table:
        doc.table(["measure", "mean", "sd", "median", "min", "max", "target / fit"], table)
    for rel_path, cap in figs.made.get("clones", []):
        doc.fig(rel_path, cap)


def _section_profiles(doc: _Doc, v: RunView):
    profs = sorted((v.path / "figures").glob("profile_*.png"))
    if not profs:
        return
    doc.h(2, "Distance profiles")
    for p in profs:
        param = p.stem[len("profile_"):]
        doc.fig(p.relative_to(v.path).as_posix(),
                f"Distance along {param} with the other parameters at the best fit, for several seeds "
                "(median and spread; from `bforest profile`)")


# ---------------------------------------------------------------------------------- entry point
def write_report(run_dir, figures: bool = True, html: bool = True, strict: bool = False) -> Path:
    """Write the figures, ``report.md`` and ``report.html`` of a run directory.

    Parameters
    ----------
    run_dir : path
        A run directory (``bforest fit`` output).
    figures : bool
        Draw the figures (False: text only, fast).
    html : bool
        Also write ``report.html`` with the figures inline.
    strict : bool
        Raise when a figure fails instead of noting it in the report.

    Returns
    -------
    Path
        The path of ``report.md``.
    """
    t0 = time.monotonic()
    v = RunView(run_dir)
    figs = _Figures(v, strict)
    if figures:
        figs.run("trees", "trees", _fig_trees, v)
        figs.run("sets", "data sets", _fig_sets, v)
        figs.run("convergence", "convergence", _fig_convergence, v)
        figs.run("mcmc", "MCMC", _fig_mcmc, v)
        figs.run("clones", "clones", _fig_clones, v)
    doc = _Doc()
    title = f"Bayes Forest run report: {v.path.name}"
    doc.h(1, title)
    _section_summary(doc, v)
    _section_target(doc, v)
    _section_model(doc, v)
    _section_parameters(doc, v)
    _section_fit(doc, v, figs)
    _section_optimizer(doc, v, figs)
    _section_evaluations(doc, v)
    _section_clones(doc, v, figs)
    _section_profiles(doc, v)
    doc.h(2, "Notes")
    from . import __version__
    notes = list(v.notes)
    if not figures:
        notes.append("figures were not drawn (figures=False)")
    doc.items(notes or ["none"])
    doc.p(f"Written {_dt.datetime.now().strftime('%Y-%m-%d %H:%M:%S')} by bforest {__version__} "
          f"in {time.monotonic() - t0:.1f} s.")
    md = v.path / "report.md"
    md.write_text(doc.markdown(), encoding="utf-8")
    if html:
        (v.path / "report.html").write_text(doc.html(v.path, title), encoding="utf-8")
    v.store.close()
    return md
