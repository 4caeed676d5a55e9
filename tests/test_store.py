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
    small = s.write_diagnostics({"chain": chain, "acceptance": 0.3, "names": ["a", "b", "c"],
                                 "posterior": {"a": {"median": 1.0}}})
    assert small["arrays"] == ["chain"] and small["acceptance"] == 0.3
    s.write_json("best.json", {"diagnostics": small})
    assert len((tmp_path / "run" / "best.json").read_text()) < 1000
    back = s.read_diagnostics()
    np.testing.assert_array_equal(back["chain"], chain)
    assert back["names"] == ["a", "b", "c"] and "arrays" not in back
