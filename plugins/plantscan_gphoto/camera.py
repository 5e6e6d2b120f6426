"""Camera ``gphoto2``: tethered DSLRs and mirrorless cameras through libgphoto2.

python-gphoto2's wheel bundles libgphoto2, so nothing else is installed.  The
module ``gphoto2`` is imported only when a camera is opened: libgphoto2's
virtual camera (used by the tests) is selected by the environment variable
``VCAMERADIR``, which python-gphoto2 reads at import time.

Two-phase capture: ``trigger`` releases the shutter and returns once the image
is in the camera; the callable it returns downloads it, so the orchestrator
overlaps the download with the next turntable move.
"""

from __future__ import annotations

import logging
import struct
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any, Literal

from pydantic import Field

from plantscan_core.errors import HardwareError, require_module
from plantscan_core.stages import CameraBackend, CaptureRequest, StageParams

log = logging.getLogger(__name__)

# libgphoto2 result codes that mean "try again in a moment".
GP_ERROR_TIMEOUT = -10
GP_ERROR_IO_USB_CLAIM = -53
GP_ERROR_IO_LOCK = -60
GP_ERROR_CAMERA_BUSY = -110
TRANSIENT = {GP_ERROR_TIMEOUT, GP_ERROR_IO_USB_CLAIM, GP_ERROR_IO_LOCK, GP_ERROR_CAMERA_BUSY}
GP_ERROR_IO = -7
GP_ERROR_IO_USB_FIND = -52
GP_ERROR_MODEL_NOT_FOUND = -105
RECONNECTABLE = {GP_ERROR_IO, GP_ERROR_IO_USB_FIND}  # the camera was reset or re-enumerated

HINTS = {
    GP_ERROR_IO_USB_CLAIM: (
        "another program holds the camera's USB device. On Linux desktops the gvfs "
        "gphoto2 volume monitor grabs cameras as they are plugged in: run "
        "`gio mount -s gphoto2` (or stop gvfs-gphoto2-volume-monitor), close Shotwell/"
        "digiKam/darktable/gphoto2, then retry"
    ),
    GP_ERROR_IO_LOCK: "another process has locked the port; close other camera programs",
    GP_ERROR_CAMERA_BUSY: (
        "the camera stays busy: check it is not writing a long burst, its card is not full, "
        "and it is in PC/PTP mode with auto power-off disabled"
    ),
    GP_ERROR_TIMEOUT: (
        "the camera does not answer: check the USB cable and hub, disable auto power-off, "
        "and that autofocus can lock (switch the lens to MF on a turntable rig)"
    ),
    GP_ERROR_IO: (
        "USB I/O failed: check permissions (install libgphoto2's udev rules or add the user "
        "to the plugdev group, see docs/hardware/gphoto2.md) and the cable"
    ),
    GP_ERROR_IO_USB_FIND: "the camera is not on the USB bus any more (unplugged or powered off)",
    GP_ERROR_MODEL_NOT_FOUND: "no camera of that model is connected",
}

SETTING_ALIASES = {
    # recipe field -> libgphoto2 config names to try, most common first
    "iso": ("iso", "isospeed"),
    "shutter_speed": ("shutterspeed", "shutterspeed2", "exposuretime"),
    "aperture": ("aperture", "f-number", "fnumber"),
    "image_format": ("imageformat", "imagequality", "imagesize"),
    "capture_target": ("capturetarget",),
}


class GPhotoParams(StageParams):
    """Recipe parameters of a ``gphoto2`` camera.

    Select the device by ``port`` (``usb:001,004``), ``serial`` or ``model``
    (substring, case-insensitive); with none given exactly one camera must be
    connected.  Settings are libgphoto2 config values as ``gphoto2
    --get-config NAME`` lists them (``"200"``, ``"1/60"``, ``"8"``,
    ``"Large Fine JPEG"``).
    """

    model: str | None = None
    port: str | None = None
    serial: str | None = None
    iso: str | None = None
    shutter_speed: str | None = None
    aperture: str | None = None
    image_format: str | None = None
    capture_target: Literal["ram", "card"] | None = "ram"
    settings: dict[str, str] = Field(default_factory=dict)
    keep_on_camera: bool = False
    check_image_size: bool = True
    retries: int = Field(default=6, ge=0, le=100)
    retry_backoff_s: float = Field(default=0.5, ge=0.0)
    # Timing model (plantscan scan --dry-run): shutter release to image in camera (focus
    # locked, ~1/60 s exposure, card/RAM write) and download of an 18 MP JPEG over USB 2.
    capture_s: float = Field(default=1.0, ge=0.0)
    download_s: float = Field(default=1.0, ge=0.0)


class GPhotoError(HardwareError):
    """A libgphoto2 call failed; ``code`` is libgphoto2's result code."""

    def __init__(self, message: str, code: int | None = None) -> None:
        self.code = code
        super().__init__(message)


_claimed_ports: set[str] = set()
_claimed_lock = threading.Lock()


def _gp():
    return require_module("gphoto2", "gphoto2", "camera plugin gphoto2")


def jpeg_size(data: bytes) -> tuple[int, int] | None:
    """(width, height) from a JPEG's SOF header, or None if not a JPEG."""
    if data[:2] != b"\xff\xd8":
        return None
    i = 2
    while i + 9 < len(data):
        if data[i] != 0xFF:
            i += 1
            continue
        marker = data[i + 1]
        if marker in (0xD8, 0x01) or 0xD0 <= marker <= 0xD7 or marker == 0xFF:
            i += 1 if marker == 0xFF else 2
            continue
        (length,) = struct.unpack(">H", data[i + 2:i + 4])
        if marker in (0xC0, 0xC1, 0xC2, 0xC3, 0xC5, 0xC6, 0xC7, 0xC9, 0xCA, 0xCB, 0xCD, 0xCE,
                      0xCF):
            h, w = struct.unpack(">HH", data[i + 5:i + 9])
            return (w, h)
        i += 2 + length
    return None


class GPhotoCamera(CameraBackend):
    """A tethered camera driven by libgphoto2 (``plugin: gphoto2``)."""

    name = "gphoto2"
    Params = GPhotoParams

    def __init__(self, params=None, context=None):
        super().__init__(params, context)
        self._cam: Any = None
        self._ctx: Any = None
        self._port: str | None = None
        self.retries_used = 0  # transient errors retried during this scan (reported in tests)

    # ------------------------------------------------------------------ naming
    @property
    def label(self) -> str:
        who = getattr(self, "camera_name", None) or "gphoto2"
        return f"camera {who!r}" + (f" ({self._port})" if self._port else "")

    # ------------------------------------------------------------------ retries
    def _call(self, what: str, fn: Callable, *args):
        """Call libgphoto2, retrying transient errors with exponential back-off."""
        gp = _gp()
        delay = self.params.retry_backoff_s
        for attempt in range(self.params.retries + 1):
            try:
                return fn(*args)
            except gp.GPhoto2Error as exc:
                if exc.code not in TRANSIENT or attempt == self.params.retries:
                    hint = HINTS.get(exc.code, "")
                    extra = (f" after {attempt + 1} tries" if exc.code in TRANSIENT else "")
                    raise GPhotoError(
                        f"{self.label}: {what} failed{extra}: libgphoto2 error {exc.code} "
                        f"({exc.string})" + (f"; {hint}" if hint else ""), exc.code
                    ) from exc
                self.retries_used += 1
                log.warning("%s: %s: %s, retrying in %.2f s", self.label, what, exc, delay)
                time.sleep(delay)
                delay = min(delay * 2, 10.0)
        raise AssertionError("unreachable")

    # ------------------------------------------------------------------ connection
    def _connect(self):
        """Find the camera the params select; return it initialised, with its port."""
        p = self.params
        detected = self._detect()
        if not detected:
            raise GPhotoError(
                f"{self.label}: no camera detected; check it is on, in PC/PTP mode and connected, "
                "and that this user may access USB cameras (docs/hardware/gphoto2.md)",
                GP_ERROR_IO_USB_FIND,
            )
        candidates = detected
        if p.port:
            candidates = [d for d in candidates if d[1] == p.port]
        if p.model:
            candidates = [d for d in candidates if p.model.lower() in d[0].lower()]
        with _claimed_lock:
            free = [d for d in candidates if d[1] not in _claimed_ports]
        if not free:
            raise GPhotoError(
                f"{self.label}: no connected camera matches "
                f"{_selector(p)} (connected: {_list(detected)})"
            )
        if p.serial is None and p.port is None and len(free) > 1:
            # Taking "the first" would swap the rig's cameras between scans.
            raise GPhotoError(
                f"{self.label}: {len(free)} connected cameras match ({_list(free)}); set "
                "params.serial (see `plantscan gphoto2-cameras`) to say which one this is"
            )
        for model, port in free:
            cam = self._open_port(model, port)
            if p.serial is None or self._serial_of(cam) == p.serial:
                return cam, port
            self._call("exit", cam.exit)
        raise GPhotoError(
            f"{self.label}: no connected camera has serial number {p.serial!r} "
            f"(connected: {_list(free)})"
        )

    def _detect(self) -> list[tuple[str, str]]:
        """(model, port) of every connected camera."""
        gp = _gp()
        return [(str(m), str(port)) for m, port in self._call("autodetect", gp.Camera.autodetect)]

    def _new_camera(self):
        """A fresh ``gphoto2.Camera`` (tests wrap it to inject faults)."""
        return _gp().Camera()

    def _open_port(self, model: str, port: str):
        gp = _gp()
        cam = self._new_camera()
        ports = gp.PortInfoList()
        ports.load()
        cam.set_port_info(ports[ports.lookup_path(port)])
        abilities = gp.CameraAbilitiesList()
        abilities.load()
        cam.set_abilities(abilities[abilities.lookup_model(model)])
        self._port = port
        self._call("connect (init)", cam.init)
        return cam

    def _serial_of(self, cam) -> str | None:
        try:
            cfg = cam.get_config()
            return str(cfg.get_child_by_name("serialnumber").get_value())
        except Exception:  # noqa: BLE001 - a camera without the setting has no serial to match
            text = str(cam.get_summary())
            for line in text.splitlines():
                if "serial number" in line.lower():
                    return line.split(":", 1)[1].strip()
        return None

    def open(self) -> None:
        self._cam, port = self._connect()
        with _claimed_lock:
            _claimed_ports.add(port)
        self._port = port
        self._apply_settings()

    def close(self) -> None:
        if self._cam is not None:
            try:
                self._cam.exit()
            except Exception:  # noqa: BLE001 - releasing must not hide the scan's own error
                pass
            self._cam = None
        with _claimed_lock:
            _claimed_ports.discard(self._port or "")

    # ------------------------------------------------------------------ settings
    def requested_settings(self) -> dict[str, str]:
        """Config name (or alias) -> value asked for by the recipe, in application order."""
        p = self.params
        out: dict[str, str] = {}
        if p.capture_target is not None:
            out["capture_target"] = p.capture_target
        for field in ("iso", "shutter_speed", "aperture", "image_format"):
            if getattr(p, field) is not None:
                out[field] = str(getattr(p, field))
        out.update(p.settings)
        return out

    def _apply_settings(self) -> None:
        wanted = self.requested_settings()
        if not wanted:
            return
        gp = _gp()
        config = self._call("read settings", self._cam.get_config)
        available = _widget_names(config)
        changed = False
        for key, value in wanted.items():
            names = SETTING_ALIASES.get(key, (key,))
            name = next((n for n in names if n in available), None)
            if name is None:
                if key == "capture_target":  # cameras without it write to RAM anyway
                    continue
                where = key if key in SETTING_ALIASES else f"settings.{key}"
                raise GPhotoError(
                    f"{self.label}: setting {key!r} (params.{where}) is not offered by this "
                    f"camera; it offers: {', '.join(sorted(available))}"
                )
            widget = config.get_child_by_name(name)
            if key == "capture_target":
                value = _capture_target_choice(widget, value)
            if widget.get_type() in (gp.GP_WIDGET_RADIO, gp.GP_WIDGET_MENU):
                choices = [str(c) for c in widget.get_choices()]
                if value not in choices:
                    raise GPhotoError(
                        f"{self.label}: params.{key} = {value!r} is not a valid {name!r}; "
                        f"valid: {', '.join(choices)}"
                    )
            try:
                widget.set_value(_typed(widget, value, gp))
            except (gp.GPhoto2Error, ValueError, TypeError) as exc:
                raise GPhotoError(f"{self.label}: cannot set {name!r} to {value!r}: {exc}") from exc
            changed = True
        if changed:
            self._call("write settings", self._cam.set_config, config)

    # ------------------------------------------------------------------ capture
    def trigger(self, request: CaptureRequest) -> Callable[[], Path]:
        """Release the shutter; return the callable that downloads the image to ``out_path``."""
        gp = _gp()
        if self._cam is None:
            self.open()
        where = self._capture_reconnecting(gp)
        folder, name = str(where.folder), str(where.name)
        return lambda: self._download(request, folder, name)

    def capture(self, request: CaptureRequest) -> Path:
        return self.trigger(request)()

    def _capture_reconnecting(self, gp):
        """Release the shutter; if the camera fell off the bus (USB reset), reconnect and retry.

        Only the shutter release is retried this way: an image not yet downloaded is lost
        with the connection, and its view is captured again on --resume.
        """
        for attempt in range(self.params.retries + 1):
            try:
                if self._cam is None:
                    self.open()
                return self._call("capture", self._cam.capture, gp.GP_CAPTURE_IMAGE)
            except GPhotoError as exc:
                if exc.code not in RECONNECTABLE or attempt == self.params.retries:
                    raise
                log.warning("%s: %s; reconnecting", self.label, exc)
                self.retries_used += 1
                self.close()
                time.sleep(self.params.retry_backoff_s * (attempt + 1))
        raise AssertionError("unreachable")

    def _download(self, request: CaptureRequest, folder: str, name: str) -> Path:
        gp = _gp()
        cfile = self._call(f"download {folder}/{name}", self._cam.file_get, folder, name,
                           gp.GP_FILE_TYPE_NORMAL)
        data = bytes(memoryview(cfile.get_data_and_size()))
        if not self.params.keep_on_camera:
            try:
                self._cam.file_delete(folder, name)
            except gp.GPhoto2Error:  # RAM captures may already be gone
                pass
        self._write(request, data, name)
        return request.out_path

    def _write(self, request: CaptureRequest, data: bytes, name: str) -> None:
        size = jpeg_size(data)
        if size is None:
            raise GPhotoError(
                f"{self.label}: the camera delivered {name!r}, not a JPEG; set the camera's "
                "image format to JPEG (params.image_format) — RAW files are not supported"
            )
        want = tuple(request.image_size)
        if self.params.check_image_size and size != want:
            raise GPhotoError(
                f"{self.label}: the camera delivers {size[0]}x{size[1]} px images but the recipe "
                f"says scan.image_size = [{want[0]}, {want[1]}]; set scan.image_size to the "
                "camera's size (or params.check_image_size: false)"
            )
        if request.image_format == "jpg":
            Path(request.out_path).write_bytes(data)  # as delivered: no second compression
            return
        import cv2
        import numpy as np

        img = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_COLOR)
        if img is None:
            raise GPhotoError(f"{self.label}: {name!r} from the camera does not decode")
        if not cv2.imwrite(str(request.out_path), img):
            raise GPhotoError(f"{self.label}: cannot write {request.out_path}")


def _selector(p: GPhotoParams) -> str:
    parts = [f"{k}={getattr(p, k)!r}" for k in ("model", "port", "serial") if getattr(p, k)]
    return ", ".join(parts) or "any camera (all already in use by other rig cameras)"


def _list(detected: list[tuple[str, str]]) -> str:
    return "; ".join(f"{m} on {port}" for m, port in detected) or "none"


def _widget_names(widget) -> set[str]:
    names = set()
    for i in range(widget.count_children()):
        child = widget.get_child(i)
        names.add(str(child.get_name()))
        names |= _widget_names(child)
    return names


def _capture_target_choice(widget, value: str) -> str:
    choices = [str(c) for c in widget.get_choices()]
    if value == "ram":
        want = [c for c in choices if "ram" in c.lower() or "sdram" in c.lower()]
    else:
        want = [c for c in choices if "card" in c.lower()]
    return want[0] if want else value


def _typed(widget, value: str, gp) -> Any:
    t = widget.get_type()
    if t == gp.GP_WIDGET_TOGGLE:
        return int(value in ("1", "true", "True", "on"))
    if t == gp.GP_WIDGET_RANGE:
        return float(value)
    return value


# --------------------------------------------------------------------------- CLI
def list_cameras(show_config: bool = False, out=None) -> int:
    """Print every camera libgphoto2 detects: model, port, serial (and its settings).

    Backs ``plantscan gphoto2-cameras``: the values to put in a recipe's
    ``params.port`` / ``params.serial`` and the spelling of each setting's choices.
    """
    import sys

    out = out or sys.stdout
    gp = _gp()
    detected = [(str(m), str(p)) for m, p in gp.Camera.autodetect()]
    if not detected:
        print("no camera detected (on, PC/PTP mode, cable, permissions: "
              "docs/hardware/gphoto2.md)", file=out)
        return 1
    for model, port in detected:
        cam = GPhotoCamera(GPhotoParams(port=port, model=model, capture_target=None))
        try:
            handle = cam._open_port(model, port)
        except GPhotoError as exc:
            print(f"{model} on {port}: cannot open: {exc}", file=out)
            continue
        try:
            print(f"{model} on {port}: serial {cam._serial_of(handle)}", file=out)
            if show_config:
                for line in _config_lines(handle.get_config(), gp):
                    print(f"  {line}", file=out)
        finally:
            handle.exit()
    return 0


def _config_lines(widget, gp, prefix: str = "") -> list[str]:
    lines = []
    for i in range(widget.count_children()):
        child = widget.get_child(i)
        name = str(child.get_name())
        if child.get_type() in (gp.GP_WIDGET_SECTION, gp.GP_WIDGET_WINDOW):
            lines += _config_lines(child, gp, prefix)
            continue
        try:
            value = child.get_value()
        except gp.GPhoto2Error:
            value = "?"
        line = f"{name} = {value}"
        if child.get_type() in (gp.GP_WIDGET_RADIO, gp.GP_WIDGET_MENU):
            line += f"  [{', '.join(str(c) for c in child.get_choices())}]"
        if child.get_readonly():
            line += "  (read-only)"
        lines.append(line)
    return lines
