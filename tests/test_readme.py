"""Every `bforest` line of the README runs as written (with small overrides where a line is long).

The lines run in order with the real console script from the repository root, so a line may use
what an earlier one wrote (the clones of the fit, say); outputs go to a temporary folder.
"""

import re
import shlex
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from conftest import QSM_DIR

ROOT = Path(__file__).resolve().parents[1]

#: (pattern, replacement) applied to a README line before it runs: smaller budgets and outputs in
#: the temporary folder; the command itself is unchanged
OVERRIDES = [
    (r"\bruns/", "{tmp}/runs/"),  # run directories
    (r"-o pine\.txt --png pine\.png", "-o {tmp}/pine.txt --png {tmp}/pine.png"),
    (r"-o tf3\.toml$", "-o {tmp}/tf3.toml"),  # the recipe of bforest init (it left tf3.toml in the repository)
    (r"(bforest fit \S+ -o \S+)", r"\1 --max-evaluations 32 --no-report"),  # ~3 min -> seconds
    (r"(bforest clones \S+) -n 30", r"\1 -n 2 --no-report"),
    (r"--budget 400 --repeats 3", "--budget 24 --repeats 1 -o {tmp}/compare -q"),
    (r"-o stands/", "-o {tmp}/stands/"),
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


@pytest.mark.slow
def test_every_readme_line_runs(tmp_path):
    if not QSM_DIR.is_dir():
        pytest.skip(f"the README's lines read the sample pines from {QSM_DIR} (needs ../shared/data/qsm)")
    exe = shutil.which("bforest") or str(Path(sys.executable).with_name("bforest"))
    for line in readme_lines():
        cmd = line
        for pat, rep in OVERRIDES:
            cmd = re.sub(pat, rep.replace("{tmp}", str(tmp_path)), cmd)
        args = shlex.split(cmd)
        args[0] = exe
        r = subprocess.run(args, capture_output=True, text=True, cwd=ROOT, timeout=600)
        assert r.returncode == 0, f"README line failed: {line}\n(ran: {cmd})\n{r.stderr[-2000:]}"
    assert (tmp_path / "runs" / "pine3" / "clones" / "clone_000.txt").exists()
    assert (tmp_path / "pine.png").exists() and (tmp_path / "compare" / "compare.png").exists()
    assert (tmp_path / "tf3.toml").exists() and not (ROOT / "tf3.toml").exists()
    assert (tmp_path / "stands" / "pines" / "stand.csv").read_text().count("\n") == 4  # a header, 3 pines


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
