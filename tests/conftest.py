"""Fixtures shared by the whole test suite."""

from __future__ import annotations

import os

import pytest


@pytest.fixture
def require_aravis() -> None:
    """Skip a test when Aravis/PyGObject cannot be used — unless POLARSHAPE_REQUIRE_ARAVIS=1
    (set by CI, which installs them), where that is a failure."""
    from polarshape.acquisition.aravis import import_aravis
    from polarshape.acquisition.camera import CameraError

    try:
        import_aravis()
    except CameraError as exc:
        if os.environ.get("POLARSHAPE_REQUIRE_ARAVIS") == "1":
            pytest.fail(f"POLARSHAPE_REQUIRE_ARAVIS=1 but Aravis is unusable: {exc}")
        pytest.skip(f"Aravis/PyGObject not installed: {exc}")
