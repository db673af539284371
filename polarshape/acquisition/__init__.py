"""Acquisition: camera backends and light rigs."""

from polarshape.acquisition.camera import Camera, CameraError, Frame
from polarshape.imaging.pixels import PIXEL_FORMATS

__all__ = ["Camera", "CameraError", "Frame", "PIXEL_FORMATS"]
