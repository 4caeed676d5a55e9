import warnings

import pytest

import bforest_core as bf
from bforest_core import registry
from bforest_core.errors import ConfigError, PluginError


def test_toy_plugin_discovered_through_entry_point(toy_plugin):
    reg = registry.discover()
    entry = reg.components[("ssm", "toy")]
    assert entry.distribution == "bforest-toy" and entry.version == "1.2.3"
    ssm = bf.component("ssm", "toy", sleep=0.0)
    assert ssm.name == "toy" and ssm.settings.sleep == 0.0
    t = ssm.simulate({"angle": 20.0}, seed=4)
    assert isinstance(t, bf.Tree) and t.n == 20


def test_broken_plugin_is_reported_and_others_still_work(toy_plugin):
    reg = registry.discover()
    errs = {e.plugin: e.error for e in reg.errors}
    assert "broken" in errs and "ImportError" in errs["broken"] and "not installed" in errs["broken"]
    assert ("executor", "serial") in reg.components and ("ssm", "toy") in reg.components


def test_strict_mode_makes_failure_fatal(toy_plugin, monkeypatch):
    monkeypatch.setenv("BFOREST_STRICT_PLUGINS", "1")
    with pytest.raises(PluginError, match="broken"):
        registry.discover(refresh=True)
    monkeypatch.delenv("BFOREST_STRICT_PLUGINS")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        registry.discover(refresh=True)


def test_unknown_name_lists_known():
    with pytest.raises(PluginError, match=r"unknown executor 'nope' \(known: .*process.*serial"):
        bf.component("executor", "nope")
    with pytest.raises(PluginError, match="unknown component kind"):
        bf.component("gizmo", "x")


def test_invalid_settings_name_key():
    with pytest.raises(ConfigError, match="workers"):
        bf.component("executor", "process", workers=0)
    with pytest.raises(ConfigError, match="colour: unknown key"):
        bf.component("executor", "serial", colour="red")


def test_conflicting_registration_names_both_distributions():
    from bforest_core.pipeline.executors import SerialExecutor

    class Other(SerialExecutor):
        pass

    reg = registry.Registry()
    reg.add(SerialExecutor, "core", "bayesforest", "0.1")
    reg.add(Other, "x", "other-dist", "2.0")
    with pytest.raises(PluginError, match="bayesforest .* and other-dist"):
        reg.get("executor", "serial")


def test_rejects_non_component():
    reg = registry.Registry()
    with pytest.raises(PluginError, match="not a subclass"):
        reg.add(int, "p", "d", "1")


def test_cli_plugins_lists_kinds_versions_and_errors(toy_plugin, tmp_path):
    import contextlib
    import io

    from bforest_core.cli import main

    buf = io.StringIO()
    with contextlib.redirect_stdout(buf):
        assert main(["plugins"]) == 0
    out = buf.getvalue()
    assert "executor" in out and "serial" in out and "bayesforest" in out
    assert "toy" in out and "bforest-toy 1.2.3" in out
    assert "load errors" in out and "broken" in out
