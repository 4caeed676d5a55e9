"""Wrong answers to bad input: `config check` runs every check `fit` runs (one code path) and
names every problem of a file at once, with "did you mean" for near misses."""

from __future__ import annotations

import pytest

from bforest_core.cli import main
from conftest import toy_config


def _lines(capsys):
    return [
        ln
        for ln in capsys.readouterr().err.strip().splitlines()
        if not ln.startswith("warning: bforest plugin 'broken'")
    ]


CASES = [  # (replace, by, words of the one-line error)
    ('ssm = "toy"\nseed = 11', 'ssm = "toyy"\nseed = 11', "target.generate.ssm: unknown ssm 'toyy'"),
    (
        "params = { angle = 30.0, segments = 12 }",
        "params = { angel = 30.0, segments = 12 }",
        "target.generate.params.angel: unknown parameter of 'toy' (known: angle, segments, lateral_len, noise) "
        "(did you mean 'angle'?)",
    ),
    (
        "params = { angle = 30.0, segments = 12 }",
        "params = { angle = 300.0, segments = 12 }",
        "target.generate.params.angle: 300.0 is outside the allowed range",
    ),
    ("seed = 3\n", "seed = -3\n", "seed: Input should be greater than or equal to 0"),
    (
        'ssm = "toy"\nseed = 11',
        'ssm = "toy"\nseed = -11',
        "target.generate.seed: Input should be greater than or equal to 0",
    ),
    ('kind = "serial"\n', 'kind = "process"\nstart_method = "forx"\n', "executor.start_method: Input should be 'fork'"),
    (
        "free.angle = { lower = 5.0, upper = 80.0 }\nfree.segments = { lower = 4, upper = 30 }",
        "",
        "ssm.free: no free parameters to fit",
    ),
    ("[clones]", "[objective]\npenalty = nan\n[clones]", "objective.penalty: Input should be a finite number"),
    (
        "[clones]",
        "[objective]\npenalty = -1\n[clones]",
        "objective.penalty: Input should be greater than or equal to 0",
    ),
    (
        "[clones]",
        "[objective]\nweights = { L = -1.0 }\n[clones]",
        "objective.weights: the weight of 'L' must be a finite number >= 0 (got -1.0)",
    ),
    (
        "[clones]",
        "[objective]\nweights = { LL = 1.0 }\n[clones]",
        "objective.weights.LL: no data set 'LL' (did you mean 'L'?)",
    ),
    ("[clones]", '[target]\nreferences = ["gone.txt"]\n[clones]', "target.references[0]: file not found"),
]


@pytest.mark.parametrize("old,new,words", CASES)
def test_config_check_rejects_what_fit_rejects(toy_plugin, tmp_path, capsys, old, new, words):
    p = toy_config(tmp_path, budget=4)
    text = p.read_text()
    assert old in text
    p.write_text(text.replace(old, new, 1))
    assert main(["config", "check", str(p)]) == 2
    err = _lines(capsys)
    assert len(err) == 1 and words in err[0], err
    assert main(["fit", str(p), "-o", str(tmp_path / "run"), "-q", "--no-report"]) == 2
    err = _lines(capsys)
    assert len(err) == 1 and words in err[0], err
    assert not (tmp_path / "run" / "evaluations.sqlite").exists()  # refused before the run folder was touched


def test_every_problem_of_a_file_at_once_with_did_you_mean(toy_plugin, tmp_path, capsys):
    p = toy_config(tmp_path, budget=4)
    text = (
        p.read_text()
        .replace("seed = 3\n", "seeed = 3\n", 1)
        .replace("max_evaluations", "max_evaluatons")
        .replace('kind = "toy-distance"', 'kind = "toy-distanse"')
        .replace("fixed = { noise = 2.0 }", "fixed = { noise = 2.0, lateral_length = 1.0 }")
        .replace("free.angle = { lower = 5.0, upper = 80.0 }", "free.angle = { lower = 5.0, uper = 80.0 }")
    )
    p.write_text(text)
    assert main(["config", "check", str(p)]) == 2
    err = _lines(capsys)
    assert len(err) == 1, err
    for words in (
        "distance.kind: unknown distance 'toy-distanse'",
        "(did you mean 'toy-distance'?)",
        "seeed: unknown key (did you mean 'seed'?)",
        "stop.max_evaluatons: unknown key (did you mean 'max_evaluations'?)",
        "ssm.free.angle.uper: unknown key (did you mean 'upper'?)",
    ):
        assert words in err[0], (words, err[0])
    p.write_text(
        text.replace("seeed", "seed")
        .replace("max_evaluatons", "max_evaluations")
        .replace("toy-distanse", "toy-distance")
        .replace("uper", "upper")
    )
    assert main(["config", "check", str(p)]) == 2
    err = _lines(capsys)
    assert (
        "ssm.fixed.lateral_length: unknown parameter of 'toy'" in err[0] and "(did you mean 'lateral_len'?)" in err[0]
    )


def test_a_fit_where_every_evaluation_failed_says_so_and_exits_non_zero(toy_plugin, tmp_path, capsys):
    p = toy_config(tmp_path, budget=4)
    p.write_text(p.read_text().replace('[ssm]\nkind = "toy"\n', '[ssm]\nkind = "toy"\nfail_above = 0.0\n', 1))
    assert main(["fit", str(p), "-o", str(tmp_path / "run"), "-q", "--no-report"]) == 1
    err = _lines(capsys)
    assert len(err) == 1 and err[0].startswith("error: every one of the 4 evaluations failed (collapsed 4;"), err
