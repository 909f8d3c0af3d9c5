"""Camera models for the simulator: exposure, rolling shutter, sensor noise, defocus, JPEG.

A `CameraModel` turns the renderer's instants into what a real camera
delivers. The frame is stamped at $t_s$ (the camera clock's stamp of the
frame, `jaxcal.sim.motion.ClockModel`); row $r$ (0 at the top) is exposed
over $[t_0 + r\\,\\ell,\\ t_0 + r\\,\\ell + E]$ with exposure $E$
(`exposure_s`), line delay $\\ell$ (`line_delay(height)`, the rolling
shutter; 0 for a global shutter) and $t_0 = t_s$, $t_s - E/2$ or $t_s - E$
when the stamp marks the start, middle or end of the first row's exposure
(`stamp`). The pixel's value is the mean of the scene over its row's
exposure, taken at `subframes` evenly spaced instants (the midpoints of equal
slices). Without a rolling shutter those instants are rendered exactly; with
one, the scene is rendered every `step_s` seconds across the whole readout and
each row's instants are linearly interpolated in time between the two
renders around them (one render per `step_s`, not one per row; each render
draws only the band of rows exposed near its instant, `Scene.render(camera, rows)`).

Then, in order: defocus (a Gaussian blur of `defocus_px` pixels' standard
deviation), grey conversion for a monochrome capture, Poisson-Gaussian
sensor noise (a value of $s$ DN holds $s / g$ photo-electrons with gain $g$
= `gain_dn` DN per electron, drawn from a Poisson law and scaled back, plus
Gaussian read noise of `read_noise_dn` DN: the standard deviation at $s$ is
$\\sqrt{g s + \\sigma_r^2}$), rounding to 8 bits, and JPEG compression at
`jpeg_quality`. Lens distortion (Brown-Conrady, OpenCV's $k_1, k_2, p_1,
p_2, k_3$) is the renderer's own (`jaxcal.sim.scene.Scene.render` warps every
render with its distortion map, so each row's time is that of the sensor row
it lands on); `distortion`, when set, is the lens's and replaces
`SimConfig.distortion`.

`lens_supersample` warps the lens at that many times the sensor's resolution
(`jaxcal.sim.scene.SUPERSAMPLE` by default; 1: a bilinear remap at the sensor's
resolution, as another renderer's post-process or a camera's own undistortion
forms images, whose corner errors repeat from frame to frame).

The presets (`PRESETS`, `camera_model(name)`), typical values rather than one
product's measurements:

- `ideal`: a pinhole taking each frame at one instant, noise-free: the
  simulator's historical camera, for analysis and the tests' exact truths.
- `global-shutter`: a machine-vision camera with a global-shutter CMOS sensor
  (the class of Sony Pregius sensors in GigE Vision / USB3 Vision cameras,
  whose EMVA 1288 data sheets give a few electrons of read noise and a full
  well near 10 ke-): 2 ms exposure, stamped at the exposure's start (what the
  GenICam `ChunkTimestamp` of such cameras reports), gain 0.03 DN/e- at 8
  bits, read noise 0.5 DN (the sensor's own and the 8-bit quantisation),
  lossless images.
- `rolling-shutter`: the RGB sensor of a USB webcam or of a common depth
  camera (e.g. Intel RealSense D4xx's colour module, an OmniVision rolling-
  shutter sensor): 25 ms top-to-bottom readout, 8 ms exposure, stamped at the
  start of the frame (the V4L2 `V4L2_BUF_FLAG_TSTAMP_SRC_SOE` convention),
  small pixels (gain 0.094 DN/e-, read noise 2 DN: about 4 DN at mid-grey),
  MJPEG at quality 90.
"""

import math
from dataclasses import dataclass

import cv2
import numpy as np

from ..records_capture import CameraNoise

#: What a frame's stamp marks: the start, middle or end of its first row's exposure.
STAMPS = ("start", "middle", "end")


@dataclass(frozen=True)
class CameraModel:
    """How a simulated camera exposes, reads out and degrades its frames (see the module docstring).

    `readout_s`: the rolling shutter's top-to-bottom readout (the line delay
    is `readout_s / height`; 0: a global shutter). `distortion`: the lens's
    OpenCV coefficients (None: `SimConfig.distortion`). `lens_supersample`: the
    lens warp's supersampling (None: the renderer's).
    """

    name: str = "ideal"
    exposure_s: float = 0.0
    readout_s: float = 0.0
    stamp: str = "middle"
    subframes: int = 8
    step_s: float = 1e-3
    read_noise_dn: float = 0.0
    gain_dn: float = 0.0
    defocus_px: float = 0.0
    jpeg_quality: int | None = None
    distortion: tuple[float, ...] | None = None
    lens_supersample: int | None = None

    def check(self) -> None:
        if self.stamp not in STAMPS:
            raise ValueError(f"camera {self.name!r}: stamp must be one of {STAMPS}, got {self.stamp!r}")
        for key in ("exposure_s", "readout_s", "read_noise_dn", "gain_dn", "defocus_px"):
            value = getattr(self, key)
            if not (math.isfinite(value) and value >= 0.0):
                raise ValueError(f"camera {self.name!r}: {key} must be a finite number >= 0, got {value}")
        if self.exposure_s > 1.0 or self.readout_s > 1.0:
            raise ValueError(f"camera {self.name!r}: exposure and readout are at most 1 s")
        if self.subframes < 1 or not self.step_s > 0.0:
            raise ValueError(f"camera {self.name!r}: subframes >= 1 and step_s > 0 are needed")
        if self.lens_supersample is not None and (
            int(self.lens_supersample) != self.lens_supersample or self.lens_supersample < 1
        ):
            raise ValueError(
                f"camera {self.name!r}: lens_supersample must be a whole number >= 1, got {self.lens_supersample}"
            )
        if self.jpeg_quality is not None and not 1 <= self.jpeg_quality <= 100:
            raise ValueError(f"camera {self.name!r}: jpeg_quality must be in 1..100, got {self.jpeg_quality}")

    @property
    def instantaneous(self) -> bool:
        """Every row at the stamp's instant, nothing added: the renderer's image as it is."""
        return (
            self.exposure_s == 0.0
            and self.readout_s == 0.0
            and self.read_noise_dn == 0.0
            and self.gain_dn == 0.0
            and self.defocus_px == 0.0
            and self.jpeg_quality is None
        )

    def line_delay(self, height: int) -> float:
        """Seconds between the exposures of consecutive rows of a `height`-row image."""
        return self.readout_s / height

    def exposure_start(self) -> float:
        """The first row's exposure start relative to the stamp (s, <= 0)."""
        return {"start": 0.0, "middle": -0.5, "end": -1.0}[self.stamp] * self.exposure_s

    def schedule(self, t_stamp: float, height: int) -> tuple[np.ndarray, np.ndarray]:
        """`(times (K,), weights (height or 1, K))`: the instants to render and each row's
        weights on them (rows sum to 1; one row of weights for all rows without a rolling shutter)."""
        n = self.subframes if self.exposure_s > 0.0 else 1
        offsets = self.exposure_s * (np.arange(n) + 0.5) / n if self.exposure_s > 0.0 else np.zeros(1)
        t0 = t_stamp + self.exposure_start()
        delay = self.line_delay(height)
        if delay == 0.0:
            return t0 + offsets, np.full((1, n), 1.0 / n)
        s = t0 + delay * np.arange(height)[:, None] + offsets[None, :]  # (rows, n) sample instants
        lo, hi = float(s.min()), float(s.max())
        k = max(2, math.ceil((hi - lo) / self.step_s) + 1)
        grid = np.linspace(lo, hi, k)
        pos = (s - lo) / (hi - lo) * (k - 1)
        i = np.clip(np.floor(pos).astype(int), 0, k - 2)
        frac = pos - i
        rows = np.broadcast_to(np.arange(height)[:, None], s.shape)
        w = np.zeros((height, k))
        np.add.at(w, (rows, i), (1.0 - frac) / n)
        np.add.at(w, (rows, i + 1), frac / n)
        return grid, w

    def capture(
        self, render_at, t_stamp: float, height: int, rng: np.random.Generator, grayscale: bool = False
    ):
        """The delivered 8-bit image (`height` rows) of the frame stamped `t_stamp` (controller seconds).

        `render_at(t, rows)`: the renderer's RGB uint8 image at instant `t`, its rows
        `rows = (first, stop)` (`(stop - first, W, 3)`) or all of them for `rows=None`
        (`(H, W, 3)`); under a rolling shutter each instant is rendered only for the
        rows exposed near it. Returns (H, W) for `grayscale`, else RGB (H, W, 3)."""
        if self.instantaneous:
            image = render_at(t_stamp, None)
            return cv2.cvtColor(image, cv2.COLOR_RGB2GRAY) if grayscale else image
        times, weights = self.schedule(t_stamp, height)
        acc = None
        for k, t in enumerate(times):
            w = weights[:, k]
            exposed = np.flatnonzero(w > 0.0)
            if exposed.size == 0:
                continue
            if weights.shape[0] == 1:  # a global shutter: every row at once
                band, rows = render_at(float(t), None).astype(np.float32), slice(None)
            else:  # the rows exposed around instant t: one band (a row's instants increase down the image)
                first, stop = int(exposed[0]), int(exposed[-1]) + 1
                band, rows = render_at(float(t), (first, stop)).astype(np.float32), slice(first, stop)
            if acc is None:
                acc = np.zeros((height, *band.shape[1:]), np.float32)
            acc[rows] += w[rows].astype(np.float32)[:, None, None] * band
        return self.degrade(acc, rng, grayscale)

    def degrade(self, image, rng: np.random.Generator, grayscale: bool = False) -> np.ndarray:
        """Defocus, grey conversion, sensor noise, 8 bits and JPEG applied to a float RGB image (DN)."""
        image = np.asarray(image, np.float32)
        if self.defocus_px > 0.0:
            image = cv2.GaussianBlur(image, (0, 0), self.defocus_px, borderType=cv2.BORDER_REPLICATE)
        if grayscale and image.ndim == 3:
            image = cv2.cvtColor(image, cv2.COLOR_RGB2GRAY)
        image = sensor_noise(image, self.gain_dn, self.read_noise_dn, rng)
        out = np.clip(np.rint(image), 0, 255).astype(np.uint8)
        if self.jpeg_quality is not None:
            out = jpeg(out, self.jpeg_quality)
        return out

    def noise_record(self) -> CameraNoise:
        """The figures a capture plan's prediction takes (`jaxcal.evaluate_plan(..., camera_model=)`):
        the corner noise the preset's sensor noise and JPEG add (`CORNER_NOISE_PX`; a model that is
        no preset has none measured: a `ValueError`), its exposure and readout."""
        preset = PRESETS.get(self.name)
        if self != preset:
            raise ValueError(
                f"camera {self.name!r}: its corner noise is measured for the presets only ({sorted(PRESETS)}); "
                "give jaxcal.evaluate_plan a jaxcal.records_capture.CameraNoise of your own"
            )
        return CameraNoise(
            self.name,
            CORNER_NOISE_PX[self.name],
            self.exposure_s,
            self.readout_s,
            self.exposure_start() + 0.0,
        )

    def metadata(self, height: int) -> dict:
        """The camera's `exposure_s`, `line_delay_s` and `stamp` for `metadata.json`."""
        return {"exposure_s": self.exposure_s, "line_delay_s": self.line_delay(height), "stamp": self.stamp}


def sensor_noise(image, gain_dn: float, read_noise_dn: float, rng: np.random.Generator) -> np.ndarray:
    """Poisson-Gaussian noise on `image` (DN, float): shot noise of `image / gain_dn`
    electrons scaled by `gain_dn`, plus Gaussian read noise of `read_noise_dn` DN."""
    image = np.asarray(image, np.float64)
    if gain_dn > 0.0:
        image = rng.poisson(np.clip(image, 0.0, None) / gain_dn) * gain_dn
    if read_noise_dn > 0.0:
        image = image + read_noise_dn * rng.standard_normal(image.shape)
    return image


def jpeg(image: np.ndarray, quality: int) -> np.ndarray:
    """`image` (uint8 grey or RGB) through JPEG compression at `quality` (OpenCV's encoder)."""
    colour = image.ndim == 3
    data = cv2.cvtColor(image, cv2.COLOR_RGB2BGR) if colour else image
    ok, buf = cv2.imencode(".jpg", data, [cv2.IMWRITE_JPEG_QUALITY, int(quality)])
    if not ok:
        raise RuntimeError("JPEG encoding failed")
    out = cv2.imdecode(buf, cv2.IMREAD_COLOR if colour else cv2.IMREAD_GRAYSCALE)
    return cv2.cvtColor(out, cv2.COLOR_BGR2RGB) if colour else out


#: The named cameras (see the module docstring for their sources).
PRESETS = {
    "ideal": CameraModel(),
    "global-shutter": CameraModel(
        name="global-shutter", exposure_s=2e-3, stamp="start", subframes=4, gain_dn=0.03, read_noise_dn=0.5
    ),
    "rolling-shutter": CameraModel(
        name="rolling-shutter",
        exposure_s=8e-3,
        readout_s=25e-3,
        stamp="start",
        subframes=8,
        gain_dn=0.094,
        read_noise_dn=2.0,
        jpeg_quality=90,
    ),
}


#: The corner noise each preset's sensor noise and JPEG add to the detector's own (px per axis, added in
#: quadrature), on stopped frames: `data/ur5e_sweeps`' ideal images (800x600), every sixth of them
#: (20 frames), each degraded 8 times (`CameraModel.degrade`, seeded), detected and compared with the
#: clean image's corners (1886 and 1878 corners; the MAD sigma of the differences is 0.9x their RMS,
#: their mean below 0.001 px). docs/performance.md, "Realistic captures in the plan's prediction".
CORNER_NOISE_PX = {"ideal": 0.0, "global-shutter": 0.0059, "rolling-shutter": 0.0157}


def camera_model(camera) -> CameraModel:
    """A `CameraModel` from a preset's name (`PRESETS`) or a model itself, checked."""
    if isinstance(camera, CameraModel):
        model = camera
    elif camera in PRESETS:
        model = PRESETS[camera]
    else:
        raise ValueError(f"unknown camera {camera!r}; the presets are {sorted(PRESETS)}")
    model.check()
    return model
