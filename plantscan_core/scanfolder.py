"""The on-disk scan folder: what acquisition writes and processing reads.

::

    SCAN/
      scan.yaml          plant id, species, recipe, rig, time
      views.jsonl        one line per finished image, appended in capture order
      images/...         the photos
      ground_truth/...   only from the virtual scanner

An image line is appended to ``views.jsonl`` only after the image is
completely on disk (temporary name, fsync, rename), so an interrupted scan can
be resumed and never lists a half-written image.  A torn last line (a crash
during the append itself) is ignored on reading and overwritten on resume.
"""

from __future__ import annotations

import datetime as _dt
import json
import os
import tempfile
from collections.abc import Callable, Iterator
from pathlib import Path, PurePosixPath
from typing import Any, Literal

import numpy as np
import yaml
from pydantic import ConfigDict, Field, ValidationError

from plantscan_core.bounds import AngleDeg, CheckedModel, error_path
from plantscan_core.data import ROLES, ViewRecord
from plantscan_core.errors import DataError, ScanFolderError
from plantscan_core.userfiles import InputFileError, load_yaml, parse_json_line, read_bytes

SCAN_YAML = "scan.yaml"
VIEWS_JSONL = "views.jsonl"
PLANNED_VIEWS_JSONL = "planned_views.jsonl"
IMAGES_DIR = "images"
GROUND_TRUTH_DIR = "ground_truth"
FORMAT = "plantscan-scan/1"


class ViewLine(CheckedModel):
    """The checks on one line of ``views.jsonl`` (read into a ``ViewRecord``)."""

    model_config = ConfigDict(extra="ignore")  # lines of newer versions may carry more

    index: int = Field(ge=0, le=10_000_000)
    role: Literal[ROLES]  # type: ignore[valid-type]
    camera: str = Field(min_length=1, max_length=200)
    tilt_index: int = Field(ge=0, le=100_000)
    tilt_deg: float = Field(ge=-90.0, le=90.0)
    angle_index: int = Field(ge=0, le=10_000_000)
    commanded_angle_deg: AngleDeg
    measured_angle_deg: AngleDeg | None = None
    file: str = Field(min_length=1, max_length=4096)
    captured_at: str = ""


class PlannedStopLine(CheckedModel):
    """The checks on one planned stop of ``planned_views.jsonl``."""

    model_config = ConfigDict(extra="ignore")

    pan_deg: AngleDeg
    tilt_deg: float = Field(ge=-90.0, le=90.0)
    angle_index: int = Field(ge=0, le=10_000_000)
    gain_mm3: float = Field(0.0, ge=0.0)
    reason: str = Field("", max_length=10_000)


class PlannedRoundLine(CheckedModel):
    """The checks on one line (one planned round) of ``planned_views.jsonl``."""

    model_config = ConfigDict(extra="ignore")

    round: int = Field(ge=1, le=100_000)
    stops: list[PlannedStopLine] = Field(default_factory=list, max_length=100_000)
    planner: str = Field("", max_length=200)
    stop_reason: str | None = Field(None, max_length=10_000)
    figures: dict[str, Any] = Field(default_factory=dict)
    created: str = ""


def _fsync_dir(path: Path) -> None:
    try:
        fd = os.open(path, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


_UMASK = _umask()


def atomic_write_bytes(path: Path, data: bytes) -> None:
    """Write ``data`` to ``path`` via a temporary file, fsync and rename."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    # mkstemp makes 0600 files; results are for the whole lab to read, like any other file.
    os.chmod(tmp, 0o666 & ~_UMASK)
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(data)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    _fsync_dir(path.parent)


def atomic_write_text(path: Path, text: str) -> None:
    """Text version of ``atomic_write_bytes`` (UTF-8)."""
    atomic_write_bytes(path, text.encode("utf-8"))


def now_iso() -> str:
    return _dt.datetime.now(_dt.UTC).isoformat(timespec="seconds")


class ScanFolder:
    """A scan folder on disk.  Use ``ScanFolder.create`` or ``ScanFolder.open``."""

    def __init__(self, root: Path, info: dict[str, Any], views: list[ViewRecord]):
        self.root = Path(root)
        self.info = info
        self._views = views

    # ------------------------------------------------------------------ creation / opening
    @classmethod
    def create(cls, root: Path, info: dict[str, Any]) -> ScanFolder:
        """Start a new scan at ``root`` (must not already hold a scan)."""
        root = Path(root)
        if (root / SCAN_YAML).exists():
            raise ScanFolderError(
                f"{root}: already holds a scan; use --resume to continue it or choose another --out"
            )
        try:
            (root / IMAGES_DIR).mkdir(parents=True, exist_ok=True)
            probe = root / ".write-test"
            probe.write_bytes(b"")
            probe.unlink()
        except OSError as exc:
            raise ScanFolderError(f"{root}: cannot write the scan folder ({exc.strerror})") from exc
        info = {"format": FORMAT, "created": now_iso(), **info}
        atomic_write_text(root / SCAN_YAML, yaml.safe_dump(info, sort_keys=False))
        (root / VIEWS_JSONL).touch()
        return cls(root, info, [])

    @classmethod
    def open(cls, root: Path) -> ScanFolder:
        """Open an existing scan; malformed files raise ``ScanFolderError`` naming them."""
        root = Path(root)
        meta = root / SCAN_YAML
        if not root.is_dir():
            raise ScanFolderError(f"{root}: no such scan folder")
        if not meta.exists():
            raise ScanFolderError(f"{meta}: missing; {root} is not a plantscan scan folder")
        try:
            info = load_yaml(meta) or {}
        except InputFileError as exc:
            raise ScanFolderError(str(exc)) from None
        if not isinstance(info, dict):
            raise ScanFolderError(f"{meta}: must be a mapping")
        scan = cls(root, info, [])
        scan._views = scan._read_views()
        return scan

    def _read_views(self) -> list[ViewRecord]:
        """The manifest's views; a torn last line is left out (``torn_line`` says which)."""
        path = self.root / VIEWS_JSONL
        lines, self.torn_line = _checked_lines(path, ViewLine, "view line")
        views: list[ViewRecord] = []
        first_line: dict[tuple[str, Any], int] = {}
        for n, d in lines:
            view = ViewRecord.from_dict(d)
            self._check_relative(view.file, f"{path}:{n}")
            # Two lines for one index, protocol stop or file would both write masks/<index>.png
            # or count one image twice: refused, naming both lines.
            for what, value in (("index", view.index), ("view", view.key),
                                ("file", PurePosixPath(view.file).as_posix())):
                earlier = first_line.setdefault((what, value), n)
                if earlier != n:
                    raise ScanFolderError(
                        f"{path}:{n}: repeats the {what} {value!r} of line {earlier} (a copied "
                        "or merged manifest?); remove one of the two lines")
            views.append(view)
        return views

    # ------------------------------------------------------------------ reading
    @property
    def views(self) -> list[ViewRecord]:
        return list(self._views)

    def views_by_role(self, role: str) -> list[ViewRecord]:
        if role not in ROLES:
            raise ValueError(f"unknown role {role!r}; valid: {', '.join(ROLES)}")
        return [v for v in self._views if v.role == role]

    @property
    def ground_truth_dir(self) -> Path:
        return self.root / GROUND_TRUTH_DIR

    @property
    def recipe_dict(self) -> dict[str, Any]:
        return self.info.get("recipe") or {}

    def _check_relative(self, rel: str, where: str) -> PurePosixPath:
        p = PurePosixPath(rel)
        if p.is_absolute() or ".." in p.parts or not p.parts:
            raise ScanFolderError(f"{where}: image path {rel!r} escapes the scan folder")
        return p

    def path_of(self, view: ViewRecord) -> Path:
        """Absolute path of a view's image; rejects paths escaping the folder and missing files."""
        rel = self._check_relative(view.file, f"{self.root / VIEWS_JSONL} (view {view.index})")
        path = (self.root / rel).resolve()
        if not path.is_relative_to(self.root.resolve()):
            raise ScanFolderError(f"view {view.index}: image path {view.file!r} escapes the scan "
                                  "folder (through a link)")
        if not path.exists():
            raise DataError(f"{path}: image of view {view.index} ({view.role}, camera "
                            f"{view.camera}, tilt {view.tilt_index}, angle "
                            f"{view.commanded_angle_deg:g}) is missing")
        return path

    def read_image(self, view: ViewRecord, reduce: int = 1, grayscale: bool = False) -> np.ndarray:
        """Decode a view's image: ``(H, W, 3) uint8`` BGR, or ``(H, W)`` with ``grayscale``."""
        return read_image(self.path_of(view), reduce=reduce, grayscale=grayscale)

    # ------------------------------------------------------------------ writing
    def append_view(self, view: ViewRecord, write_image: Callable[[Path], Any]) -> ViewRecord:
        """Write one image atomically, then append its line to ``views.jsonl``.

        ``write_image(tmp_path)`` writes the image to a temporary path inside
        the folder; it is fsynced and renamed to ``view.file`` before the line
        is appended (and the line is fsynced too).
        """
        rel = self._check_relative(view.file, "new view")
        final = self.root / rel
        final.parent.mkdir(parents=True, exist_ok=True)
        tmp = final.with_name(f".{final.stem}.partial{final.suffix}")
        try:
            write_image(tmp)
            if not tmp.exists():
                raise DataError(f"{tmp}: the camera reported success but wrote no file")
            with open(tmp, "rb+") as f:
                os.fsync(f.fileno())
            os.replace(tmp, final)
            _fsync_dir(final.parent)
        finally:
            if tmp.exists():
                tmp.unlink()
        self._append_line(view)
        self._views.append(view)
        return view

    def _append_line(self, view: ViewRecord) -> None:
        _append_json_line(self.root / VIEWS_JSONL, view.to_dict())

    # ------------------------------------------------------------------ planned views
    def planned_rounds(self):
        """The rounds of planned plant stops (``planned_views.jsonl``) of an adaptive scan.

        A list of ``trajectory.PlannedRound`` in the order they were planned; a
        torn last line (a crash during the append) is left out.  Malformed lines
        raise ``ScanFolderError`` naming file and line.
        """
        from plantscan_core.trajectory import PlannedRound

        path = self.root / PLANNED_VIEWS_JSONL
        out = []
        for n, d in _checked_lines(path, PlannedRoundLine, "planned round")[0]:
            rnd = PlannedRound.from_dict(d)
            if rnd.round != len(out) + 1:
                raise ScanFolderError(f"{path}:{n}: round {rnd.round} where round "
                                      f"{len(out) + 1} was expected")
            out.append(rnd)
        return out

    def append_planned_round(self, planned_round) -> None:
        """Record a round of planned stops (a ``trajectory.PlannedRound``), fsynced.

        Written before any of its stops is captured, so a resumed scan captures the
        same stops instead of planning again.
        """
        _append_json_line(self.root / PLANNED_VIEWS_JSONL, planned_round.to_dict())

    def done_keys(self) -> set[tuple[str, str, int, int]]:
        """Keys (role, camera, tilt_index, angle_index) of the images already captured."""
        return {v.key for v in self._views}

    def __iter__(self) -> Iterator[ViewRecord]:
        return iter(self._views)

    def __repr__(self) -> str:
        return f"ScanFolder({str(self.root)!r}, {len(self._views)} views)"


def _checked_lines(path: Path, model: type[CheckedModel], what: str
                   ) -> tuple[list[tuple[int, dict[str, Any]]], int | None]:
    """The JSON objects of a JSON-lines file, each checked by ``model``, with their line
    numbers; and the number of a torn last line (no newline: a crash during its append,
    left out), or None.  ``ScanFolderError`` names file and line of a malformed ``what``."""
    if not path.exists():
        return [], None
    try:
        data = read_bytes(path)
    except InputFileError as exc:
        raise ScanFolderError(str(exc)) from None
    lines = data.split(b"\n")
    torn = len(lines) if lines[-1] != b"" else None
    out = []
    for n, line in enumerate(lines[:-1], start=1):
        if not line.strip():
            continue
        try:
            d = parse_json_line(line, path, n)
            if not isinstance(d, dict):
                raise ValueError(f"a {what} is a JSON object")
            model.model_validate(d)
        except InputFileError as exc:
            raise ScanFolderError(str(exc)) from None
        except ValidationError as exc:
            problems = "; ".join(f"{error_path(e['loc'])}: {e['msg']}" for e in exc.errors())
            raise ScanFolderError(f"{path}:{n}: malformed {what} ({problems})") from None
        except (ValueError, KeyError, TypeError) as exc:
            raise ScanFolderError(f"{path}:{n}: malformed {what} ({exc})") from exc
        out.append((n, d))
    return out, torn


def _append_json_line(path: Path, record: dict[str, Any]) -> None:
    """Append one JSON line to ``path`` and fsync it (a torn last line is dropped first)."""
    data = path.read_bytes() if path.exists() else b""
    if data and not data.endswith(b"\n"):
        # Drop a torn last line left by a crash during an append.
        with open(path, "r+b") as f:
            f.truncate(data.rfind(b"\n") + 1)
    with open(path, "ab") as f:
        f.write((json.dumps(record, sort_keys=True) + "\n").encode())
        f.flush()
        os.fsync(f.fileno())


JPEG_SUFFIXES = (".jpg", ".jpeg", ".jpe", ".jfif")

# EXIF orientation -> the transform OpenCV's imread applies (verified pixel for pixel).
_ORIENT = {2: lambda a: a[:, ::-1], 3: lambda a: a[::-1, ::-1], 4: lambda a: a[::-1],
           5: lambda a: a.swapaxes(0, 1), 6: lambda a: a.swapaxes(0, 1)[:, ::-1],
           7: lambda a: a.swapaxes(0, 1)[::-1, ::-1], 8: lambda a: a.swapaxes(0, 1)[::-1]}


def _decode_jpeg(path: Path, reduce: int, grayscale: bool) -> np.ndarray:
    """Decode a JPEG strictly: a truncated or corrupt file is an error, never grey fill.

    libjpeg repairs a damaged stream with grey (or garbage) blocks and only
    warns on stderr, which OpenCV's ``imread`` passes by; libjpeg-turbo through
    ``simplejpeg`` with ``strict=True`` raises on the same warnings.  Output is
    identical to ``cv2.imread`` (same DCT scaling, upsampling and EXIF orientation;
    tests/core/test_scanfolder.py checks it pixel for pixel).
    """
    import simplejpeg

    data = path.read_bytes()
    try:
        h, w, _, _ = simplejpeg.decode_jpeg_header(data)
        img = simplejpeg.decode_jpeg(data, "GRAY" if grayscale else "BGR",
                                     min_height=-(-h // reduce), min_width=-(-w // reduce),
                                     strict=True)
    except ValueError as exc:
        raise DataError(f"{path}: corrupt or truncated JPEG ({exc}); the image cannot be "
                        "trusted: capture it again, or set segment.bad_images: skip") from None
    if grayscale:
        img = img[..., 0]
    orientation = _exif_orientation(data)
    if orientation in _ORIENT:
        img = np.ascontiguousarray(_ORIENT[orientation](img))
    return img


def _exif_orientation(data: bytes) -> int:
    """The EXIF orientation tag of a JPEG (1 when absent); reads the header only."""
    if b"Exif" not in data[:65536]:
        return 1
    import io

    from PIL import Image

    try:
        with Image.open(io.BytesIO(data)) as im:
            return int(im.getexif().get(0x0112, 1))
    except (OSError, ValueError, SyntaxError):
        return 1


def read_image(path: Path, reduce: int = 1, grayscale: bool = False) -> np.ndarray:
    """Decode an image file as ``(H, W, 3) uint8`` BGR (``(H, W)`` with ``grayscale``).

    Every decode of a scan image goes through here, so ``iostats`` counts them.
    ``DataError`` naming the file when it is missing, truncated or corrupt
    (JPEG through ``_decode_jpeg``; PNG's CRCs make OpenCV refuse a damaged one).
    """
    import cv2

    from plantscan_core import iostats

    if grayscale:
        flags = {1: cv2.IMREAD_GRAYSCALE, 2: cv2.IMREAD_REDUCED_GRAYSCALE_2,
                 4: cv2.IMREAD_REDUCED_GRAYSCALE_4, 8: cv2.IMREAD_REDUCED_GRAYSCALE_8}
    else:
        flags = {1: cv2.IMREAD_COLOR, 2: cv2.IMREAD_REDUCED_COLOR_2,
                 4: cv2.IMREAD_REDUCED_COLOR_4, 8: cv2.IMREAD_REDUCED_COLOR_8}
    if reduce not in flags:
        raise ValueError(f"reduce must be one of {sorted(flags)}, got {reduce}")
    path = Path(path)
    if not path.exists():
        raise DataError(f"{path}: image file not found")
    if path.suffix.lower() in JPEG_SUFFIXES:
        img = _decode_jpeg(path, reduce, grayscale)
    else:
        img = cv2.imread(str(path), flags[reduce])
    iostats.count_decode(path)
    if img is None:
        raise DataError(f"{path}: cannot decode image (corrupt or unsupported format)")
    return img
