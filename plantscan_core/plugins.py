"""Plugin manager: entry points, isolation of broken plugins, the stage registry."""

from __future__ import annotations

import contextlib
import importlib.metadata as md
import os
import sys
import traceback
from dataclasses import dataclass, field
from functools import cache
from pathlib import Path
from typing import Any

import pluggy

from plantscan_core import hookspecs
from plantscan_core.errors import PluginError
from plantscan_core.stages import ACQUISITION_BASES, Stage
from plantscan_core.steps import CORE_TABLE, StageTable, Step

ENTRY_POINT_GROUP = "plantscan"
STRICT_ENV = "PLANTSCAN_STRICT_PLUGINS"


@dataclass(frozen=True)
class Registration:
    """One registered stage implementation and where it came from."""

    stage: str
    name: str
    cls: type[Stage]
    plugin: str
    distribution: str
    version: str


@dataclass(frozen=True)
class FailedPlugin:
    """An entry point that could not be loaded or registered."""

    name: str
    value: str
    distribution: str
    error: str


@cache
def _module_distributions() -> dict[str, tuple[str, str]]:
    """Top-level import package -> (distribution, version), from installed metadata."""
    out: dict[str, tuple[str, str]] = {}
    for packages, dists in md.packages_distributions().items():
        for dist in dists:
            try:
                out.setdefault(packages, (dist, md.version(dist)))
            except md.PackageNotFoundError:
                continue
    return out


def distribution_of_module(module: str) -> tuple[str, str] | None:
    """(distribution, version) that provides ``module``, or None (e.g. a test file)."""
    return _module_distributions().get(module.split(".")[0])


class StageRegistry:
    """(stage kind, name) -> implementation, and the stage table.

    Passed to ``plantscan_register_stages``.  ``steps`` starts as the core's
    table (``plantscan_core.steps.CORE_TABLE``); ``add_step`` lets a plugin add
    a step of its own, which recipes may then name.
    """

    def __init__(self) -> None:
        self._items: dict[tuple[str, str], Registration] = {}
        self.steps: StageTable = CORE_TABLE.copy()
        self._step_plugins: dict[str, str] = {}
        self._current_plugin = "<in-process>"
        self._current_dist = "<in-process>"

    @property
    def bases(self) -> dict[str, type[Stage]]:
        """Stage kind -> base: acquisition's, then the stage table's, in pipeline order."""
        return {**{b.stage: b for b in ACQUISITION_BASES}, **self.steps.bases}

    def add_step(self, step: Step, after: str | None = None) -> None:
        """Add a processing step to the table, after the section ``after`` (default: last
        before the exporters); removed with the plugin that added it."""
        try:
            self.steps.add(step, after)
        except ValueError as exc:
            raise PluginError(f"plugin {self._current_plugin!r}: {exc}") from None
        self._step_plugins[step.section] = self._current_plugin

    def add(self, cls: type[Stage]) -> None:
        """Register ``cls`` under ``(cls.stage, cls.name)``."""
        bases = self.bases
        if not (isinstance(cls, type) and issubclass(cls, Stage)) or cls.stage not in bases:
            raise PluginError(
                f"plugin {self._current_plugin!r}: {cls!r} is not a subclass of a plantscan stage "
                f"base ({', '.join(b.__name__ for b in bases.values())})"
            )
        if not cls.name:
            raise PluginError(f"plugin {self._current_plugin!r}: {cls.__name__} has no 'name'")
        key = (cls.stage, cls.name)
        if key in self._items:
            other = self._items[key]
            raise PluginError(
                f"duplicate {cls.stage} {cls.name!r}: registered by {other.distribution} "
                f"(plugin {other.plugin}, {other.cls.__module__}.{other.cls.__qualname__}) and by "
                f"{self._current_dist} (plugin {self._current_plugin}, "
                f"{cls.__module__}.{cls.__qualname__})"
            )
        self._items[key] = Registration(cls.stage, cls.name, cls, self._current_plugin,
                                        self._current_dist, cls.version())

    def remove(self, stage: str, name: str) -> None:
        self._items.pop((stage, name), None)

    def remove_plugin(self, plugin: str, keys: set[tuple[str, str]] | None = None) -> None:
        """Forget what ``plugin`` registered (only ``keys`` when given) and the steps it added."""
        for key, reg in list(self._items.items()):
            if reg.plugin == plugin and (keys is None or key in keys):
                del self._items[key]
        for section, owner in list(self._step_plugins.items()):
            if owner == plugin:
                self.steps.remove(section)
                del self._step_plugins[section]

    def get(self, stage: str, name: str) -> Registration:
        """The registration of ``name`` for ``stage``; PluginError listing the available ones."""
        try:
            return self._items[(stage, name)]
        except KeyError:
            avail = self.names(stage)
            raise PluginError(
                f"no {stage} plugin named {name!r}; available: "
                f"{', '.join(avail) if avail else '(none installed)'}"
            ) from None

    def names(self, stage: str) -> list[str]:
        return sorted(n for (s, n) in self._items if s == stage)

    def __iter__(self):
        order = list(self.bases)
        return iter(sorted(self._items.values(),
                           key=lambda r: (order.index(r.stage) if r.stage in order else len(order),
                                          r.name)))

    def __contains__(self, key: tuple[str, str]) -> bool:
        return key in self._items


@dataclass
class PluginManager:
    """pluggy manager plus the registry and the list of plugins that failed."""

    pm: pluggy.PluginManager
    registry: StageRegistry = field(default_factory=StageRegistry)
    failed: list[FailedPlugin] = field(default_factory=list)
    loaded: list[tuple[str, str, str]] = field(default_factory=list)

    # typed wrappers around hook calls -------------------------------------------------
    def register(self, plugin: Any, name: str | None = None, distribution: str = "<in-process>"):
        """Register a plugin module/object and the stages it adds; undo on error."""
        plugin_name = name or getattr(plugin, "__name__", repr(plugin))
        self.pm.register(plugin, name=plugin_name)
        before = set(self.registry._items)
        self.registry._current_plugin, self.registry._current_dist = plugin_name, distribution
        try:
            impl = getattr(plugin, "plantscan_register_stages", None)
            if impl is not None:
                impl(registry=self.registry)
            self.pm.check_pending()
        except BaseException:
            self.registry.remove_plugin(plugin_name, set(self.registry._items) - before)
            self.pm.unregister(plugin)
            raise
        finally:
            self.registry._current_plugin = self.registry._current_dist = "<in-process>"
        self.loaded.append((plugin_name, distribution, _dist_version(distribution)))
        return plugin

    def unregister(self, plugin: Any) -> None:
        """Remove a plugin and every stage it registered."""
        name = self.pm.get_name(plugin)
        self.registry.remove_plugin(name)
        self.loaded = [x for x in self.loaded if x[0] != name]
        self.pm.unregister(plugin)

    def before_stage(self, stage: str, plugin: Stage, context) -> None:
        self.pm.hook.plantscan_before_stage(stage=stage, plugin=plugin, context=context)

    def after_stage(self, stage: str, plugin: Stage, context, seconds: float, cached: bool):
        self.pm.hook.plantscan_after_stage(stage=stage, plugin=plugin, context=context,
                                           seconds=seconds, cached=cached)

    def on_stage_error(self, stage: str, plugin: Stage, context, error: BaseException) -> None:
        self.pm.hook.plantscan_on_stage_error(stage=stage, plugin=plugin, context=context,
                                              error=error)

    def evaluate(self, run_dir: Path, truth_dir: Path) -> dict[str, Any]:
        merged: dict[str, Any] = {}
        for part in self.pm.hook.plantscan_evaluate(run_dir=run_dir, truth_dir=truth_dir):
            if part:
                merged.update(part)
        return merged

    def warm_up(self, display: Any = None) -> list[tuple[str, str]]:
        """Each plugin's ``plantscan_warm_up``: (plugin name, what it did or its error).

        ``display``: a ``progress.Display`` that shows each plugin's warm-up as a step
        (compiling kernels takes a minute).
        """
        done = []
        for impl in self.pm.hook.plantscan_warm_up.get_hookimpls():
            step = (display.step(f"warm-up {impl.plugin_name}") if display is not None
                    else contextlib.nullcontext())
            try:
                with step:
                    said = impl.function()
            except Exception as exc:  # noqa: BLE001 - one plugin's failure is reported only
                said = "failed: " + "".join(traceback.format_exception_only(type(exc), exc))
            if said:
                done.append((impl.plugin_name, said.strip()))
        return done

    def add_commands(self, subparsers) -> None:
        """Let each plugin add CLI commands; one that fails is reported, the others still add."""
        for impl in self.pm.hook.plantscan_add_commands.get_hookimpls():
            try:
                impl.function(subparsers=subparsers)
            except Exception as exc:  # noqa: BLE001 - a broken plugin must not break the CLI
                detail = "".join(traceback.format_exception_only(type(exc), exc)).strip()
                self.failed.append(FailedPlugin(impl.plugin_name, "plantscan_add_commands",
                                                "", detail))
                print(f"plantscan: warning: plugin {impl.plugin_name!r} could not add its "
                      f"commands: {detail}", file=sys.stderr)

    def build(self, stage: str, name: str, params: dict[str, Any] | None = None, context=None):
        """Instantiate the ``stage`` plugin ``name`` with validated ``params``."""
        cls = self.registry.get(stage, name).cls
        return cls(cls.Params(**(params or {})), context)


def _dist_version(dist: str) -> str:
    try:
        return md.version(dist)
    except (md.PackageNotFoundError, ValueError):
        return ""


def new_manager() -> PluginManager:
    """An empty manager with the hookspecs added (no plugin loaded)."""
    pm = pluggy.PluginManager(hookspecs.PROJECT)
    pm.add_hookspecs(hookspecs)
    return PluginManager(pm)


def load_plugins(strict: bool | None = None) -> PluginManager:
    """Load every ``plantscan`` entry point, each in its own try/except.

    A plugin that fails to import or to register is recorded in ``failed`` and
    reported by ``plantscan plugins``; the others still load.  With
    ``PLANTSCAN_STRICT_PLUGINS=1`` (or ``strict=True``) the first failure raises.
    """
    if strict is None:
        strict = os.environ.get(STRICT_ENV, "") not in ("", "0", "false", "no")
    manager = new_manager()
    for ep in sorted(md.entry_points(group=ENTRY_POINT_GROUP), key=lambda e: e.name):
        dist = ep.dist.name if ep.dist is not None else "<unknown>"
        try:
            module = ep.load()
            manager.register(module, name=ep.name, distribution=dist)
        except Exception as exc:  # noqa: BLE001 - any failure of a plugin is isolated
            detail = "".join(traceback.format_exception_only(type(exc), exc)).strip()
            manager.failed.append(FailedPlugin(ep.name, ep.value, dist, detail))
            if strict:
                raise PluginError(
                    f"plugin {ep.name!r} ({ep.value}, from {dist}) failed to load: {detail}"
                ) from exc
    if manager.failed and not os.environ.get("PLANTSCAN_QUIET_PLUGINS"):
        names = ", ".join(f.name for f in manager.failed)
        print(f"plantscan: warning: {len(manager.failed)} plugin(s) failed to load ({names}); "
              "see `plantscan plugins`", file=sys.stderr)
    return manager


_default: PluginManager | None = None


def get_manager() -> PluginManager:
    """The process-wide manager, loaded on first use."""
    global _default
    if _default is None:
        _default = load_plugins()
    return _default
