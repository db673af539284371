"""The simulated imperfect sensor (issue 16, part 3): per-pixel maps, rendering, calibration frames."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
import torch
import yaml

from polarshape.acquisition.simulated import SimulatedCamera
from polarshape.brdf.geometry import sensor_plane_stokes
from polarshape.imaging.mosaic import MosaicLayout
from polarshape.io.images import read_image
from polarshape.io.polarimetric import read_polarimetric_calibration
from polarshape.scene.config import parse_scene_config
from polarshape.scene.render import mosaic_radiance, polariser_angle_map, shade_stokes
from polarshape.scene.sensor_defects import SensorDefects

REPO = Path(__file__).resolve().parents[2]
REAL = {"analyser_angle_error_deg": 1.5, "extinction_ratio": 150.0, "prnu": 0.01, "black_level_12bit": 64.0,
        "hot_pixel_fraction": 0.002, "defects_seed": 5}


def _scene(size: int = 32, lights: int = 2, **sensor: object) -> dict:
    d = yaml.safe_load((REPO / "configs" / "scenes" / "blob.yaml").read_text())
    d["camera"]["width"] = d["camera"]["height"] = size
    f = 3200.0 * size / 256
    d["camera"]["intrinsics"].update(fx=f, fy=f, cx=size / 2 - 0.5, cy=size / 2 - 0.5)
    d["lights"] = d["lights"][:lights]
    d["sensor"].update(sensor)
    return d


def _wrap_deg(x: torch.Tensor) -> torch.Tensor:
    return torch.rad2deg((x + math.pi / 2) % math.pi - math.pi / 2)


def _estimate_from_bench(bench: Path):  # noqa: ANN202 (PolarimetricCalibration)
    """The calibration estimated from the simulated bench frames in ``bench`` (flat/, polariser/, dark/)."""
    from polarshape.acquisition.polarimetric import estimate_polarimetric_calibration

    def stack(sub: str) -> np.ndarray:
        return np.stack([read_image(p) for p in sorted((bench / sub).glob("*.png"))])

    angles = [float(x) for x in (bench / "polariser" / "angles.txt").read_text().split()]
    return estimate_polarimetric_calibration(polariser=stack("polariser"), angles_deg=angles,
                                             layout=MosaicLayout.imx250mzr(), bit_depth=12,
                                             flat=stack("flat"), dark=stack("dark"), black_level=64.0)


def test_maps_reproducible_from_seed_and_statistics_match() -> None:
    layout = MosaicLayout.imx250mzr()
    defects = SensorDefects(analyser_angle_error_deg=1.5, extinction_ratio=150.0, prnu=0.01,
                            hot_pixel_fraction=0.001, dead_pixel_fraction=0.0005, defects_seed=3)
    a, b = defects.draw(layout, 256, 256), defects.draw(layout, 256, 256)
    for name in ("angle_rad", "diattenuation", "gain", "hot", "dead", "hot_level_12bit"):
        assert torch.equal(getattr(a, name), getattr(b, name)), name
    other = SensorDefects(**{**defects.__dict__, "defects_seed": 4}).draw(layout, 256, 256)
    assert not torch.equal(a.angle_rad, other.angle_rad)
    nominal = polariser_angle_map(layout, 256, 256, dtype=torch.float64)
    err = _wrap_deg(a.angle_rad - nominal)
    assert abs(err.std().item() - 1.5) < 0.03 and abs(err.mean().item()) < 0.03
    er = (1 + a.diattenuation) / (1 - a.diattenuation)
    assert torch.allclose(er, torch.full_like(er, 150.0), rtol=1e-9)
    good = ~a.dead
    assert abs(a.gain[good].std().item() - 0.01) < 5e-4 and abs(a.gain[good].mean().item() - 1) < 5e-4
    n = 256 * 256
    assert int(a.hot.sum()) == round(0.001 * n) and int(a.dead.sum()) == round(0.0005 * n)
    assert not bool((a.hot & a.dead).any())
    assert bool((a.hot_level_12bit[a.hot] >= 0.5 * 4095).all()) and bool((a.hot_level_12bit[~a.hot] == 0).all())
    assert bool((a.gain[a.dead] == 0).all())


def test_validation_names_the_field() -> None:
    for field, value in (("prnu", -0.1), ("extinction_ratio", 0.5), ("hot_pixel_fraction", 0.7),
                         ("analyser_angle_error_deg", -1.0)):
        with pytest.raises(ValueError, match=f"sensor.{field}"):
            parse_scene_config(_scene(**{field: value}))
    assert parse_scene_config(_scene()).sensor.to_defects().is_ideal


def test_ideal_sensor_frames_bit_identical_to_the_ideal_polariser_formula() -> None:
    """The ideal sensor renders exactly today's frames: the radiance equals the old closed form
    ½ (s0 + s1 cos 2θ + s2 sin 2θ) bit for bit, so the noisy counts do too."""
    cam = SimulatedCamera(parse_scene_config(_scene()))
    with cam:
        stokes = torch.randn(3, 32, 32, dtype=torch.float64, generator=torch.Generator().manual_seed(0))
        angle = cam._angle_map
        s0, s1, s2 = stokes.unbind(-3)
        old = 0.5 * (s0 + s1 * torch.cos(2.0 * angle) + s2 * torch.sin(2.0 * angle))
        assert torch.equal(mosaic_radiance(stokes, angle), old)
        radiance = cam.radiance(0)
    cap = SimulatedCamera(parse_scene_config(_scene())).render_capture(progress=False)
    assert "sensor_maps" not in cap.ground_truth
    # frame level: today's pipeline (old closed form, then SensorModel.expose with the seed's generator)
    ref = SimulatedCamera(parse_scene_config(_scene()))
    with ref:
        gen = torch.Generator().manual_seed(ref.seed)
        for k in range(2):
            sk = sensor_plane_stokes(shade_stokes(ref.scene, ref.geometry, ref.scene.lights[k],
                                                  albedo_scale=ref._albedo), basis=ref._basis)
            a0, a1, a2 = sk.unbind(-3)
            two = 2.0 * ref._angle_map
            old_rad = 0.5 * (a0 + a1 * torch.cos(two) + a2 * torch.sin(two))
            expected = ref.sensor.expose(old_rad, exposure_us=ref.exposure_us, gain_db=ref.gain_db, bit_depth=12,
                                         generator=gen)
            assert np.array_equal(cap.frames[k], expected.astype(np.uint16))
    # the ideal path is also the generic path with D = 1, g = 1
    assert torch.equal(mosaic_radiance(stokes, angle, torch.ones_like(angle), torch.ones_like(angle)), old)
    assert radiance.shape == (32, 32)


def test_imperfect_sensor_renders_its_maps_and_exposes_truth() -> None:
    ideal = SimulatedCamera(parse_scene_config(_scene()))
    real = SimulatedCamera(parse_scene_config(_scene(**REAL)))
    with ideal, real:
        r0, r1 = ideal.radiance(0), real.radiance(0)
        assert not torch.equal(r0, r1)
        truth = real.sensor_truth()
        maps = real._maps
        assert maps is not None
        obj = r0 > 0
        assert torch.allclose((r1[obj] / r0[obj]).mean(), torch.tensor(1.0, dtype=r1.dtype), atol=0.02)
        frame = real.capture().image
        hot = maps.hot.cpu().numpy()
        assert bool((frame[hot] >= 64 + 0.5 * 4095 - 10).all())  # hot pixels far above black
        assert float(np.median(frame[~obj.cpu().numpy() & ~hot])) == pytest.approx(64, abs=2)
    assert truth.bit_depth == 12 and bool(truth.defects.sum() == maps.hot.sum())
    assert float(truth.black_level[~truth.defects].mean()) == 64.0
    cap = SimulatedCamera(parse_scene_config(_scene(**REAL))).render_capture(progress=False)
    gt = cap.ground_truth["sensor_maps"]
    assert gt.shape == (32, 32, 5) and np.allclose(gt[..., 0], truth.angle_rad.numpy(), atol=1e-6)


def test_calibration_frames_written_and_readable(tmp_path: Path) -> None:
    cam = SimulatedCamera(parse_scene_config(_scene(**REAL)))
    out = cam.render_calibration_frames(tmp_path / "cal", angles_deg=[0, 30, 60, 90, 120, 150], n_flat=3, n_dark=2)
    flat = [read_image(p) for p in sorted((out / "flat").glob("*.png"))]
    pol = sorted((out / "polariser").glob("*.png"))
    dark = sorted((out / "dark").glob("*.png"))
    assert len(flat) == 3 and len(pol) == 6 and len(dark) == 2
    angles = [float(x) for x in (out / "polariser" / "angles.txt").read_text().split()]
    assert angles == [0, 30, 60, 90, 120, 150]
    meta = json.loads((out / "truth.json").read_text())
    assert meta["mount_offset_deg"] == 3.7 and meta["angle_convention"] == "counterclockwise_on_screen"
    level = (np.median(flat[0]) - 64) / (4095 - 64)
    assert 0.45 < level < 0.55  # the flat sits at ~50 % of the range
    truth = read_polarimetric_calibration(out / "truth_polcal.npz", expect_shape=(32, 32))
    assert truth.bit_depth == 12
    with pytest.raises(ValueError, match="angles_deg"):
        cam.render_calibration_frames(tmp_path / "bad", angles_deg=[0, 180])


def test_simulated_calibration_frames_estimate_close_to_truth(tmp_path: Path) -> None:
    cam = SimulatedCamera(parse_scene_config(_scene(**REAL)))
    out = cam.render_calibration_frames(tmp_path / "cal", n_flat=16, n_dark=8)
    est = _estimate_from_bench(out)
    truth = read_polarimetric_calibration(out / "truth_polcal.npz")
    assert torch.equal(est.defects, truth.defects)
    good = ~truth.defects
    err = _wrap_deg(est.angle_rad - truth.angle_rad)[good]
    assert err.pow(2).mean().sqrt().item() < 0.4  # vs the 1.5° σ of the errors themselves
    assert (est.diattenuation - truth.diattenuation)[good].abs().mean().item() < 0.01
    g_est, g_true = est.gain / est.gain[good].mean(), truth.gain / truth.gain[good].mean()
    assert (g_est - g_true)[good].std().item() < 0.005  # vs the 1 % PRNU
    assert (est.black_level - truth.black_level)[good].abs().max().item() < 2.0


@pytest.mark.slow
def test_capture_with_simulated_calibration_has_small_dolp_bias(tmp_path: Path) -> None:
    """Imperfect capture + polcal.npz estimated from its bench frames → preprocess → DoLP close to the
    ideal sensor's (issue 16 target: |bias| ≤ 0.002)."""
    from polarshape.io.capture import load_capture, write_capture
    from polarshape.io.polarimetric import write_polarimetric_calibration
    from polarshape.recover import preprocess as pre

    def dolp(capture) -> tuple[torch.Tensor, torch.Tensor]:
        inp = pre.preprocess_capture(capture, dtype=torch.float64)
        s0, s1, s2 = inp.stokes.unbind(1)
        return torch.sqrt(s1 ** 2 + s2 ** 2) / s0.clamp_min(1e-12), inp.valid

    ideal = SimulatedCamera(parse_scene_config(_scene(96, 6))).render_capture(progress=False)
    real = SimulatedCamera(parse_scene_config(_scene(96, 6, **REAL)))
    with real:
        capture = real.render_capture(progress=False)
        bench = real.render_calibration_frames(tmp_path / "bench", n_flat=16, n_dark=8)
    est = _estimate_from_bench(bench)
    folder = tmp_path / "capture"
    write_capture(folder, capture)
    write_polarimetric_calibration(folder / "polcal.npz", est)
    spec = yaml.safe_load((folder / "capture.yaml").read_text())
    spec["camera"]["polarimetric_calibration"] = "polcal.npz"
    (folder / "capture.yaml").write_text(yaml.safe_dump(spec, sort_keys=False))
    d_ideal, v_ideal = dolp(ideal)
    d_raw, v_raw = dolp(capture)
    d_cal, v_cal = dolp(load_capture(folder))
    both = v_ideal & v_cal & v_raw
    bias_cal = float((d_cal[both] - d_ideal[both]).mean())
    bias_raw = float((d_raw[both] - d_ideal[both]).mean())
    assert abs(bias_cal) <= 0.002
    assert abs(bias_cal) < abs(bias_raw) or abs(bias_raw) < 0.001


def test_cli_simulate_calibration(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    from polarshape.cli import main

    scene = tmp_path / "real.yaml"
    scene.write_text(yaml.safe_dump(_scene(**REAL)))
    out = tmp_path / "bench"
    code = main(["simulate", "calibration", str(scene), "--out", str(out), "--n-flat", "2", "--n-dark", "2",
                 "--angles", "0", "45", "90", "135", "-q"])
    assert code == 0 and "calibration frames" in capsys.readouterr().out
    assert len(list((out / "flat").glob("*.png"))) == 2 and len(list((out / "polariser").glob("*.png"))) == 4
    assert (out / "polariser" / "angles.txt").read_text().split() == ["0", "45", "90", "135"]
    assert main(["simulate", "calibration", str(scene), "--out", str(out), "-q"]) != 0  # exists: refused
