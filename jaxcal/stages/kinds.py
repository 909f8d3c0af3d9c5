"""Capture kinds: what a dataset's layout says about how to calibrate it.

A capture is resolved once, by `CaptureKind.of`, into three independent
choices, and every difference between kinds is a property here; the stages
ask the kind, they do not test flags of their own.

| property                | eye-to-hand sweeps | eye-in-hand sweeps | markers on every link | poses        | no encoder log | tracker sweeps  | tracker poses   |
| ----------------------- | ------------------ | ------------------ | --------------------- | ------------ | -------------- | --------------- | --------------- |
| `fixed_frame`           | `T_cam_base`       | `T_board_base`     | `T_cam_base`          | (its mount)  | (its mount)    | `T_device_base` | `T_device_base` |
| `fixed_frame_free`      | yes                | yes                | yes                   | yes          |                | not with `device_is_base` | not with `device_is_base` |
| `images`                | yes                | yes                | yes                   | yes          |                | no (samples)    | no (samples)    |
| `inverts_poses`         | no                 | yes                | no                    | eye-in-hand  |                | no              | no              |
| `has_arcs`              | yes                | yes                | yes                   | no           |                | yes             | no              |
| `fits_points`           | no                 | no                 | no                    | no           |                | no              | yes             |
| `sequential`            | no                 | no                 | yes                   | no           |                | no              | no              |
| `axis_fit_uses_poses`   | yes                | yes                | no                    | (no fit)     | no             | yes             | (no fit)        |
| `refines_corners`       | yes                | yes                | yes                   | yes          |                | no (no corners) | no (no corners) |
| `refines_other_cameras` | yes                | no                 | no                    | eye-to-hand  | no             | no              | no              |
| `keeps_two_stage_gauge` | yes                | yes                | no                    | no           | no             | yes             | no              |
| `identifiability_tol`   | 1e-6               | 1e-6               | 1e-3                  | 1e-3         | 1e-3           | 1e-6            | 1e-3            |
| `per_view_angles`       | no                 | no                 | no                    | no           | yes            | no              | no              |
| `single_joint_sweeps`   | yes                | yes                | no                    | no           |                | yes             | no              |
| `fits_rates`            | yes                | yes                | yes                   | yes          | no             | yes             | yes             |
| `rates_from_arcs`       | yes                | yes                | yes                   | no           | no             | yes             | no              |
| `terms_in`              | refinement         | refinement         | refinement            | refinement   |                | (none)          | point fit       |
| `default_terms`         | compliance, backlash | compliance, backlash | compliance, backlash | compliance, backlash | | ()          | ()              |
| `fixed_board`           | no                 | yes                | no                    | eye-in-hand  |                | no              | no              |
| `flange_targets_only`   | yes                | no                 | no                    | no           |                | yes             | no              |
| `unsupported`           |                    |                    | without encoders      | without encoders |            |                 |                 |
| `sensor`                | camera             | camera             | camera                | camera       |                | device          | device          |
| `targets_label`         | target(s)          | target(s)          | target(s)             | target(s)    |                | point           | point           |
| `ee_point`              | target origin, camera frame | camera origin, board frame | (eye-to-hand's) | (its mount's) |  | measured point, device frame | measured point, device frame |

- **Eye-to-hand, single-joint sweeps** (the seed method): fixed cameras film
  targets on the flange while one joint turns at a time.
- **Eye-in-hand**: the camera rides on the flange and films a board fixed in
  the world. The camera's pose in the board frame follows exactly the arcs a
  flange target traces in a fixed camera's frame, so the same fits run on
  the inverted PnP poses, the board in the role of the camera and the camera
  in that of the flange target.
- **Markers on every link, arbitrary motion** (`Motion.FREE`): every joint
  moves at once; the seed's sequential procedure recovers each joint's arc
  from its child link's plate with the earlier joints undone.
- **Poses** (`Motion.POSES`, stop-and-shoot or any motion with the target
  on the flange only): no arcs; the refinement starts from the nominal
  robot and a closed-form hand-eye estimate of the camera and mount.
- **No encoder log**: the arcs are fitted with per-frame angles (ratios are
  not identifiable), and the refinement makes each view's joint angle an
  unknown.
- **Tracker sweeps** (`Mount.DEVICE`): an external measuring device (laser
  tracker, motion capture, the controller's logged tool point) gives a 3-D
  point (and optionally an orientation) per sample in its own frame: the
  samples are the arcs' marker positions, the device pose `T_device_base`
  plays `T_cam_base`'s role, or, with `device_is_base`, is the identity
  (the device frame is the base frame, which makes the base height d1
  identifiable). No corners: the two-stage fit is the result (see
  `jaxcal.stages.refine` for why a point refinement would add nothing).
- **Tracker poses** (`Mount.DEVICE`, `Motion.POSES`): the most common
  calibration in the field, stop-and-shoot poses where every joint moves
  between samples. No arcs: the point samples are fitted directly to the
  forward kinematics (`jaxcal._pointfit`, the residual model of point
  samples), which gives the kinematic corrections, the device frame and the
  point's mount, and, gated by cross-validation, joint compliance and
  transmission harmonics.
"""

import enum
from dataclasses import dataclass

import numpy as np

from .._correction import ParameterLayout
from .._kinematics import KinematicModel

#: Independence threshold of the refinement's identifiability search when the
#: corners alone decide the gauge (no encoders, or markers on every link): a
#: zero offset then only shows through the home pose of the other joints'
#: sweeps, nearly degenerate with the link geometry (parallel axes: the default
#: threshold keeps directions with singular values ~1e-7 of the largest).
STRICT_TOL = 1e-3
#: ... and otherwise.
DEFAULT_TOL = 1e-6
#: A joint counts as "at zero" (not the one sweeping) within this angle.
AT_ZERO_DEG = 0.05
#: The sweeping joint must be at least this far from zero for encoder-based assignment.
MOVING_DEG = 0.5


class Mount(enum.Enum):
    """Where the camera is: fixed in the world, or on the flange."""

    EYE_TO_HAND = "eye_to_hand"
    EYE_IN_HAND = "eye_in_hand"
    DEVICE = "device"


class Motion(enum.Enum):
    """How the robot moved: one joint at a time, or every joint at once."""

    SWEEPS = "sweeps"
    FREE = "free"
    POSES = "poses"


@dataclass(frozen=True)
class CaptureKind:
    """The kind of a capture (see the module docstring for what each implies)."""

    mount: Mount
    motion: Motion
    encoders: bool
    device_is_base: bool = False

    @classmethod
    def of(
        cls,
        *,
        camera_on_flange: bool,
        segments: tuple,
        encoders: bool,
        link_targets: bool,
        device: bool = False,
        device_is_base: bool = False,
        device_poses: bool = False,
    ) -> "CaptureKind":
        """The kind of a dataset: the camera's mount (`device`: an external
        measuring device, whose samples are single-joint sweeps or, with
        `device_poses`, stop-and-shoot poses: see `device_poses`), and, when
        every motion segment has `joint: null` (arbitrary motion), markers on
        every link if targets ride on links other than the flange
        (`link_targets`), else poses of the flange target. `device_is_base`:
        the device frame is the robot's base frame (tracker data only)."""
        if device:
            motion = Motion.POSES if device_poses else Motion.SWEEPS
            return cls(Mount.DEVICE, motion, encoders, device_is_base)
        arbitrary = bool(segments) and all(j is None for j, _, _ in segments)
        if not arbitrary:
            motion = Motion.SWEEPS
        elif link_targets and not camera_on_flange:
            motion = Motion.FREE
        else:
            motion = Motion.POSES
        return cls(Mount.EYE_IN_HAND if camera_on_flange else Mount.EYE_TO_HAND, motion, encoders)

    @property
    def eye_in_hand(self) -> bool:
        return self.mount is Mount.EYE_IN_HAND

    @property
    def device(self) -> bool:
        """An external measuring device's samples (no images)."""
        return self.mount is Mount.DEVICE

    @property
    def fixed_frame(self) -> str:
        """Name of the frame the robot base is located in."""
        return {Mount.EYE_IN_HAND: "T_board_base", Mount.DEVICE: "T_device_base"}.get(
            self.mount, "T_cam_base"
        )

    @property
    def fixed_frame_free(self) -> bool:
        """The fixed frame's pose is an unknown (with `device_is_base` it is the identity)."""
        return not self.device_is_base

    @property
    def images(self) -> bool:
        """Observations come from images (detection and PnP), not from a device's samples."""
        return not self.device

    @property
    def refines_corners(self) -> bool:
        """The reprojection refinement applies (there are corners to reproject)."""
        return self.images

    @property
    def inverts_poses(self) -> bool:
        """The fits run on inverted PnP poses (the camera's pose in the board frame)."""
        return self.eye_in_hand

    @property
    def has_arcs(self) -> bool:
        """Joint axes come from arc fits (sweeps, or the sequential procedure)."""
        return self.motion is not Motion.POSES

    @property
    def fits_points(self) -> bool:
        """The device's samples are fitted directly to the forward kinematics
        (stop-and-shoot poses: `jaxcal._pointfit`), not through arcs."""
        return self.device and self.motion is Motion.POSES

    @property
    def sequential(self) -> bool:
        """Each joint's arc comes from its child link's plate, earlier joints undone."""
        return self.motion is Motion.FREE

    @property
    def axis_fit_uses_poses(self) -> bool:
        """The axis fit matches the marker zero poses too, not only the lines: the
        zero configuration is known in the sweeps (encoders) and one marker
        serves every arc (not so with markers on every link)."""
        return self.encoders and self.motion is Motion.SWEEPS

    @property
    def refines_other_cameras(self) -> bool:
        """Further fixed cameras join the refinement (each with its own pose)."""
        return self.mount is Mount.EYE_TO_HAND and self.motion is not Motion.FREE and self.encoders

    @property
    def keeps_two_stage_gauge(self) -> bool:
        """The refinement frees only what the axis fit could see. Without
        encoders the lines-only axis fit holds the mount at nominal, which the
        corners do see; with markers on every link the mounts are the
        refinement's own: the corners decide."""
        return self.encoders and self.motion is Motion.SWEEPS

    @property
    def identifiability_tol(self) -> float:
        """Independence threshold of the refinement's identifiability search."""
        return DEFAULT_TOL if self.keeps_two_stage_gauge else STRICT_TOL

    @property
    def per_view_angles(self) -> bool:
        """Without an encoder log each view's joint angle is an unknown of the refinement."""
        return not self.encoders

    @property
    def single_joint_sweeps(self) -> bool:
        """One joint turns at a time: frames are assigned to sweeps, whose arcs also
        show the clock offset (else each frame's angles are read at its time)."""
        return self.motion is Motion.SWEEPS

    @property
    def fits_rates(self) -> bool:
        """The encoder rates (reduction ratios) are unknowns of the refinement: an
        encoder log gives each view's angle up to them."""
        return self.encoders

    @property
    def rates_from_arcs(self) -> bool:
        """The refinement starts the encoder rates from the arc fits (else at one)."""
        return self.encoders and self.has_arcs

    @property
    def terms_in(self) -> str | None:
        """Where the non-geometric terms (`jaxcal._terms`) are fitted: `"refinement"` (every
        corner, each view's basis from the encoder log), `"point fit"` (stop-and-shoot samples)
        or None (no encoder log to read the poses and their approach from; tracker sweeps,
        whose two-stage fit is final)."""
        if self.fits_points:
            return "point fit"
        return "refinement" if self.refines_corners and self.encoders else None

    @property
    def default_terms(self) -> tuple[str, ...]:
        """The families `terms="auto"` tries: compliance and lost motion where the
        refinement fits terms (every camera capture with an encoder log: a cobot's
        sag and backlash are millimetres at the tool); none on tracker data (named
        with `terms`: the point fit's published figures are the geometric model's)."""
        return ("compliance", "backlash") if self.terms_in == "refinement" else ()

    @property
    def fixed_board(self) -> bool:
        """The camera films a board fixed in the world; the fits' target is the
        board's pattern riding on the flange (`Setup.board`)."""
        return self.mount is Mount.EYE_IN_HAND

    @property
    def flange_targets_only(self) -> bool:
        """The two-stage arcs come from the flange's targets alone (a target on
        another link is not used, and said so)."""
        return self.mount is not Mount.EYE_IN_HAND and self.motion is Motion.SWEEPS

    @property
    def unsupported(self) -> str | None:
        """Why a capture of this kind cannot be calibrated (None when it can)."""
        if self.encoders or self.device:
            return None
        if self.motion is Motion.POSES:
            return (
                "a pose-based capture (arbitrary motion, no plate on the links) needs the encoder log: "
                "each image's joint positions come from it"
            )
        if self.motion is Motion.FREE:
            return (
                "arbitrary motion (no single-joint 'motion' segment) needs the encoder log: the "
                "sequential method undoes each joint's rotation with its encoder angle"
            )
        return None

    @property
    def sensor(self) -> str:
        """What observes the robot, in words: `camera` or `device`."""
        return "device" if self.device else "camera"

    @property
    def targets_label(self) -> str:
        """What the sensor observes on the robot, in words."""
        return "point" if self.device else "target(s)"

    @property
    def ee_point(self) -> str:
        """The point whose error the validation reports, and its frame, in words."""
        return {
            Mount.EYE_IN_HAND: "camera origin, board frame",
            Mount.DEVICE: "measured point, device frame",
        }.get(self.mount, "target origin, camera frame")

    def layout(self, model: KinematicModel, num_markers: int = 1, **kwargs) -> ParameterLayout:
        """The correction vector's layout for this kind (the fixed frame's name,
        eye-in-hand names); `kwargs` as `ParameterLayout`'s."""
        return ParameterLayout.of(
            model, num_markers, eye_in_hand=self.eye_in_hand, fixed_name=self.fixed_frame, **kwargs
        )

    @property
    def label(self) -> str:
        """`eye_to_hand` / `eye_in_hand` / `device` (the `setup` field of `result.json`)."""
        return self.mount.value

    def describe(self) -> str:
        if self.device:
            parts = [
                "external measuring device"
                + (" (its frame is the base frame)" if self.device_is_base else "")
            ]
        else:
            parts = [self.mount.value.replace("_", "-")]
        parts.append(
            {
                Motion.SWEEPS: "single-joint sweeps",
                Motion.FREE: "markers on every link, free motion",
                Motion.POSES: "stop-and-shoot poses" if self.device else "poses of the flange target",
            }[self.motion]
        )
        parts.append(
            ("joint positions" if self.device else "encoder log") if self.encoders else "no encoder log"
        )
        return ", ".join(parts)


#: A tracker table's samples are single-joint sweeps (from zero) when at least
#: this share of them has one joint away from zero and the others at zero.
SWEEP_SHARE = 0.5


def single_joint_share(q: np.ndarray | None) -> float | None:
    """The share of configurations `q (N, joints)` with exactly one joint more than
    `MOVING_DEG` from zero and every other within `AT_ZERO_DEG` (None without `q`)."""
    if q is None or len(q) == 0:
        return None
    away = np.abs(q) > np.radians(MOVING_DEG)
    still = np.abs(q) < np.radians(AT_ZERO_DEG)
    one = (away.sum(axis=1) == 1) & ((away | still).all(axis=1))
    return float(one.mean())


def device_poses(
    segments: tuple, has_joint: bool, single_joint_share: float | None, unassigned: int = 0
) -> bool:
    """Whether a measuring device's samples are fitted as stop-and-shoot poses rather
    than as single-joint sweeps: no sample names its sweeping joint, and either every
    motion segment has `joint: null`, or there are no segments and fewer than
    `SWEEP_SHARE` of the samples look like a sweep from zero (`single_joint_share`,
    from the table's joint positions; None without them: sweeps, which then need
    segments or an encoder log). A table that names sweeping joints for some samples
    and leaves others empty (`unassigned` of them) mixes sweeps and poses: with the
    joint positions given, the point fit takes every sample at once."""
    if has_joint:
        return unassigned > 0 and single_joint_share is not None
    if segments:
        return all(j is None for j, _, _ in segments)
    return single_joint_share is not None and single_joint_share < SWEEP_SHARE
