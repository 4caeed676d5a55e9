"""Fuzz test of the QSM readers: mutated sample files either read as a valid Tree or raise
QSMFormatError -- never another exception type, never a hang.

Mutations (fixed seed): truncation, byte flips, NaN injection, shuffled parent ids, removed
columns, duplicated/deleted lines, and for MAT files rewritten matrices with NaN, shuffled parent
columns and removed columns. Mutated files go to ``tmp_path``.
"""

from __future__ import annotations

import signal
import warnings
from pathlib import Path

import numpy as np

import bforest_core as bf
from bforest_core import QSMFormatError, Tree

SEED = 20240611
MIN_CASES = 300

TEXT_SAMPLES = ["itsme_tree_v240_cylinder.txt", "archi_tree1_treeqsm_v23.txt"]
CSV_SAMPLES = ["coffeetree_simpleforest.csv", "coffeetree_archi.csv"]
MAT_SAMPLES = [
    "itsme_qsm_tree_v240_notria.mat",
    "itsme_qsms_tree_v230.mat",
    "itsme_qsm_tree_v200.mat",
    "coffeetree_treeqsm_optqsm.mat",
    "wytham_tf3.mat",
    "itsme_qsm_trunk.mat",
]
H5_SAMPLES = ["pine_ruotsinkyla_3.mat"]


class _Timeout(Exception):
    pass


def _alarm(signum, frame):
    raise _Timeout()


def _text_mutations(rng, data: bytes, csv: bool):
    """Yield (label, bytes) mutations of a text table."""
    lines = data.split(b"\n")
    header = 1 if (csv or data[:6].lower() == b"radius") else 0
    sep = b"," if csv else b"\t"
    body = [ln for ln in lines[header:] if ln.strip()]
    n = len(body)
    # truncation anywhere (mid-line included)
    for _ in range(6):
        cut = int(rng.integers(0, len(data)))
        yield f"truncate@{cut}", data[:cut]
    # byte flips
    for _ in range(8):
        arr = bytearray(data)
        for pos in rng.integers(0, len(arr), size=int(rng.integers(1, 12))):
            arr[pos] = int(rng.integers(0, 256))
        yield "byteflip", bytes(arr)
    # NaN / inf / garbage injection into a random number field
    for token in (b"NaN", b"inf", b"-inf", b"nan", b"1e999", b"x", b"", b"-0"):
        i = int(rng.integers(0, n))
        fields = body[i].rstrip(b"\r").split(sep)
        j = int(rng.integers(0, len(fields)))
        fields[j] = token
        new = list(body)
        new[i] = sep.join(fields)
        yield f"inject {token!r} row {i + 1} col {j + 1}", b"\n".join(lines[:header] + new)
    # shuffled parents (column 9 in TreeQSM text; the parent id column in CSV)
    if csv:
        names = [s.strip() for s in lines[0].decode().split(",")]
        pcol = names.index("parentID") if "parentID" in names else names.index("parent_ID")
    else:
        pcol = 8
    for k in (2, 10, n):
        rows = [r.rstrip(b"\r").split(sep) for r in body]
        sel = rng.choice(n, size=min(k, n), replace=False)
        vals = [rows[s][pcol] for s in sel]
        perm = rng.permutation(len(vals))
        for s, p in zip(sel, perm):
            rows[s][pcol] = vals[p]
        yield f"shuffle parents k={k}", b"\n".join(lines[:header] + [sep.join(r) for r in rows])
    # random parent value (may be out of range / self / cycle)
    for _ in range(3):
        rows = [r.rstrip(b"\r").split(sep) for r in body]
        i = int(rng.integers(0, n))
        rows[i][pcol] = str(int(rng.integers(-3, n + 5))).encode()
        yield f"parent row {i + 1}", b"\n".join(lines[:header] + [sep.join(r) for r in rows])
    # removed columns (everywhere, header included)
    for _ in range(3):
        ncol = len(body[0].split(sep))
        j = int(rng.integers(0, ncol))
        out = []
        for ln in lines[:header] + body:
            f = ln.rstrip(b"\r").split(sep)
            if len(f) == ncol:
                del f[j]
            out.append(sep.join(f))
        yield f"remove column {j + 1}", b"\n".join(out)
    # deleted / duplicated lines
    for _ in range(2):
        i = int(rng.integers(0, n))
        new = list(body)
        if rng.random() < 0.5:
            del new[i]
            lab = "delete"
        else:
            new.insert(i, body[i])
            lab = "duplicate"
        yield f"{lab} line {i + header + 1}", b"\n".join(lines[:header] + new)


def _binary_mutations(rng, data: bytes):
    for _ in range(8):
        cut = int(rng.integers(0, len(data)))
        yield f"truncate@{cut}", data[:cut]
    for _ in range(10):
        arr = bytearray(data)
        for pos in rng.integers(0, len(arr), size=int(rng.integers(1, 8))):
            arr[pos] ^= int(rng.integers(1, 256))
        yield "byteflip", bytes(arr)
    # flips restricted to the first 1 kB (headers, tags, sizes)
    for _ in range(6):
        arr = bytearray(data)
        for pos in rng.integers(0, min(1024, len(arr)), size=int(rng.integers(1, 4))):
            arr[pos] ^= int(rng.integers(1, 256))
        yield "headerflip", bytes(arr)


def _matrix_mutations(rng, path: Path, tmp: Path):
    """Rewrite numeric MAT content: the n x 14 CylData and the TreeQSM 2.0 flat variables."""
    import scipy.io as sio

    m = sio.loadmat(str(path))
    key = next((k for k in m if not k.startswith("__") and getattr(m[k], "ndim", 0) == 2 and m[k].shape[1] == 14), None)
    if key is not None:
        base = m[key].astype(np.float64)
        n = base.shape[0]
        variants = []
        for _ in range(4):
            d = base.copy()
            d[rng.integers(0, n), rng.integers(0, 14)] = rng.choice([np.nan, np.inf, -1.0, 0.0, 1e9])
            variants.append(("cell", d))
        for _ in range(3):
            d = base.copy()
            sel = rng.choice(n, size=int(rng.integers(2, n)), replace=False)
            d[sel, 8] = d[rng.permutation(sel), 8]
            variants.append(("shuffle parents", d))
        variants.append(("remove column", np.delete(base, int(rng.integers(0, 14)), axis=1)))
        variants.append(("uint8 ids", base))
        for i, (lab, d) in enumerate(variants):
            p = tmp / f"mx_{path.stem}_{i}.mat"
            if lab == "uint8 ids":
                sio.savemat(str(p), {key: d.astype(np.float32)})
            else:
                sio.savemat(str(p), {key: d})
            yield f"{lab}", p
    if "CPar" in m:
        names = ["Rad", "Len", "Sta", "Axe", "CPar", "CExt", "BoC", "Added"]
        base = {k: m[k] for k in names if k in m}
        n = base["Rad"].size
        for i in range(5):
            d = {k: v.copy() for k, v in base.items()}
            what = ["nan", "shuffle", "drop", "ext", "boc"][i]
            if what == "nan":
                d["Rad"] = d["Rad"].astype(float)
                d["Rad"][rng.integers(0, n)] = np.nan
            elif what == "shuffle":
                d["CPar"] = d["CPar"][rng.permutation(n)]
            elif what == "drop":
                del d[str(rng.choice(["Len", "Sta", "Axe", "CPar"]))]
            elif what == "ext":
                d["CExt"] = d["CExt"][rng.permutation(n)]
            else:
                d["BoC"] = d["BoC"][:, :2]
            p = tmp / f"flat_{i}.mat"
            sio.savemat(str(p), d)
            yield f"flat {what}", p


_HAS_ALARM = hasattr(signal, "setitimer")


def _check(path: Path, label: str, failures: list):
    if _HAS_ALARM:  # a hang becomes a failure instead of stalling the suite
        signal.signal(signal.SIGALRM, _alarm)
        signal.setitimer(signal.ITIMER_REAL, 10.0)
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            out = bf.read_qsm(path)
        trees = out if isinstance(out, list) else [out]
        for t in trees:
            if not isinstance(t, Tree) or t.n < 1 or not np.all(t.radius > 0) or not np.all(t.length > 0):
                failures.append(f"{label}: returned an invalid result {t!r}")
        return "tree"
    except QSMFormatError as exc:
        if not str(exc).startswith(str(path)):
            failures.append(f"{label}: QSMFormatError does not name the file: {exc}")
        return "error"
    except _Timeout:
        failures.append(f"{label}: took more than 10 s")
        return "hang"
    except Exception as exc:  # the property under test
        failures.append(f"{label}: {type(exc).__name__}: {exc}")
        return "other"
    finally:
        if _HAS_ALARM:
            signal.setitimer(signal.ITIMER_REAL, 0)


def test_fuzz_readers_only_raise_qsmformaterror(tmp_path, qsm_dir):
    rng = np.random.default_rng(SEED)
    failures: list[str] = []
    outcomes = {"tree": 0, "error": 0}
    k = 0

    def run(label, data: bytes, suffix: str):
        nonlocal k
        p = tmp_path / f"case{k:04d}{suffix}"
        k += 1
        p.write_bytes(data)
        r = _check(p, label, failures)
        outcomes[r] = outcomes.get(r, 0) + 1
        p.unlink()

    for name in TEXT_SAMPLES + CSV_SAMPLES:
        data = (qsm_dir / name).read_bytes()
        suffix = Path(name).suffix
        for label, mutated in _text_mutations(rng, data, csv=suffix == ".csv"):
            run(f"{name} {label}", mutated, suffix)
    for name in MAT_SAMPLES + H5_SAMPLES:
        data = (qsm_dir / name).read_bytes()
        for label, mutated in _binary_mutations(rng, data):
            run(f"{name} {label}", mutated, ".mat")
    for name in ("wytham_tf3.mat", "itsme_qsm_tree_v200.mat"):
        for label, p in _matrix_mutations(rng, qsm_dir / name, tmp_path):
            k += 1
            r = _check(p, f"{name} {label}", failures)
            outcomes[r] = outcomes.get(r, 0) + 1
    # content in the wrong container
    for name, suffix in (
        ("coffeetree_archi.csv", ".mat"),
        ("wytham_tf3.mat", ".txt"),
        ("wytham_tf3.mat", ".csv"),
        ("itsme_qsm_tree_v200.mat", ".dat"),
    ):
        run(f"{name} as {suffix}", (qsm_dir / name).read_bytes(), suffix)

    assert k >= MIN_CASES, f"only {k} fuzz cases"
    assert not failures, f"{len(failures)} of {k} cases failed:\n" + "\n".join(failures[:30])
    # the mutations must exercise both outcomes
    assert outcomes["tree"] > 20 and outcomes["error"] > 100, outcomes


def _hand_file(tmp_path: Path, radius: float = 0.1) -> Path:
    """A small TreeQSM text file of the hand-built tree, its first radius set to ``radius``."""
    from conftest import hand_tree

    t = hand_tree()
    r = t.radius.copy()
    r[0] = radius
    p = tmp_path / f"hand_{radius:g}.txt"
    bf.write_tree(Tree(t.start, t.axis, t.length, r, t.parent, t.extension), p)
    return p


def test_special_files_and_huge_values_are_one_clear_error(tmp_path):
    """A FIFO (reading one would wait for ever), a symbolic link loop, a broken link and a radius
    of 1e300 (an infinite volume) each give a QSMFormatError naming the problem, never a hang."""
    import os

    cases = []
    if hasattr(os, "mkfifo"):
        os.mkfifo(tmp_path / "pipe.txt")
        cases.append((tmp_path / "pipe.txt", "is a FIFO"))
    if hasattr(os, "symlink"):
        os.symlink(tmp_path / "loop_b.txt", tmp_path / "loop_a.txt")
        os.symlink(tmp_path / "loop_a.txt", tmp_path / "loop_b.txt")
        os.symlink(tmp_path / "nowhere.txt", tmp_path / "broken.txt")
        cases += [(tmp_path / "loop_a.txt", "symbolic link loop"), (tmp_path / "broken.txt", "broken symbolic link")]
    cases.append((_hand_file(tmp_path, 1e300), "too large to compute with"))
    assert bf.read_qsm(_hand_file(tmp_path, 0.2)).n == 7
    for path, words in cases:
        failures: list[str] = []
        assert _check(path, path.name, failures) == "error", failures
        try:
            bf.read_qsm(path)
        except QSMFormatError as exc:
            assert words in str(exc), (path.name, str(exc))


def test_a_bad_native_csv_sidecar_is_an_error_not_ignored(tmp_path):
    import json

    from conftest import hand_tree

    p = tmp_path / "t.csv"
    bf.write_tree(hand_tree(), p)
    side = p.with_suffix(".json")
    good = json.loads(side.read_text())
    assert bf.read_qsm(p).n == 7
    for bad, words in (
        ({**good, "topology": "sideways"}, "topology 'sideways' is not one of"),
        ({**good, "metadata": [1, 2]}, "metadata is not a JSON object"),
    ):
        side.write_text(json.dumps(bad))
        failures: list[str] = []
        assert _check(p, "sidecar", failures) == "error", failures
        try:
            bf.read_qsm(p)
        except QSMFormatError as exc:
            assert words in str(exc) and str(exc).startswith(str(side))


def test_a_nan_added_flag_is_an_error_not_true(tmp_path, qsm_dir):
    import scipy.io as sio

    m = {k: v for k, v in sio.loadmat(str(qsm_dir / "itsme_qsm_tree_v200.mat")).items() if not k.startswith("__")}
    assert "Added" in m
    m["Added"] = m["Added"].astype(float)
    m["Added"].flat[1] = np.nan
    p = tmp_path / "nan_added.mat"
    sio.savemat(str(p), m)
    failures: list[str] = []
    assert _check(p, "nan added", failures) == "error" and not failures, failures
    try:
        bf.read_qsm(p)
    except QSMFormatError as exc:
        assert "non-finite values in 'added'" in str(exc)
