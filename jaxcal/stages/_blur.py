"""Why a sweep lost its frames: motion blur, told from where the target was lost.

A target that smears across more than a few pixels during the exposure is
no longer found (its markers' bits and corners blur together). A sweep
accelerates from rest, so blur loses the frames where the joint turns
fastest and keeps the slow ones near the ends: when the lost frames are the
fast ones, blur is the cause, and the exposure times the target's image
speed says by how much. A sweep fast throughout may keep only a few fast
frames where the target happened to show well: with the exposure known, blur
is also named when most lost frames smeared the target beyond a detector. The image speed comes from the frames where the
target was found: how far its corners moved per radian of the joint,
times the joint's speed from the encoder log.
"""

import numpy as np

from ._observe import CameraObservations
from ._setup import Setup
from ._synchronise import Sync

#: The lost frames are the fast ones when their median joint speed is this many times the found ones'.
FASTER = 1.5
#: With the exposure known, a smear under this many pixels does not lose a target (px).
SMEAR_PX = 2.0
#: A sweep has lost frames worth explaining when at least this share of them lost the target.
LOST_SHARE = 0.3
#: Blur also explains a sweep's lost frames, fast or not compared with the found ones, when at
#: least this share of them smeared the target by more than `SMEAR_PX` (a sweep fast throughout).
SMEARED_SHARE = 0.75
#: A sweep that lost more than this share of its frames to blur makes the result suspect: an arc's
#: precision goes as the square root of its frames, so more than half lost costs over sqrt(2), and
#: the frames left bunch at the sweep's slow ends.
SUSPECT_SHARE = 0.5


def joint_speed(sync: Sync, joint: int, rows: np.ndarray) -> np.ndarray | None:
    """The joint's speed (rad/s) at the frames `rows`, from the encoder log; None without one."""
    if sync.log_q is None:
        return None
    enc_t, enc_q = sync.log_q
    rate = np.gradient(enc_q[:, joint], enc_t)
    return np.abs(np.interp(sync.t_ctrl[rows], enc_t, rate))


def image_rate(obs: CameraObservations, sync: Sync, joint: int, rows: np.ndarray) -> float | None:
    """How far the target's corners move in the image per radian of the joint (px/rad): the
    median over consecutive found frames of the centroid's displacement over the angle turned."""
    centroids, angles = [], []
    for i in rows:
        det = obs.detections[i]
        if det and sync.q is not None:
            d = next(iter(det.values()))
            centroids.append(d.pixels.mean(axis=0))
            angles.append(sync.q[i, joint])
    if len(centroids) < 2:
        return None
    c, a = np.asarray(centroids), np.asarray(angles)
    dq = np.abs(np.diff(a))
    keep = dq > np.radians(0.5)
    if not keep.any():
        return None
    return float(np.median(np.linalg.norm(np.diff(c, axis=0), axis=1)[keep] / dq[keep]))


def lost_to_blur(setup: Setup, obs: CameraObservations, sync: Sync, joint: int) -> str:
    """Why joint `joint`'s sweep lost its target, when it is motion blur: a sentence naming
    the lost frames, the joint's speed there, the blur the exposure implies and what to
    change; "" when the target was not lost mostly in the sweep's fast frames."""
    rows = np.flatnonzero(np.asarray(sync.joint) == joint)
    if rows.size == 0 or getattr(obs, "detections", None) is None:  # a device's samples do not blur
        return ""
    found = np.array([bool(obs.detections[i]) for i in rows])
    lost = ~found
    speed = joint_speed(sync, joint, rows)
    if speed is None or lost.sum() < max(2, LOST_SHARE * rows.size):
        return ""
    fast = float(np.median(speed[lost]))
    slow = float(np.median(speed[found])) if found.any() else 0.0
    exposure = getattr(obs.camera, "exposure_s", None)
    if exposure is not None and exposure <= 0.0:  # stated instantaneous: nothing smears (trial 14)
        return ""
    rate = image_rate(obs, sync, joint, rows)
    smear = None if exposure is None or rate is None else exposure * speed * rate  # px, per frame
    top = float(np.max(speed[lost]))
    if fast > 0.0 and fast >= FASTER * slow:  # the lost frames are the fast ones
        text = (
            f"motion blur, most likely: the target was lost in {int(lost.sum())} of the sweep's {rows.size} "
            f"frames, the fast ones (the joint turns at {np.degrees(fast):.0f} deg/s there, "
            + (
                f"{np.degrees(slow):.0f} deg/s where it was found)"
                if found.any()
                else "and it was found in none)"
            )
        )
    elif smear is not None and np.mean(smear[lost] > SMEAR_PX) >= SMEARED_SHARE:
        # A sweep so fast that the target smears almost everywhere: the frames it was found in are
        # fast too, but most of those lost smeared it beyond what a detector keeps.
        text = (
            f"motion blur, most likely: the target was lost in {int(lost.sum())} of the sweep's {rows.size} "
            f"frames, {int(np.sum(smear[lost] > SMEAR_PX))} of them while the joint turned at "
            f"{np.degrees(float(np.min(speed[lost][smear[lost] > SMEAR_PX]))):.0f}-{np.degrees(top):.0f} deg/s"
        )
    else:
        return ""
    if smear is not None:
        if exposure * top * rate < SMEAR_PX:
            return ""
        shown = f"{exposure * slow * rate:.1f} px" if found.any() else "nowhere"
        text = text.replace("motion blur, most likely", "motion blur") + (
            f"; with the {1e3 * exposure:g} ms exposure the target smears by up to {exposure * top * rate:.0f} px "
            f"there (it was found at {shown}{' median' if found.sum() > 1 else ''})"
        )
    elif exposure is None:
        text += " (the metadata gives no exposure_s to tell the smear)"
    return (
        text
        + "; shorten the exposure (a smear under a pixel or two keeps the corners), sweep slower, or film "
        "the poses standing still (stop-and-shoot)"
    )


def blur_notes(setup: Setup, obs: CameraObservations, sync: Sync) -> tuple[str, ...]:
    """A note per joint whose sweep lost its fast frames to motion blur (`lost_to_blur`) but
    kept enough for its arc (the verdict's `blur_rows` weigh what the loss costs)."""
    names = setup.dataset.joint_names
    return tuple(
        f"joint {names[j]!r}: {cause}"
        for j in range(len(names))
        if (cause := lost_to_blur(setup, obs, sync, j))
    )


def blur_rows(setup: Setup, obs: CameraObservations, sync: Sync) -> tuple[tuple[str, float, float, str], ...]:
    """The verdict's rows `(name, value, limit, reason)` for the sweeps that lost their fast
    frames to motion blur (`lost_to_blur`): the share of the sweep's frames lost, against
    `SUSPECT_SHARE`; the reason names the blur, the frames the arc rests on and what to change."""
    names = setup.dataset.joint_names
    rows = []
    for j in range(len(names)):
        cause = lost_to_blur(setup, obs, sync, j)
        if not cause:
            continue
        frames = np.flatnonzero(np.asarray(sync.joint) == j)
        kept = sum(bool(obs.detections[i]) for i in frames)
        share = 1.0 - kept / frames.size
        rows.append(
            (
                f"{names[j]}.blur_lost_share",
                share,
                SUSPECT_SHARE,
                f"joint {names[j]!r}: "
                + cause.replace(
                    "; shorten the exposure",
                    f"; its arc rests on the {kept} slow frames left, so the result is less accurate than the "
                    "corners' noise says; shorten the exposure",
                    1,
                ),
            )
        )
    return tuple(rows)
