"""The run report: fit curves on a synthetic sphere with known DoLP and shading, HTML and PNG output."""

from __future__ import annotations

import math
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


# --- issue 14: what ran, warnings, validation, surface preview, parameters with meaning and truth ----------


def _validated(data: ReportData, *, polarised: bool = True) -> ReportData:
    """``data`` with a depth map, held-out frames, params["validation"] / ["checks"], a loss history, truth."""
    size = data.mask.shape[0]
    v, u = np.mgrid[0:size, 0:size]
    r2 = ((u - (size - 1) / 2) ** 2 + (v - (size - 1) / 2) ** 2) / (size / 2) ** 2
    data.depth = np.where(data.mask, 1.0 - 0.3 * np.sqrt(np.clip(1 - r2, 0, None)), np.nan)
    data.holdout_lights = [1, 3]
    data.holdout_observed = data.observed[[1, 3]]
    data.holdout_predicted = data.observed[[1, 3]] * 1.05
    per_light = lambda e: [{"light": j, "s0_rel_rmse": e, "dolp_rmse": 0.01, "aolp_mae_deg": 2.0} for j in (1, 3)]  # noqa: E731
    models = {name: {"per_light": per_light(e), "s0_rel_rmse": e, "dolp_rmse": 0.01, "aolp_mae_deg": 2.0, "seconds": 1.5}
              for name, e in (("fmbrdf", 0.0123), ("baek", 0.0456), ("l_ts", 0.0789), ("lambertian", 0.1011))}
    data.params.update(
        model="fmbrdf",
        params={"ior": 1.52, "alpha": 0.26, "beta": 2.1, "kappa": 0.0, "k_s": 7.5, "k_b": 3.9, "r_k": 0.52},
        capture={"has_polarisation": polarised, "projection": "orthographic"},
        validation={"holdout": [1, 3], "mode": "auto", "reason": None, "models": models,
                    "ranking": ["fmbrdf", "baek", "l_ts", "lambertian"], "noise_floor_s0_rel": 0.0099,
                    "timings_s": {"fmbrdf": 1.5, "total": 6.0}, "warm_start": "the run's normals"},
        checks={"warnings": [{"name": "FitResidualWarning", "message": "fit residual 36× the noise: check <lights>"}],
                "residual_to_noise": 36.0},
        losses={"history": [{"stage": "level0", "iteration": i, "loss": 1e-3 / (1 + i), "ior": 1.5, "alpha": 0.3 - 0.01 * i,
                             "beta": 2.0, "kappa": 0.0, "r_k": 0.5} for i in range(5)]},
    )
    data.truth = {"ior": 1.5, "alpha": 0.25, "k_s": 7.619, "radiance_to_full_scale": 7.619}
    return data


def test_display_range_is_the_1_to_99_percent_range_of_the_mask() -> None:
    from polarshape.report import display_range

    image = np.linspace(0.4, 0.6, 1000).reshape(40, 25)
    image[0, 0] = 50.0  # one hot pixel: a max-scaled map would show the rest as one flat colour
    lo, hi = display_range(image)
    assert lo == pytest.approx(np.percentile(image, 1)) and hi == pytest.approx(np.percentile(image, 99))
    assert lo == pytest.approx(0.402, abs=1e-3) and hi == pytest.approx(0.598, abs=1e-3)
    mask = np.zeros((40, 25), bool)
    mask[20:] = True  # only the mask counts, NaN ignored
    image[30, 6] = np.nan
    lo, hi = display_range(image, mask)
    assert lo == pytest.approx(0.501, abs=5e-4) and hi == pytest.approx(0.599, abs=5e-4)
    assert display_range(np.full((4, 4), np.nan)) is None
    assert display_range(np.full((4, 4), 2.0)) == (2.0, 2.0)


def test_empty_and_constant_maps_get_a_note() -> None:
    from polarshape.report import empty_map_note

    assert empty_map_note(np.full((3, 3), np.nan)) == "nothing to show: no finite value"
    assert empty_map_note(np.where(np.eye(3, dtype=bool), 0.5, np.nan)) == "constant: 0.5 everywhere"
    assert empty_map_note(np.arange(9.0).reshape(3, 3)) is None


@pytest.mark.parametrize("projection", ["orthographic", "perspective"])
def test_shaded_surface_of_a_sphere_is_not_constant(projection: str) -> None:
    from polarshape.report import shaded_surface

    size = 48
    v, u = np.mgrid[0:size, 0:size]
    x, y = (u - (size - 1) / 2) / (size / 2), (v - (size - 1) / 2) / (size / 2)
    inside = x**2 + y**2 < 0.9
    depth = np.where(inside, 1.0 - 0.2 * np.sqrt(np.clip(1 - x**2 - y**2, 0, None)), np.nan)
    if projection == "orthographic":
        view = np.broadcast_to(np.array([0.0, 0.0, -1.0]), (size, size, 3))
        shade = shaded_surface(depth, view, pixel_size=0.2 / (size / 2))
    else:  # rays through a pinhole 60° wide
        ray = np.stack([x * 0.5, y * 0.5, np.ones_like(x)], -1)
        view = -ray / np.linalg.norm(ray, axis=-1, keepdims=True)
        shade = shaded_surface(depth, view, projection="perspective")
    assert np.isnan(shade[~inside]).all() and np.isfinite(shade[inside]).all()
    assert 0.0 <= np.nanmin(shade) and np.nanmax(shade) <= 1.0
    assert np.nanstd(shade) > 0.1  # relief, not one grey
    # the key light is up-left of the camera: the up-left of the sphere is the brighter side
    assert np.nanmean(shade[: size // 2, : size // 2]) > np.nanmean(shade[size // 2:, size // 2:]) + 0.1


def test_html_report_shows_validation_warnings_surface_and_parameters(tmp_path: Path) -> None:
    files = write_report(tmp_path, _validated(_sphere_data()), fmt="html")
    page = files[0].read_text()
    for name in ("surface", "holdout", "models", "loss_history"):
        assert tmp_path / "report" / f"{name}.png" in files and f'src="report/{name}.png"' in page
    # warnings at the top, in the coloured box, with name and (escaped) message
    box = page.index("class='warn'")
    assert box < page.index("<img") and "FitResidualWarning" in page[box:page.index("<img")]
    assert "check &lt;lights&gt;" in page
    # what ran and the held-out error, before the figures
    head = page[:page.index("<img")]
    assert "FMBRDF: normals and material fitted to intensity and polarisation" in head
    assert "held-out validation on lights [1, 3]: fmbrdf s0 rel. RMSE 0.0123 (noise floor 0.0099" in head
    # the model comparison table: every model, its rank, this run's model marked, the noise floor
    table = page[page.index("<h2>Model comparison (held-out lights)</h2>"):]
    table = table[:table.index("</table>")]
    for rank, name, err in ((1, "FMBRDF ★ this run", "0.0123"), (2, "Baek et al. 2018 pBRDF", "0.0456"),
                            (3, "Lambertian + Torrance–Sparrow", "0.0789"), (4, "Lambertian", "0.1011")):
        assert f"<td>{rank}</td><td>{name}</td><td>{err}</td>" in table
    assert "noise alone): 0.0099" in table
    # parameters: meaning, units, the true value beside the fitted one
    params = page[page.index("<h2>Parameters</h2>"):]
    params = params[:params.index("</table>")]
    assert "<th>true</th>" in params and "<td>alpha</td><td>α</td><td>0.26</td><td>0.25</td>" in params
    assert "<td>beta</td><td>β</td><td>2.1</td><td>—</td>" in params  # no truth given for β
    assert "index of refraction" in params and "not a GGX or Beckmann α" in params
    assert "per unit relative irradiance E" in params and "× 7.619" in params
    assert "residual_to_noise" in page and "validation.fmbrdf" in page


def test_html_report_says_why_a_section_is_missing(tmp_path: Path) -> None:
    data = _sphere_data(rendered=False, error=False)
    data.params["capture"] = {"has_polarisation": False}
    data.params["model"] = "fmbrdf"
    page = write_report(tmp_path, data, fmt="html")[0].read_text()
    names = {p.name for p in (tmp_path / "report").iterdir()}
    assert names.isdisjoint({"surface.png", "holdout.png", "models.png", "loss_history.png"})
    assert "no depth map" in page and "no held-out prediction" in page and "no loss history" in page
    assert "held-out validation: no params[&#x27;validation&#x27;] (not run)" in page
    assert "no params[&#x27;checks&#x27;]" in page and "<b>no warnings</b>" in page
    assert "intensity-only FMBRDF: no polarisation above noise" in page
    assert "<th>true</th>" not in page  # no truth: no truth column
    assert "not known yet when this page was written" in page


def test_rewrite_report_page_shows_the_final_timings(tmp_path: Path) -> None:
    from polarshape.report import rewrite_report_page

    data = _sphere_data()
    files = write_report(tmp_path, data, fmt="html")
    plots = {f: f.stat().st_mtime_ns for f in files[1:]}
    data.params["timings_s"].update(report=0.75, total=9.25)
    data.params["warnings"] = ["SuspiciousInputWarning: the frames look shuffled"]
    rewrite_report_page(tmp_path, data)
    page = files[0].read_text()
    assert "<td>total</td><td>9.250</td>" in page and "not known yet" not in page
    assert "SuspiciousInputWarning" in page and "the frames look shuffled" in page
    assert {f: f.stat().st_mtime_ns for f in files[1:]} == plots  # plots not redrawn


def test_html_report_shows_the_near_field_rounds_with_their_relaxation(tmp_path: Path) -> None:
    """The near-field rounds of params.json (as a run writes them) in the report: the model rounds' relaxation
    has its column (n/a in the other rounds), and a key the table does not know yet still shows."""
    import json

    from polarshape.nearfield import NearFieldIteration, NearFieldResult

    rounds = [NearFieldIteration(0, "plane", 1.0, 1.0, math.nan, math.nan, 0.2, 0.25),
              NearFieldIteration(1, "ps", 0.36, 0.36, 3.5, 0.05, 0.04, 0.75),
              NearFieldIteration(2, "model-ps", 0.35, 0.35, 1.5, 0.01, 0.03, 1.25, relaxation=0.5)]
    run = NearFieldResult(inputs=None, result=None, depth=np.full((2, 2), 0.35),  # type: ignore[arg-type]
                          iterations=rounds, converged=False, estimated=True, projection="perspective",
                          reference_depth_m=1.0)
    record = run.as_dict()
    record = json.loads(json.dumps(record))  # as read back from params.json (NaN → null)
    record["iterations"][2]["a_later_key"] = 7
    data = _sphere_data(rendered=False, error=False)
    data.params["nearfield"] = record
    page = write_report(tmp_path, data, fmt="html")[0].read_text()
    assert "<th>relaxation (share of the searched move taken)</th><th>seconds</th><th>a_later_key</th>" in page
    assert "<td>2</td><td>model-ps</td>" in page and "<td>0.5</td><td>1.25</td><td>7</td></tr>" in page
    assert "<td>1</td><td>ps</td>" in page and "<td>n/a</td><td>0.75</td><td>n/a</td></tr>" in page


def test_material_truth_of_a_simulated_scene() -> None:
    import yaml

    from polarshape.report import material_truth

    scene = yaml.safe_load((Path(__file__).resolve().parents[1] / "configs" / "scenes" / "sphere.yaml").read_text())
    provenance = {"simulator": "polarshape SimulatedCamera", "exposure_us": 10000.0, "gain_db": 0.0, "scene": scene}
    truth = material_truth(provenance)
    scale = 80000.0 / 10500.0  # electrons per radiance / electrons at full scale (12 bit, 0 dB, no black level)
    assert truth == pytest.approx({"ior": 1.5, "alpha": 0.25, "beta": 2.0, "kappa": 0.0, "k_s": 1.0 * scale,
                                   "k_b": 0.5 * scale, "r_k": 0.5, "radiance_to_full_scale": scale})
    assert material_truth({**provenance, "gain_db": 6.0})["k_s"] == pytest.approx(scale * 10 ** 0.3)
    scene["objects"][0]["texture"] = {"kind": "checker"}  # textured body albedo: no single k_b
    assert "k_b" not in material_truth(provenance) and "r_k" not in material_truth(provenance)
    scene["objects"][0].update(material={"model": "lambertian", "k_d": 0.6}, texture=None)
    assert material_truth(provenance)["albedo_median"] == pytest.approx(0.6 / np.pi * scale)
    assert material_truth(None) is None and material_truth({"source": "a real camera"}) is None
