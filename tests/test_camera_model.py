"""The simulator's camera model (`jaxcal.sim.camera`) against analytic expectations:
a moving point's blur length, a rolling-shutter row's time, the sensor noise's
standard deviation, and the dataset metadata it writes."""

import json

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import pytest
from test_clocksync import OFFSET_S as CLOCK_OFFSET_S
from test_clocksync import _sweeps as clock_sweeps

from jaxcal._clocksync import exposure_middle, fit_clock_offset
from jaxcal.cli import CAMERAS
from jaxcal.errors import DatasetError
from jaxcal.io._metadata import CameraInfo, read_cameras
from jaxcal.io._schema import Loc
from jaxcal.io.dataset import load_dataset
from jaxcal.markers import TargetSpec
from jaxcal.sim.camera import PRESETS, CameraModel, camera_model, sensor_noise
from jaxcal.sim.scene import CameraSpec, Scene
from jaxcal.sim.simulate import SimConfig, simulate

# --------------------------------------------------------------------------- the schedule (no rendering)


def test_presets_match_the_command_line():
    assert tuple(PRESETS) == CAMERAS
    for name in PRESETS:
        assert camera_model(name).name == name
    assert camera_model("ideal").instantaneous
    with pytest.raises(ValueError, match="unknown camera"):
        camera_model("pinhole")
    with pytest.raises(ValueError, match="stamp"):
        camera_model(CameraModel(stamp="begin"))


@pytest.mark.parametrize("stamp, start", [("start", 0.0), ("middle", -0.5), ("end", -1.0)])
def test_global_shutter_samples_the_exposure_evenly(stamp, start):
    cam = CameraModel(exposure_s=0.01, stamp=stamp, subframes=4)
    times, w = cam.schedule(2.0, 480)
    assert w.shape == (1, 4) and np.allclose(w, 0.25)
    assert np.allclose(times, 2.0 + 0.01 * (start + (np.arange(4) + 0.5) / 4))


def test_rolling_shutter_row_times():
    """Each row's weighted mean instant is its exposure's middle, t0 + r * line delay + E / 2."""
    cam = CameraModel(exposure_s=0.004, readout_s=0.024, stamp="start", subframes=4, step_s=5e-4)
    height = 120
    times, w = cam.schedule(1.0, height)
    assert w.shape == (height, len(times)) and np.allclose(w.sum(axis=1), 1.0)
    expected = 1.0 + cam.line_delay(height) * np.arange(height) + 0.002
    assert np.allclose(w @ times, expected, atol=1e-12)


def _moving_line(speed_px_s: float, width: int = 96, height: int = 40, x0: float = 20.0):
    """A renderer of a bright vertical line (a 1.5 px box, area-sampled) at x0 + speed * t."""
    cols = np.arange(width)

    def render_at(t: float, rows=None) -> np.ndarray:
        x = x0 + speed_px_s * t
        cover = np.clip(np.minimum(cols + 0.5, x + 0.75) - np.maximum(cols - 0.5, x - 0.75), 0.0, 1.0)
        row = np.rint(160.0 * cover / 1.5).astype(np.uint8)
        image = np.repeat(np.repeat(row[None, :, None], height, axis=0), 3, axis=2)
        return image if rows is None else image[rows[0] : rows[1]]

    return render_at


def _half_max_width(profile: np.ndarray) -> float:
    """Width at half maximum of a single-peaked profile, crossings interpolated linearly."""
    p = profile - np.median(profile)
    half = 0.5 * p.max()
    above = np.flatnonzero(p >= half)
    i, j = above[0], above[-1]
    left = i - 1 + (half - p[i - 1]) / (p[i] - p[i - 1])
    right = j + (p[j] - half) / (p[j] - p[j + 1])
    return float(right - left)


def test_blur_length_is_speed_times_exposure():
    speed, exposure = 1500.0, 0.01  # 15 px of travel
    cam = CameraModel(exposure_s=exposure, subframes=32)
    image = cam.capture(_moving_line(speed), 0.0, 40, np.random.default_rng(0))
    assert abs(_half_max_width(image[20, :, 0].astype(float)) - speed * exposure) < 1.0


def test_rolling_shutter_line_lands_where_its_row_time_says():
    speed, height = 800.0, 40
    cam = CameraModel(readout_s=0.05, stamp="start", step_s=1e-3)
    image = cam.capture(_moving_line(speed, height=height), 0.0, height, np.random.default_rng(0))
    cols = np.arange(image.shape[1])
    for r in (0, 13, 39):
        p = image[r, :, 0].astype(float)
        x = (p * cols).sum() / p.sum()
        assert abs(x - (20.0 + speed * cam.line_delay(height) * r)) < 0.1, r


def test_noise_std_matches_the_poisson_gaussian_model():
    rng = np.random.default_rng(3)
    gain, read = 0.094, 2.0
    for level in (20.0, 128.0, 220.0):
        flat = np.full((300, 300), level)
        noisy = sensor_noise(flat, gain, read, rng)
        assert abs(noisy.mean() - level) < 0.05
        assert abs(noisy.std() / np.sqrt(gain * level + read**2) - 1.0) < 0.02
        delivered = CameraModel(gain_dn=gain, read_noise_dn=read).degrade(flat, rng).astype(float)
        assert abs(delivered.std() / np.sqrt(gain * level + read**2 + 1.0 / 12.0) - 1.0) < 0.02


# --------------------------------------------------------------------------- metadata


def test_camera_metadata_round_trip_and_checks():
    info = CameraInfo("cam0", 64, 48, None, np.zeros(5), exposure_s=0.008, line_delay_s=5e-4, stamp="start")
    d = json.loads(json.dumps(info.to_dict()))
    (back,) = read_cameras({"cameras": [d]}, Loc("metadata.json", "cameras"), ())
    assert (back.exposure_s, back.line_delay_s, back.stamp) == (0.008, 5e-4, "start")
    plain = CameraInfo("cam0", 64, 48, None, np.zeros(5)).to_dict()
    assert "exposure_s" not in plain
    (back,) = read_cameras({"cameras": [plain | {"stamp": None}]}, Loc("m", "cameras"), ())
    assert (back.exposure_s, back.line_delay_s, back.stamp) == (None, None, None)
    for bad, match in (
        ({"stamp": "begin"}, "stamp"),
        ({"exposure_s": -0.001}, "exposure_s"),
        ({"line_delay_s": 0.5}, "seconds per row"),
    ):
        with pytest.raises(DatasetError, match=match):
            read_cameras({"cameras": [d | bad]}, Loc("m", "cameras"), ())


# --------------------------------------------------------------------------- rendered


def _sphere_scene(width: int = 96, height: int = 64, depth: float = 0.3):
    """A white sphere on a slide joint along x, filmed from `depth` above by a camera looking down."""
    spec = mujoco.MjSpec()
    spec.visual.global_.offwidth, spec.visual.global_.offheight = width, height
    spec.visual.headlight.ambient = [1.0, 1.0, 1.0]
    mat = spec.add_material(name="white")
    mat.emission, mat.rgba = 1.0, [1.0, 1.0, 1.0, 1.0]
    body = spec.worldbody.add_body(name="slider")
    body.add_joint(name="x", type=mujoco.mjtJoint.mjJNT_SLIDE, axis=[1.0, 0.0, 0.0])
    body.add_geom(type=mujoco.mjtGeom.mjGEOM_SPHERE, size=[0.004, 0, 0], material="white", pos=[0, -0.04, 0])
    cam = CameraSpec("cam0", width, height, 50.0)
    spec.worldbody.add_camera(name="cam0", pos=[0.0, 0.0, depth], quat=[1.0, 0.0, 0.0, 0.0], fovy=50.0)
    return Scene(spec, (), (cam,), ("world", "slider"), ("x",)), cam


def test_a_band_of_rows_renders_as_the_full_image_has_it():
    """`Scene.render(camera, rows)` draws a band of rows alone (a rolling shutter renders each
    instant only for the rows exposed near it): the full image's rows, with a floor, shadows and
    a plate in view, to the rasteriser's rounding (its projection differs in the last bits, which
    can flip a multisample at an edge: a pixel in thousands; a band one row off differs in 12 %);
    a lens's camera falls back to slicing the full image."""
    from jaxcal.robots import load_robot
    from jaxcal.sim.scene import PlateSpec, build_scene

    T_world_base = np.eye(4)
    T_world_base[2, 3] = -3.0
    T_world_target = np.eye(4)
    T_world_target[:3, :3] = np.diag([1.0, -1.0, -1.0])  # facing the camera
    T_world_target[2, 3] = 0.5
    spec = TargetSpec(kind="charuco", squares=(5, 4), square_length=0.03, marker_length=0.022)
    cameras = [
        CameraSpec("cam0", 160, 120),
        CameraSpec("lens", 160, 120, distortion=(-0.1, 0.02, 0.0, 0.0, 0.0)),
    ]
    with build_scene(
        load_robot("ur5e"),
        plates=[PlateSpec(spec, "world", T_world_target)],
        cameras=cameras,
        T_world_base=T_world_base,
        floor_z=-0.4,
        shadows=True,
    ) as scene:
        for name in ("cam0", "lens"):
            full = scene.render(name)
            assert full.std() > 20.0  # the plate is in view
            differ = []
            for rows in [(0, 120), (0, 7), (37, 52), (59, 60), (111, 120)]:
                band = scene.render(name, rows).astype(int)
                assert band.shape == (rows[1] - rows[0], 160, 3)
                differ.append(np.abs(band - full[rows[0] : rows[1]]).max(axis=-1).ravel() > 0)
                assert differ[-1].mean() < 0.05, (name, rows)
            assert np.concatenate(differ).mean() < 5e-3, name
        with pytest.raises(ValueError, match="not a band"):
            scene.render("cam0", (50, 50))


@pytest.mark.slow
def test_rendered_blur_and_row_time():
    scene, cam = _sphere_scene()
    depth, speed = 0.3, 0.4  # m, m/s
    f = cam.K[0, 0] / depth  # px per metre at the sphere
    row = cam.K[1, 1] * 0.04 / depth + cam.K[1, 2]  # the sphere's row (y = -0.04 m is image down)

    def render_at(t, rows=None):
        scene.set_angles([speed * t])
        return scene.render("cam0", rows)

    with scene:
        exposure = 0.12  # 11 px of travel: several times the sphere's width
        blurred = CameraModel(exposure_s=exposure, stamp="middle", subframes=48)
        image = blurred.capture(render_at, 0.0, cam.height, np.random.default_rng(0))
        profile = image[int(round(row)) - 1 : int(round(row)) + 2, :, 0].astype(float).sum(axis=0)
        assert abs(_half_max_width(profile) - speed * exposure * f) < 1.0

        rolling = CameraModel(readout_s=0.1, stamp="start", step_s=5e-4)
        image = rolling.capture(render_at, 0.0, cam.height, np.random.default_rng(0)).astype(float)[..., 0]
        image -= np.median(image)
        rows, cols = np.mgrid[: cam.height, : cam.width]
        x = (image * cols).sum() / image.sum()
        t_row = rolling.line_delay(cam.height) * (image * rows).sum() / image.sum()
        assert abs(x - (cam.K[0, 2] + f * speed * t_row)) < 0.3


@pytest.mark.slow
def test_simulate_writes_the_camera_into_the_metadata(tmp_path):
    config = SimConfig(resolution=(64, 48), frames_per_joint=2, camera="rolling-shutter", grayscale=True)
    ds = load_dataset(simulate(config, tmp_path / "ds", progress=False))
    cam = ds.cameras[0]
    model = PRESETS["rolling-shutter"]
    assert (cam.exposure_s, cam.stamp) == (model.exposure_s, model.stamp)
    assert cam.line_delay_s == pytest.approx(model.readout_s / 48)
    assert (
        json.loads((tmp_path / "ds" / "metadata.json").read_text())["simulation"]["camera"]
        == "rolling-shutter"
    )


# --------------------------------------------------------------------------- the estimator: exposure middles


def test_exposure_middle_of_the_stamps():
    t = np.array([1.0, 2.0])
    assert np.allclose(exposure_middle(t, 0.01, "start"), t + 0.005)
    assert np.allclose(exposure_middle(t, 0.01, "middle"), t)
    assert np.allclose(exposure_middle(t, 0.01, "end"), t - 0.005)
    assert exposure_middle(t, None, "start") is t and exposure_middle(t, 0.01, None) is t


def test_clock_offset_from_start_stamped_frames_is_the_exposure_middles():
    """Analytic sweeps whose frames are exposed around `t_mid` but stamped at their exposure's
    start: moved to their exposure's middle, the frames give the offset of the exact middles
    (the fit's own noise aside, within its standard deviation of the truth); the bare stamps
    give one half an exposure early."""
    data, t_mid, enc_t, enc_q, _ = clock_sweeps(0)
    exposure = 0.012
    stamps = np.asarray(t_mid) - 0.5 * exposure

    solve = jax.jit(lambda t: fit_clock_offset(data, t, enc_t, enc_q))

    def fit(t_cam):
        return solve(jnp.asarray(t_cam))

    exact = fit(t_mid)
    assert abs(float(exact.offset_s) - CLOCK_OFFSET_S) < 3.0 * float(exact.std_s)
    middles = float(fit(exposure_middle(stamps, exposure, "start")).offset_s)
    assert abs(middles - float(exact.offset_s)) < 1e-7
    bare = float(fit(stamps).offset_s)
    assert abs(bare - (float(exact.offset_s) - 0.5 * exposure)) < 1e-5
