"""Importers: data that users already have (photometric-stereo folders, light files) → capture folders.

- :mod:`.lightfiles` — light files (``x y z`` per line; the RTI ``.lp`` format) in an explicit
  frame (``opencv`` | ``diligent``), and writing their directions into a capture's ``capture.yaml``;
- :mod:`.diligent` — DiLiGenT-style folders (images, ``light_directions.txt``,
  ``light_intensities.txt``, ``mask.png``, ``Normal_gt``) → a capture of plain intensity frames.

Importers write through :func:`polarshape.io.capture.write_capture` (atomic) and never write over
their source.
"""

from polarshape.io.importers.diligent import DEFAULT_RGB_WEIGHTS, import_diligent, rgb_to_mono
from polarshape.io.importers.lightfiles import (
    LIGHT_FRAMES,
    LightFile,
    from_diligent_frame,
    read_light_file,
    set_capture_light_directions,
    to_diligent_frame,
)

__all__ = [
    "DEFAULT_RGB_WEIGHTS",
    "LIGHT_FRAMES",
    "LightFile",
    "from_diligent_frame",
    "import_diligent",
    "read_light_file",
    "rgb_to_mono",
    "set_capture_light_directions",
    "to_diligent_frame",
]
