"""Markers on every link, arbitrary motion: the seed's sequential initialisation.

When every joint moves at once, no marker traces a clean arc. But a marker on
the child link of joint 1 moves with joint 1 only, so its poses do; the arc
fit (with the encoder) gives joint 1's axis and rate. Undoing joint 1's
rotation, $R(V_1, -r_1 \\alpha_1)$ about that axis, in the poses of the
marker on the child link of joint 2 leaves a motion of joint 2 alone; and so
on to the flange. This is the product of exponentials read backwards:

$$T_{cam,m}(\\alpha) = e^{\\hat\\xi_1 r_1\\alpha_1} \\cdots e^{\\hat\\xi_j r_j\\alpha_j}\\,
T_{cam,m}(0),$$

with every axis $\\xi_i$ expressed at the zero configuration of the joints
before it, exactly what the joint-sweep method measures. The per-joint arcs
then go to the axis fit (lines only: each joint's arc has its own marker) and
the refinement adjusts everything on every corner of every link's marker.

NumPy glue around the jitted arc fit (`jaxcal._arcfit.fit_arc`), one joint
after the other; the maths is the arc fit's.
"""

import numpy as np

from ._arcdata import make_arc_data
from ._npgeom import axis_rotation


def undo_joint(P, O, C, direction, point, angle):
    """Turn poses back about a fitted axis: $P' = Q + R(V, -\\theta)(P - Q)$,
    $O' = R(V, -\\theta) O$, and the $(p, w)$ covariances rotated alike.

    **Arguments:** positions `P` `(F, 3)`, orientations `O` `(F, 3, 3)`,
    covariances `C` `(F, 6, 6)`; the axis `direction` $V$ (unit) and `point`
    $Q$; the joint's turn `angle` $\\theta$ `(F,)` in each frame (rad).
    """
    R = axis_rotation(np.asarray(direction) / np.linalg.norm(direction), -np.asarray(angle))
    Q = np.asarray(point)
    P2 = Q + np.einsum("fab,fb->fa", R, P - Q)
    O2 = R @ O
    B = np.zeros((len(R), 6, 6))
    B[:, :3, :3] = R
    B[:, 3:, 3:] = R
    return P2, O2, B @ C @ np.swapaxes(B, 1, 2)


def arm_targets(ds, nominal):
    """The targets riding on the arm, each with its link index in
    `nominal.link_names` (1 the child of the first joint, ..., joints + 1 the
    flange), flange first; and, per joint, the target whose poses give its arc
    (on the joint's child link; the flange's for the last joint), or a
    `ValueError` naming the joint without one."""
    links = list(nominal.link_names)
    n = nominal.num_joints
    on_arm = [(t, links.index(t.link)) for t in ds.targets if t.link in links[1:]]
    on_arm.sort(key=lambda tk: (tk[1] != n + 1, tk[1]))
    targets = [t for t, _ in on_arm]
    link = np.array([k for _, k in on_arm], int)
    per_joint = []
    for j in range(n):
        want = (j + 1,) if j < n - 1 else (n, n + 1)
        cands = [i for i, k in enumerate(link) if k in want]
        if not cands:
            raise ValueError(
                f"joint {nominal.joint_names[j]!r}: no target on link {links[j + 1]!r}"
                + (f" or {links[n + 1]!r}" if j == n - 1 else "")
                + "; arbitrary motion needs a marker on the child link of every joint"
            )
        per_joint.append(cands)
    return targets, link, per_joint


def link_poses(poses, targets, cands):
    """The poses of a joint's arc target (the candidate seen in most rows):
    positions `(k, 3)`, orientations `(k, 3, 3)`, covariances `(k, 6, 6)` and
    the rows `(k,)` they come from."""
    seen = [sum(targets[i].name in p for p in poses) for i in cands]
    t = targets[cands[int(np.argmax(seen))]]
    idx = np.array([f for f, p in enumerate(poses) if t.name in p], int)
    if idx.size == 0:
        raise ValueError(
            f"target {t.name!r} is never seen: no image shows its markers as metadata.json describes them; "
            "check its dictionary, first_id and squares against the printed plate"
        )
    P = np.stack([poses[f][t.name].T_cam_target[:3, 3] for f in idx])
    O = np.stack([poses[f][t.name].T_cam_target[:3, :3] for f in idx])
    C = np.stack([poses[f][t.name].cov for f in idx])
    return P, O, C, idx


def sequential_sweeps(rows, poses, targets, per_joint, q, t_cam, fit_one, frames: int | None = None):
    """The sequential procedure: per joint, its child link's marker poses with
    the earlier joints undone, and the arc fit of them.

    **Arguments:**
    - `rows`, `poses` (per row a dict target name -> `PoseEstimate`), `q`
      `(rows, joints)` commanded joint positions from the encoder log (rad),
      `t_cam` `(rows,)`.
    - `targets`, `per_joint`: from `arm_targets` (the first candidate target
      seen in most frames is used).
    - `fit_one`: the jitted arc fit of one joint's `ArcData`.
    - `frames`: pad every sweep to this many frames (default: the rows), so
      captures of similar length share the compiled arc fit.

    **Returns:** `(positions, orientations, covariances, mask, arcs)`: per
    joint `(joints, 1, F, ...)` arrays over all rows (padded, masked), and the
    list of `ArcFitResult`s.
    """
    F = len(rows) if frames is None else int(frames)
    n = len(per_joint)
    q_all = np.zeros((F, q.shape[1]))
    q_all[: len(rows)] = q
    Ps = np.zeros((n, 1, F, 3))
    Os = np.broadcast_to(np.eye(3), (n, 1, F, 3, 3)).copy()
    Cs = np.broadcast_to(np.eye(6), (n, 1, F, 6, 6)).copy()
    mask = np.zeros((n, 1, F), bool)
    arcs = []
    for j, cands in enumerate(per_joint):
        P, O, C, idx = link_poses(poses, targets, cands)
        for i, arc in enumerate(arcs):  # undo joints 0 .. j-1, outermost first
            angle = float(arc.rate) * q[idx, i]
            P, O, C = undo_joint(P, O, C, np.asarray(arc.direction), np.asarray(arc.point), angle)
        Ps[j, 0, idx], Os[j, 0, idx], Cs[j, 0, idx], mask[j, 0, idx] = P, O, C, True
        arcs.append(fit_one(make_arc_data(Ps[j], Os[j], q_all[:, j], mask[j], covariances=Cs[j])))
    return Ps, Os, Cs, mask, arcs


def start_mounts(T_cam_links, poses, targets, link):
    """Each target's mount on its link from its PnP poses and the two-stage
    robot, $T_{link,target} \\approx (T_{cam,base} T_{base,link}(q))^{-1}
    T_{cam,target}$ per frame: the rotations averaged (nearest rotation to
    their sum), the median translation.

    **Arguments:** `T_cam_links` `(rows, links, 4, 4)` the two-stage chain to
    every link in each row; `poses`; `targets`; `link` (index per target).
    """
    out = []
    for t, k in zip(targets, link):
        est = [
            np.linalg.inv(T_cam_links[f, k]) @ p[t.name].T_cam_target
            for f, p in enumerate(poses)
            if t.name in p
        ]
        out.append(average_pose(np.stack(est)))
    return np.stack(out)


def average_pose(T: np.ndarray) -> np.ndarray:
    """A robust mean of poses `(k, 4, 4)` (per-frame estimates of one fixed
    transform): the nearest rotation to the sum of the rotations, the median
    translation."""
    U, _, Vt = np.linalg.svd(T[:, :3, :3].sum(0))
    out = np.eye(4)
    out[:3, :3] = U @ np.diag([1.0, 1.0, np.linalg.det(U @ Vt)]) @ Vt
    out[:3, 3] = np.median(T[:, :3, 3], axis=0)
    return out
