"""Same results before and after a refactoring: seven jobs run with two checkouts, compared row by row.

Runs, with one checkout's own ``.venv/bin/bforest``, into a folder:

1. ``demo``: ``bforest demo --quick``;
2. ``recipe``: a fit of a copy of ``examples/real/pine_lignum.toml`` made small (``[stop]
   max_evaluations`` 64, no wall time, ``[select]`` of 3 candidates on 2 seed sets, the CMA-ES
   search's first design of 16 and generations of 8);
3. ``resumed``: the same fit, killed once part of its evaluations are logged, then continued with
   ``bforest fit --resume`` (it must also equal ``recipe``);
4. ``compare``: ``bforest compare`` of that recipe over every bundled optimiser on 16 evaluations
   (its run seed made the same on both sides: since issue 76 a repeat's run seed is drawn from the
   base seed's stream, before it was the base seed itself, so a checkout without
   ``seeds.repeat_seeds`` gets that drawn seed as its base seed);
5.-7. ``init-pine1``, ``init-tf1``, ``init-tf2``: ``bforest init`` on pine_ruotsinkyla_1 (LIGNUM),
   wytham_tf1 and wytham_tf2 (SOT, the latter with its stem guide), each recipe made small as in 2
   (``[stop] max_evaluations`` 32) and fitted.

and compares two such folders: every row of every ``evaluations.sqlite`` (tables ``evaluations``,
``heldout`` and ``log``; the columns that time an evaluation, ``seconds``, ``worker`` and
``finished``, and the log's row counter ``seq`` left out, its records compared in order) and the bytes of every ``best.json`` (its ``"seconds"`` line, the run's
wall time, left out). A parameter one checkout's model takes as a fixed parameter and the other's
as a setting (:data:`MOVED`, LIGNUM's ``piece_length`` since issue 76) is left out of the logged
parameters and ``best.json``'s, and the line says so. The held-out scores' ``scoring`` column, a hash
of the config's scoring sections (whose form a refactoring may change: a setting removed or moved,
as issue 76's ``light_model`` and ``piece_length``), is compared by which rows share a hash, not
by its value. Prints one line per file and a verdict;
exits 1 on a difference.

    python3 benchmarks/identical_runs.py run /path/to/checkout OUT_DIR
    python3 benchmarks/identical_runs.py compare OUT_BEFORE OUT_AFTER
    python3 benchmarks/identical_runs.py both /path/to/before /path/to/after OUT_DIR

The jobs take ten minutes or so per checkout on two cores.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import signal
import sqlite3
import subprocess
import sys
import time
import tomllib
from pathlib import Path

OPTIMIZERS = "abc-smc,cma,de,emcee,ga,nlopt,turbo"
KILL_AFTER = 20  # evaluations logged before the resumed job's first session is killed
#: bforest init's jobs: (name, QSM file of the sample data, evaluation budget)
INIT_JOBS = [
    ("init-pine1", "pine_ruotsinkyla_1.mat", 32),
    ("init-tf1", "wytham_tf1.mat", 32),
    ("init-tf2", "wytham_tf2.mat", 32),
]
#: parameters that moved from a model's parameters to its settings: left out of the logged parameters
MOVED = {"piece_length"}
TIMING_COLUMNS = {"seconds", "worker", "finished"}
ROW_IDS = {"seq"}  # the log's row counter: a resumed run's log is rewritten under new numbers, in order


def _small(raw: dict, budget: int) -> dict:
    """A recipe made small and deterministic: its budget, no wall time, 3 candidates on 2 seed sets,
    the CMA-ES search's first design of 16 and generations of 8 (settings of another search kept)."""
    raw = dict(raw)
    raw["stop"] = {"max_evaluations": budget}  # no wall time: a clock must not decide where a run stops
    raw["select"] = {**raw.get("select", {}), "top": 3, "sets": 2}
    opt = raw.get("optimizer", {})
    if opt.get("kind") == "cma":
        raw["optimizer"] = {**opt, "init_design": 16, "starts": 2, "population": 8}
    return raw


def _write_toml(checkout: Path, raw: dict, path: Path) -> Path:
    """``raw`` written by the checkout's own TOML writer (this script needs nothing but python3)."""
    dump = "import json, sys, tomli_w; sys.stdout.write(tomli_w.dumps(json.load(sys.stdin)))"
    python = checkout / ".venv" / "bin" / "python"
    text = subprocess.run([str(python), "-c", dump], input=json.dumps(raw), capture_output=True, text=True, check=True)
    path.write_text(text.stdout, encoding="utf-8")
    return path


def small_recipe(checkout: Path, out: Path) -> Path:
    """A copy of the checkout's pine_lignum recipe with a small, deterministic budget."""
    src = checkout / "examples" / "real" / "pine_lignum.toml"
    raw = tomllib.loads(src.read_text(encoding="utf-8"))
    if not raw["target"]["qsm"].startswith("sample:"):  # a sample tree is found wherever the recipe is
        raw["target"]["qsm"] = str((src.parent / raw["target"]["qsm"]).resolve())
    return _write_toml(checkout, _small(raw, 64), out / "recipe.toml")


def compare_recipe(checkout: Path, recipe: Path, out: Path) -> Path:
    """The recipe with the base seed that makes ``compare``'s repeat 0 run on the same seed in a
    checkout before issue 76 (run seed = base seed) as in one after (the base seed's stream, tag 6)."""
    if "def repeat_seeds" in (checkout / "bforest_core" / "pipeline" / "seeds.py").read_text(encoding="utf-8"):
        return recipe
    python = checkout / ".venv" / "bin" / "python"
    code = "import numpy as np; print(int(np.random.SeedSequence([1, 6]).spawn(1)[0].generate_state(1, np.uint32)[0]))"
    seed = int(subprocess.run([str(python), "-c", code], capture_output=True, text=True, check=True).stdout)
    raw = tomllib.loads(recipe.read_text(encoding="utf-8"))
    assert raw.get("seed", 1) == 1
    return _write_toml(checkout, {**raw, "seed": seed}, out / "compare.toml")


def _logged(run: Path) -> int:
    db = run / "evaluations.sqlite"
    if not db.exists():
        return 0
    try:
        with sqlite3.connect(f"file:{db}?mode=ro", uri=True, timeout=1) as con:
            return con.execute("SELECT COUNT(*) FROM evaluations").fetchone()[0]
    except sqlite3.Error:
        return 0


def run_jobs(checkout: Path, out: Path) -> None:
    checkout, out = checkout.resolve(), out.resolve()
    bforest = checkout / ".venv" / "bin" / "bforest"
    if not bforest.exists():
        sys.exit(f"{bforest}: missing (python3 dev.py env in {checkout} makes it)")
    out.mkdir(parents=True, exist_ok=True)
    recipe = small_recipe(checkout, out)
    qsm_dir = checkout.parent / "shared" / "data" / "qsm"
    # the recipes name sample trees (sample:NAME): read from the shared data unless told otherwise
    os.environ.setdefault("BFOREST_DATA_DIR", str(qsm_dir))

    def run(*args):
        t0 = time.monotonic()
        subprocess.run([str(bforest), *map(str, args)], check=True, cwd=out, stdout=subprocess.DEVNULL)
        print(f"  {args[0]} {args[-1] if args[0] != 'fit' else ''} ({time.monotonic() - t0:.0f} s)", flush=True)

    print(f"{checkout}: jobs into {out}", flush=True)
    run("demo", "--quick", "-q", "--overwrite", "-o", out / "demo")
    run("fit", recipe, "-q", "--no-report", "--overwrite", "-o", out / "recipe")
    # the resumed job: its first session is killed (with its workers) once KILL_AFTER are logged
    resumed = out / "resumed"
    proc = subprocess.Popen(
        [str(bforest), "fit", str(recipe), "-q", "--no-report", "--overwrite", "-o", str(resumed)],
        cwd=out,
        stdout=subprocess.DEVNULL,
        start_new_session=True,
    )
    while proc.poll() is None and _logged(resumed) < KILL_AFTER:
        time.sleep(0.05)
    if proc.poll() is not None:
        sys.exit(f"{resumed}: the first session finished before it could be killed")
    os.killpg(proc.pid, signal.SIGKILL)
    proc.wait()
    print(f"  killed the first session of {resumed.name} after {_logged(resumed)} evaluations", flush=True)
    run("fit", recipe, "-q", "--no-report", "--resume", "-o", resumed)
    run(
        "compare",
        compare_recipe(checkout, recipe, out),
        "--optimizers",
        OPTIMIZERS,
        "--budget",
        16,
        "--repeats",
        1,
        "-q",
        "--overwrite",
        "-o",
        out / "compare",
    )
    for name, qsm, budget in INIT_JOBS:
        written = out / f"{name}.toml"
        run("init", qsm_dir / qsm, "--overwrite", "-o", written)
        raw = _small(tomllib.loads(written.read_text(encoding="utf-8")), budget)
        run(
            "fit",
            _write_toml(checkout, raw, out / f"{name}-small.toml"),
            "-q",
            "--no-report",
            "--overwrite",
            "-o",
            out / name,
        )


def _normal(value):
    """A logged JSON value with the :data:`MOVED` parameters left out (other values as they are)."""
    if not (isinstance(value, str) and value.startswith("{") and any(m in value for m in MOVED)):
        return value
    d = json.loads(value)
    return json.dumps({k: v for k, v in d.items() if k not in MOVED}, sort_keys=True)


def _rows(db: Path) -> dict[str, list[tuple]]:
    with sqlite3.connect(f"file:{db}?mode=ro", uri=True) as con:
        out = {}
        for table, order in (("evaluations", "idx"), ("heldout", "point, seeds, scoring"), ("log", "seq")):
            cols = [r[1] for r in con.execute(f"PRAGMA table_info({table})") if r[1] not in TIMING_COLUMNS | ROW_IDS]
            rows = con.execute(f"SELECT {', '.join(cols)} FROM {table} ORDER BY {order}").fetchall()
            rows = [tuple(_normal(v) for v in row) for row in rows]
            if "scoring" in cols:  # a hash of the config's scoring sections: which rows share one, not its value
                j, seen = cols.index("scoring"), {}
                rows = [(*r[:j], f"scoring {seen.setdefault(r[j], len(seen))}", *r[j + 1 :]) for r in rows]
            out[table] = rows
        return out


def _best_bytes(path: Path) -> bytes:
    return re.sub(rb'\n  "seconds": [^\n]*\n', b"\n", path.read_bytes())


def _without_moved(x):
    if isinstance(x, dict):
        return {k: _without_moved(v) for k, v in x.items() if k not in MOVED}
    return [_without_moved(v) for v in x] if isinstance(x, list) else x


def _same_best(a: Path, b: Path) -> tuple[bool, str]:
    """Byte for byte (but the wall time); else the same but for the :data:`MOVED` parameters."""
    if _best_bytes(a) == _best_bytes(b):
        return True, "bytes"
    ja, jb = (_without_moved(json.loads(_best_bytes(p))) for p in (a, b))
    return ja == jb, f"bytes but {', '.join(sorted(MOVED))} (a setting now)"


def compare_folders(a: Path, b: Path) -> bool:
    files = sorted({p.relative_to(a) for p in a.rglob("*") if p.name in ("evaluations.sqlite", "best.json")})
    other = sorted({p.relative_to(b) for p in b.rglob("*") if p.name in ("evaluations.sqlite", "best.json")})
    same = files == other
    if not same:
        print(
            f"DIFFERENT sets of files: only in {a}: {sorted(set(files) - set(other))}; only in {b}: "
            f"{sorted(set(other) - set(files))}"
        )
    for rel in files:
        if not (b / rel).exists():
            continue
        if rel.name == "best.json":
            ok, how = _same_best(a / rel, b / rel)
            print(f"{'same' if ok else 'DIFFERENT'}  {rel} ({how})")
        else:
            ra, rb = _rows(a / rel), _rows(b / rel)
            ok = ra == rb
            counts = ", ".join(f"{t} {len(r)}" for t, r in ra.items())
            print(f"{'same' if ok else 'DIFFERENT'}  {rel} (rows: {counts})")
            for t in ra:
                if ra[t] != rb[t]:
                    i = next((i for i, (x, y) in enumerate(zip(ra[t], rb[t])) if x != y), min(len(ra[t]), len(rb[t])))
                    print(f"    {t}: first difference at row {i}")
        same &= ok
    # a resumed run ends where the uninterrupted one does
    for folder in (a, b):
        if (folder / "recipe").is_dir() and (folder / "resumed").is_dir():
            ok = _rows(folder / "recipe" / "evaluations.sqlite") == _rows(folder / "resumed" / "evaluations.sqlite")
            ok &= _best_bytes(folder / "recipe" / "best.json") == _best_bytes(folder / "resumed" / "best.json")
            print(f"{'same' if ok else 'DIFFERENT'}  {folder}: resumed vs uninterrupted recipe fit")
            same &= ok
    print(f"verdict: {'IDENTICAL' if same else 'DIFFERENT'} ({len(files)} files)")
    return same


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    sub = ap.add_subparsers(dest="cmd", required=True)
    s = sub.add_parser("run", help="run the four jobs with a checkout's .venv into OUT")
    s.add_argument("checkout", type=Path)
    s.add_argument("out", type=Path)
    s = sub.add_parser("compare", help="compare two folders of the jobs")
    s.add_argument("a", type=Path)
    s.add_argument("b", type=Path)
    s = sub.add_parser("both", help="run with both checkouts into OUT/before, OUT/after and compare")
    s.add_argument("before", type=Path)
    s.add_argument("after", type=Path)
    s.add_argument("out", type=Path)
    args = ap.parse_args()
    if args.cmd == "run":
        run_jobs(args.checkout, args.out)
        return 0
    if args.cmd == "compare":
        return 0 if compare_folders(args.a, args.b) else 1
    run_jobs(args.before, args.out / "before")
    run_jobs(args.after, args.out / "after")
    return 0 if compare_folders(args.out / "before", args.out / "after") else 1


if __name__ == "__main__":
    sys.exit(main())
