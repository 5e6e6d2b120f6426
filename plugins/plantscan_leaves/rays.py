"""Rays cast at a plant's closed surface, the scene built on the other core.

The leaf stages cast inward rays at the whole plant (the piece judge's thickness, the
measurer's thick shares) through Open3D's ``RaycastingScene``.  Building its BVH is one
thread's work that holds the GIL (1.7 s at 2.7 M faces, measured: a Python thread beside
it stands still), so in the leaf stages' process it runs alone whatever else is ready.
For a large mesh the scene is built in a helper process instead (this file run as a
script: numpy and Open3D only), started when the segmenter's passes start (its surface
fields keep both cores busy before): by the time the piece judge casts, the BVH is
there, built on the core the passes leave idle (dicot seed 1009, 2.7 M faces: the
judge 2.9 -> 0.7 s; the helper costs ~0.8 s more CPU than a build here: its Python,
numpy and Open3D).  ``PLANTSCAN_RAY_HELPER=0`` keeps every scene in-process (the
batch's workers do when there are several: no core is idle there).
The helper casts with the same Open3D on the same float32 arrays, so its hits are the
in-process scene's to the bit (tests/leaves/test_rays.py); where it cannot start or dies,
the scene is built here and the rays give the same answer, only later.

Protocol on the helper's stdin/stdout (little-endian): the parent writes the vertex and
face counts (two uint64), the float32 vertices and the uint32 faces; the helper answers
one byte when its BVH is built; then per cast the parent writes a ray count (uint64; 0
ends the helper) and the float32 rays (N, 6), the helper the float32 hit distances (N,).
"""

from __future__ import annotations

import atexit
import logging
import os
import select
import subprocess
import sys
import threading
import weakref

import numpy as np

log = logging.getLogger(__name__)

# A mesh with fewer faces builds its BVH in-process: the helper's start (Python, numpy,
# Open3D: ~0.7 s of CPU) and its memory traffic beside the segmenter cost about what a
# BVH of ~1 M faces does (dicot validation plants of 0.4-0.9 M faces: no faster with it,
# 1.7-2.7 M: 1-3 s faster; docs/benchmarks/leaf_speed.md, session 26).
HELPER_MIN_FACES = 1_000_000
# How long a cast waits for the helper's BVH before building one here instead: far more
# than a build takes (1.7 s at 2.7 M faces), so only a helper that hangs or starves hits it.
READY_TIMEOUT_S = 120.0
_HEADER = np.dtype("<u8")
_READY = b"R"


class LocalScene:
    """An Open3D scene in this process (its BVH built on the first cast)."""

    def __init__(self, vertices: np.ndarray, faces: np.ndarray) -> None:
        import open3d as o3d

        self._o3d = o3d
        self._scene = o3d.t.geometry.RaycastingScene()
        self._scene.add_triangles(o3d.core.Tensor(np.asarray(vertices, np.float32)),
                                  o3d.core.Tensor(np.asarray(faces, np.uint32)))

    def t_hit(self, rays: np.ndarray) -> np.ndarray:
        """(N,) float32 distance along each ray (origin xyz, direction xyz) to its first
        hit, inf where it hits nothing."""
        rays = np.ascontiguousarray(rays, np.float32).reshape(-1, 6)
        return self._scene.cast_rays(self._o3d.core.Tensor(rays))["t_hit"].numpy()

    def close(self) -> None:
        self._scene = None


class HelperScene:
    """The scene of a mesh held by a helper process, started at once (its BVH built
    while this process goes on); ``t_hit`` as ``LocalScene``'s, falling back to one
    built here if the helper fails."""

    def __init__(self, vertices: np.ndarray, faces: np.ndarray) -> None:
        self._v = np.ascontiguousarray(vertices, np.float32)
        self._f = np.ascontiguousarray(faces, np.uint32)
        self._lock = threading.Lock()
        self._ready = False
        self._local: LocalScene | None = None
        self._proc = subprocess.Popen(_helper_command(), stdin=subprocess.PIPE,
                                      stdout=subprocess.PIPE, stderr=subprocess.DEVNULL)
        # the mesh goes down the pipe from a thread (the pipe's writes release the GIL):
        # the caller is not held while the helper starts and reads ~50 MB
        self._feeder = threading.Thread(target=self._feed, daemon=True)
        self._feeder.start()
        _LIVE.add(self)

    def _feed(self) -> None:
        try:
            pipe = self._proc.stdin
            pipe.write(np.array([len(self._v), len(self._f)], _HEADER).tobytes())
            pipe.write(memoryview(self._v).cast("B"))
            pipe.write(memoryview(self._f).cast("B"))
            pipe.flush()
        except (OSError, ValueError):  # the helper is gone: t_hit falls back
            pass

    def t_hit(self, rays: np.ndarray) -> np.ndarray:
        rays = np.ascontiguousarray(rays, np.float32).reshape(-1, 6)
        with self._lock:  # one conversation with the helper at a time
            if self._local is None:
                try:
                    return self._remote(rays)
                except (OSError, ValueError, EOFError) as exc:  # TimeoutError is an OSError
                    log.warning("ray-casting helper failed (%s: %s): the scene is built in "
                                "this process", type(exc).__name__, exc)
                    self._stop()
                    self._local = LocalScene(self._v, self._f)
            return self._local.t_hit(rays)

    def _remote(self, rays: np.ndarray) -> np.ndarray:
        out, inp = self._proc.stdin, self._proc.stdout
        if not self._ready:  # the helper answers once it has read the whole mesh
            ready, _, _ = select.select([inp], [], [], READY_TIMEOUT_S)
            if not ready:
                raise TimeoutError(f"no scene from the helper within {READY_TIMEOUT_S:g} s")
            if inp.read(1) != _READY:
                raise EOFError(f"helper exited with code {self._proc.wait()}")
            self._feeder.join()
            self._ready = True
        out.write(np.array([len(rays)], _HEADER).tobytes())
        out.write(memoryview(rays).cast("B"))
        out.flush()
        return _read_array(inp, np.float32, len(rays))

    def _stop(self) -> None:
        proc = self._proc
        if proc.poll() is None and not self._ready:  # it may not even read: no goodbye
            proc.kill()
            proc.wait()
        if proc.poll() is None:
            try:
                proc.stdin.write(np.array([0], _HEADER).tobytes())
                proc.stdin.flush()
                proc.wait(timeout=2)
            except (OSError, ValueError, subprocess.TimeoutExpired):
                proc.kill()
                proc.wait()
        for pipe in (proc.stdin, proc.stdout):
            try:
                pipe.close()
            except OSError:
                pass
        _LIVE.discard(self)

    def close(self) -> None:
        with self._lock:
            self._stop()
            if self._local is not None:
                self._local.close()


_LIVE: weakref.WeakSet[HelperScene] = weakref.WeakSet()


def _helper_command() -> list[str]:
    """The helper's command line: this file run by this Python (-P: the script's folder,
    this package's modules, is not put on its path)."""
    return [sys.executable, "-P", "-u", os.path.abspath(__file__)]


@atexit.register
def _stop_helpers() -> None:
    for scene in list(_LIVE):
        scene.close()


def make_scene(vertices: np.ndarray, faces: np.ndarray) -> LocalScene | HelperScene:
    """The scene of a mesh: a helper process's for ``HELPER_MIN_FACES`` faces and more
    (unless ``PLANTSCAN_RAY_HELPER=0``), else one in this process."""
    if len(faces) >= HELPER_MIN_FACES and os.environ.get("PLANTSCAN_RAY_HELPER", "1") != "0":
        try:
            return HelperScene(vertices, faces)
        except OSError as exc:
            log.warning("ray-casting helper not started (%s): the scene is built in this "
                        "process", exc)
    return LocalScene(vertices, faces)


def _read_array(stream, dtype, count: int) -> np.ndarray:
    out = np.empty(count, dtype)
    view = memoryview(out).cast("B")
    got = 0
    while got < len(view):
        n = stream.readinto(view[got:])
        if not n:
            raise EOFError(f"pipe closed after {got} of {len(view)} bytes")
        got += n
    return out


def _serve(inp, out) -> None:
    """The helper: read the mesh, build its BVH, answer casts until a count of 0."""
    nv, nf = (int(x) for x in _read_array(inp, _HEADER, 2))
    vertices = _read_array(inp, np.float32, 3 * nv).reshape(nv, 3)
    faces = _read_array(inp, np.uint32, 3 * nf).reshape(nf, 3)
    scene = LocalScene(vertices, faces)
    scene.t_hit(np.zeros((1, 6), np.float32))  # the BVH, now
    out.write(_READY)
    out.flush()
    while True:
        n = int(_read_array(inp, _HEADER, 1)[0])
        if not n:
            return
        rays = _read_array(inp, np.float32, 6 * n).reshape(n, 6)
        out.write(memoryview(np.ascontiguousarray(scene.t_hit(rays), np.float32)).cast("B"))
        out.flush()


if __name__ == "__main__":
    # the answers go down a copy of stdout; what Open3D prints goes to stderr (discarded)
    _answers = os.fdopen(os.dup(1), "wb")
    os.dup2(2, 1)
    try:
        _serve(sys.stdin.buffer, _answers)
    except EOFError:  # the parent went away
        pass
