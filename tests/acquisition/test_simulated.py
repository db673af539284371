"""The simulated camera: Camera protocol, settings, reproducibility, ground truth, capture folders."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from polarshape.acquisition.camera import Camera, CameraError
from polarshape.acquisition.simulated import SimulatedCamera
from polarshape.io.atomic import OutputExistsError
from polarshape.io.capture import load_capture
from polarshape.scene.config import parse_scene_config

CENTER = (0.0005, -0.0003, 0.4)
RADIUS = 0.004


def _scene(projection: str = "orthographic", **sensor):
    camera = {"projection": projection, "width": 64, "height": 48}
    if projection == "orthographic":
        camera["pixel_size_m"] = 1.6e-4
    else:
        camera["intrinsics"] = {"fx": 2000.0, "fy": 2100.0, "cx": 33.2, "cy": 22.7}
    return parse_scene_config({
        "camera": camera,
        "sensor": sensor,
        "objects": [{"shape": {"type": "sphere", "center": list(CENTER), "radius": RADIUS},
                     "material": {"model": "lambertian", "k_d": 0.8}}],
        "lights": [{"direction": [0.0, 0.0, -1.0]}, {"zenith_deg": 40, "azimuth_deg": 30, "intensity": 0.5}],
    })


def test_implements_the_camera_protocol_and_checks_its_state():
    cam = SimulatedCamera(_scene())
    assert isinstance(cam, Camera)
    with pytest.raises(CameraError, match="not open"):
        cam.capture()
    with pytest.raises(CameraError, match="PolarizeMono14"):
        cam.configure(pixel_format="PolarizeMono14")
    with pytest.raises(CameraError, match="exposure_us"):
        cam.configure(exposure_us=0.0)
    with pytest.raises(CameraError, match="0..1"):
        cam.set_light(2)
    with cam:
        frame = cam.capture()
        assert frame.image.shape == (48, 64) and frame.image.dtype == np.uint16
        assert frame.bit_depth == 12 and frame.pixel_format == "PolarizeMono12"
        assert frame.metadata["light_index"] == 0 and cam.capture().frame_id == 1
    cam.close()  # idempotent
    with pytest.raises(CameraError, match="not open"):
        cam.capture()


@pytest.mark.parametrize(
    "pixel_format,bits,dtype",
    [("PolarizeMono8", 8, np.uint8), ("PolarizeMono12p", 12, np.uint16), ("PolarizeMono16", 16, np.uint16)],
)
def test_pixel_formats_set_the_bit_depth(pixel_format, bits, dtype):
    with SimulatedCamera(_scene(read_noise_e=0.0, shot_noise="none", electrons_per_radiance=1e6)) as cam:
        cam.configure(pixel_format=pixel_format)
        frame = cam.capture()
    assert frame.bit_depth == bits and frame.image.dtype == dtype
    assert frame.image.max() <= 2**bits - 1
    assert frame.image.max() >= (2**bits - 1) * 0.99  # bright enough to saturate


def test_exposure_and_gain_scale_the_signal():
    with SimulatedCamera(_scene(read_noise_e=0.0, shot_noise="none", electrons_per_radiance=20000.0)) as cam:
        base = cam.capture().image.astype(np.int64)
        cam.configure(exposure_us=20000.0)
        double = cam.capture().image.astype(np.int64)
        cam.configure(exposure_us=10000.0, gain_db=20 * math.log10(2.0))
        gained = cam.capture().image.astype(np.int64)
    lit = base > 50
    assert lit.sum() > 500
    assert np.abs(double[lit] - 2 * base[lit]).max() <= 1  # rounding
    assert np.abs(gained[lit] - 2 * base[lit]).max() <= 1


def test_lights_switch_and_frames_reproduce_bit_exactly():
    def frames(seed):
        with SimulatedCamera(_scene(), seed=seed) as cam:
            out = []
            for i in (0, 1, 0):
                cam.set_light(i)
                out.append(cam.capture().image)
            return out

    a, b, c = frames(7), frames(7), frames(8)
    assert all(np.array_equal(x, y) for x, y in zip(a, b, strict=True))
    assert not np.array_equal(a[0], c[0])
    assert not np.array_equal(a[0], a[2])  # same light, fresh noise
    assert a[0].astype(float).sum() > 1.2 * a[1].astype(float).sum()  # the second light is dimmer


@pytest.mark.parametrize("projection", ["orthographic", "perspective"])
def test_ground_truth_normals_match_the_analytic_sphere(projection):
    with SimulatedCamera(_scene(projection)) as cam:
        truth = cam.ground_truth()
        origins, directions = cam.scene.camera.rays()
    c = torch.tensor(CENTER, dtype=torch.float64)
    t_ca = ((c - origins) * directions).sum(-1)
    d2 = ((origins + t_ca[..., None] * directions - c) ** 2).sum(-1)
    hit = d2 < RADIUS**2
    p = origins + (t_ca - torch.sqrt((RADIUS**2 - d2).clamp_min(0)))[..., None] * directions
    n = (p - c) / RADIUS
    expect = torch.nn.functional.normalize(n.reshape(24, 2, 32, 2, 3).sum((1, 3)), dim=-1).numpy()
    block = hit.reshape(24, 2, 32, 2).all(3).all(1).numpy()
    assert truth["normals"].shape == (24, 32, 3) and truth["normals"].dtype == np.float32
    assert np.array_equal(truth["mask"], block) and block.sum() > 50
    assert np.abs(truth["normals"][block] - expect[block]).max() < 1e-5  # float32 storage: ~1e-7
    assert np.isnan(truth["normals"][~block]).all() and np.isnan(truth["depth"][~block]).all()
    depth = p[..., 2].reshape(24, 2, 32, 2).mean((1, 3)).numpy()
    assert np.allclose(truth["depth"][block], depth[block], rtol=1e-6)


def test_render_capture_writes_a_loadable_folder_and_refuses_to_overwrite(tmp_path):
    out = tmp_path / "cap"
    cam = SimulatedCamera(_scene("perspective"))
    capture = cam.render_capture(out, progress=False)
    assert capture.frames.shape == (2, 48, 64) and capture.mask.shape == (24, 32)
    loaded = load_capture(out)
    assert np.array_equal(loaded.frames, capture.frames)
    assert np.array_equal(loaded.mask, capture.mask)
    assert loaded.spec.camera.projection == "perspective" and loaded.spec.camera.intrinsics.fx == 2000.0
    assert loaded.spec.lights[1].direction[2] < 0 and loaded.spec.lights[1].intensity == 0.5
    assert np.array_equal(np.isnan(loaded.ground_truth["normals"]), np.isnan(capture.ground_truth["normals"]))
    assert loaded.ground_truth["depth"].shape == (24, 32)
    assert loaded.ground_truth["scene"]["seed"] == 0
    with pytest.raises(OutputExistsError):
        cam.render_capture(out, progress=False)
    again = cam.render_capture(out, overwrite=True, progress=False)
    assert np.array_equal(again.frames, capture.frames)  # reopened with the same seed


@pytest.mark.cuda
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
def test_cuda_renders_what_the_cpu_renders():
    scene = _scene("perspective", read_noise_e=0.0, shot_noise="none")
    with SimulatedCamera(scene) as cpu, SimulatedCamera(scene, device="cuda") as gpu:
        for i in (0, 1):
            cpu.set_light(i)
            gpu.set_light(i)
            assert torch.allclose(cpu.radiance(i), gpu.radiance(i).cpu(), rtol=1e-9, atol=1e-12)
            assert np.abs(cpu.capture().image.astype(int) - gpu.capture().image.astype(int)).max() <= 1


def test_a_two_material_object_has_a_material_ground_truth():
    config = _scene()
    data = config.model_dump(mode="json")
    data["objects"][0]["split"] = {"normal": [1.0, 0.0, 0.0], "offset": 0.0,
                                   "material": {"model": "lambertian", "k_d": 0.2}}
    with SimulatedCamera(parse_scene_config(data)) as cam:
        two = cam.ground_truth()
    with SimulatedCamera(config) as cam:
        assert "materials" not in cam.ground_truth()  # one material: no map
    materials, mask = two["materials"], two["mask"]
    assert materials.dtype == np.int16 and bool((materials[~mask] == -1).all())
    assert set(np.unique(materials[mask])) <= {0, 1, -2} and (materials == 0).any() and (materials == 1).any()
    cols = np.nonzero(mask.any(0))[0]
    assert bool((materials[:, cols[0]][mask[:, cols[0]]] == 0).all())  # left (x < 0): the object's own material
    assert bool((materials[:, cols[-1]][mask[:, cols[-1]]] == 1).all())  # right: the split's
