"""plantscan camera backend for USB webcams through OpenCV (``plugin: opencv``)."""

from plantscan_opencvcam.camera import OpenCVCamera, OpenCVCamParams

__all__ = ["OpenCVCamera", "OpenCVCamParams"]
