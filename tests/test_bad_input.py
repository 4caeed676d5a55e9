"""Wrong answers to bad input on the command line: one line, exit 2, never a traceback or a hang."""

from __future__ import annotations

from bforest_core.cli import main
from conftest import toy_config


def _err(capsys):
    return [
        ln
        for ln in capsys.readouterr().err.strip().splitlines()
        if not ln.startswith("warning: bforest plugin 'broken'")
    ]


def test_distance_statistics_other_than_ks_and_too_many_lines(toy_plugin, tmp_path, capsys):
    import bforest_core as bf

    a = tmp_path / "a.txt"
    bf.write_tree(bf.component("ssm", "toy").simulate({"segments": 30}, 1), a)
    for stat in ("cvm", "ad", "w1", "energy"):
        assert main(["distance", str(a), str(a), "--sets", "B1", "--statistic", stat, "--lines", "8"]) == 2
        err = _err(capsys)
        assert len(err) == 1 and "needs --empty-cost" in err[0], err
        assert (
            main(
                ["distance", str(a), str(a), "--sets", "B1", "--statistic", stat, "--lines", "8", "--empty-cost", "1.0"]
            )
            == 0
        ), _err(capsys)
        assert "distance (sliced" in capsys.readouterr().out
    assert main(["distance", str(a), str(a), "--lines", "100000000"]) == 2
    err = _err(capsys)
    assert len(err) == 1 and "--lines must be between 1 and 65536" in err[0]


def test_max_evaluations_zero_and_an_output_that_is_a_file(toy_plugin, tmp_path, capsys):
    p = toy_config(tmp_path, budget=4)
    assert main(["fit", str(p), "-o", str(tmp_path / "r"), "--max-evaluations", "0", "-q"]) == 2
    assert "--max-evaluations must be at least 1" in _err(capsys)[0]
    (tmp_path / "taken").write_text("x")
    assert main(["fit", str(p), "-o", str(tmp_path / "taken"), "-q", "--no-report"]) == 2
    err = _err(capsys)
    assert len(err) == 1 and "exists and is not a folder" in err[0]


def test_simulate_values_outside_the_models_range(toy_plugin, capsys):
    assert main(["simulate", "--ssm", "toy", "--set", "angle=1000"]) == 2
    err = _err(capsys)
    assert len(err) == 1 and "--set angle=1000: outside the allowed range [0.0, 90.0] deg" in err[0]


def test_terminal_escapes_in_a_file_name_are_not_echoed_raw(tmp_path, capsys):
    name = tmp_path / "evil\x1b[2J\x07.txt"
    assert main(["info", str(name)]) == 2
    err = capsys.readouterr().err
    assert "\x1b" not in err and "\x07" not in err and "\\x1b[2J\\x07" in err


def test_report_markdown_carries_no_raw_html():
    from bforest_core.report.document import Document

    doc = Document()
    doc.h(2, "tree <script>alert(1)</script>.txt")
    doc.p("target <img src=x onerror=alert(1)>.mat; a < b and 3<4 stay as written")
    doc.table(["file"], [["</td><script>"]])
    md = doc.markdown()
    assert "<script" not in md and "<img" not in md and "</" not in md
    assert "&lt;script>alert(1)&lt;/script>" in md and "a < b and 3<4 stay" in md


def test_a_plugins_parameter_names_must_be_identifiers(toy_plugin, tmp_path, monkeypatch, capsys):
    from bforest_toy import ToySSM

    from bforest_core import ParameterSpec

    p = toy_config(tmp_path, budget=4)
    real = ToySSM.parameters.fget
    monkeypatch.setattr(
        ToySSM,
        "parameters",
        property(lambda self: real(self) + [ParameterSpec("<img src=x onerror=alert(1)>", 1.0, 0.0, 2.0)]),
    )
    assert main(["config", "check", str(p)]) == 2
    err = _err(capsys)
    assert len(err) == 1 and "parameter name '<img src=x onerror=alert(1)>' is not a Python identifier" in err[0]
