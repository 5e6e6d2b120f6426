"""Undistortion of images and masks with a calibrated ``CameraModel`` (and back).

plantscan carves *distorted* masks with the distortion inside the projection
(``CameraModel.project_camera_points``), so the pipeline never resamples a
mask; these helpers are for users who want undistorted images (viewers,
third-party tools) and for the measurement behind that decision
(docs/segmentation.md, ``benchmarks/segmentation.py``).

The seed's radial model is OpenCV's with ``k1 = d1, k2 = d2`` and no tangential
or ``k3`` terms, so ``CameraModel.K`` / ``CameraModel.dist_coeffs`` go straight
into ``cv2.initUndistortRectifyMap``.  The undistorted image keeps ``K`` (same
focal length and principal point: a pure pinhole view of the same size).
"""

from __future__ import annotations

import cv2
import numpy as np

from plantscan_core.data import CameraModel


def _size(model: CameraModel, shape: tuple[int, ...]) -> tuple[int, int]:
    h, w = shape[:2]
    if model.width and model.height and (model.width, model.height) != (w, h):
        raise ValueError(f"camera model is {model.width}x{model.height} px but the image is "
                         f"{w}x{h} px; use CameraModel.scaled() for a resized image")
    return w, h


def undistort_maps(model: CameraModel, size: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """Remap tables distorted -> undistorted.

    Parameters
    ----------
    model : CameraModel
    size : (width, height), px

    Returns
    -------
    map_u, map_v : (H, W) float32 arrays
        For every pixel of the undistorted image, where to sample the distorted one.
    """
    return cv2.initUndistortRectifyMap(model.K, model.dist_coeffs, None, model.K, size,
                                       cv2.CV_32FC1)


def distort_maps(model: CameraModel, size: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """Remap tables undistorted -> distorted (the inverse of ``undistort_maps``).

    For every pixel of the distorted image the radial model is inverted
    (``CameraModel.undistort_points``) and mapped through ``K``.
    """
    w, h = size
    u, v = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
    xy = model.undistort_points(np.stack([u.ravel(), v.ravel()], axis=1))
    map_u = (xy[:, 0] * model.f + model.cu).reshape(h, w).astype(np.float32)
    map_v = (xy[:, 1] * model.fy + model.cv).reshape(h, w).astype(np.float32)
    return map_u, map_v


def undistort_image(image: np.ndarray, model: CameraModel) -> np.ndarray:
    """(H, W[, 3]) image as a distortion-free pinhole camera with ``model.K`` would see it.

    Bilinear resampling; pixels that come from outside the frame are black.
    """
    map_u, map_v = undistort_maps(model, _size(model, image.shape))
    return cv2.remap(image, map_u, map_v, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT)


def _remap_mask(mask: np.ndarray, map_u: np.ndarray, map_v: np.ndarray) -> np.ndarray:
    # Bilinear on 0/255 then > 127: the boundary moves to where coverage crosses 1/2,
    # which keeps one-pixel structures that nearest-neighbour sampling would break.
    resampled = cv2.remap(mask.astype(np.uint8) * 255, map_u, map_v, cv2.INTER_LINEAR,
                          borderMode=cv2.BORDER_CONSTANT)
    return resampled > 127


def undistort_mask(mask: np.ndarray, model: CameraModel) -> np.ndarray:
    """(H, W) bool mask of a distorted image -> the same mask in the undistorted image."""
    return _remap_mask(mask, *undistort_maps(model, _size(model, mask.shape)))


def distort_mask(mask: np.ndarray, model: CameraModel) -> np.ndarray:
    """(H, W) bool mask of an undistorted image -> the mask in the camera's distorted image."""
    return _remap_mask(mask, *distort_maps(model, _size(model, mask.shape)))
