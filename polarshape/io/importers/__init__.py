"""Importers: data that users already have (photometric-stereo folders, light files) → capture folders.

- :mod:`.lightfiles` — light files (``x y z`` per line; the RTI ``.lp`` format) in an explicit
  frame (``opencv`` | ``diligent``), and writing their directions into a capture's ``capture.yaml``;
- :mod:`.destination` — where an import may write (never over or around its sources);
- :mod:`.diligent` — DiLiGenT-style folders (images, ``light_directions.txt``,
  ``light_intensities.txt``, ``mask.png``, ``Normal_gt``) → a capture of plain intensity frames;
- :mod:`.stacks` — already-demosaiced polariser stacks (four images 0/45/90/135 per light, or one
  4-channel ``.npy`` / 4-page TIFF per light) and a light file → a capture whose raw mosaic holds
  each stack pixel as one 2×2 super-pixel;
- :mod:`.arena` — frames saved by Lucid's Arena SDK / ArenaView (headerless ``.raw`` in any
  PolarizeMono format, 16-bit TIFF/PNG, a left shift found and undone) and a light file → a capture.

Importers write through :func:`polarshape.io.capture.write_capture` (atomic) and never write over
their source.
"""

from polarshape.io.importers.arena import ARENA_PIXEL_FORMATS, ArenaFrame, import_arena, read_arena_frame
from polarshape.io.importers.diligent import DEFAULT_RGB_WEIGHTS, import_diligent, rgb_to_mono
from polarshape.io.importers.lightfiles import (
    LIGHT_FRAMES,
    LightFile,
    from_diligent_frame,
    read_light_file,
    set_capture_light_directions,
    to_diligent_frame,
)
from polarshape.io.importers.stacks import STACK_LABELS_DEG, Stack, import_stack, read_stack

__all__ = [
    "ARENA_PIXEL_FORMATS",
    "ArenaFrame",
    "DEFAULT_RGB_WEIGHTS",
    "LIGHT_FRAMES",
    "LightFile",
    "STACK_LABELS_DEG",
    "Stack",
    "from_diligent_frame",
    "import_arena",
    "import_diligent",
    "import_stack",
    "read_arena_frame",
    "read_light_file",
    "read_stack",
    "rgb_to_mono",
    "set_capture_light_directions",
    "to_diligent_frame",
]
