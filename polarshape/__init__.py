"""polarshape: shape and reflectance from polarisation images under known lights, with the Fresnel
Microfacet BRDF (FMBRDF).

The public face, each imported on first use so that ``import polarshape`` (and the command line's
``--help``) does not load torch:

* :func:`run_pipeline` (:mod:`polarshape.pipeline`) — the whole run as a configuration describes;
* :func:`recover_normals` (:mod:`polarshape.normals`) — normals (and reflectance) from prepared inputs;
* :func:`fmbrdf_stokes` (:mod:`polarshape.brdf`) — the FMBRDF forward model, Stokes vectors out;
* :func:`stokes_from_mosaic` (:mod:`polarshape.imaging.demosaic`) — a raw polarisation mosaic to Stokes;
* ``__version__`` — the installed package version.

Errors a user can cause are :class:`polarshape.errors.PolarshapeError` subclasses.
"""

from __future__ import annotations

import importlib
from importlib.metadata import PackageNotFoundError, version
from typing import TYPE_CHECKING, Any

#: The version when polarshape runs from a source tree that is not installed; keep it equal to
#: ``[project] version`` in pyproject.toml (tests/test_version.py checks).
_SOURCE_VERSION = "0.1.0"


def _installed_version() -> str:
    try:
        return version("polarshape")
    except PackageNotFoundError:
        return _SOURCE_VERSION


__version__: str = _installed_version()

#: Public name -> the module that defines it (imported by :func:`__getattr__` on first use).
_LAZY: dict[str, str] = {
    "fmbrdf_stokes": "polarshape.brdf",
    "recover_normals": "polarshape.normals",
    "run_pipeline": "polarshape.pipeline",
    "stokes_from_mosaic": "polarshape.imaging.demosaic",
}

__all__ = ["__version__", *sorted(_LAZY)]

if TYPE_CHECKING:
    from polarshape.brdf import fmbrdf_stokes
    from polarshape.imaging.demosaic import stokes_from_mosaic
    from polarshape.normals import recover_normals
    from polarshape.pipeline import run_pipeline


def __getattr__(name: str) -> Any:
    """Import a public name's module on first use (PEP 562) and keep the name for later lookups."""
    module = _LAZY.get(name)
    if module is None:
        raise AttributeError(f"module 'polarshape' has no attribute {name!r}")
    value = getattr(importlib.import_module(module), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted({*globals(), *_LAZY})
