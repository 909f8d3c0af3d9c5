"""Stage 2, observe: intrinsics, marker detection and PnP (with covariance)
in every frame of the cameras the calibration uses (OpenCV, through
`jaxcal.vision`)."""

import time
from dataclasses import dataclass

import numpy as np

from .._clocksync import exposure_middle
from ..errors import CalibrationError
from ..io.dataset import CameraInfo, Dataset, DeviceInfo, TargetInfo
from ..records import Intrinsics
from ..records_stages import ByTarget
from ..vision import Detection, PoseEstimate, calibrate_intrinsics, detect_frames, estimate_pose
from ._setup import Options, Setup


@dataclass(frozen=True, eq=False)
class CameraObservations:
    """One camera's frames.

    - `rows`: the frame-table rows of this camera; `t_cam`: their camera-clock
      times (s), each frame's exposure middle when the metadata says where the
      stamp sits in the exposure (`frame_times`), else its stamp.
    - `detections`: per row, the `jaxcal.vision.Detection` of each target found (`ByTarget`).
    - `poses`: per row, the `PoseEstimate` of each target (`ByTarget`; targets not found, or
      without a pose, are absent). For an eye-in-hand camera, the camera's
      pose in the board frame (the inverted PnP pose, covariance carried).
    - `K`, `dist`: the intrinsics used; `intrinsics`: where they came from.
    - `dropped`: rows whose PnP reprojection error is far above the rest
      (`pnp_outliers`): their poses are left out (their corners still go to
      the refinement, whose robust loss weighs them).
    - `has_orientation`: the poses carry a measured orientation (False for a
      device measuring a point: only `T_cam_target[:3, 3]` and `cov[:3, :3]` count).
    - `t_first_row`: with a rolling shutter of known line delay, each frame's
      first-row time (its exposure middle); `t_cam` then holds the time of its
      poses, the first row's plus the mean row of its detected corners times the
      line delay (`pose_times`). `None` otherwise (every row at `t_cam`).
    """

    camera: CameraInfo
    rows: np.ndarray
    detections: tuple[ByTarget[Detection], ...]
    poses: tuple[ByTarget[PoseEstimate], ...]
    t_cam: np.ndarray
    K: np.ndarray
    dist: np.ndarray | None
    intrinsics: Intrinsics
    dropped: tuple = ()
    has_orientation: bool = True
    t_first_row: np.ndarray | None = None

    @property
    def frame_times(self) -> np.ndarray:
        """Each frame's first-row time (s, camera clock): the time its corner rows are counted from."""
        return self.t_cam if self.t_first_row is None else self.t_first_row

    @property
    def found(self) -> np.ndarray:
        """Rows where some target has a pose."""
        return np.array([bool(p) for p in self.poses])


@dataclass(frozen=True, eq=False)
class SampleObservations:
    """A measuring device's samples (tracker data, `Mount.DEVICE`): no images, so no
    detections and no intrinsics, only the measured point per sample.

    - `camera`: the device (`jaxcal.io.dataset.DeviceInfo`), in the role a camera has
      for images: the source of the observations, named in the outputs.
    - `rows`, `t_cam`: the sample rows and their device-clock stamps (s).
    - `poses`: per sample, the point's pose in the device frame (`ByTarget` of the one
      point's `PoseEstimate`: the position, the orientation when measured, else the identity, and the covariance;
      only `T_cam_target[:3, 3]` and `cov[:3, :3]` count without orientations).
    - `has_orientation`: the samples carry a measured orientation.
    """

    camera: DeviceInfo
    rows: np.ndarray
    poses: tuple[ByTarget[PoseEstimate], ...]
    t_cam: np.ndarray
    has_orientation: bool
    dropped: tuple = ()

    @property
    def found(self) -> np.ndarray:
        """Every sample holds its point."""
        return np.ones(len(self.rows), bool)

    @property
    def intrinsics(self) -> Intrinsics:
        """What `result.json` says of intrinsics: there are none."""
        return Intrinsics(source=f"none ({self.camera.kind.replace('_', ' ')} samples, no images)")


@dataclass(frozen=True, eq=False)
class Observations:
    """The two-stage camera's observations and the further cameras' (for the refinement)."""

    primary: CameraObservations | SampleObservations
    others: tuple[CameraObservations, ...]
    #: Seconds per step: free-form.
    timings: dict[str, float]
    notes: tuple[str, ...] = ()


#: A pose is an outlier when its PnP reprojection RMS exceeds this many times
#: the camera's median, and `PNP_OUTLIER_PX` pixels.
PNP_OUTLIER_RATIO = 5.0
PNP_OUTLIER_PX = 0.5


def pnp_outliers(poses: list) -> dict[int, dict]:
    """Per row, the targets whose PnP reprojection RMS is far above the camera's
    median (`PNP_OUTLIER_RATIO` times, and over `PNP_OUTLIER_PX`): a misdetected
    or distorted target (a smudged or bent plate, a reflection) whose pose
    would pull the arcs. `{row: {target: rms_px}}`."""
    rms = [p.rms_px for d in poses for p in d.values()]
    if len(rms) < 5:
        return {}
    limit = max(PNP_OUTLIER_RATIO * float(np.median(rms)), PNP_OUTLIER_PX)
    out = {}
    for i, d in enumerate(poses):
        bad = {name: p.rms_px for name, p in d.items() if p.rms_px > limit}
        if bad:
            out[i] = bad
    return out


def camera_rows(ds: Dataset, camera: str) -> np.ndarray:
    """The frame-table rows of `camera`."""
    rows = np.flatnonzero(ds.frames.camera == camera)
    if rows.size == 0:
        raise CalibrationError(f"{ds.root / 'frames.csv'}: no frames for camera {camera!r}")
    return rows


def detect_poses(
    ds: Dataset, rows, targets, K, dist, *, workers=None, progress=True, detections=None
) -> tuple[list, list]:
    """Detections and PnP poses of `targets` in the frames `rows`; `detections` (per row a dict
    target name -> `Detection`) are taken as they are instead of detecting the images.

    **Returns:** `(detections, poses)`: per row a dict target name ->
    `Detection`, and per row a dict target name -> `PoseEstimate`.
    """
    if detections is None:
        paths = [ds.image_path(int(i)) for i in rows]
        dets = detect_frames(
            paths, [t.spec for t in targets], K=K, dist=dist, workers=workers, progress=progress
        )
    else:
        dets = _given(detections, rows, targets)
    poses = []
    for det in dets:
        p = {}
        for t in targets:
            d = det.get(t.name)
            if d is not None:
                est = estimate_pose(d, t.spec, K, dist)
                if est is not None:
                    p[t.name] = est
        poses.append(p)
    return dets, poses


def _given(detections, rows, targets) -> list:
    """Given detections of one camera's `rows` (`observe`'s `detections`), checked: one dict per
    row, the targets' names only."""
    dets = [dict(d) for d in detections]
    if len(dets) != len(rows):
        raise CalibrationError(f"{len(dets)} frames of detections given for the camera's {len(rows)} frames")
    names = {t.name for t in targets}
    unknown = sorted({k for d in dets for k in d} - names)
    if unknown:
        raise CalibrationError(f"detections given for unknown targets {unknown} (targets: {sorted(names)})")
    return dets


def self_calibrate(
    ds: Dataset, camera: CameraInfo, targets, rows, *, workers=None, progress=True, detections=None
):
    """Intrinsics from the ChArUco frames themselves (the seed's variant); `(K, dist, rms_px)`.
    `detections`: the frames' detections given (`observe`'s), else the images are detected."""
    charuco = [t for t in targets if t.spec.kind == "charuco"]
    if not charuco:
        raise CalibrationError(
            f"{ds.root / 'metadata.json'}: camera {camera.name!r} has no intrinsics (K is null) and no "
            "ChArUco target to self-calibrate them from"
        )
    t = charuco[0]
    if detections is None:
        paths = [ds.image_path(int(i)) for i in rows]
        dets = detect_frames(paths, [t.spec], workers=workers, progress=progress)
    else:
        dets = _given(detections, rows, targets)
    found = [d[t.name] for d in dets if t.name in d]
    return calibrate_intrinsics(found, t.spec, (camera.width, camera.height))


def observe_camera(
    ds: Dataset,
    camera: CameraInfo,
    targets: tuple[TargetInfo, ...],
    options: Options,
    *,
    invert: bool = False,
    detections=None,
) -> CameraObservations:
    """Intrinsics (from the metadata, else self-calibrated from the ChArUco
    frames), detection and PnP in every frame of `camera`; with `invert`, the
    poses are the camera's in the target frame. `detections`: per frame of the
    camera (its frame-table rows in order) a dict target name -> `Detection`,
    taken instead of detecting the images."""
    rows = camera_rows(ds, camera.name)
    K, dist = camera.K, camera.dist
    source, rms_px = "metadata", None
    if K is None:
        options.say(
            f"camera {camera.name}: no intrinsics in the metadata, self-calibrating from the ChArUco frames"
        )
        K, dist, rms = self_calibrate(
            ds,
            camera,
            targets,
            rows,
            workers=options.workers,
            progress=options.progress,
            detections=detections,
        )
        source, rms_px = "self-calibrated (ChArUco)", float(rms)
    intrinsics = Intrinsics(source, rms_px=rms_px, K=np.asarray(K), distortion=np.asarray(dist))
    if detections is None:
        options.say(
            f"detecting {', '.join(t.name for t in targets)} in {len(rows)} frames of camera {camera.name}"
        )
    dets, poses = detect_poses(
        ds, rows, targets, K, dist, workers=options.workers, progress=options.progress, detections=detections
    )
    outliers = pnp_outliers(poses)
    poses = [{k: p for k, p in d.items() if k not in outliers.get(i, {})} for i, d in enumerate(poses)]
    if invert:
        poses = [{k: p.inverse() for k, p in d.items()} for d in poses]
    dropped = tuple((int(rows[i]), name, rms) for i, bad in outliers.items() for name, rms in bad.items())
    t_frame = frame_times(ds, camera, rows)
    t_poses = pose_times(t_frame, dets, camera.line_delay_s)
    return CameraObservations(
        camera,
        rows,
        tuple(map(ByTarget.of, dets)),
        tuple(map(ByTarget.of, poses)),
        t_poses,
        np.asarray(K),
        dist,
        intrinsics,
        dropped,
        t_first_row=None if t_poses is t_frame else t_frame,
    )


def frame_times(ds: Dataset, camera: CameraInfo, rows) -> np.ndarray:
    """Camera-clock times of `camera`'s frames `rows`: the middle of each frame's exposure when the
    metadata gives the camera's `exposure_s` and `stamp`, else the stamps as they are."""
    return np.asarray(exposure_middle(ds.frames.timestamp[rows], camera.exposure_s, camera.stamp))


def pose_times(t_frame: np.ndarray, detections: list, line_delay_s: float | None) -> np.ndarray:
    """The times the frames' poses refer to under a rolling shutter: each frame's
    first-row time plus the mean row of its detected corners (every target's) times
    the line delay, $t + \\bar y\\,\\ell$. `t_frame` itself (the same array) when
    the line delay is unknown or zero: a global shutter.

    A pose from corners spread over rows is the plate's at about its mean row's
    time; the refinement times every corner at its own row (`jaxcal._reprojection`)."""
    if not line_delay_s:
        return t_frame
    rows = np.array(
        [
            np.mean(np.concatenate([d.pixels[:, 1] for d in det.values()])) if det else 0.0
            for det in detections
        ]
    )
    return np.asarray(t_frame, np.float64) + rows * line_delay_s


def observe_device(setup: Setup) -> SampleObservations:
    """A measuring device's samples as poses of its point, in the device frame:
    the position (identity rotation when no orientation was measured) and the
    sample's isotropic covariance (`TrackerSamples.covariances`)."""
    ds = setup.dataset
    s, name = ds.samples, setup.targets[0].name
    cov = s.covariances()
    k = cov.shape[-1]
    poses = []
    for i in range(len(s.sample)):
        T = np.eye(4)
        T[:3, 3] = s.position[i]
        if s.orientation is not None:
            T[:3, :3] = s.orientation[i]
        C = np.eye(6)
        C[:k, :k] = cov[i]
        poses.append(ByTarget((name,), (PoseEstimate(T, C, 0.0, 1, 0.0),)))
    rows = np.arange(len(s.sample))
    return SampleObservations(
        setup.camera, rows, tuple(poses), ds.frames.timestamp, s.orientation is not None
    )


def _too_small(camera, targets) -> str:
    """The distance from `camera` beyond which the smallest of `targets`' markers is too small
    to be found (`TargetSpec.min_marker_px`), as a clause of an error; "" without markers or `K`."""
    sizes = [(t.spec.marker_length, t.spec.min_marker_px) for t in targets if t.spec.min_marker_px]
    if camera.K is None or not sizes:
        return ""
    length, px = min(sizes)
    far = float(camera.K[0, 0]) * length / px
    return (
        f", or whether the markers are big enough in the images: a {1e3 * length:g} mm marker is under "
        f"the {px:g} px a side it needs to be found beyond {far:.2f} m from this camera (fx "
        f"{float(camera.K[0, 0]):.0f} px): film it closer, at a higher resolution, or print it larger"
    )


def observe(setup: Setup, options: Options, detections: dict | None = None) -> Observations:
    """Observe the two-stage camera (and, for the refinement, every further
    camera): a `CalibrationError` when no target is found at all. A measuring
    device's samples are its observations as they are (`observe_device`).

    `detections`: camera name -> per frame of that camera (its rows of the frame
    table, in order) a dict target name -> `jaxcal.vision.Detection`, used instead
    of detecting the camera's images (everything after detection, PnP on, is the
    same): corners from another detector, or analytic ones (`jaxcal.sim.corners`)
    for studies of the estimator without rendering."""
    given = {} if detections is None else dict(detections)
    ds = setup.dataset
    t0 = time.perf_counter()
    if not setup.kind.images:
        return Observations(observe_device(setup), (), {"observe_s": time.perf_counter() - t0})
    primary = observe_camera(
        ds,
        setup.camera,
        setup.targets,
        options,
        invert=setup.kind.inverts_poses,
        detections=given.get(setup.camera.name),
    )
    if not primary.found.any():
        raise CalibrationError(
            f"{ds.root}: no target was found in any of the {len(primary.rows)} images of camera "
            f"{setup.camera.name!r}; check the targets' dictionary "
            f"({', '.join(sorted({t.spec.dictionary for t in setup.targets}))}), ids and sizes in metadata.json"
            + _too_small(setup.camera, setup.targets)
        )
    timings = {"detect_s": time.perf_counter() - t0}
    t0 = time.perf_counter()
    others = []
    for c in setup.extra_cameras:
        options.say(
            f"camera {c.name}: detecting {', '.join(t.name for t in setup.targets)} for the refinement"
        )
        others.append(observe_camera(ds, c, setup.targets, options, detections=given.get(c.name)))
    if setup.extra_cameras:
        timings["detect_other_cameras_s"] = time.perf_counter() - t0
    notes = []
    for o in (primary, *others):
        if o.dropped:
            files = [f"{ds.frames.file[r]} ({name}, {rms:.2f} px)" for r, name, rms in o.dropped[:10]]
            notes.append(
                f"camera {o.camera.name!r}: {len(o.dropped)} pose(s) left out of the "
                f"{'arc fits' if setup.kind.has_arcs else 'closed-form start'}, their PnP "
                f"reprojection error far above the rest: {', '.join(files)}"
                + (" ..." if len(o.dropped) > 10 else "")
            )
    return Observations(primary, tuple(others), timings, tuple(notes))
