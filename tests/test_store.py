import json

import numpy as np
import pytest

from bforest_core.pipeline.store import Evaluation, RunDirError, RunStore


def test_evaluations_are_committed_one_by_one(tmp_path):
    s = RunStore.create(tmp_path / "run", "seed = 1\n")
    s.add(Evaluation(0, {"a": 1.0}, [7], 0.5, {"S1": 0.5}, "ok", seconds=0.1, worker="w:1"))
    # another connection (another process) sees it at once
    other = RunStore.open(tmp_path / "run")
    assert other.count() == 1 and other.evaluations()[0].params == {"a": 1.0}
    s.add(Evaluation(1, {"a": 2.0}, [7], 0.25, {"S1": None}, "collapsed", message="m"))
    assert other.count() == 2 and other.evaluations()[1].per_set == {"S1": None}
    # the best is a grown tree, even where a failure's penalty distance is lower
    assert other.best().idx == 0
    # the best after n evaluations looks at the first n only
    s.add(Evaluation(2, {"a": 3.0}, [7], 0.125, {"S1": 0.125}, "ok"))
    assert other.best().idx == 2 and other.best(before=2).idx == 0 and other.best(before=0) is None
    with pytest.raises(RunDirError, match="already holds a run"):
        RunStore.create(tmp_path / "run", "seed = 1\n")
    with pytest.raises(RunDirError, match="not a run directory"):
        RunStore.open(tmp_path / "nothing")


def test_a_store_used_as_a_context_closes_its_connection(tmp_path):
    import sqlite3

    RunStore.create(tmp_path / "run", "seed = 1\n").close()
    with RunStore.open(tmp_path / "run") as s:
        assert s.count() == 0
    with pytest.raises(sqlite3.ProgrammingError, match="closed"):
        s.count()


def test_large_diagnostics_go_to_npz(tmp_path):
    s = RunStore.create(tmp_path / "run", "seed = 1\n")
    chain = np.random.default_rng(0).normal(size=(50, 16, 3))
    small = s.write_diagnostics(
        {"chain": chain, "acceptance": 0.3, "names": ["a", "b", "c"], "posterior": {"a": {"median": 1.0}}}
    )
    assert small["arrays"] == ["chain"] and small["acceptance"] == 0.3
    s.write_json("best.json", {"diagnostics": small})
    assert len((tmp_path / "run" / "best.json").read_text()) < 1000
    back = s.read_diagnostics()
    np.testing.assert_array_equal(back["chain"], chain)
    assert back["names"] == ["a", "b", "c"] and "arrays" not in back


def test_a_fit_writes_the_files_runfiles_names(toy_plugin, tmp_path):
    import fnmatch

    import bforest_core as bf
    from bforest_core.pipeline.store import RunFiles
    from conftest import toy_config

    bf.fit(bf.load_config(toy_config(tmp_path, budget=8)), tmp_path / "run", progress=False)
    run = RunFiles(tmp_path / "run")
    for p in (
        run.config_path,
        run.evaluations_path,
        run.best_path,
        run.best_tree_path,
        run.target_tree_path,
        run.target_sets_path,
        run.distance_path,
        run.clones_dir(),
        run.figures_dir,
    ):
        assert p.exists(), p
    assert run.finished() and run.read_best()["n_evaluations"] == 8
    unnamed = [
        p.name
        for p in run.path.iterdir()
        if p.name != RunFiles.LOCK and not any(fnmatch.fnmatch(p.name, g) for g in RunFiles.DERIVED)
    ]
    assert not unnamed, f"files of a run that RunFiles does not name: {unnamed}"
    with pytest.raises(RunDirError, match="no best.json"):
        RunFiles(tmp_path).read_best()


def test_run_folder_file_names_are_spelled_only_in_the_store():
    import ast
    from pathlib import Path

    from bforest_core.pipeline.store import RunFiles

    names = {v for k, v in vars(RunFiles).items() if k.isupper() and isinstance(v, str)}
    core = Path(__file__).resolve().parents[1] / "bforest_core"
    found = []
    for f in sorted(core.rglob("*.py")):
        rel = f.relative_to(core).as_posix()
        if rel == "pipeline/store.py":
            continue
        tree = ast.parse(f.read_text(encoding="utf-8"))
        docs = {
            id(n.body[0].value)
            for n in ast.walk(tree)
            if isinstance(n, (ast.Module, ast.FunctionDef, ast.ClassDef))
            and n.body
            and isinstance(n.body[0], ast.Expr)
            and isinstance(n.body[0].value, ast.Constant)
        }
        for node in ast.walk(tree):
            if isinstance(node, ast.Constant) and isinstance(node.value, str) and id(node) not in docs:
                # file names (folder names such as "clones" are also the words of commands)
                hits = [n for n in names if "." in n and n in node.value]
                if hits:
                    found.append(f"{rel}:{node.lineno}: {', '.join(sorted(hits))}")
    assert not found, "run-folder file names spelled outside pipeline/store.py:\n" + "\n".join(found)


def test_jsonable_writes_numpy_and_paths_and_only_loosely_anything_else(tmp_path):
    from pathlib import Path

    from bforest_core.io import json_text, jsonable, write_json

    data = {"a": np.float32(0.5), "b": np.arange(3), "c": np.int64(7), "p": Path("x") / "y", "t": (1, 2)}
    assert jsonable(data) == {"a": 0.5, "b": [0, 1, 2], "c": 7, "p": "x/y", "t": [1, 2]}
    with pytest.raises(TypeError, match="not JSON serialisable: object"):
        jsonable({"o": object()})
    assert jsonable({"o": 1j, (1, 2): 3}, loose=True) == {"o": "1j", "(1, 2)": 3}
    # the run folder's files keep NaN (Python's json reads it back); strict text has null
    assert json_text({"x": float("nan"), "y": np.float64("inf")}, indent=None) == '{"x": NaN, "y": Infinity}'
    assert json_text({"x": float("nan"), "y": [np.float64("-inf"), 1.5]}, strict=True, indent=None) == (
        '{"x": null, "y": [null, 1.5]}'
    )
    # the evaluation log's columns: one line, keys sorted, as json.dumps writes them
    params = {"b": 2, "a": 0.1, "c": None}
    assert json_text(params, indent=None, sort_keys=True) == json.dumps(params, sort_keys=True)
    path = write_json(tmp_path / "x.json", {"v": np.arange(2)})
    assert path.read_text(encoding="utf-8") == '{\n  "v": [\n    0,\n    1\n  ]\n}'
    assert not list(tmp_path.glob("*.tmp"))
