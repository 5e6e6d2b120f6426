"""plantscan camera backend for tethered cameras through libgphoto2 (``plugin: gphoto2``)."""

from plantscan_gphoto.camera import GPhotoCamera, GPhotoError, GPhotoParams

__all__ = ["GPhotoCamera", "GPhotoError", "GPhotoParams"]
