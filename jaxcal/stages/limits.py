"""What a plausible calibration looks like: the limits of the verdict's checks (`jaxcal.stages.verdict`)."""

from dataclasses import dataclass


@dataclass(frozen=True)
class Limits:
    """What a plausible calibration looks like (each a bound on the reported estimate).

    - `origin_mm`, `origin_deg`: a joint origin's translation (norm) and each
      of its roll / pitch / yaw away from nominal (3 sigma of a real arm's
      deviation is a few mm and a fraction of a degree).
    - `zero_offset_deg`: a zero offset's correction.
    - `ratio_percent`: a reduction ratio away from nominal.
    - `mount_mm`, `mount_deg`: a target mount away from its nominal (when the
      metadata gives one).
    - `board_scale_percent`: the joint axes' spacing measured through the
      target against the nominal robot's (a mis-sized target scales every
      measured length, the tool point's error with it, while a real arm's axes
      agree with its datasheet to about a millimetre over its long links:
      docs/calibrate.md).
    - `arc_residual`, `axis_residual`: whitened RMS of the arc fits and of the
      axis fit (about 1 when the pose covariances are honest).
    - `sigma_px`, `outlier_fraction`: the refinement's pixel noise and the
      share of corners it rejects.
    - `intrinsics_rms_px`: a self-calibration's reprojection RMS.
    - `shutter_sigmas`, `readout_s`: a global-shutter refinement whose residuals
      point to a rolling shutter's line delay by more than `shutter_sigmas`
      standard deviations and a readout (the delay times the image height) of
      at least `readout_s` (the score test of `jaxcal._diagnostics.line_delay_test`).
    - `arm_false_alarm`: how often each of the arm checks may flag a rigid
      arm (`jaxcal.stages._armcheck`, gravity sag or backlash: an arm that is
      not rigid): the score test of the sweeps' axes moving with the gravity
      torques is flagged above the F law's quantile at this rate, where the
      compliance the axes fit is one of a real arm: positive (a sag) and at
      least `arm_compliance_rad_per_kNm` (200 kN m/rad; a UR5's shoulder is
      32); the arcs' clock against the refinement's beyond the normal law's
      two-sided quantile (2.58 at 0.01).
    - `correlation_sigmas`: the refinement's residuals repeat from frame to frame
      (each corner's along a run of the capture), or are shared by the views of one
      pose, by more than this many standard deviations (the one-sided tests of
      `jaxcal.stages._refine.error_correlation`); the covariance then takes the kernel
      sandwich where larger. Such a result is `suspect` when that sandwich grows the tool
      point's 1-sigma by more than `correlation_growth` (the errors then matter to the
      answer); below it the verdict notes the correlation and the result stands, its
      uncertainty the sandwich's (a capture of small steps between frames, whose detector
      errors repeat a little, is not refused for it).
    - `lens_sigmas`, `lens_px`: a refinement whose residuals point to a radial
      distortion beyond the given lens by more than `lens_sigmas` standard deviations
      and a shift of at least `lens_px` at the image's corner (the score test of
      `jaxcal._diagnostics.lens_test`); `intrinsics_sigmas`, `intrinsics_px`: likewise,
      focal lengths and a principal point beyond the given ones
      (`jaxcal._diagnostics.intrinsics_test`; a lower limit than the lens's: a focal length 1 %
      off, which the camera's distance absorbs, reads 9.6 sigmas and leaves the tool point
      15 times its claimed error).
    - `encoder_interpolation`: how far interpolating the encoder log linearly where the sweeps
      accelerate puts the target off, beyond what a joint's zero and ratio absorb
      (`_verdict.interpolation_error` at the target's distance from the axis, RMS over the
      joint's frames), against the frames' own scatter (the arc's position RMS).
      `data/ur5e_sweeps`' log thinned to 10, 20 and 50 Hz reads 1.67, 1.27 and 0.11; the first
      two double the tool point's error or more. `stamp_jitter`: likewise, the camera stamps'
      jitter around a steady frame rate times the sweeps' speed, at the target
      (`_timing.stamp_jitter_s`).
    - `ee_sigma_mm`: the tool point's 1-sigma uncertainty the covariance
      implies (RMS over random configurations): above it, the capture does
      not determine the robot well enough to trust it.
    - `joint_span_deg`, `joint_span_mm`: stop-and-shoot poses, the least span of
      each revolute (prismatic) joint's positions over the distinct poses: a joint
      that stays put leaves its zero offset and the geometry it carries
      undetermined, whatever the other joints do.
    - `outlier_fraction` also bounds the share of stop-and-shoot poses the robust
      point fit rejects; `noise_scale`, the calibrated model's residual scale over the
      noise the samples state (a noise in metres given as millimetres, or a model that misses
      most of the error, makes every figure that uses the stated noise wrong).
    """

    origin_mm: float = 15.0
    origin_deg: float = 3.0
    zero_offset_deg: float = 5.0
    ratio_percent: float = 5.0
    mount_mm: float = 30.0
    mount_deg: float = 10.0
    board_scale_percent: float = 0.4
    arc_residual: float = 5.0
    axis_residual: float = 5.0
    sigma_px: float = 2.0
    outlier_fraction: float = 0.2
    intrinsics_rms_px: float = 1.0
    shutter_sigmas: float = 10.0
    readout_s: float = 1e-3
    arm_false_alarm: float = 0.01
    arm_compliance_rad_per_kNm: float = 0.005
    correlation_sigmas: float = 5.0
    correlation_growth: float = 1.2
    lens_sigmas: float = 10.0
    lens_px: float = 0.5
    intrinsics_sigmas: float = 5.0
    encoder_interpolation: float = 0.5
    stamp_jitter: float = 0.5
    intrinsics_px: float = 0.5
    ee_sigma_mm: float = 3.0
    joint_span_deg: float = 5.0
    joint_span_mm: float = 10.0
    noise_scale: float = 30.0
