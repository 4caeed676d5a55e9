"""Exports of a run: the best-fit tree and the clones in other file formats, and the evaluation
log as one flat table.

Trees go out through the installed QSM writers (``bforest plugins`` lists them), chosen by a
writer's name (``treeqsm-text``, ``treeqsm-mat``, ``bforest-csv``, ``simpleforest-csv``,
``archi-csv``, ``ply``, ``obj``, ``las``, ``xyz``, or a plugin's) or by a file suffix (``txt``,
``mat``, ``csv``, ``ply``, ``obj``, ``las``, ``laz``, ``xyz``, ...). An existing file is never
overwritten unless asked.
"""

from __future__ import annotations

import csv
from pathlib import Path

from ..errors import BayesForestError
from ..io import whole_file
from .store import RunFiles, RunStore


class ExportError(BayesForestError):
    """An export cannot be written as asked (unknown format, existing file, nothing to export)."""


#: writers that take the synthetic-scan settings
SCAN_WRITERS = ("las", "xyz")


def _writer(fmt: str):
    """(writer name, suffix) of a format given as a writer name or a suffix."""
    from ..registry import discover

    reg = discover()
    names = reg.names("qsm_writer")
    if fmt in names:
        cls = reg.get("qsm_writer", fmt)
        return fmt, cls.suffixes[0]
    suffix = "." + fmt.lower().lstrip(".")
    from ..errors import QSMFormatError
    from ..io import writer_for

    try:
        return writer_for(Path("tree" + suffix)).name, suffix  # the suffix's own writer (highest priority)
    except QSMFormatError:
        pass
    known = sorted(set(names) | {s.lstrip(".") for n in names for s in reg.get("qsm_writer", n).suffixes})
    raise ExportError(f"unknown export format {fmt!r} (known: {', '.join(known)})")


def run_trees(run_dir: Path, what: tuple[str, ...] = ("best", "clones")) -> list[Path]:
    """The tree files of a run: ``best_tree.txt``, ``clones/clone_*.txt`` and (``posterior``)
    the posterior clones ``clones_posterior/clone_*.txt``."""
    files, run = [], RunFiles(run_dir)
    if "best" in what and run.best_tree_path.exists():
        files.append(run.best_tree_path)
    if "clones" in what:
        files += sorted(run.clones_dir().glob("clone_*.txt"))
    if "posterior" in what:
        files += sorted(run.clones_dir(posterior=True).glob("clone_*.txt"))
    return files


def _stem(src: Path) -> str:
    """Export name of a run's tree file: posterior clones get a ``posterior_`` prefix."""
    return f"posterior_{src.stem}" if src.parent.name == RunFiles.CLONES_POSTERIOR else src.stem


def export_trees(
    run_dir,
    formats: list[str],
    out_dir=None,
    what: tuple[str, ...] = ("best", "clones"),
    overwrite: bool = False,
    scan: dict | None = None,
) -> list[Path]:
    """Write the run's trees in each of ``formats`` into ``out_dir`` (default ``RUN/export``).

    ``scan`` holds settings of the synthetic-scan writers (``las``, ``xyz``: density, mode,
    scanner, reference_range, noise, seed); the other writers do not take them.

    Raises
    ------
    ExportError
        For an unknown format, a run without trees, or a file that exists (without ``overwrite``);
        nothing is written then.
    """
    from ..io import read_tree, write_tree

    run_dir = Path(run_dir)
    RunStore.open(run_dir).close()  # a run directory, or a clear error
    if out_dir is not None and not str(out_dir).strip():
        raise ExportError("-o: an empty folder name; name a folder, or leave -o out for RUN/export")
    out_dir = Path(out_dir) if out_dir is not None else RunFiles(run_dir).export_dir
    if not [f for f in formats if str(f).strip()]:
        raise ExportError("--format: no format named (e.g. --format ply,las; bforest plugins lists the writers)")
    writers = list(dict.fromkeys(_writer(f) for f in formats if str(f).strip()))  # a format named twice: once
    files = run_trees(run_dir, what)
    if not files:
        raise ExportError(f"{run_dir}: no trees to export ({' or '.join(what)}: run the fit / bforest clones first)")
    shared = {sfx for _, sfx in writers if [w[1] for w in writers].count(sfx) > 1}
    # two formats with one suffix (csv and simpleforest-csv) get the writer's name in the file name
    plan = [
        (src, name, out_dir / (f"{_stem(src)}_{name}{suffix}" if suffix in shared else f"{_stem(src)}{suffix}"))
        for src in files
        for name, suffix in writers
    ]
    existing = [dst for _, _, dst in plan if dst.exists()]
    if existing and not overwrite:
        raise ExportError(
            f"{existing[0]} exists ({len(existing)} files would be replaced); pass --overwrite to "
            "replace them or choose another -o"
        )
    prov = run_provenance(run_dir)
    out = []
    for src, name, dst in plan:
        tree = read_tree(src)
        tree.metadata.update(prov.get(src.relative_to(run_dir).as_posix(), {}))
        opts = dict(scan or {}) if name in SCAN_WRITERS else {}
        out.append(write_tree(tree, dst, format=name, **opts))
    return out


def run_provenance(run_dir) -> dict[str, dict]:
    """Where each tree file of a run came from: ``{path in the run: {model, params, fixed, seed,
    role, run}}`` for ``best_tree.txt`` (the answer's parameters and first model seed,
    ``best.json``) and every clone and posterior clone (its parameters and seed,
    ``clones/summary.json``, ``clones_posterior/summary.json``); writers record it (``.mat``
    ``rundata.bforest``, the CSV sidecar, comments, the LAS VLR). Files the run does not describe
    are left out."""
    import json
    import tomllib

    run_dir = Path(run_dir)
    run = RunFiles(run_dir)
    try:
        raw = tomllib.loads(run.config_path.read_text(encoding="utf-8"))
    except (OSError, tomllib.TOMLDecodeError):
        raw = {}
    ssm = raw.get("ssm") if isinstance(raw.get("ssm"), dict) else {}
    base = {"model": ssm.get("kind"), "run": str(run_dir.resolve())}
    if isinstance(ssm.get("fixed"), dict) and ssm["fixed"]:
        base["fixed"] = dict(ssm["fixed"])
    out: dict[str, dict] = {}

    def _read(p):
        try:
            return json.loads(p.read_text(encoding="utf-8"))
        except (OSError, ValueError):
            return None

    best = _read(run.best_path)
    if isinstance(best, dict) and best.get("params") is not None:
        seeds = best.get("seeds") or []
        out[RunFiles.BEST_TREE] = {
            **base,
            "params": best["params"],
            "seed": seeds[0] if seeds else None,
            "role": "best fit",
        }
    for folder, role in ((RunFiles.CLONES, "clone"), (RunFiles.CLONES_POSTERIOR, "posterior clone")):
        summary = _read(run_dir / folder / RunFiles.CLONE_SUMMARY)
        for r in (summary or {}).get("rows", []) if isinstance(summary, dict) else []:
            if r.get("status") == "ok" and r.get("file"):
                out[f"{folder}/{r['file']}"] = {
                    **base,
                    "params": r.get("params"),
                    "seed": r.get("seed"),
                    "role": f"{role} {r.get('index')}",
                }
    return {k: {kk: vv for kk, vv in v.items() if vv is not None} for k, v in out.items()}


def export_evaluations(run_dir, path, overwrite: bool = False) -> int:
    """Flatten ``evaluations.sqlite`` into a CSV (one row per evaluation: index, status, seconds,
    distance, one column per parameter, one ``D[<set>]`` per data set, seeds, worker, message);
    returns the number of rows."""
    run_dir, path = Path(run_dir), Path(path)
    if path.exists() and not overwrite:
        raise ExportError(f"{path} exists; pass --overwrite to replace it")
    with RunStore.open(run_dir) as store:
        evs = store.evaluations()
    params = list(dict.fromkeys(k for e in evs for k in e.params))
    sets = list(dict.fromkeys(k for e in evs for k in e.per_set))
    path.parent.mkdir(parents=True, exist_ok=True)
    with whole_file(path) as part, open(part, "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(
            ["evaluation", "status", "seconds", "distance"]
            + params
            + [f"D[{s}]" for s in sets]
            + ["seeds", "worker", "message"]
        )
        for e in evs:
            w.writerow(
                [e.idx, e.status, f"{e.seconds:.6g}", repr(float(e.distance))]
                + [e.params.get(k, "") for k in params]
                + ["" if e.per_set.get(s) is None else repr(float(e.per_set[s])) for s in sets]
                + [" ".join(map(str, e.seeds)), e.worker, e.message]
            )
    return len(evs)
