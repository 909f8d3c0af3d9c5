"""Capture kinds: what a dataset's layout says about how to calibrate it.

A capture is resolved once, by `CaptureKind.of`, into three independent
choices, and every difference between kinds is a property here; the stages
ask the kind, they do not test flags of their own.

| property                | eye-to-hand sweeps | eye-in-hand sweeps | markers on every link | poses        | no encoder log |
| ----------------------- | ------------------ | ------------------ | --------------------- | ------------ | -------------- |
| `fixed_frame`           | `T_cam_base`       | `T_board_base`     | `T_cam_base`          | (its mount)  | (its mount)    |
| `inverts_poses`         | no                 | yes                | no                    | eye-in-hand  |                |
| `has_arcs`              | yes                | yes                | yes                   | no           |                |
| `sequential`            | no                 | no                 | yes                   | no           |                |
| `axis_fit_uses_poses`   | yes                | yes                | no                    | (no fit)     | no             |
| `refines_other_cameras` | yes                | no                 | no                    | eye-to-hand  | no             |
| `keeps_two_stage_gauge` | yes                | yes                | no                    | no           | no             |
| `identifiability_tol`   | 1e-6               | 1e-6               | 1e-3                  | 1e-3         | 1e-3           |
| `per_view_angles`       | no                 | no                 | no                    | no           | yes            |

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
"""

import enum
from dataclasses import dataclass

#: Independence threshold of the refinement's identifiability search when the
#: corners alone decide the gauge (no encoders, or markers on every link): a
#: zero offset then only shows through the home pose of the other joints'
#: sweeps, nearly degenerate with the link geometry (parallel axes: the default
#: threshold keeps directions with singular values ~1e-7 of the largest).
STRICT_TOL = 1e-3
#: ... and otherwise.
DEFAULT_TOL = 1e-6


class Mount(enum.Enum):
    """Where the camera is: fixed in the world, or on the flange."""

    EYE_TO_HAND = "eye_to_hand"
    EYE_IN_HAND = "eye_in_hand"


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

    @classmethod
    def of(
        cls, *, camera_on_flange: bool, segments: tuple, encoders: bool, link_targets: bool
    ) -> "CaptureKind":
        """The kind of a dataset: the camera's mount, and, when every motion
        segment has `joint: null` (arbitrary motion), markers on every link if
        targets ride on links other than the flange (`link_targets`), else
        poses of the flange target."""
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
    def fixed_frame(self) -> str:
        """Name of the frame the robot base is located in."""
        return "T_board_base" if self.eye_in_hand else "T_cam_base"

    @property
    def inverts_poses(self) -> bool:
        """The fits run on inverted PnP poses (the camera's pose in the board frame)."""
        return self.eye_in_hand

    @property
    def has_arcs(self) -> bool:
        """Joint axes come from arc fits (sweeps, or the sequential procedure)."""
        return self.motion is not Motion.POSES

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
    def label(self) -> str:
        """`eye_to_hand` / `eye_in_hand` (the `setup` field of `result.json`)."""
        return self.mount.value

    def describe(self) -> str:
        parts = [self.mount.value.replace("_", "-")]
        parts.append(
            {
                Motion.SWEEPS: "single-joint sweeps",
                Motion.FREE: "markers on every link, free motion",
                Motion.POSES: "poses of the flange target",
            }[self.motion]
        )
        parts.append("encoder log" if self.encoders else "no encoder log")
        return ", ".join(parts)
