"""The small faults of the second probe: files written whole, code spans in report.md, the
distance's statistic, export's empty and repeated arguments, silent config values, the report's
resolution, the time of a stopped evaluation, the demo's help."""

from __future__ import annotations

import errno
import math

import pytest

import bforest_core as bf
from bforest_core.errors import ConfigError
from conftest import hand_tree, toy_config


def _cli(capsys, *args) -> tuple[int, str, list[str]]:
    from bforest_core.cli.main import main

    capsys.readouterr()
    code = main([str(a) for a in args])
    out, err = capsys.readouterr()
    return code, out, [ln for ln in err.splitlines() if "plugin 'broken'" not in ln]


@pytest.fixture(scope="module")
def run(toy_plugin, tmp_path_factory):
    d = tmp_path_factory.mktemp("small")
    bf.fit(bf.load_config(toy_config(d, budget=8)), d / "run", progress=False)
    return d / "run"


# ------------------------------------------------------------------------------ files written whole
def test_a_full_disk_leaves_the_old_file_or_none_never_half_of_one(tmp_path, monkeypatch):
    """A tree written as PLY and a report whose writing stops on a full disk half way: the file
    before is left as it was (or none is there), no half-written file, no temporary folder."""
    from pathlib import Path

    from bforest_core.io import whole_file, write_tree

    real = Path.write_text

    def half_then_full(self, text, *a, **kw):  # half the text reaches the disk, then it is full
        real(self, text[: len(text) // 2], *a, **kw)
        raise OSError(errno.ENOSPC, "No space left on device", str(self))

    old = tmp_path / "report.html"
    old.write_text("<html>the report before</html>")
    monkeypatch.setattr(Path, "write_text", half_then_full)
    with pytest.raises(OSError, match="No space left"):
        with whole_file(old) as part:
            part.write_text("<html>" + "x" * 10_000 + "</html>")
    monkeypatch.setattr(Path, "write_text", real)
    assert old.read_text() == "<html>the report before</html>"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["report.html"]

    from bforest_formats import writers

    def full_ply(self, tree, path, **options):
        Path(path).write_bytes(b"ply\nformat binary_little_endian 1.0\n")  # the header, then no room
        raise OSError(errno.ENOSPC, "No space left on device", str(path))

    monkeypatch.setattr(writers.PLYWriter, "write", full_ply)
    with pytest.raises(OSError, match="No space left"):
        write_tree(hand_tree(), tmp_path / "tree.ply")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["report.html"]  # no tree.ply at all


def test_a_writer_s_side_files_keep_their_names(tmp_path):
    """Written whole through a temporary folder: the branch file TreeQSM's text writer puts beside
    its cylinder file is named after the real file."""
    from bforest_core.io import write_tree

    write_tree(hand_tree(), tmp_path / "cylinder_t.txt", branch_file=True)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["branch_t.txt", "cylinder_t.txt"]


# ------------------------------------------------------------------------------ report.md
def test_report_markdown_shows_code_spans_as_they_are_and_escapes_tags_elsewhere():
    from bforest_core.report.document import Document

    doc = Document()
    doc.p("file `runs/<tree>/best.json` of <script>alert(1)</script> and `a<b`")
    md = doc.markdown()
    assert "`runs/<tree>/best.json`" in md and "`a<b`" in md  # a code span shows its text as it is
    assert "&lt;script>alert(1)&lt;/script>" in md  # outside one, no tag opens


# ------------------------------------------------------------------------------ distance, export
def test_an_unknown_statistic_is_named(tmp_path, capsys):
    from bforest_core.io import write_tree

    for name in ("a.txt", "b.txt"):
        write_tree(hand_tree(), tmp_path / name)
    code, _, err = _cli(capsys, "distance", tmp_path / "a.txt", tmp_path / "b.txt", "--statistic", "bogus")
    assert code == 2 and len(err) == 1, err
    assert "bogus" in err[0] and "'ks'" in err[0] and "empty-cost" not in err[0]


def test_export_refuses_an_empty_folder_or_format_and_counts_what_it_writes(run, tmp_path, capsys, monkeypatch):
    monkeypatch.chdir(tmp_path)
    code, _, err = _cli(capsys, "export", run, "--format", "ply", "-o", "")
    assert code == 2 and "-o: an empty folder name" in err[0] and not list(tmp_path.iterdir())
    code, _, err = _cli(capsys, "export", run, "--format", "")
    assert code == 2 and "--format: no format named" in err[0]
    code, out, err = _cli(capsys, "export", run, "--format", "txt,txt,mat", "-o", tmp_path / "out")
    files = sorted(p.name for p in (tmp_path / "out").iterdir())
    assert code == 0 and files == ["best_tree.mat", "best_tree.txt"]
    assert f"wrote {len(files)} files" in out


# ------------------------------------------------------------------------------ silent config values
@pytest.mark.parametrize(
    "edit,words",
    [
        ("[objective]\nweights = { L = 0.0 }\n", "every data set's weight is 0, so every distance would be 0"),
        ("[stop]\ntarget_distance = nan\n", "stop.target_distance: Input should be a finite number"),
        ("[objective]\ntimeout = inf\n", "objective.timeout: Input should be a finite number"),
    ],
)
def test_values_that_passed_without_a_word_are_refused(toy_plugin, tmp_path, edit, words):
    from bforest_core.pipeline.checks import preflight

    p = toy_config(tmp_path, budget=8)
    text = p.read_text()
    section = edit.split("\n", 1)[0]
    if section in text:
        text = text.replace(section + "\n", edit, 1)
    else:
        text += "\n" + edit
    p.write_text(text)
    with pytest.raises(ConfigError, match=words.replace("(", r"\(").replace(")", r"\)")):
        preflight(bf.load_config(p))


def test_a_whole_number_parameter_given_a_fraction_is_refused(tmp_path):
    p = tmp_path / "sot.toml"
    p.write_text(
        '[target.generate]\nssm = "sot"\nparams = { max_iter = 9 }\n'
        '[ssm]\nkind = "sot"\nfixed = { max_iter = 10.5 }\nfree.init_lambda = { lower = 0.4, upper = 0.6 }\n'
    )
    with pytest.raises(
        ConfigError, match=r"ssm.fixed.max_iter: 10.5 is not a whole number \(max_iter counts whole cycles\)"
    ):
        bf.load_config(p)


# ------------------------------------------------------------------------------ report, demo
def test_the_report_s_resolution_is_one_it_can_draw(run, capsys):
    code, _, err = _cli(capsys, "report", run, "--dpi", "2400")
    assert code == 2 and len(err) == 1 and "--dpi must be between 20 and 600 (got 2400)" in err[0]


def test_the_demo_s_help_names_no_file_beside_the_run(capsys):
    from bforest_core.cli.main import build_parser

    text = build_parser()._subparsers._group_actions[0].choices["demo"].format_help()
    assert "-o.toml" not in text and "--overwrite" in text


def test_a_task_stopped_at_its_time_limit_logs_the_time_it_ran():
    from bforest_core.pipeline.worker import _lost_task, _task_limit, evaluate_task

    lost = _lost_task(1.0, ["L"], 0.5, evaluate_task, ({"angle": 1.0}, [1, 2]), "timeout", "still running")
    assert lost["seconds"] == _task_limit(0.5, ({"angle": 1.0}, [1, 2])) == 2 * 0.5 + 2.0
    crashed = _lost_task(1.0, ["L"], 0.5, evaluate_task, ({"angle": 1.0}, [1]), "crashed", "killed")
    assert crashed["seconds"] == 0.0 and math.isfinite(lost["distance"])
