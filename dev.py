#!/usr/bin/env python3
"""Set-up and entry commands of Bayes Forest: needs only Python >= 3.11 and pip.

    python3 dev.py demo     fit a growth model to the embedded default target (writes ./demo-run)
    python3 dev.py test     run the whole test suite (arguments go to pytest); with
                            [tool.bforest] lint = true in pyproject.toml, first ruff check
                            and ruff format --check
    python3 dev.py env      only create or refresh .venv (then use .venv/bin/bforest, .venv/bin/python)

Each creates (or reuses) the virtual environment ``.venv`` beside this file and installs the
project into it (editable, with the test, Dask, SLURM and amortised extras and the example third-party
plugins).
The install is redone only when a packaging file changed.
"""

from __future__ import annotations

import hashlib
import os
import subprocess
import sys
import venv
from pathlib import Path

ROOT = Path(__file__).resolve().parent
VENV = ROOT / ".venv"
STAMP = VENV / ".install-stamp"
#: the example third-party plugins installed beside the project: a growth model, a growth form of SOT
EXAMPLES = [ROOT / "docs" / "examples" / name for name in ("bforest-example-ssm", "bforest-example-sot-form")]
BIN = VENV / ("Scripts" if os.name == "nt" else "bin")


def _fingerprint() -> str:
    h = hashlib.sha256()
    for f in [ROOT / "pyproject.toml", Path(__file__), *(e / "pyproject.toml" for e in EXAMPLES)]:
        if f.exists():
            h.update(f.read_bytes())
    h.update(sys.version.encode())
    return h.hexdigest()


def ensure_env() -> Path:
    if sys.version_info < (3, 11):  # noqa: UP036 - dev.py runs on the system's python3, maybe older
        sys.exit(f"Bayes Forest needs Python >= 3.11 (this is {sys.version.split()[0]})")
    py = BIN / ("python.exe" if os.name == "nt" else "python")
    if not py.exists():
        print(f"creating virtual environment {VENV} ...", flush=True)
        venv.EnvBuilder(with_pip=True).create(VENV)
    fp = _fingerprint()
    if not STAMP.exists() or STAMP.read_text() != fp:
        print("installing Bayes Forest and its dependencies into .venv ...", flush=True)
        pip = [str(py), "-m", "pip", "install", "--disable-pip-version-check", "-q"]
        subprocess.check_call(pip + ["-e", f"{ROOT}[dev,dask,slurm,amortised]"])
        for example in EXAMPLES:
            if (example / "pyproject.toml").exists():
                subprocess.check_call(pip + ["-e", str(example)])
        STAMP.write_text(fp)
    return py


def lint_enabled() -> bool:
    """``[tool.bforest] lint`` of pyproject.toml: whether ``test`` runs ruff before pytest."""
    import tomllib

    conf = tomllib.loads((ROOT / "pyproject.toml").read_text(encoding="utf-8"))
    return bool(conf.get("tool", {}).get("bforest", {}).get("lint", False))


def lint() -> int:
    """``ruff check`` and ``ruff format --check`` over the repository (rules in pyproject.toml)."""
    ruff = str(BIN / "ruff")
    for args in (["check", "."], ["format", "--check", "."]):
        rc = subprocess.call([ruff, *args], cwd=ROOT)
        if rc:
            return rc
    return 0


def main(argv: list[str]) -> int:
    if not argv or argv[0] not in ("demo", "test", "env"):
        print(__doc__)
        return 2
    py = ensure_env()
    cmd, rest = argv[0], argv[1:]
    if cmd == "env":
        return 0
    if cmd == "demo":
        return subprocess.call([str(BIN / "bforest"), "demo", *rest])
    if lint_enabled():
        rc = lint()
        if rc:
            return rc
    # tests: pytest exit code 5 (no tests collected) is a failure here too
    rc = subprocess.call([str(py), "-m", "pytest", *rest], cwd=ROOT)
    return 1 if rc == 5 else rc


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
