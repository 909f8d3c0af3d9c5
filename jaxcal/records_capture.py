"""What a capture's camera and arm do to its measurements, as figures a prediction can use.

The simulator's camera and arm models (`jaxcal.sim.camera`, `jaxcal.sim.arm`)
render images and move joints; a calibration module may not import them
(`docs/architecture.md`). These frozen records carry the few numbers the
capture planner's prediction needs (`jaxcal.evaluate_plan(...,
camera_model=, arm=)`): `CameraModel.noise_record()` and `ArmModel.figures()`
make them from the simulator's presets, and anyone may write their own.
Like `jaxcal.records`, this module imports nothing from jaxcal but it.
"""

from dataclasses import dataclass

from .records import Record


@dataclass(frozen=True, eq=False)
class CameraNoise(Record):
    """A camera model's effect on one frame's corners.

    - `name`: the model's name (a preset's).
    - `added_sigma_px`: the corner noise its sensor noise and compression add to the
      detector's own (px per axis, independent: added in quadrature), measured on a
      stopped frame.
    - `exposure_s`, `readout_s`: the exposure and the rolling shutter's top-to-bottom
      readout (0: a global shutter); `exposure_start_s`: the first row's exposure start
      relative to the frame's stamp (<= 0). A frame is blurred or skewed only if the arm
      moves during `[stamp + exposure_start_s, stamp + exposure_start_s + readout_s + exposure_s]`.
    """

    name: str = "ideal"
    added_sigma_px: float = 0.0
    exposure_s: float = 0.0
    readout_s: float = 0.0
    exposure_start_s: float = 0.0

    @property
    def window_s(self) -> tuple[float, float]:
        """The frame's exposure window relative to its stamp (s): first row's start, last row's end."""
        return self.exposure_start_s, self.exposure_start_s + self.readout_s + self.exposure_s


@dataclass(frozen=True, eq=False)
class ArmFigures(Record):
    """An arm model's deviations from a rigid arm with perfect encoders.

    `compliance` (rad per kN m of gravity torque) and `backlash_deg` (lost motion, deg) take
    one value for every joint or one per joint, the last holding for the joints after it
    (empty `compliance`: rigid); `counts_per_rev`: motor encoder counts per motor turn;
    `latency_s`: how late the joint readings are stamped.
    """

    name: str = "ideal"
    compliance: tuple[float, ...] = ()
    backlash_deg: tuple[float, ...] = (0.0,)
    counts_per_rev: int = 2**17
    latency_s: float = 0.0
