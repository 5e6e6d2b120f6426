"""Run a scan with the ``gphoto2`` camera against libgphoto2's virtual camera.

Executed in a subprocess by ``test_gphoto.py``: python-gphoto2 chooses the
virtual USB layer at import time from ``VCAMERADIR``, so it must be set before
``gphoto2`` is imported.  Faults are injected at the libgphoto2 call level:
``GPHOTO_FAULTS`` (JSON) maps a ``gphoto2.Camera`` method name to the list of
libgphoto2 error codes its next calls raise, one per call (0: the real
virtual-camera call runs).

Usage: ``python gphoto_runner.py RECIPE_JSON OUT [resume]`` prints a JSON
summary (views, retries, error) on the last line; ``python gphoto_runner.py
--probe CASES_JSON`` opens the camera with each case's params, takes one image
of the case's size, and prints each case's error (or None).
"""

from __future__ import annotations

import json
import os
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

import gphoto2 as gp  # noqa: E402  (after VCAMERADIR, which the parent sets)
import hwfakes  # noqa: E402
from plantscan_gphoto import plugin as gphoto_plugin  # noqa: E402
from plantscan_gphoto.camera import GPhotoCamera  # noqa: E402
from plantscan_serial import plugin as serial_plugin  # noqa: E402

from plantscan_core.acquire import acquire  # noqa: E402
from plantscan_core.errors import PlantScanError  # noqa: E402
from plantscan_core.hookspecs import hookimpl  # noqa: E402
from plantscan_core.plugins import new_manager  # noqa: E402
from plantscan_core.recipe import validate_recipe  # noqa: E402

FAULTS: dict[str, list[int]] = json.loads(os.environ.get("GPHOTO_FAULTS", "{}"))
RETRIES: dict[int, int] = {}  # camera object -> transient errors it retried


class FaultyCamera:
    """A real ``gphoto2.Camera`` whose listed methods first raise the given error codes."""

    def __init__(self, cam):
        self._cam = cam

    def __getattr__(self, name):
        attr = getattr(self._cam, name)
        if name not in FAULTS or not callable(attr):
            return attr

        def call(*args, **kwargs):
            code = FAULTS[name].pop(0) if FAULTS[name] else 0
            if code:  # 0 lets the real call through
                raise gp.GPhoto2Error(code)
            return attr(*args, **kwargs)

        return call


class FaultyGPhotoCamera(GPhotoCamera):
    name = "gphoto2-faulty"

    def _new_camera(self):
        return FaultyCamera(super()._new_camera())

    def close(self):
        RETRIES[id(self)] = self.retries_used
        super().close()


class _FaultyPlugin:
    @staticmethod
    @hookimpl
    def plantscan_register_stages(registry):
        registry.add(FaultyGPhotoCamera)


def probe(cases_file: str) -> None:
    """Open a camera with each case's params and take one image; print ok/error per case."""
    from plantscan_core.stages import CaptureRequest

    results = []
    for i, case in enumerate(json.loads(Path(cases_file).read_text())):
        cam = GPhotoCamera(GPhotoCamera.Params(**case["params"]))
        cam.camera_name = f"probe{i}"
        try:
            cam.open()
            out = Path(cases_file).with_name(f"probe{i}.jpg")
            cam.capture(CaptureRequest(out, "plant", "cam0", 0, 0.0, 0, 0.0, None,
                                       tuple(case["size"]), "jpg"))
            config = cam._cam.get_config()  # read back from the (virtual) camera
            values = {n: str(config.get_child_by_name(n).get_value())
                      for n in case.get("read", [])}
            results.append({"error": None, "values": values})
        except PlantScanError as exc:
            results.append({"error": str(exc)})
        finally:
            cam.close()
    print(json.dumps(results))


def command(argv: list[str]) -> None:
    """Run the plugin's CLI sub-command as ``plantscan`` would (parser from the hook)."""
    import argparse

    parser = argparse.ArgumentParser(prog="plantscan")
    sub = parser.add_subparsers()
    gphoto_plugin.plantscan_add_commands(subparsers=sub)
    args = parser.parse_args(argv)
    sys.exit(args.func(args))


def main() -> None:
    if sys.argv[1] == "--probe":
        probe(sys.argv[2])
        return
    if sys.argv[1] == "--command":
        command(sys.argv[2:])
    raw = json.loads(Path(sys.argv[1]).read_text())
    out = Path(sys.argv[2])
    m = new_manager()
    m.register(hwfakes)
    m.register(gphoto_plugin, name="gphoto")
    m.register(serial_plugin, name="serial")
    m.register(_FaultyPlugin(), name="gphoto-faulty")
    recipe = validate_recipe(raw, m.registry)
    error = None
    try:
        acquire(recipe, out, m, raw_recipe=raw, resume=len(sys.argv) > 3)
    except PlantScanError as exc:
        error = {"type": type(exc).__name__, "message": str(exc)}
    views = [json.loads(line) for line in (out / "views.jsonl").read_text().splitlines()
             if line.strip()] if (out / "views.jsonl").exists() else []
    print(json.dumps({"views": views, "retries": sum(RETRIES.values()), "error": error}))


if __name__ == "__main__":
    main()
