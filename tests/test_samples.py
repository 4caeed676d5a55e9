"""The sample trees (issue 78, item 3): ``bforest data list|fetch|path`` and ``sample:NAME``.

Nothing here reaches the internet: every download is served by a local HTTP server on the
loopback address (127.0.0.1) through ``BFOREST_DATA_MIRROR``, the way an institute's mirror is
used; a source that cannot be reached is a closed port of 127.0.0.1.
"""

from __future__ import annotations

import hashlib
import re

import pytest

import bforest_core as bf
from bforest_core import samples
from bforest_core.cli import main
from conftest import QSM_DIR, closed_port, served
from test_init import excurrent_tree


@pytest.fixture
def tiny(tmp_path, monkeypatch):
    """A sample of the catalogue's form whose file the test writes (a small pine-like tree as TreeQSM text),
    served from ``tmp_path/source``; the cache is ``tmp_path/cache``."""
    src = tmp_path / "source"
    src.mkdir()
    bf.write_tree(excurrent_tree(), src / "tiny.txt")
    data = (src / "tiny.txt").read_bytes()
    s = samples.Sample(
        "tiny", "tiny.txt", "owner/repo", "0" * 40, "data/tiny.txt", "MIT", hashlib.sha256(data).hexdigest(),
        len(data), "a hand-built tree", "this test",
    )  # fmt: skip
    monkeypatch.setitem(samples.SAMPLES, "tiny", s)
    monkeypatch.setenv("BFOREST_DATA_DIR", str(tmp_path / "cache"))
    monkeypatch.delenv("BFOREST_DATA_MIRROR", raising=False)
    return src


def test_every_sample_names_its_source_at_a_commit_its_licence_and_its_file():
    assert len(samples.SAMPLES) == 17
    for name, s in samples.SAMPLES.items():
        assert s.name == name and s.filename.startswith(name + ".")
        assert re.fullmatch(r"https://raw\.githubusercontent\.com/[\w.-]+/[\w.-]+/[0-9a-f]{40}/\S+", s.url), s.url
        assert s.licence and s.cite and s.about and re.fullmatch(r"[0-9a-f]{64}", s.sha256)
    assert samples.SAMPLES["pine_ruotsinkyla_3"].licence.startswith("none stated")
    assert samples.SAMPLES["itsme_qsm_tree_v240"].licence == "MIT"


def test_the_catalogue_holds_the_files_the_tests_read():
    """Each checksum and size is that of the sample file the project's tests and benchmarks read."""
    if not QSM_DIR.is_dir():
        pytest.skip(f"the sample files are not in {QSM_DIR} (needs ../shared/data/qsm)")
    for s in samples.SAMPLES.values():
        p = QSM_DIR / s.filename
        assert p.stat().st_size == s.size and samples.sha256_of(p) == s.sha256, s.name


def test_fetch_from_a_local_server_then_read_it_as_sample_name(tiny, tmp_path, capsys):
    with served(tiny) as (url, asked):
        env = {"BFOREST_DATA_MIRROR": url}
        with pytest.MonkeyPatch.context() as mp:
            for k, v in env.items():
                mp.setenv(k, v)
            assert main(["data", "fetch", "tiny"]) == 0
            out = capsys.readouterr().out
            assert f"tiny: fetched, {tmp_path / 'cache' / 'tiny.txt'} (SHA-256 checked; licence: MIT)" in out
            assert main(["data", "fetch", "tiny"]) == 0  # there already: not downloaded again
            assert "tiny: already there" in capsys.readouterr().out
    assert asked == ["/tiny.txt"]
    assert (tmp_path / "cache" / "tiny.txt").read_bytes() == (tiny / "tiny.txt").read_bytes()
    assert sorted(p.name for p in (tmp_path / "cache").iterdir()) == ["tiny.txt"]  # no temporary file left
    assert main(["data", "path", "tiny"]) == 0
    assert capsys.readouterr().out.strip() == str(tmp_path / "cache" / "tiny.txt")
    assert bf.read_qsm("sample:tiny").n == 44
    assert main(["info", "sample:tiny"]) == 0 and "cylinders     44" in capsys.readouterr().out


def test_fetch_into_a_folder_the_user_names(tiny, tmp_path, capsys):
    with served(tiny) as (url, _), pytest.MonkeyPatch.context() as mp:
        mp.setenv("BFOREST_DATA_MIRROR", url)
        assert main(["data", "fetch", "tiny", "-o", str(tmp_path / "data")]) == 0
    assert (tmp_path / "data" / "tiny.txt").is_file() and not (tmp_path / "cache").exists()
    (tmp_path / "data" / "tiny.txt").write_text("my own file\n")
    capsys.readouterr()
    assert main(["data", "fetch", "tiny", "-o", str(tmp_path / "data")]) == 2  # never over a file of the user's
    err = capsys.readouterr().err.strip().splitlines()
    assert err == [
        f"error: {tmp_path / 'data' / 'tiny.txt'}: exists and is not the sample tiny; replace it with --overwrite"
    ]
    with served(tiny) as (url, _), pytest.MonkeyPatch.context() as mp:
        mp.setenv("BFOREST_DATA_MIRROR", url)
        assert main(["data", "fetch", "tiny", "-o", str(tmp_path / "data"), "--overwrite"]) == 0
    assert (tmp_path / "data" / "tiny.txt").read_bytes() == (tiny / "tiny.txt").read_bytes()


def test_a_source_that_cannot_be_reached_is_one_line(tiny, tmp_path, capsys, monkeypatch):
    url = f"http://127.0.0.1:{closed_port()}"
    monkeypatch.setenv("BFOREST_DATA_MIRROR", url)
    assert main(["data", "fetch", "tiny"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert (
        len(err) == 1 and err[0].startswith(f"error: cannot reach {url}/tiny.txt (") and "BFOREST_DATA_MIRROR" in err[0]
    )
    assert not (tmp_path / "cache").exists() or not list((tmp_path / "cache").iterdir())


def test_a_file_that_is_not_the_sample_is_refused_and_nothing_is_written(tiny, tmp_path, capsys, monkeypatch):
    (tiny / "tiny.txt").write_text("a changed file\n")
    with served(tiny) as (url, _):
        monkeypatch.setenv("BFOREST_DATA_MIRROR", url)
        assert main(["data", "fetch", "tiny"]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert (
            len(err) == 1 and "not the file Bayes Forest was tested with" in err[0] and "nothing was written" in err[0]
        )
        (tiny / "tiny.txt").unlink()
        assert main(["data", "fetch", "tiny"]) == 2
        assert capsys.readouterr().err.strip() == f"error: {url}/tiny.txt: the server answered 404 File not found"
    assert not list((tmp_path / "cache").iterdir())


def test_a_sample_not_fetched_or_unknown_says_what_to_do(tiny, tmp_path, capsys):
    assert main(["info", "sample:tiny"]) == 2
    assert capsys.readouterr().err.strip() == (
        f"error: sample:tiny: not fetched yet (looked in {tmp_path / 'cache'}); fetch it with 'bforest data fetch tiny'"
    )
    assert main(["data", "fetch", "wytham_tf9"]) == 2
    assert "unknown sample 'wytham_tf9'; did you mean wytham_tf5, wytham_tf4, wytham_tf3?" in capsys.readouterr().err
    cfg = tmp_path / "run.toml"
    cfg.write_text(
        '[target]\nqsm = "sample:tiny"\n[ssm]\nkind = "sot"\nfree.branch_angle = { lower = 30.0, upper = 80.0 }\n'
    )
    assert main(["config", "check", str(cfg)]) == 2
    assert "target.qsm: sample:tiny: not fetched yet" in capsys.readouterr().err
    assert bf.load_config(cfg).target.qsm == "sample:tiny"  # kept as written: the run finds it where it is fetched


def test_the_cache_follows_the_users_settings(monkeypatch, tmp_path):
    monkeypatch.delenv("BFOREST_DATA_DIR", raising=False)
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "xdg"))
    assert samples.data_dir() == tmp_path / "xdg" / "bayesforest" / "samples"
    monkeypatch.delenv("XDG_CACHE_HOME")
    monkeypatch.setenv("HOME", str(tmp_path / "home"))
    assert samples.data_dir() == tmp_path / "home" / ".cache" / "bayesforest" / "samples"
    monkeypatch.setenv("BFOREST_DATA_DIR", str(tmp_path / "mine"))
    assert samples.data_dir() == tmp_path / "mine"


def test_init_on_a_sample_writes_a_recipe_that_names_it(tiny, tmp_path, capsys, monkeypatch):
    with served(tiny) as (url, _):
        monkeypatch.setenv("BFOREST_DATA_MIRROR", url)
        assert main(["data", "fetch", "tiny"]) == 0
    monkeypatch.chdir(tmp_path)
    assert main(["init", "sample:tiny"]) == 0
    assert "next: bforest fit tiny.toml -o runs/tiny" in capsys.readouterr().out
    text = (tmp_path / "tiny.toml").read_text()
    assert '\nqsm = "sample:tiny"\n' in text and "`bforest init sample:tiny`" in text
    assert bf.load_config(tmp_path / "tiny.toml").target.qsm == "sample:tiny"
