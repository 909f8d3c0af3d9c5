"""ROS messages -> jaxcal's dataset pieces: images, intrinsics, stamps, motion segments.

Pure functions of deserialised `rosbags` messages (ROS 1 and ROS 2 alike:
`rosbags` gives both the same field layout, except the ROS 1 CameraInfo's
upper-case `K`, `D`, which `camera_intrinsics` reads either way). Nothing
here opens a bag; `jaxcal.io.rosbag` does.
"""

from dataclasses import dataclass

import numpy as np

from ..errors import BagEncodingError

#: Raw `sensor_msgs/Image` encodings read, with their channel count.
RAW_ENCODINGS = {"mono8": 1, "bgr8": 3, "rgb8": 3}
#: `sensor_msgs/CameraInfo.distortion_model` values read, with their coefficient counts
#: (ROS's D: plumb_bob k1 k2 p1 p2 k3; rational_polynomial adds k4 k5 k6: OpenCV's order).
DISTORTION_MODELS = {"plumb_bob": (5,), "rational_polynomial": (8,), "": (0,)}
_PNG = b"\x89PNG\r\n\x1a\n"
_JPEG = b"\xff\xd8\xff"


def stamp_ns(header) -> int:
    """A `std_msgs/Header`'s stamp as integer nanoseconds (no float rounding)."""
    return int(header.stamp.sec) * 1_000_000_000 + int(header.stamp.nanosec)


@dataclass(frozen=True)
class EncodedImage:
    """One image ready for the dataset: the file's bytes, its extension and size."""

    data: bytes
    suffix: str
    width: int
    height: int


def encode_raw(msg, where: str) -> EncodedImage:
    """A `sensor_msgs/Image` (mono8, bgr8, rgb8) as a lossless PNG (BGR channel order, OpenCV's)."""
    enc = str(msg.encoding).lower()
    if enc not in RAW_ENCODINGS:
        raise BagEncodingError(
            f"{where}: image encoding {msg.encoding!r} is not supported (supported: {', '.join(RAW_ENCODINGS)}, "
            "or sensor_msgs/CompressedImage in PNG or JPEG)"
        )
    ch = RAW_ENCODINGS[enc]
    h, w, step = int(msg.height), int(msg.width), int(msg.step)
    buf = np.asarray(msg.data, np.uint8)
    if step < w * ch or buf.size < step * h:
        raise BagEncodingError(
            f"{where}: {msg.encoding} image of {w}x{h} with step {step} holds {buf.size} bytes "
            f"(expected at least {w * ch} per row and {step * h} in all)"
        )
    if step >= 2 * w * ch:  # row padding is a few bytes of alignment, not whole rows' worth
        guess = {1: "mono8", 3: "bgr8 or rgb8"}.get(step // w, f"{step // w} bytes a pixel")
        raise BagEncodingError(
            f"{where}: {msg.encoding} image of {w}x{h} with step {step}: {step / (w * ch):g} times the "
            f"{w * ch} bytes a {msg.encoding} row holds, as the rows of {guess} are; is the encoding "
            "field right?"
        )
    img = buf[: step * h].reshape(h, step)[:, : w * ch].reshape((h, w, ch) if ch > 1 else (h, w))
    if enc == "rgb8":
        img = img[..., ::-1]
    import cv2  # here: a command that reads no bag's images does not load OpenCV for it

    ok, png = cv2.imencode(".png", np.ascontiguousarray(img))
    if not ok:  # pragma: no cover - OpenCV encodes any 8-bit array
        raise BagEncodingError(f"{where}: OpenCV could not encode the image as PNG")
    return EncodedImage(png.tobytes(), ".png", w, h)


def encode_compressed(msg, where: str) -> EncodedImage:
    """A `sensor_msgs/CompressedImage`: decoded with `cv2.imdecode` (to check it and read its size); a
    PNG or JPEG keeps its bytes as they are (no second compression), anything else becomes a PNG."""
    data = bytes(np.asarray(msg.data, np.uint8).tobytes())
    fmt = str(msg.format).lower()
    if "compresseddepth" in fmt.replace(" ", ""):
        raise BagEncodingError(f"{where}: compressedDepth images ({msg.format!r}) are not supported")
    import cv2

    img = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise BagEncodingError(f"{where}: cv2.imdecode cannot decode the image (format {msg.format!r})")
    if img.dtype != np.uint8:
        raise BagEncodingError(
            f"{where}: {img.dtype} image (format {msg.format!r}); only 8-bit images are read"
        )
    h, w = img.shape[:2]
    if data.startswith(_PNG):
        return EncodedImage(data, ".png", w, h)
    if data.startswith(_JPEG):
        return EncodedImage(data, ".jpg", w, h)
    ok, png = cv2.imencode(".png", img)
    if not ok:  # pragma: no cover
        raise BagEncodingError(f"{where}: OpenCV could not re-encode the image as PNG")
    return EncodedImage(png.tobytes(), ".png", w, h)


def camera_intrinsics(msg, where: str) -> tuple[list | None, list, int, int]:
    """`(K or None, distortion, width, height)` of a `sensor_msgs/CameraInfo`.

    K is `None` when the message carries none (all zeros: an uncalibrated
    camera), so the calibration self-calibrates. Distortion: plumb_bob's 5 or
    rational_polynomial's 8 coefficients (OpenCV's order), five zeros when D
    is empty; another model is a `BagEncodingError`.
    """
    k = np.asarray(getattr(msg, "k", getattr(msg, "K", None)), np.float64).reshape(-1)
    d = np.asarray(getattr(msg, "d", getattr(msg, "D", ())), np.float64).reshape(-1)
    model = str(msg.distortion_model)
    if model not in DISTORTION_MODELS and d.size and np.any(d != 0):
        raise BagEncodingError(
            f"{where}: distortion model {model!r} is not supported (supported: plumb_bob, rational_polynomial)"
        )
    if d.size == 0 or not np.any(d != 0):
        dist = [0.0] * 5
    elif d.size in (4, 5, 8, 12, 14):
        dist = d.tolist()
    else:
        raise BagEncodingError(f"{where}: {model} distortion has {d.size} coefficients; expected 5 or 8")
    K = None if k.size != 9 or not np.any(k != 0) else k.reshape(3, 3).tolist()
    return K, dist, int(msg.width), int(msg.height)


# --------------------------------------------------------------------------- motion segments


@dataclass(frozen=True)
class SegmentOptions:
    """How motion segments are found in a joint log.

    - `velocity_threshold`: a joint moves when its speed exceeds this (rad/s,
      or m/s for a prismatic joint); the speed is a central difference over
      `window_s`, so encoder quantisation (about 5e-5 rad a count) reads as
      about 1e-3 rad/s, well below the default.
    - `min_segment_s`: shorter single-joint intervals are ignored (a window's
      worth of two joints starting or stopping together).
    """

    velocity_threshold: float = 0.02
    window_s: float = 0.1
    min_segment_s: float = 0.1


def joint_speeds(t: np.ndarray, q: np.ndarray, window_s: float) -> np.ndarray:
    """|dq/dt| per sample and joint, a central difference over `window_s` (interpolated; clamped at the ends)."""
    h = window_s / 2
    lo, hi = np.maximum(t - h, t[0]), np.minimum(t + h, t[-1])
    span = np.maximum(hi - lo, 1e-12)
    return np.stack(
        [np.abs(np.interp(hi, t, q[:, j]) - np.interp(lo, t, q[:, j])) / span for j in range(q.shape[1])], 1
    )


def _runs(code: np.ndarray) -> list[tuple[int, int, int]]:
    """Runs of equal values: `(value, first index, last index + 1)`."""
    edges = np.r_[0, np.flatnonzero(np.diff(code)) + 1, len(code)]
    return [(int(code[s]), int(s), int(e)) for s, e in zip(edges[:-1], edges[1:])]


def segment_tuples(segments: list[dict]) -> list[tuple]:
    """`find_segments`' `motion` entries as a dataset's segments: `(joint or None, start, end)`."""
    return [(s["joint"], s["start"], s["end"]) for s in segments]


def find_segments(
    t, q, joint_names, options: SegmentOptions = SegmentOptions()
) -> tuple[list[dict], list[str]]:
    """The `motion` list of a joint log (docs/dataset.md), and notes saying what was found.

    A sweep segment is a maximal interval in which exactly one joint moves
    (speed above `options.velocity_threshold`); runs of the same joint
    separated only by standstill (a turnaround, or a stepped sweep that stops
    for each image) are one segment. Stop-and-shoot captures, where several
    joints move together between still poses, have no such interval: the
    whole log becomes one `{"joint": null}` segment, which makes the capture
    pose-based (`Motion.POSES`, or `Motion.FREE` with markers on every link).
    When both occur the single-joint sweeps are kept and the multi-joint
    moves (transitions between sweeps) left out, with a note.
    """
    t, q = np.asarray(t, np.float64), np.asarray(q, np.float64)
    moving = joint_speeds(t, q, options.window_s) > options.velocity_threshold
    count = moving.sum(axis=1)
    code = np.where(count == 1, moving.argmax(axis=1), np.where(count == 0, -1, -2))
    runs = _runs(code)
    merged: list[list[int]] = []  # [joint, first, end]
    last_joint = None
    for value, s, e in runs:
        if value >= 0:
            if merged and last_joint == value:
                merged[-1][2] = e
            else:
                merged.append([value, s, e])
            last_joint = value
        elif value == -2:
            last_joint = None
    segments = [
        {"joint": joint_names[j], "start": float(t[s]), "end": float(t[e - 1])}
        for j, s, e in merged
        if t[e - 1] - t[s] >= options.min_segment_s
    ]
    several = any(v == -2 and t[e - 1] - t[s] >= options.min_segment_s for v, s, e in runs)
    notes = []
    if segments:
        notes.append(
            f"{len(segments)} single-joint sweep segment(s) found in the joint log: "
            + ", ".join(f"{s['joint']} {s['start']:.3f}-{s['end']:.3f} s" for s in segments)
        )
        if several:
            notes.append(
                "intervals where several joints moved at once are left out (transitions between sweeps)"
            )
        return segments, notes
    if several:
        notes.append(
            "no joint moves alone but several move together: a stop-and-shoot (pose-based) capture, one "
            "'joint: null' segment over the whole log"
        )
        return [{"joint": None, "start": float(t[0]), "end": float(t[-1])}], notes
    notes.append("no joint moves faster than the threshold in the joint log: no motion segments written")
    return [], notes
