"""Errors meant for the user: each message names the file, view, parameter or path."""

from __future__ import annotations


class PlantScanError(Exception):
    """Base of every error plantscan reports to a user (printed without a traceback)."""


class PluginError(PlantScanError):
    """A plugin failed to load, is missing, or registered a duplicate name."""


class RecipeError(PlantScanError):
    """A recipe is invalid.  ``errors`` holds every ``(path, message)`` found at once."""

    def __init__(self, errors: list[tuple[str, str]], source: str = "recipe") -> None:
        self.errors = list(errors)
        self.source = source
        lines = [f"{path}: {msg}" if path else msg for path, msg in self.errors]
        super().__init__(f"{source}: {len(self.errors)} error(s)\n" + "\n".join(lines))


class ScanFolderError(PlantScanError):
    """A scan folder is malformed, incomplete or not writable."""


class DataError(PlantScanError):
    """An input file (image, mask, calibration, mesh) is missing or unreadable."""


class StageError(PlantScanError):
    """A stage failed; the original exception is chained as ``__cause__``."""

    def __init__(self, stage: str, plugin: str, message: str) -> None:
        self.stage = stage
        self.plugin = plugin
        super().__init__(f"{stage} ({plugin}): {message}")


class HardwareError(PlantScanError):
    """A camera or motion axis could not do what was asked."""


def require_module(module: str, extra: str, what: str):
    """Import ``module`` (a hardware backend's library) or say which extra installs it.

    Hardware libraries are optional (``pip install 'plantscan[gphoto2]'``, ``[phidget]``,
    ``[serial]``, ``[all]``): a lab PC that only processes scans has none of them.

    Raises
    ------
    HardwareError
        naming ``what`` needs it and the ``pip install`` line that adds it.
    """
    import importlib

    try:
        return importlib.import_module(module)
    except ImportError as exc:
        raise HardwareError(
            f"{what}: the Python package {module.split('.')[0]!r} is not installed "
            f"({exc}); install it with: pip install 'plantscan[{extra}]'") from exc
