"""Acquisition: camera backends and light rigs."""

from polarshape.acquisition.camera import PIXEL_FORMATS, Camera, CameraError, Frame

__all__ = ["Camera", "CameraError", "Frame", "PIXEL_FORMATS"]
