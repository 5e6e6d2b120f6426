"""Plugin loading: isolation of broken plugins, duplicates, strict mode, entry points."""

from __future__ import annotations

import importlib.metadata as md
import sys
import tomllib
import types
from pathlib import Path

import pytest

from plantscan_core import plugins
from plantscan_core.errors import PluginError
from plantscan_core.hookspecs import hookimpl
from plantscan_core.stages import Segmenter, StageParams

ROOT = Path(__file__).resolve().parents[2]


def _plugin_module(name: str, seg_name: str) -> types.ModuleType:
    """A plugin module registering one segmenter called ``seg_name``."""
    mod = types.ModuleType(name)

    class Seg(Segmenter):
        class Params(StageParams):
            threshold: float = 1.0

        def segment(self, image, background, view=None):
            return image[..., 0] > self.params.threshold

    Seg.name = seg_name
    Seg.__module__ = name

    @hookimpl
    def plantscan_register_stages(registry):
        registry.add(Seg)

    mod.plantscan_register_stages = plantscan_register_stages
    return mod


class FakeDist:
    def __init__(self, name):
        self.name = name


def _ep(name: str, value: str, dist: str) -> md.EntryPoint:
    ep = md.EntryPoint(name=name, value=value, group=plugins.ENTRY_POINT_GROUP)
    return ep._for(FakeDist(dist)) if hasattr(ep, "_for") else ep


@pytest.fixture
def fake_entry_points(monkeypatch):
    """Replace the installed entry points with modules made in the test."""
    installed: dict[str, types.ModuleType] = {}

    def install(eps: list[tuple[str, types.ModuleType | None, str]]):
        out = []
        for name, module, dist in eps:
            modname = f"_plantscan_test_{name}"
            if module is not None:
                sys.modules[modname] = module
                installed[modname] = module
            out.append(_ep(name, modname, dist))
        monkeypatch.setattr(plugins.md, "entry_points",
                            lambda group=None: [e for e in out if group in (None, e.group)])

    yield install
    for modname in installed:
        sys.modules.pop(modname, None)


def test_broken_plugin_is_reported_and_others_still_load(fake_entry_points, monkeypatch, capsys):
    monkeypatch.delenv(plugins.STRICT_ENV, raising=False)
    broken = types.ModuleType("broken")

    @hookimpl
    def plantscan_register_stages(registry):
        raise RuntimeError("camera SDK not found")

    broken.plantscan_register_stages = plantscan_register_stages
    fake_entry_points([
        ("alpha", _plugin_module("_plantscan_test_alpha", "alpha-seg"), "dist-alpha"),
        ("broken", broken, "dist-broken"),
        ("missing", None, "dist-missing"),  # import fails: no such module
        ("omega", _plugin_module("_plantscan_test_omega", "omega-seg"), "dist-omega"),
    ])
    manager = plugins.load_plugins()
    assert manager.registry.names("segmenter") == ["alpha-seg", "omega-seg"]
    failed = {f.name: f for f in manager.failed}
    assert set(failed) == {"broken", "missing"}
    assert "camera SDK not found" in failed["broken"].error
    assert "ModuleNotFoundError" in failed["missing"].error
    assert "2 plugin(s) failed to load" in capsys.readouterr().err


def test_strict_mode_makes_a_broken_plugin_fatal(fake_entry_points, monkeypatch):
    fake_entry_points([("missing", None, "dist-missing")])
    monkeypatch.setenv(plugins.STRICT_ENV, "1")
    with pytest.raises(PluginError, match="missing.*failed to load"):
        plugins.load_plugins()


def test_duplicate_stage_name_names_both_distributions(fake_entry_points, monkeypatch):
    monkeypatch.delenv(plugins.STRICT_ENV, raising=False)
    fake_entry_points([
        ("first", _plugin_module("_plantscan_test_first", "same"), "labA-plugins"),
        ("second", _plugin_module("_plantscan_test_second", "same"), "labB-plugins"),
    ])
    manager = plugins.load_plugins()
    assert manager.registry.names("segmenter") == ["same"]
    [failed] = manager.failed
    assert "labA-plugins" in failed.error and "labB-plugins" in failed.error
    assert "duplicate segmenter 'same'" in failed.error


def test_misspelt_hook_is_caught_by_check_pending(plantscan_manager):
    mod = types.ModuleType("typo")

    @hookimpl
    def plantscan_register_stagez(registry):  # misspelt on purpose
        pass

    mod.plantscan_register_stagez = plantscan_register_stagez
    with pytest.raises(Exception, match="plantscan_register_stagez"):
        plantscan_manager.register(mod, name="typo")
    assert not plantscan_manager.pm.is_registered(mod)


def test_register_use_unregister_in_process(plantscan_manager):
    mod = _plugin_module("_plantscan_test_inproc", "inproc")
    plantscan_manager.register(mod, name="inproc")
    try:
        seg = plantscan_manager.build("segmenter", "inproc", {"threshold": 5})
        import numpy as np

        img = np.zeros((2, 2, 3), np.uint8)
        img[0, 0] = 9
        assert seg.segment(img, None).tolist() == [[True, False], [False, False]]
    finally:
        plantscan_manager.unregister(mod)
    with pytest.raises(PluginError, match="no segmenter plugin named 'inproc'"):
        plantscan_manager.registry.get("segmenter", "inproc")


def test_non_stage_class_is_rejected(plantscan_manager):
    mod = types.ModuleType("bad")

    @hookimpl
    def plantscan_register_stages(registry):
        registry.add(dict)

    mod.plantscan_register_stages = plantscan_register_stages
    with pytest.raises(PluginError, match="not a subclass of a plantscan stage"):
        plantscan_manager.register(mod, name="bad")


def test_installed_entry_points_match_pyproject():
    declared = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["entry-points"]
    declared = declared["plantscan"]
    installed = {ep.name: ep.value for ep in md.entry_points(group="plantscan")
                 if ep.dist is not None and ep.dist.name == "plantscan"}
    assert installed == declared, "reinstall (pip install -e .) after editing pyproject.toml"
    for name, value in declared.items():
        package = value.split(".")[0]
        assert (ROOT / "plugins" / package).is_dir(), f"entry point {name}: no plugins/{package}"


def test_every_default_plugin_loads():
    manager = plugins.load_plugins(strict=False)
    assert manager.failed == [], [f.error for f in manager.failed]


def test_a_mesher_written_before_the_views_were_passed_still_runs():
    """Meshers now receive the carving views (the cone over the pot no view carves); a
    lab's mesher with the older ``mesh(self, volume)`` must keep working unchanged."""
    from plantscan_core.steps import call_mesher

    class Old:
        def mesh(self, volume):
            return ("old", volume)

    class New:
        def mesh(self, volume, views=None):
            return ("new", volume, views)

    assert call_mesher(Old(), "vol", "views") == ("old", "vol")
    assert call_mesher(New(), "vol", "views") == ("new", "vol", "views")
