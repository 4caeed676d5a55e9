"""``bforest demo``: the main job on an embedded default target, end to end.

The target is grown by the bundled SOT model with known parameters (so no external file is
needed); the demo fits two of those parameters back with the GA using a *different* model seed
(as in the papers' synthetic tests), grows clones of the best fit and writes the report.
"""

from __future__ import annotations

import time
from pathlib import Path

DEMO_TOML = """\
# Bayes Forest demo: recover two SOT parameters from a tree grown with known values.
seed = 1

[target.generate]
ssm = "sot"
seed = 7
params = {{ max_iter = {cycles}, init_lambda = 0.58, branch_angle = 50.0 }}

[ssm]
kind = "sot"
fixed = {{ max_iter = {cycles} }}
free.init_lambda  = {{ lower = 0.45, upper = 0.65 }}
free.branch_angle = {{ lower = 30.0, upper = 80.0 }}

[features]
kind = "branch-segment"
sets = ["S0,1", "B1,2"]

[distance]
lines = 128

[optimizer]
kind = "ga"
population = {population}
generations = {generations}

[executor]
kind = "process"
workers = 2

[stop]
max_evaluations = {budget}

[clones]
count = {clones}
"""

TRUE_PARAMS = {"init_lambda": 0.58, "branch_angle": 50.0}


def demo_config_text(quick: bool = False) -> str:
    if quick:
        return DEMO_TOML.format(cycles=10, population=8, generations=3, budget=24, clones=4)
    return DEMO_TOML.format(cycles=14, population=16, generations=10, budget=160, clones=12)


def _written_by_demo(run_dir: Path) -> bool:
    """Whether the run in ``run_dir`` is an earlier demo's (its config is one of the demo's)."""
    import tomllib

    from ..config import parse_config
    from ..pipeline.fit import same_config

    return any(same_config(run_dir, parse_config(tomllib.loads(demo_config_text(q)))) for q in (False, True))


def _check_demo_output(out: Path) -> None:
    """Refuse to replace a run in ``out`` that an earlier demo did not write."""
    from ..pipeline.store import RunDirError, RunStore

    if out.is_dir() and RunStore.state(out) != "new" and not _written_by_demo(out):
        raise RunDirError(f"{out}: holds a run that is not a demo's; choose another -o, or replace it with --overwrite")


def run_demo(out: Path, quick: bool = False, progress: bool = True, overwrite: bool = False) -> int:
    """Fit, clone and report the demo into ``out``. Its config is written only there, as the
    run's own ``config.toml`` (``bforest fit OUT/config.toml -o OUT --resume`` continues it):
    nothing lands beside the run folder."""
    from ..pipeline.rundir import run_lock

    out = Path(out)
    with run_lock(out):  # the whole demo: its fit, clones and report
        if not overwrite:
            _check_demo_output(out)
        return _run_demo(out, quick, progress)


def _run_demo(out: Path, quick: bool, progress: bool) -> int:
    import tomllib

    from ..config import parse_config
    from ..pipeline.clones import clones
    from ..pipeline.fit import fit

    cfg = parse_config(tomllib.loads(demo_config_text(quick)), source="demo config")
    t0 = time.monotonic()
    print(f"Bayes Forest demo: fitting SOT to a tree it grew with {TRUE_PARAMS} (model seed differs)")
    res = fit(cfg, out, progress=progress, overwrite=True)
    print(f"fit: best distance {res.distance:.4f} after {res.n_evaluations} evaluations ({res.stop_reason})")
    for k, v in res.params.items():
        if k in TRUE_PARAMS:
            err = abs(v - TRUE_PARAMS[k]) / abs(TRUE_PARAMS[k])
            print(f"  {k:<14} fitted {v:8.4f}   true {TRUE_PARAMS[k]:8.4f}   error {100 * err:5.1f} %")
    s = clones(out, progress=progress)
    print(
        f"clones: {s['ok']} of {s['count']} grown; mean distance to the target "
        f"{s.get('distance', {}).get('mean', float('nan')):.4f}"
    )
    try:
        from ..report.build import write_report

        rep = write_report(out)
        print(f"report: {rep}")
    except ImportError:
        pass
    print(f"run directory: {out} ({time.monotonic() - t0:.0f} s)")
    return 0
