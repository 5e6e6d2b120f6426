"""Reading the files a user hands plantscan: UTF-8 text, bounded YAML, ``file:line`` errors.

Every text file the project reads from a user (recipes, ``scan.yaml``,
calibration files, manifests, COLMAP models) goes through ``read_text`` and,
for YAML, ``load_yaml``: a file that is not UTF-8 (a UTF-16 export, a Latin-1
editor) is refused with the line and byte where decoding failed, instead of a
``UnicodeDecodeError`` traceback, and YAML is bounded in size, nesting depth and
node count so that a hostile or broken file fails fast with its name (a
1000-deep nesting raised ``RecursionError``; anchors can expand a small file
into billions of nodes).  Every parser error names ``file:line``.
"""

from __future__ import annotations

import codecs
import json
from pathlib import Path
from typing import Any

import yaml

from plantscan_core.errors import DataError

MAX_TEXT_BYTES = 64 * 1024 * 1024
"""Largest text file read (a 360-view manifest is ~150 kB, a COLMAP images.txt of 10 000
images with their 2D points ~1 GB is not accepted: export it without points)."""

MAX_YAML_BYTES = 4 * 1024 * 1024
"""Largest YAML file: recipes and calibrations are a few kB."""

MAX_YAML_DEPTH = 32
"""Deepest nesting of mappings and lists: a recipe is 6 deep at most."""

MAX_YAML_NODES = 200_000
"""Most nodes a YAML document may expand to (aliases counted each time they are used)."""


class InputFileError(DataError):
    """A user file is unreadable, not UTF-8 or malformed; the message starts ``file:line:``."""

    def __init__(self, path: Path | str, message: str, line: int | None = None) -> None:
        self.path = str(path)
        self.line = line
        self.detail = message
        where = f"{path}:{line}" if line is not None else str(path)
        super().__init__(f"{where}: {message}")


def decode_utf8(data: bytes, path: Path | str) -> str:
    """``data`` as text (UTF-8, a leading BOM dropped); ``InputFileError`` naming the line."""
    if data.startswith((codecs.BOM_UTF16_LE, codecs.BOM_UTF16_BE)):
        raise InputFileError(path, "is UTF-16 text; save it as UTF-8", 1)
    try:
        return data.decode("utf-8-sig")
    except UnicodeDecodeError as exc:
        line = data.count(b"\n", 0, exc.start) + 1
        column = exc.start - (data.rfind(b"\n", 0, exc.start) + 1) + 1
        raise InputFileError(path, f"not UTF-8 text (byte 0x{data[exc.start]:02x} at column "
                             f"{column}); save it as UTF-8", line) from None


def read_bytes(path: Path | str, limit: int = MAX_TEXT_BYTES) -> bytes:
    """The bytes of a user file; ``InputFileError`` when missing, unreadable or too large."""
    path = Path(path)
    try:
        size = path.stat().st_size
        if size > limit:
            raise InputFileError(path, f"is {size / 1e6:.1f} MB; at most {limit / 1e6:.0f} MB "
                                 "is read (is it the right file?)")
        return path.read_bytes()
    except FileNotFoundError:
        raise InputFileError(path, "file not found") from None
    except IsADirectoryError:
        raise InputFileError(path, "is a folder, not a file") from None
    except OSError as exc:
        raise InputFileError(path, f"cannot read ({exc.strerror or exc})") from exc


def read_text(path: Path | str, limit: int = MAX_TEXT_BYTES) -> str:
    """A user text file, decoded as UTF-8; see ``decode_utf8`` and ``read_bytes``."""
    return decode_utf8(read_bytes(path, limit), path)


def parse_yaml(text: str, path: Path | str) -> Any:
    """Safe-load YAML ``text`` of ``path``, bounded in depth and nodes; ``file:line`` errors."""
    try:
        value = yaml.safe_load(text)
    except yaml.MarkedYAMLError as exc:
        mark = exc.problem_mark or exc.context_mark
        what = " ".join(" ".join(str(p).split()) for p in (exc.context, exc.problem) if p)
        raise InputFileError(path, f"not valid YAML: {what or exc}",
                             mark.line + 1 if mark is not None else None) from None
    except yaml.YAMLError as exc:  # ReaderError: a control character; one line, no position
        raise InputFileError(path, "not valid YAML: " + " ".join(str(exc).split())) from None
    except RecursionError:
        raise InputFileError(path, f"nested deeper than {MAX_YAML_DEPTH} levels") from None
    check_shape(value, path)
    return value


def check_shape(value: Any, path: Path | str, max_depth: int = MAX_YAML_DEPTH,
                max_nodes: int = MAX_YAML_NODES) -> None:
    """Refuse a parsed document nested deeper than ``max_depth`` or larger than ``max_nodes``.

    Iterative (no recursion limit to hit), and stops at the first excess, so an
    alias bomb is refused after ``max_nodes`` steps, not after expanding it.
    """
    stack = [(value, 1)]
    nodes = 0
    while stack:
        node, depth = stack.pop()
        nodes += 1
        if nodes > max_nodes:
            raise InputFileError(path, f"expands to more than {max_nodes} values (YAML aliases?)")
        if isinstance(node, dict):
            children = list(node.keys()) + list(node.values())
        elif isinstance(node, list):
            children = node
        else:
            continue
        if depth >= max_depth and children:
            raise InputFileError(path, f"nested deeper than {max_depth} levels")
        stack.extend((c, depth + 1) for c in children)


def load_yaml(path: Path | str, limit: int = MAX_YAML_BYTES) -> Any:
    """Read and parse a user YAML file (UTF-8, bounded); ``InputFileError`` naming file:line."""
    return parse_yaml(read_text(path, limit), path)


def parse_json_line(line: bytes | str, path: Path | str, lineno: int) -> Any:
    """One JSON line of a manifest; ``InputFileError`` naming ``file:line``."""
    if isinstance(line, bytes):
        try:
            line = line.decode("utf-8")
        except UnicodeDecodeError:
            raise InputFileError(path, "not UTF-8 text", lineno) from None
    try:
        value = json.loads(line)
    except json.JSONDecodeError as exc:
        raise InputFileError(path, f"not valid JSON ({exc.msg} at column {exc.colno})",
                             lineno) from None
    except RecursionError:
        raise InputFileError(path, "nested too deep", lineno) from None
    check_shape(value, f"{path}:{lineno}", max_nodes=10_000)
    return value
