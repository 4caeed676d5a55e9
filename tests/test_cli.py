"""The `bforest` command: help, version, readable one-line errors with exit code 2."""

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from bforest_core.cli import main
from conftest import TOY_DIR, qsm_path


def run_cli(*args):
    return subprocess.run([sys.executable, "-m", "bforest_core.cli", *args], capture_output=True, text=True)


def test_version_and_help():
    r = run_cli("--version")
    assert r.returncode == 0 and r.stdout.startswith("bforest ")
    r = run_cli("--help")
    assert r.returncode == 0
    for cmd in ("demo", "fit", "clones", "report", "compare", "distance", "simulate", "info", "plugins", "config"):
        assert cmd in r.stdout
    assert run_cli().returncode == 2


def test_usage_error_is_one_line_exit_2():
    r = run_cli("fit")
    assert r.returncode == 2 and "error:" in r.stderr and "Traceback" not in r.stderr


@pytest.mark.parametrize(
    "name, content, msg",
    [
        ("missing.mat", None, "file not found"),
        ("tree.xyz", b"1 2 3\n", "unsupported file type '.xyz'"),
        ("empty.txt", b"", "file is empty"),
    ],
)
def test_info_bad_files(tmp_path, name, content, msg):
    p = tmp_path / name
    if content is not None:
        p.write_bytes(content)
    r = run_cli("info", str(p))
    assert r.returncode == 2
    assert r.stderr.startswith("error: ") and msg in r.stderr and str(p) in r.stderr
    assert "Traceback" not in r.stderr and len(r.stderr.strip().splitlines()) == 1


def test_debug_shows_traceback(tmp_path):
    r = run_cli("--debug", "info", str(tmp_path / "missing.mat"))
    assert r.returncode != 0 and "Traceback" in r.stderr


def test_simulate_unknown_parameter(toy_plugin, capsys):
    assert main(["simulate", "--ssm", "toy", "--set", "bogus=1"]) == 2
    err = capsys.readouterr().err
    assert "unknown parameter(s) for SSM 'toy': bogus" in err
    assert main(["simulate", "--ssm", "nosuch"]) == 2
    assert "unknown ssm 'nosuch'" in capsys.readouterr().err


def test_info_on_real_pine(capsys):
    p = qsm_path("pine_ruotsinkyla_3.mat")
    assert main(["info", str(p)]) == 0
    out = capsys.readouterr().out
    assert "cylinders     876" in out and "branches      300" in out and "height        9.94 m" in out


def test_distance_of_a_tree_to_itself_and_the_permutation_test(capsys):
    p = qsm_path("pine_ruotsinkyla_3.mat")
    assert main(["distance", str(p), str(p), "--sets", "S1 B1", "--lines", "64", "--test"]) == 0
    out = capsys.readouterr().out
    assert "distance (sliced, ks, 64 lines): 0.0000" in out
    assert "S1         0.0000  (rows A 362, B 362)" in out
    # identical trees are indistinguishable: every permuted D >= D0 = 0, so p = 1 after 100 draws
    assert "permutation test: p = 1.0000 (100 draws" in out and "not distinguishable" in out


def test_distance_columns_name_the_column_that_differs(capsys):
    import json

    from scipy.stats import ks_2samp

    from bforest_core.io import read_qsm
    from bforest_core.registry import component

    a, b = qsm_path("pine_ruotsinkyla_1.mat"), qsm_path("pine_ruotsinkyla_3.mat")
    assert main(["distance", str(b), str(b), "--lines", "16", "--columns"]) == 0
    out = capsys.readouterr().out
    assert "    L_t          KS 0.000" in out and "    alpha        KS 0.000" in out
    assert main(["distance", str(a), str(b), "--lines", "16", "--columns", "--json"]) == 0
    got = {r["column"]: r for r in json.loads(capsys.readouterr().out)["columns"]["B1"]}
    fs = component("features", "branch-segment", sets=["B1"])
    ta, tb = read_qsm(a), read_qsm(b)
    fs.prepare([tb])
    ua, ub = fs.extract(ta)["B1"], fs.extract(tb)["B1"]
    j = fs.columns("B1").index("L_t")
    assert got["L_t"]["ks"] == pytest.approx(ks_2samp(ua[:, j], ub[:, j]).statistic, abs=1e-12)
    assert got["L_t"]["median_data"] == pytest.approx(float(np.median(ub[:, j])))


def test_distance_sets_keep_open_ranges(capsys):
    p = qsm_path("pine_ruotsinkyla_3.mat")
    assert main(["distance", str(p), str(p), "--sets", "S1;B2+", "--lines", "16"]) == 0
    out = capsys.readouterr().out
    assert "S1 " in out and "B2+ " in out


# ------------------------------------------------------------------ messages and paths (issue 15)
def _bforest(*args, cwd=None):
    import shutil

    exe = shutil.which("bforest") or str(Path(sys.executable).with_name("bforest"))
    return subprocess.run([exe, *args], capture_output=True, text=True, cwd=cwd)


def test_config_without_target_says_what_to_add(tmp_path):
    p = tmp_path / "run.toml"
    p.write_text('[ssm]\nkind = "sot"\n')
    r = _bforest("config", "check", str(p))
    assert r.returncode == 2 and "no [target]" in r.stderr and 'qsm = "path/to/tree.mat"' in r.stderr


def test_config_check_names_a_missing_target_file(tmp_path):
    p = tmp_path / "run.toml"
    p.write_text('[target]\nqsm = "trees/missing.mat"\n[ssm]\nkind = "sot"\n')
    r = _bforest("config", "check", str(p))
    assert r.returncode == 2 and "target.qsm: file not found" in r.stderr
    assert str(tmp_path / "trees" / "missing.mat") in r.stderr  # resolved against the config's folder


def test_simulate_checks_the_output_format_before_growing(tmp_path):
    import time

    t0 = time.monotonic()
    r = _bforest("simulate", "--ssm", "lignum", "--preset", "sf_real", "-o", str(tmp_path / "tree.xyz1"))
    assert r.returncode == 2 and "no writer for '.xyz1'" in r.stderr
    assert time.monotonic() - t0 < 20 and not list(tmp_path.iterdir())


def test_info_per_order_table_text_json_and_csv():
    import csv
    import io
    import json

    p = str(qsm_path("pine_ruotsinkyla_3.mat"))
    r = _bforest("info", p)
    assert r.returncode == 0 and "mean angle (deg)" in r.stdout and "base diameter" in r.stdout
    data = json.loads(_bforest("info", p, "--json").stdout)
    orders = {o["order"]: o for o in data["orders"]}
    assert orders[1]["n_branches"] == 73 and orders[0]["mean_angle_deg"] is None  # NaN -> null
    assert data["metrics_m"]["height"] == pytest.approx(9.936, abs=1e-3)
    rows = list(csv.DictReader(io.StringIO(_bforest("info", p, "--csv").stdout)))
    assert [int(r["order"]) for r in rows] == sorted(orders) and float(rows[1]["length_m"]) == pytest.approx(
        orders[1]["length_m"]
    )


def test_distance_json():
    import json

    a, b = str(qsm_path("pine_ruotsinkyla_1.mat")), str(qsm_path("pine_ruotsinkyla_3.mat"))
    d = json.loads(_bforest("distance", a, b, "--json").stdout)
    assert set(d["per_set"]) == {"S1", "B1"} and 0 < d["distance"] < 1
    assert d["distance"] == pytest.approx(sum(d["per_set"].values()) / 2)


def test_every_option_has_a_help_line():
    import argparse

    from bforest_core.cli.main import build_parser

    missing = []

    def walk(parser, path):
        for a in parser._actions:
            if isinstance(a, argparse._SubParsersAction):
                for name, sp in a.choices.items():
                    walk(sp, path + [name])
            elif not a.help and not isinstance(a, argparse._HelpAction):
                missing.append(f"{' '.join(path)} {'/'.join(a.option_strings) or a.dest}")

    walk(build_parser(), ["bforest"])
    assert not missing, "options without a help line: " + ", ".join(missing)


def _subcommands(parser, path=("bforest",)):
    """``(path, parser)`` of every subcommand, nested ones (``config check``) included."""
    import argparse

    for a in parser._actions:
        if isinstance(a, argparse._SubParsersAction):
            for name, sp in a.choices.items():
                yield path + (name,), sp
                yield from _subcommands(sp, path + (name,))


def test_every_subcommand_speaks_one_vocabulary():
    """Issue 78, item 8: the run folder was DIR in clones/report/profile and RUN in export, the
    config RUN.toml in fit and CONFIG in calibrate, clones -n beside profile --n, --replace beside
    --overwrite, and several subcommands had no description. This walks whatever subcommands
    exist (a new one is checked with no edit here): each opens its --help with a description; a
    run folder is RUN, a run configuration CONFIG.toml, a count -n/--count, the replacing flag
    --overwrite, -q is --quiet; a command that can be resumed or writes a report takes -q."""
    import argparse

    from bforest_core.cli.main import build_parser

    RUN, CONFIG, bad = "RUN", "CONFIG.toml", []
    subs = list(_subcommands(build_parser()))
    assert len(subs) >= 16
    for path, sp in subs:
        name = " ".join(path)
        text = sp.format_help()
        if not sp.description or sp.description not in " ".join(text.split()):
            bad.append(f"{name}: no description line")
        visible = [a for a in sp._actions if a.help != argparse.SUPPRESS and not isinstance(a, argparse._HelpAction)]
        flags = {o for a in visible for o in a.option_strings}
        for a in visible:
            what = f"{name} {'/'.join(a.option_strings) or a.dest}"
            helptext = a.help or ""
            if a.metavar in ("DIR", "RUN.toml", "CONFIG") and "run" in helptext.split():
                bad.append(f"{what}: metavar {a.metavar}")
            if ("run folder" in helptext) != (a.metavar == RUN) or "run director" in helptext:
                bad.append(f"{what}: a run folder is '{RUN}', said 'run folder' (metavar {a.metavar})")
            if not a.option_strings and "configuration" in helptext and a.metavar != CONFIG:
                bad.append(f"{what}: a run configuration is '{CONFIG}' (metavar {a.metavar})")
            if a.dest == "n" and a.option_strings != ["-n", "--count"]:
                bad.append(f"{what}: a count is -n/--count")
            if a.dest in ("overwrite", "replace") and a.option_strings != ["--overwrite"]:
                bad.append(f"{what}: the replacing flag is --overwrite")
            if "-q" in a.option_strings and (a.option_strings != ["-q", "--quiet"] or a.help != "no progress bars"):
                bad.append(f"{what}: -q is -q/--quiet, 'no progress bars'")
        if flags & {"--resume", "--no-report"} and "-q" not in flags:
            bad.append(f"{name}: can be resumed or reports, but has no -q")
    assert not bad, "\n".join(bad)
    (simulate,) = [sp for path, sp in subs if path[-1] == "simulate"]
    (out,) = [a for a in simulate._actions if "-o" in a.option_strings]
    assert all(f" {x}" in out.help for x in ("txt", "mat", "csv", "ply", "obj", "las", "laz", "xyz"))


def test_old_spellings_still_work(toy_plugin, tmp_path, monkeypatch):
    """``clones --replace`` and ``profile --n`` (the names before the one vocabulary) are still
    taken, hidden from --help."""
    from bforest_core.cli.main import build_parser

    p = build_parser()
    assert p.parse_args(["clones", "r", "--replace"]).overwrite is True
    assert p.parse_args(["profile", "r", "--param", "x", "--n", "5"]).n == 5
    assert p.parse_args(["profile", "r", "--param", "x"]).n == 11
    assert p.parse_args(["clones", "r"]).overwrite is False


def test_a_fit_that_fails_before_it_starts_leaves_no_folder(tmp_path, capsys):
    """Issue 78, item 8: a fit stopped by a missing QSM left a folder holding only .bforest.lock."""
    cfg = tmp_path / "run.toml"
    cfg.write_text(
        '[target]\nqsm = "missing.mat"\n[ssm]\nkind = "sot"\nfree.branch_angle = { lower = 30.0, upper = 80.0 }\n'
    )
    assert main(["fit", str(cfg), "-o", str(tmp_path / "runs" / "new"), "-q"]) == 2
    assert "missing.mat" in capsys.readouterr().err
    assert not (tmp_path / "runs" / "new").exists()
    (tmp_path / "mine").mkdir()  # a folder the user made stays, without a lock file in it
    assert main(["fit", str(cfg), "-o", str(tmp_path / "mine"), "-q"]) == 2
    assert (tmp_path / "mine").is_dir() and not list((tmp_path / "mine").iterdir())


def test_dev_py_lists_its_commands():
    import pathlib

    r = subprocess.run(
        [sys.executable, str(pathlib.Path(__file__).parents[1] / "dev.py")], capture_output=True, text=True
    )
    assert r.returncode == 2 and all(f"dev.py {c}" in r.stdout for c in ("demo", "test", "env"))


def test_fit_progress_bar_counts_to_the_plan_and_closes_with_the_reason(toy_plugin, tmp_path):
    """The GA plans population x (generations + 1) evaluations; the bar ends with why it stopped."""
    import os

    from conftest import toy_config

    p = toy_config(tmp_path, optimizer="ga", optimizer_settings="population = 6\ngenerations = 3", budget=1000)
    from conftest import TOY_DIR

    env = {
        **os.environ,
        "PYTHONPATH": os.pathsep.join([str(toy_plugin), str(TOY_DIR)]),
    }  # the toy plugin, for the subprocess
    exe = Path(sys.executable).with_name("bforest")
    r = subprocess.run(
        [str(exe), "fit", str(p), "-o", str(tmp_path / "run"), "--no-report"], capture_output=True, text=True, env=env
    )
    assert r.returncode == 0, r.stderr
    assert "/24" in r.stderr and "stopped:" in r.stderr
    # the summary lists the fitted parameters apart from the fixed one
    out = r.stdout
    assert out.index("fitted:") < out.index("  angle =") < out.index("fixed:") < out.index("  noise =")
    assert "stopped on its wall time" not in out  # the optimiser ended it, not the clock


def test_fit_says_when_the_wall_time_and_not_the_budget_decided_where_it_stopped(toy_plugin, tmp_path):
    # (a fit that ends on its budget says nothing of it: the progress-bar test above)
    import os

    from conftest import TOY_DIR, toy_config

    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(toy_plugin), str(TOY_DIR)])}
    p = toy_config(tmp_path, budget=30)
    p.write_text(p.read_text().replace("max_evaluations = 30\n", "max_evaluations = 30\nwall_time = 0.000001\n"))
    exe = str(Path(sys.executable).with_name("bforest"))
    r = subprocess.run(
        [exe, "fit", str(p), "-o", str(tmp_path / "run"), "--no-report"], capture_output=True, text=True, env=env
    )
    assert r.returncode == 0, r.stderr
    assert "(wall time (1e-06 s) reached)" in r.stdout
    assert "WARNING: the search stopped on its wall time ([stop] wall_time) after" in r.stdout
    best = json.loads((tmp_path / "run" / "best.json").read_text())
    assert best["stop_kind"] == "wall_time" and best["stop"] == {"search": "wall_time", "timeouts": 0}
    assert best["n_evaluations"] < 30


def test_a_fit_on_its_budget_is_marked_so_and_a_timed_out_growth_warns(toy_plugin, tmp_path):
    """best.json's stop kind: "budget" for a fit that ran its evaluations; "timeout", with the
    count, when growths ran past [objective] timeout (its answer then depends on the machine's
    speed), warned of by the fit and in the report."""
    from bforest_core.pipeline.fit import fit
    from bforest_core.pipeline.store import clock_warning
    from conftest import toy_config

    run = tmp_path / "run"
    fit(toy_config(tmp_path, budget=12), run, progress=False)
    best = json.loads((run / "best.json").read_text())
    assert best["stop_kind"] == "budget" and best["stop"] == {"search": "budget", "timeouts": 0}
    assert clock_warning(best) is None
    # every growth sleeps 0.2 s against a timeout of 0.05 s: each one times out
    p = toy_config(tmp_path, budget=3)
    text = p.read_text().replace('kind = "toy"\n', 'kind = "toy"\nsleep = 0.2\n')
    p.write_text(text.replace("[stop]", "[objective]\ntimeout = 0.05\n[stop]"))
    exe = str(Path(sys.executable).with_name("bforest"))
    env = {**__import__("os").environ, "PYTHONPATH": __import__("os").pathsep.join([str(toy_plugin), str(TOY_DIR)])}
    r = subprocess.run([exe, "fit", str(p), "-o", str(tmp_path / "slow")], capture_output=True, text=True, env=env)
    best = json.loads((tmp_path / "slow" / "best.json").read_text())
    assert best["stop_kind"] == "timeout" and best["stop"] == {"search": "budget", "timeouts": 3}
    assert "WARNING: 3 growth(s) ran past [objective] timeout" in r.stdout
    assert "3 growth(s) ran past [objective] timeout" in (tmp_path / "slow" / "report.md").read_text()


def test_compare_and_clones_show_bars_with_totals(toy_plugin, tmp_path):
    """compare counts to optimisers x repeats x budget; clones counts to the clones it grows."""
    import os

    from conftest import TOY_DIR, toy_config

    p = toy_config(tmp_path, budget=1000)
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(toy_plugin), str(TOY_DIR)])}
    exe = str(Path(sys.executable).with_name("bforest"))
    r = subprocess.run(
        [
            exe,
            "compare",
            str(p),
            "--optimizers",
            "toy-random,ga",
            "--budget",
            "12",
            "--repeats",
            "2",
            "-o",
            str(tmp_path / "cmp"),
        ],
        capture_output=True,
        text=True,
        env=env,
    )
    assert r.returncode == 0, r.stderr
    assert "/48" in r.stderr  # 2 optimisers x 2 repeats x 12 evaluations
    r = subprocess.run(
        [exe, "fit", str(p), "-o", str(tmp_path / "run"), "--no-report"], capture_output=True, text=True, env=env
    )
    assert r.returncode == 0, r.stderr
    r = subprocess.run([exe, "clones", str(tmp_path / "run"), "-n", "5"], capture_output=True, text=True, env=env)
    assert r.returncode == 0, r.stderr
    assert "5/5" in r.stderr


def test_a_dead_worker_pool_is_one_line_that_says_resume(tmp_path, monkeypatch, capsys):
    """A worker whose start-up fails (or that is killed) breaks the process pool: one line that
    says what happened and that finished evaluations are kept, no traceback."""
    from concurrent.futures.process import BrokenProcessPool

    import bforest_core.pipeline.fit as fit_mod

    def broken(*a, **k):
        raise BrokenProcessPool("A process in the process pool was terminated abruptly")

    monkeypatch.setattr(fit_mod, "fit", broken)
    cfg = tmp_path / "run.toml"
    cfg.write_text("")
    monkeypatch.setattr("bforest_core.config.load_config", lambda p: None)
    assert main(["fit", str(cfg), "-o", str(tmp_path / "run")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1, err
    assert err[0].startswith("error: the worker processes stopped (A process in the process pool was terminated")
    assert "continue with --resume" in err[0]


def test_output_cut_short_by_the_reader_is_no_error():
    """`bforest info ... | head -1`: the reader closes the pipe after one line of a 190 KB table;
    bforest stops quietly (exit 0, nothing on stderr but the reader's warnings about the file)."""
    import shutil
    import subprocess
    import sys
    from pathlib import Path

    from conftest import qsm_path

    exe = shutil.which("bforest") or str(Path(sys.executable).with_name("bforest"))
    p = subprocess.Popen(
        [exe, "info", str(qsm_path("wytham_tf1.mat")), "--csv", "--table", "branches"],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    assert p.stdout.readline().startswith("reconstruction,branch,order")
    p.stdout.close()  # the reader is gone; the rest of the table (> the pipe's 64 KB) cannot be written
    err = p.stderr.read()
    assert p.wait(60) == 0, err
    assert "Broken pipe" not in err and "Traceback" not in err and "error" not in err


def test_a_repair_read_twice_is_reported_once():
    # `distance` reads the file as tree A and as tree B: its 278 renormalised axes are one warning
    p = qsm_path("wytham_tf1.mat")
    r = run_cli("distance", str(p), str(p), "--sets", "S1", "--lines", "16")
    warned = [ln for ln in r.stderr.splitlines() if "axes not unit vectors" in ln]
    assert r.returncode == 0 and len(warned) == 1 and warned[0].startswith("warning: ")
