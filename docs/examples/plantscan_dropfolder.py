"""A complete plantscan camera plugin in one file: the "drop-folder" camera.

Many lab cameras come with their own tethering software that saves every
photo into a folder.  This camera takes the next new image file that appears
in that folder as the photo of the current view.

Publish it from your own distribution with five lines of pyproject.toml::

    [project]
    name = "plantscan-dropfolder"
    version = "1.0.0"
    [project.entry-points.plantscan]
    dropfolder = "plantscan_dropfolder"

and use it in a recipe::

    scan:
      cameras:
        - {name: cam0, plugin: dropfolder, params: {folder: /data/tether/cam0}}
"""

from __future__ import annotations

import shutil
import time
from pathlib import Path

from pydantic import Field

from plantscan_core.errors import HardwareError
from plantscan_core.hookspecs import hookimpl
from plantscan_core.stages import CameraBackend, CaptureRequest, StageParams


class DropFolderCamera(CameraBackend):
    """Takes the next image file that the camera's own software writes into ``folder``."""

    name = "dropfolder"

    class Params(StageParams):
        folder: Path
        pattern: str = "*.jpg"
        timeout_s: float = Field(default=30.0, gt=0)

    def open(self) -> None:
        if not self.params.folder.is_dir():
            raise HardwareError(f"dropfolder: {self.params.folder} is not a folder")
        self._seen = {p.name for p in self.params.folder.glob(self.params.pattern)}

    def capture(self, request: CaptureRequest) -> Path:
        deadline = time.monotonic() + self.params.timeout_s
        while time.monotonic() < deadline:
            new = sorted(p for p in self.params.folder.glob(self.params.pattern)
                         if p.name not in self._seen)
            if new:
                self._seen.add(new[0].name)
                shutil.copyfile(new[0], request.out_path)
                return request.out_path
            time.sleep(0.05)
        raise HardwareError(f"dropfolder: no new {self.params.pattern} in {self.params.folder} "
                            f"after {self.params.timeout_s:g} s (camera {request.camera})")


@hookimpl
def plantscan_register_stages(registry) -> None:
    registry.add(DropFolderCamera)
