"""Every `bforest` line of the README runs as written on a fresh clone (with small overrides where a
line is long).

The README's walk-through must work for a user who cloned the repository and has nothing beside
it (issue 78, item 3): the lines run in order with the real console script in a copy of the
repository's tracked files in a temporary folder, with an empty sample cache; its first line
fetches the sample trees, served from a local HTTP server on 127.0.0.1 (``BFOREST_DATA_MIRROR``,
as from a mirror) since the tests never reach the internet.
"""

import os
import re
import shlex
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

import bforest_core as bf
from conftest import QSM_DIR, served
from test_docs_standalone import tracked_files

ROOT = Path(__file__).resolve().parents[1]
#: why `bforest posterior` cannot run here (the extra bayesforest[amortised] is missing), or None
AMORTISED_MISSING = bf.component("amortised", "flow").missing()

#: (pattern, replacement) applied to a README line before it runs: smaller budgets (the README's
#: fit takes minutes: 32 evaluations test that it runs); the command itself is unchanged
OVERRIDES = [
    (r"(bforest fit \S+ -o \S+)", r"\1 --max-evaluations 32 --no-report"),
    (r"(bforest clones \S+) -n 30", r"\1 -n 2 --no-report"),
    (r"--budget 400 --repeats 3", "--budget 24 --repeats 1 -q"),
    (r"(bforest stand \S+ -o \S+)", r"\1 --max-evaluations 16 -n 2 -q"),  # ~10 min -> a minute
]


def readme_lines() -> list[str]:
    text = (ROOT / "README.md").read_text(encoding="utf-8")
    blocks = re.findall(r"```\n(.*?)```", text, re.S)
    lines = []
    for b in blocks:
        for line in b.splitlines():
            line = line.split("  #")[0].strip()
            if line.startswith(".venv/bin/bforest"):
                lines.append(line)
    return lines


def test_the_readme_has_bforest_lines():
    lines = readme_lines()
    assert len(lines) >= 6 and any(" fit " in x for x in lines) and any(" clones " in x for x in lines)
    assert lines[0].startswith(".venv/bin/bforest data fetch ")  # the walk-through fetches its trees first


@pytest.mark.slow
@pytest.mark.timeout(900)  # a dozen commands, each a process of its own: over the suite's 300 s on a busy machine
def test_every_readme_line_runs_on_a_fresh_clone(tmp_path):
    if not QSM_DIR.is_dir():
        pytest.skip(f"the sample files to serve are not in {QSM_DIR} (needs ../shared/data/qsm)")
    clone = tmp_path / "clone"
    for f in tracked_files():
        rel = f.relative_to(ROOT)
        (clone / rel).parent.mkdir(parents=True, exist_ok=True)
        shutil.copy2(f, clone / rel)
    assert not (clone.parent / "shared").exists()  # nothing beside the clone
    exe = shutil.which("bforest") or str(Path(sys.executable).with_name("bforest"))
    env = {k: v for k, v in os.environ.items() if k not in ("BFOREST_DATA_DIR", "BFOREST_QSM_DIR")}
    env["BFOREST_DATA_DIR"] = str(tmp_path / "cache")
    with served(QSM_DIR) as (url, asked):
        env["BFOREST_DATA_MIRROR"] = url
        for line in readme_lines():
            cmd = line
            for pat, rep in OVERRIDES:
                cmd = re.sub(pat, rep, cmd)
            args = shlex.split(cmd)
            if args[1] == "posterior" and AMORTISED_MISSING:
                continue  # its own test skips saying why (tests/test_amortised.py)
            args[0] = exe
            r = subprocess.run(args, capture_output=True, text=True, cwd=clone, env=env, timeout=600)
            assert r.returncode == 0, f"README line failed: {line}\n(ran: {cmd})\n{r.stderr[-2000:]}"
    assert {"/pine_ruotsinkyla_3.mat", "/wytham_tf3.mat", "/pine_ruotsinkyla_1.mat"} <= set(asked)
    assert {"pine_ruotsinkyla_3.mat", "wytham_tf3.mat"} <= {p.name for p in (tmp_path / "cache").iterdir()}
    assert (clone / "stands" / "pines" / "stand.csv").read_text().count("\n") == 4  # a header, 3 pines
    assert (clone / "runs" / "pine3" / "clones" / "clone_000.txt").exists()
    assert (clone / "pine.png").exists() and (clone / "runs" / "compare-pine_lignum" / "compare.png").exists()
    assert 'qsm = "sample:wytham_tf3"' in (clone / "tf3.toml").read_text()


def test_the_user_guides_fits_write_to_different_run_folders():
    """Issue 33: sections 3 and 5b both fitted into ``runs/pine3``, so a reader following the
    guide stopped at the second fit with "already holds a run". Every ``bforest fit ... -o DIR``
    of the guide that neither resumes nor overwrites needs a folder of its own."""
    text = (ROOT / "docs" / "user-guide.md").read_text(encoding="utf-8")
    outs = []
    for line in text.splitlines():
        args = shlex.split(line.split("  #")[0]) if line.startswith("$ bforest fit ") else []
        if "-o" in args and not {"--resume", "--overwrite"} & set(args):
            outs.append(args[args.index("-o") + 1])
    assert len(outs) >= 3, outs
    assert len(outs) == len(set(outs)), f"two fits of the user guide write to one folder: {outs}"
