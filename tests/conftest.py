"""Shared fixtures: the real sample QSMs live in ../shared/data/qsm (never copied here)."""
from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
QSM_DIR = Path(os.environ.get("BFOREST_QSM_DIR", ROOT.parent / "shared" / "data" / "qsm"))


def qsm_path(name: str) -> Path:
    """Path of a real sample file; skips the test with a reason when the data folder is absent."""
    p = QSM_DIR / name
    if not p.exists():
        pytest.skip(f"real QSM sample {name} not found in {QSM_DIR} (needs ../shared/data/qsm beside the repo)")
    return p


@pytest.fixture
def qsm_dir() -> Path:
    if not QSM_DIR.is_dir():
        pytest.skip(f"real QSM samples not found: {QSM_DIR} is missing (needs ../shared/data/qsm)")
    return QSM_DIR


def hand_tree(topology: str = "source"):
    """The hand-built tree of spec features-distance.md §7 (trunk of 3 vertical cylinders and
    three laterals with known beta/alpha/L_t/R_f/L_a)."""
    from bforest_core import Tree

    s60, c60 = np.sin(np.radians(60)), np.cos(np.radians(60))
    start = [[0, 0, 0], [0, 0, 1], [0, 0, 2],           # trunk 0,1,2
             [0, 0, 1], [0.8 * s60, 0, 1 + 0.8 * c60],  # lateral A (2 cyl) on trunk 0's end
             [0, 0, 1.5],                              # lateral B mid trunk 1
             [0, 0, 2.25]]                             # lateral C on trunk 2
    axis = [[0, 0, 1]] * 3 + [[s60, 0, c60]] * 2 + [[0, 1, 0], [-1, 0, 0]]
    length = [1, 1, 1, 0.8, 0.5, 0.6, 0.6]
    radius = [0.20, 0.15, 0.10, 0.05, 0.04, 0.04, 0.03]
    parent = [-1, 0, 1, 0, 3, 1, 2]
    extension = [1, 2, -1, 4, -1, -1, -1]
    return Tree(start, axis, length, radius, parent, extension, topology=topology)
