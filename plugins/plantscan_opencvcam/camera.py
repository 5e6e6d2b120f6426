"""Camera ``opencv``: USB webcams (UVC) through OpenCV's ``VideoCapture``, for low-cost rigs.

A webcam streams continuously and buffers a few frames, so the frame read
just after a turntable move may predate it.  Each capture therefore drops
``flush_frames`` frames before keeping one; after opening, ``warmup_frames``
let auto-exposure and white balance settle.  ``device`` is a camera index
(``0``), a device path (``/dev/video2``, ``/dev/v4l/by-id/...``), or anything
else ``VideoCapture`` opens (an image sequence ``frames/%03d.png``, a video
file, an RTSP/HTTP stream), which is how the tests drive it.
"""

from __future__ import annotations

import logging
import time
from pathlib import Path

from pydantic import Field

from plantscan_core.errors import HardwareError
from plantscan_core.stages import CameraBackend, CaptureRequest, StageParams

log = logging.getLogger(__name__)

BACKENDS = ("any", "v4l2", "gstreamer", "ffmpeg", "images", "dshow", "msmf", "avfoundation")


class OpenCVCamParams(StageParams):
    """Recipe parameters of an ``opencv`` camera."""

    device: int | str = 0
    backend: str = Field(default="any", description=f"one of {', '.join(BACKENDS)}")
    fourcc: str | None = Field(default=None, description="e.g. MJPG: lets USB2 webcams reach "
                               "full resolution at usable frame rates")
    set_size: bool = True
    warmup_frames: int = Field(default=10, ge=0)
    flush_frames: int = Field(default=3, ge=0)
    properties: dict[str, float] = Field(
        default_factory=dict,
        description="CAP_PROP_* name (without the prefix) -> value, e.g. {AUTOFOCUS: 0, FOCUS: "
                    "40, AUTO_EXPOSURE: 1, EXPOSURE: 156}")
    jpeg_quality: int = Field(default=95, ge=1, le=100)
    retries: int = Field(default=2, ge=0)
    # Timing model (plantscan scan --dry-run)
    capture_s: float = Field(default=0.3, ge=0.0)
    download_s: float = Field(default=0.0, ge=0.0)


class OpenCVCamera(CameraBackend):
    """A webcam or any ``cv2.VideoCapture`` source (``plugin: opencv``)."""

    name = "opencv"
    Params = OpenCVCamParams

    def __init__(self, params=None, context=None):
        super().__init__(params, context)
        if self.params.backend not in BACKENDS:
            raise ValueError(f"backend {self.params.backend!r}: valid: {', '.join(BACKENDS)}")
        self.cap = None
        self.frames_read = 0

    @property
    def label(self) -> str:
        who = getattr(self, "camera_name", None) or "opencv"
        return f"camera {who!r} (device {self.params.device!r})"

    def _backend_id(self) -> int:
        import cv2

        return {"any": cv2.CAP_ANY, "v4l2": cv2.CAP_V4L2, "gstreamer": cv2.CAP_GSTREAMER,
                "ffmpeg": cv2.CAP_FFMPEG, "images": cv2.CAP_IMAGES, "dshow": cv2.CAP_DSHOW,
                "msmf": cv2.CAP_MSMF, "avfoundation": cv2.CAP_AVFOUNDATION}[self.params.backend]

    def open(self, size: tuple[int, int] | None = None) -> None:
        import cv2

        p = self.params
        if size is None and self.context.recipe is not None:
            size = tuple(self.context.recipe.scan.image_size)
        cap = cv2.VideoCapture(p.device, self._backend_id())
        if not cap.isOpened():
            hint = ""
            if isinstance(p.device, int) or str(p.device).startswith("/dev/video"):
                hint = ("; check it is plugged in (`v4l2-ctl --list-devices`), that this user is "
                        "in the 'video' group, and that no other program (a browser, cheese, "
                        "another scan) is using it")
            raise HardwareError(f"{self.label}: cannot open the video device{hint}")
        if p.fourcc:
            cap.set(cv2.CAP_PROP_FOURCC, cv2.VideoWriter_fourcc(*p.fourcc[:4].ljust(4)))
        if p.set_size and size is not None:
            cap.set(cv2.CAP_PROP_FRAME_WIDTH, size[0])
            cap.set(cv2.CAP_PROP_FRAME_HEIGHT, size[1])
        for prop, value in p.properties.items():
            key = f"CAP_PROP_{prop.upper()}"
            if not hasattr(cv2, key):
                cap.release()
                raise HardwareError(f"{self.label}: params.properties.{prop}: no OpenCV property "
                                    f"{key}")
            if not cap.set(getattr(cv2, key), float(value)):
                log.warning("%s: the device ignored %s = %s", self.label, key, value)
        self.cap = cap
        for _ in range(p.warmup_frames):
            self._read_frame(keep=False)

    def close(self) -> None:
        if self.cap is not None:
            self.cap.release()
            self.cap = None

    def _read_frame(self, keep: bool = True):
        ok, frame = self.cap.read() if keep else (self.cap.grab(), None)
        if ok:
            self.frames_read += 1
        return ok, frame

    def capture(self, request: CaptureRequest) -> Path:
        import cv2

        size = tuple(request.image_size)
        if self.cap is None:
            self.open(size)
        frame = None
        for attempt in range(self.params.retries + 1):
            for _ in range(self.params.flush_frames):
                self._read_frame(keep=False)  # frames buffered before the rig stopped
            ok, frame = self._read_frame()
            if ok and frame is not None:
                break
            if attempt < self.params.retries:
                log.warning("%s: no frame (attempt %d), reopening", self.label, attempt + 1)
                self.close()
                time.sleep(0.2 * (attempt + 1))
                self.open(size)
        else:
            raise HardwareError(f"{self.label}: no frame after {self.params.retries + 1} tries; "
                                "the device stopped streaming (unplugged, or USB bandwidth "
                                "exhausted by several webcams on one hub: try fourcc MJPG)")
        h, w = frame.shape[:2]
        if (w, h) != size:
            raise HardwareError(
                f"{self.label}: the device delivers {w}x{h} px frames but the recipe says "
                f"scan.image_size = [{size[0]}, {size[1]}]; set scan.image_size to a size the "
                "webcam supports (`v4l2-ctl --list-formats-ext`)")
        if frame.ndim == 2:
            frame = cv2.cvtColor(frame, cv2.COLOR_GRAY2BGR)
        params = [cv2.IMWRITE_JPEG_QUALITY, self.params.jpeg_quality] if (
            request.image_format == "jpg") else []
        if not cv2.imwrite(str(request.out_path), frame, params):
            raise HardwareError(f"{self.label}: cannot write {request.out_path}")
        return request.out_path
