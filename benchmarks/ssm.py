"""Benchmarks of the two structure growth models (docs/models.md A.12 and B.9).

    .venv/bin/python benchmarks/ssm.py [--repeats 5] [--full]

Each model's part lives in its own module: ``benchmarks/ssm_sot.py`` (SOT) and
``benchmarks/ssm_lignum.py`` (simplified stochastic LIGNUM, written separately).
"""

from __future__ import annotations

import argparse
import importlib
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--full", action="store_true", help="include the slow cases (SOT at 30 cycles, ...)")
    args = ap.parse_args(argv)

    # ---- SOT
    from ssm_sot import bench_sot

    bench_sot(args.repeats, args.full)

    # ---- LIGNUM: benchmarks/ssm_lignum.py (written separately) is expected to offer
    #      bench_lignum(repeats, full), like bench_sot; a main(argv) is used otherwise.
    print()
    try:
        lignum = importlib.import_module("ssm_lignum")
    except ModuleNotFoundError:
        print("LIGNUM benchmark: benchmarks/ssm_lignum.py not present yet")
        return
    if hasattr(lignum, "bench_lignum"):
        lignum.bench_lignum(args.repeats, args.full)
    else:
        lignum.main(["--repeats", str(args.repeats)] + (["--full"] if args.full else []))


if __name__ == "__main__":
    main()
