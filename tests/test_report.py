"""The run report: fit curves on a synthetic sphere with known DoLP and shading, HTML and PNG output."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from polarshape.report import ReportData, fit_curves, write_report

PNG = b"\x89PNG\r\n\x1a\n"


def _sphere_data(size: int = 40, rendered: bool = True, error: bool = True) -> ReportData:
    """An orthographic unit sphere, Lambertian s0 under 4 lights, DoLP = 0.3 sin²θ_V along the azimuth."""
    v, u = np.mgrid[0:size, 0:size]
    x = (u - (size - 1) / 2) / (size / 2)
    y = (v - (size - 1) / 2) / (size / 2)
    mask = x**2 + y**2 < 0.95
    nz = -np.sqrt(np.clip(1 - x**2 - y**2, 0, None))
    normals = np.where(mask[..., None], np.stack([x, y, nz], -1), np.nan)
    lights = np.array([[0.3, 0.0, -1.0], [-0.3, 0.2, -1.0], [0.0, -0.4, -1.0], [0.0, 0.0, -1.0]])
    lights /= np.linalg.norm(lights, axis=1, keepdims=True)
    irradiance = np.array([1.0, 0.8, 1.2, 1.0])
    albedo = np.where(mask, 0.5, np.nan)
    shading = np.clip(np.einsum("hwc,kc->khw", np.nan_to_num(normals), lights), 0, None)  # (K, H, W)
    s0 = albedo * irradiance[:, None, None] * shading
    theta_v = np.arccos(np.clip(-nz, -1, 1))
    dolp = 0.3 * np.sin(theta_v) ** 2
    phi = np.arctan2(y, x)
    observed = np.stack([s0, s0 * dolp * np.cos(2 * phi), s0 * dolp * np.sin(2 * phi)], axis=1)  # (K, 3, H, W)
    view = np.broadcast_to(np.array([0.0, 0.0, -1.0]), (size, size, 3))
    params = {
        "model": "test<model>",
        "params": {"ior": 1.5, "alpha": 0.3},
        "metrics": {"normals": {"mean_deg": 2.0, "median_deg": 1.5}},
        "timings_s": {"input": 1.0, "recovery": 2.5},
        "skipped": ["mesh: mesh_poisson.ply <disabled>"],
        "summary": "a summary line",
    }
    return ReportData(
        normals=normals, albedo=albedo, mask=mask, observed=observed,
        rendered=observed * 1.02 if rendered else None, lights=np.broadcast_to(lights[:, None, None], (4, size, size, 3)),
        irradiance=np.broadcast_to(irradiance[:, None, None], (4, size, size)), view=view,
        valid=(s0 > 0.01) & mask[None], params=params,
        error_map=np.where(mask, np.abs(x) * 5, np.nan) if error else None, seed=1, max_curve_pixels=3000,
    )


def test_fit_curves_recover_the_known_dependences() -> None:
    data = _sphere_data()
    curves = fit_curves(data)
    assert curves["theta_v"].size == 3000  # sampled down to max_curve_pixels
    assert np.allclose(curves["dolp_obs"], 0.3 * np.sin(np.radians(curves["theta_v"])) ** 2, atol=1e-9)
    assert np.allclose(curves["shading_obs"], np.cos(np.radians(curves["theta_l"])), atol=1e-9)
    ok = np.isfinite(curves["dolp_obs_med"])
    assert ok.sum() >= 8
    expected = 0.3 * np.sin(np.radians(curves["dolp_bins"][ok])) ** 2
    assert np.allclose(curves["dolp_obs_med"][ok], expected, atol=0.02)  # 3° bins
    assert np.allclose(curves["dolp_fit_med"][ok], curves["dolp_obs_med"][ok], atol=1e-9)  # DoLP is scale-free
    ok = np.isfinite(curves["shading_fit_med"])
    assert np.allclose(curves["shading_fit_med"][ok], 1.02 * curves["shading_obs_med"][ok], rtol=1e-9)


def test_fit_curves_without_a_rendering_or_albedo() -> None:
    data = _sphere_data(rendered=False)
    data.albedo = None
    curves = fit_curves(data)
    assert "dolp_fit" not in curves and "shading_fit_med" not in curves
    assert np.nanmax(curves["shading_obs"]) == pytest.approx(0.5, rel=0.02)  # s0 / E = albedo · cos θ_L


def test_html_report(tmp_path: Path) -> None:
    files = write_report(tmp_path, _sphere_data(), fmt="html")
    assert files[0] == tmp_path / "report.html"
    page = files[0].read_text()
    for name in ("maps", "polarisation", "fit_curves", "residuals", "error_map"):
        path = tmp_path / "report" / f"{name}.png"
        assert path in files and path.read_bytes()[:8] == PNG
        assert f'src="report/{name}.png"' in page
    assert "a summary line" in page and "recovery" in page and "2.500" in page and "ior" in page
    assert "test&lt;model&gt;" in page and "&lt;disabled&gt;" in page and "<disabled>" not in page
    assert not list(tmp_path.rglob(".*tmp*"))  # atomic writes left no temporary file


def test_html_report_without_rendering_or_ground_truth(tmp_path: Path) -> None:
    files = write_report(tmp_path, _sphere_data(rendered=False, error=False), fmt="html")
    names = {f.name for f in files}
    assert "error_map.png" not in names and {"report.html", "residuals.png", "polarisation.png"} <= names


@pytest.mark.parametrize("error", [True, False])
def test_png_report(tmp_path: Path, error: bool) -> None:
    files = write_report(tmp_path, _sphere_data(error=error), fmt="png")
    assert files == [tmp_path / "report.png"]
    assert files[0].read_bytes()[:8] == PNG and files[0].stat().st_size > 20_000


def test_report_refuses_an_existing_report_and_unknown_format(tmp_path: Path) -> None:
    from polarshape.io.atomic import OutputExistsError

    write_report(tmp_path, _sphere_data(), fmt="png")
    with pytest.raises(OutputExistsError):
        write_report(tmp_path, _sphere_data(), fmt="png")
    with pytest.raises(ValueError, match="'html' or 'png'"):
        write_report(tmp_path / "x", _sphere_data(), fmt="pdf")  # type: ignore[arg-type]
