"""Hand-eye as a product: captures on disk, `jaxcal handeye`, detections to data, checks, verdicts, honest std."""

import csv
import dataclasses
import json
import shutil
import types

import cv2
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx
import pytest

import jaxcal
from jaxcal import _handeye as he
from jaxcal._handeye.consistency import homography_rotations
from jaxcal._linalg import concurrent_decompositions
from jaxcal.cli import main
from jaxcal.errors import DatasetError
from jaxcal.io.handeye import (
    POSE_COLUMNS,
    HandEyeCamera,
    load_hand_eye_capture,
    matrix_to_quaternion,
    matrix_to_rpy,
    pose_rows,
    quaternion_to_matrix,
    repeated_poses,
    rpy_to_matrix,
    write_hand_eye_description,
)
from jaxcal.io.ros import read_easy_handeye, read_static_transform
from jaxcal.markers import TargetSpec
from jaxcal.vision import Detection, hand_eye_from_detections

K = np.array([[600.0, 0.0, 319.5], [0.0, 600.0, 239.5], [0.0, 0.0, 1.0]])
DIST = np.array([-0.12, 0.05, 0.001, -0.0005, 0.0])
CHESSBOARD = TargetSpec("chessboard", squares=(8, 7), square_length=0.025, margin=0.02, name="board")


def _pose(rotvec, t) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = cv2.Rodrigues(np.asarray(rotvec, np.float64))[0]
    T[:3, 3] = t
    return T


def _err(T_est, T_true):
    """(translation error m, rotation error rad)."""
    dR = np.asarray(T_est)[:3, :3] @ T_true[:3, :3].T
    return np.linalg.norm(np.asarray(T_est)[:3, 3] - T_true[:3, 3]), np.linalg.norm(cv2.Rodrigues(dR)[0])


def eye_in_hand_views(rng, target: TargetSpec, frames: int):
    """Analytic eye-in-hand views of `target` 0.5 m away: `(T_base_ee, T_cam_board (frames, 4, 4), X, Y)`,
    X = T_ee_cam, Y = T_base_board; the board's relative rotations span about 30 deg about every axis."""
    X = _pose([0.1, -0.1, 1.5], [0.04, -0.03, 0.07])
    Y = _pose([np.pi, 0.0, 0.2], [0.6, 0.05, 0.02])
    centre = _pose([0.0, 0.0, 0.0], -target.points().mean(0))
    A = np.stack(
        [
            _pose(rng.normal(0.0, 0.25, 3), [*rng.normal(0.0, 0.02, 2), 0.5 + rng.normal(0.0, 0.03)]) @ centre
            for _ in range(frames)
        ]
    )
    T_base_ee = np.stack([Y @ np.linalg.inv(a) @ np.linalg.inv(X) for a in A])  # A = X^-1 T^-1 Y
    return T_base_ee, A, X, Y


def project(target, A, dist=None):
    P = target.points()
    out = []
    for a in A:
        uv, _ = cv2.projectPoints(P, cv2.Rodrigues(a[:3, :3])[0], a[:3, 3], K, dist)
        out.append(uv.reshape(-1, 2))
    return np.stack(out)


# --------------------------------------------------------------------------- detections to data


def test_detections_with_distortion_give_the_exact_answer():
    """Distorted analytic detections (some frames missing) through `hand_eye_from_detections`: the
    distortion is removed inside, frames are padded to a bucket, and the solve is exact."""
    rng = np.random.default_rng(0)
    T_base_ee, A, T_ee_cam, Y = eye_in_hand_views(rng, CHESSBOARD, 12)
    uv = project(CHESSBOARD, A, DIST)
    ids = np.arange(CHESSBOARD.num_points)
    dets = [Detection(ids, p) for p in uv]
    dets[3] = None
    dets[7] = {"other": Detection(ids, uv[7])}  # detect_frames' dicts work too
    obs = hand_eye_from_detections(dets, CHESSBOARD, T_base_ee, K, DIST, eye_in_hand=True, sigma_px=0.1)
    assert obs.frames == 12 and obs.data.T_base_ee.shape == (16, 4, 4)  # padded to the 16-frame bucket
    assert obs.data.board_points.shape == (48, 3)  # 42 corners padded to 48
    assert obs.poses[0][3] is None and obs.poses[0][7] is None
    assert np.asarray(obs.data.mask)[0, :12].any(-1).tolist() == [f not in (3, 7) for f in range(12)]
    r = jax.jit(jaxcal.calibrate_hand_eye)(obs.data)
    assert bool(r.result == optx.RESULTS.successful)
    np.testing.assert_allclose(r.T_ee_cam[0], T_ee_cam, atol=1e-7)
    np.testing.assert_allclose(r.T_base_board, Y, atol=1e-7)
    assert float(r.pixel_rms) < 1e-5


def test_symmetric_target_is_resolved_by_the_robot():
    """A symmetric circle grid whose detections come back turned by 180 degrees in some frames (as
    OpenCV reports them): the robot's motion says which, and the solve is exact. The blobs are the
    circles' images' centroids, not the images of their centres (`circle_centre_shift`): they
    are moved back, without which the camera lies 15 um off."""
    from jaxcal.vision._pose import circle_centre_shift

    target = TargetSpec("circles", squares=(7, 6), square_length=0.03, marker_length=0.015, name="grid")
    rng = np.random.default_rng(1)
    T_base_ee, A, T_ee_cam, Y = eye_in_hand_views(rng, target, 10)
    ids = np.arange(target.num_points)
    uv = project(target, A) + np.stack([circle_centre_shift(target, ids, a, K, None) for a in A])
    flip = target.rotations()[1]
    turned = [1, 4, 5, 8]
    dets = []
    for f, p in enumerate(uv):
        ids = np.arange(target.num_points)
        if f in turned:  # feature k reported as the one 180 degrees away
            ids = np.argsort(flip)[ids]
        order = np.argsort(ids)
        dets.append(Detection(ids[order], p[order]))
    obs = hand_eye_from_detections(dets, target, T_base_ee, K, eye_in_hand=True, sigma_px=0.1)
    assert sorted(f for _, f, _ in obs.turned) == turned and {a for *_, a in obs.turned} == {180}
    r = jax.jit(jaxcal.calibrate_hand_eye)(obs.data)
    np.testing.assert_allclose(r.T_ee_cam[0], T_ee_cam, atol=1e-7)


def test_a_single_marker_passes_the_pose_check_and_solves_exactly():
    """One square marker (4 corners, the smallest target): its homography is the null vector of an
    8 x 9 system, and the pose check's rotations are exact (a reduced SVD once left the null vector
    out and refused every single-marker capture as "robot poses and images disagree")."""
    tag = TargetSpec("aruco", dictionary="DICT_APRILTAG_36h11", marker_length=0.048, first_id=10, name="tag")
    rng = np.random.default_rng(4)
    T_base_ee, A, T_ee_cam, Y = eye_in_hand_views(rng, tag, 8)
    uv = project(tag, A)
    R, ok = homography_rotations(uv[None], np.ones(uv.shape[:2], bool)[None], K[None], tag.points())
    assert ok.all()
    np.testing.assert_allclose(R[0], A[:, :3, :3], atol=1e-9)
    ids = np.arange(tag.num_points)
    obs = hand_eye_from_detections([Detection(ids, p) for p in uv], tag, T_base_ee, K, eye_in_hand=True)
    r = jax.jit(jaxcal.calibrate_hand_eye)(obs.data)
    np.testing.assert_allclose(r.T_ee_cam[0], T_ee_cam, atol=1e-7)


@pytest.mark.parametrize("lost", [None, 5])
def test_robot_poses_shifted_against_the_images_are_named_with_the_shift(lost):
    """Pose rows shifted against the images (every pose logged one frame late, or a row lost at
    frame 5 and the rows after it renumbered) are refused naming the shift and where it starts,
    not the generic advice; a shuffle matches no shift (`test_shuffled_robot_poses_...`)."""
    rng = np.random.default_rng(2)
    T_base_ee, A, _, _ = eye_in_hand_views(rng, CHESSBOARD, 12)
    uv = project(CHESSBOARD, A)
    ids = np.arange(CHESSBOARD.num_points)
    if lost is None:  # row f holds the pose of image f - 1 (the first row repeated)
        rows, images = T_base_ee[np.r_[0, 0:11]], range(12)
        want = "from frame img00 on, each frame's robot pose is written 1 row later (frame img00's in the row of frame img01)"
    else:  # image 5's row is gone and the later rows renumbered: the last image has no row
        rows, images = T_base_ee[np.r_[0:lost, lost + 1 : 12]], range(11)
        want = "from frame img06 on, each frame's robot pose is written 1 row earlier (frame img06's in the row of frame img05): the robot pose row of frame img05 is missing"
    with pytest.raises(jaxcal.InconsistentPosesError, match="robot poses and images disagree") as e:
        hand_eye_from_detections(
            [Detection(ids, uv[f]) for f in images],
            CHESSBOARD,
            rows,
            K,
            eye_in_hand=True,
            frame_names=[f"img{f:02d}" for f in images],
        )
    assert want in str(e.value) and "rotation unit" not in str(e.value), str(e.value)


def test_a_target_read_from_json_takes_lists():
    """`squares` as JSON gives it (a list) is a tuple in the target: it hashes and detects."""
    target = TargetSpec("chessboard", squares=[8, 7], square_length=0.025)
    assert target.squares == (8, 7) and hash(target) == hash(
        TargetSpec("chessboard", squares=(8, 7), square_length=0.025)
    )
    with pytest.raises(ValueError, match="squares must be two whole numbers"):
        TargetSpec("chessboard", squares=[8, 7, 1], square_length=0.025)


def test_shuffled_robot_poses_are_refused_naming_frames():
    rng = np.random.default_rng(2)
    T_base_ee, A, _, _ = eye_in_hand_views(rng, CHESSBOARD, 12)
    uv = project(CHESSBOARD, A)
    ids = np.arange(CHESSBOARD.num_points)
    names = [f"img{f:02d}" for f in range(12)]
    with pytest.raises(
        jaxcal.InconsistentPosesError, match=r"robot poses and images disagree.*frames img0"
    ) as e:
        hand_eye_from_detections(
            [Detection(ids, p) for p in uv],
            CHESSBOARD,
            T_base_ee[rng.permutation(12)],
            K,
            eye_in_hand=True,
            frame_names=names,
        )
    # The advice names what can change relative rotation angles, and says what cannot.
    assert "in the images' order" in str(e.value) and "rotation unit (rad or deg)" in str(e.value)
    assert "m or mm" not in str(e.value) and "translation unit, the quaternion component order" in str(
        e.value
    )


# --------------------------------------------------------------------------- pose pairs with covariances


def test_pose_pairs_with_per_frame_covariances():
    """PnP-like per-frame 6x6 covariances (each frame its own scale and correlation): equal to the
    scalar-sigma solve when they are diagonal and equal; with them 3 corrupted frames of 15 (2 deg /
    5 mm robot errors) are all flagged and the camera pose is closer than with scalar sigmas."""
    rng = np.random.default_rng(3)
    T_base_ee, A, T_ee_cam, Y = eye_in_hand_views(rng, CHESSBOARD, 15)
    sig = np.array([1e-3, 1e-3, 3e-3, 2e-3, 2e-3, 1e-3])
    cov = []
    noisy = []
    for a in A:
        L = np.diag(sig * rng.uniform(0.5, 2.0)) @ (np.eye(6) + 0.2 * rng.normal(size=(6, 6)))
        C = L @ L.T
        e = L @ rng.normal(size=6)
        n = a.copy()
        n[:3, 3] += e[:3]
        n[:3, :3] = cv2.Rodrigues(e[3:])[0] @ a[:3, :3]
        cov.append(C)
        noisy.append(n)
    bad = [2, 7, 11]
    T_rec = T_base_ee.copy()
    for f in bad:
        T_rec[f] = T_rec[f] @ _pose(np.radians(2.0) * np.array([0.6, 0.0, 0.8]), [0.003, -0.004, 0.0])
    solve = jax.jit(jaxcal.calibrate_hand_eye)
    # Diagonal, equal covariances == scalar sigmas (a different compiled path, the same numbers).
    plain = jaxcal.make_hand_eye_poses(
        T_base_ee, A, eye_in_hand=True, sigma_translation=1e-3, sigma_rotation=2e-3
    )
    same = jaxcal.make_hand_eye_poses(
        T_base_ee, A, eye_in_hand=True, cov=np.broadcast_to(np.diag([1e-6] * 3 + [4e-6] * 3), (15, 6, 6))
    )
    r0, r1 = solve(plain), solve(same)
    np.testing.assert_allclose(r1.T_ee_cam, r0.T_ee_cam, atol=1e-10)
    np.testing.assert_allclose(r1.std_robot_cam, r0.std_robot_cam, rtol=1e-6)
    r = solve(jaxcal.make_hand_eye_poses(T_rec, np.stack(noisy), eye_in_hand=True, cov=np.stack(cov)))
    assert r.rejected_frames().tolist() == bad
    trans, rot = _err(r.T_ee_cam[0], T_ee_cam)
    std = np.asarray(r.std_robot_cam[0])
    assert trans < 3 * np.linalg.norm(std[:3]) and rot < 3 * np.linalg.norm(std[3:])
    scalar = solve(jaxcal.make_hand_eye_poses(T_rec, np.stack(noisy), eye_in_hand=True))
    assert scalar.rejected_frames().tolist() == bad
    trans_s, rot_s = _err(scalar.T_ee_cam[0], T_ee_cam)
    assert trans < trans_s and rot < rot_s
    with pytest.raises(jaxcal.NotPositiveDefiniteError, match="camera 0, frame 4"):
        bent = np.stack(cov)
        bent[4] = -bent[4]
        jaxcal.make_hand_eye_poses(T_rec, np.stack(noisy), eye_in_hand=True, cov=bent)


def test_batched_covariance_and_robot_noise_solves_keep_lapack_calls_ordered():
    rng = np.random.default_rng(4)
    T_base_ee, A, _, _ = eye_in_hand_views(rng, CHESSBOARD, 8)
    cov = np.broadcast_to(np.diag([1e-6] * 3 + [4e-6] * 3), (8, 6, 6))
    for kw in (dict(cov=cov), dict(cov=cov, robot_sigma_translation=1e-3, robot_sigma_rotation=1e-3)):
        d = jaxcal.make_hand_eye_poses(T_base_ee, A, eye_in_hand=True, **kw)
        d = jax.tree.map(lambda x: jnp.stack([x, x]) if eqx.is_array(x) else x, d)
        assert concurrent_decompositions(eqx.filter_vmap(jaxcal.calibrate_hand_eye), d) == []


# --------------------------------------------------------------------------- stages, verdicts, statistics


def _pixel_data(rng, frames=16, sigma=0.3, robot=None, bad=(), robot_noise=0.0):
    T_base_ee, A, T_ee_cam, Y = eye_in_hand_views(rng, CHESSBOARD, frames)
    uv = project(CHESSBOARD, A) + rng.normal(0.0, sigma, (frames, CHESSBOARD.num_points, 2))
    T_rec = np.stack(
        [T @ _pose(rng.normal(0.0, robot_noise, 3), rng.normal(0.0, robot_noise, 3)) for T in T_base_ee]
    )
    for f in bad:
        T_rec[f] = T_rec[f] @ _pose(np.radians(2.0) * np.array([0.0, 0.6, 0.8]), [0.005, 0.0, 0.0])
    kw = {} if robot is None else dict(robot_sigma_translation=robot[0], robot_sigma_rotation=robot[1])
    data = jaxcal.make_hand_eye_pixels(
        T_rec, uv, K, CHESSBOARD.points(), eye_in_hand=True, sigma_px=sigma, **kw
    )
    return jaxcal.pad_hand_eye(data), T_ee_cam


@pytest.fixture(scope="module")
def robot_noise_data():
    rng = np.random.default_rng(5)
    return _pixel_data(rng, sigma=0.2, robot=(5e-4, 5e-4), bad=(3, 9), robot_noise=3e-4)


@pytest.mark.slow
@pytest.mark.parametrize("max_steps", [200, 400])
def test_rejection_with_robot_noise_does_not_depend_on_max_steps(robot_noise_data, max_steps):
    """Robot noise on: each stage reports its own result and steps; once converged, the frames
    rejected (the two 2 deg / 5 mm robot errors) are the same whatever the cap."""
    from jaxcal.handeye import hand_eye_solver

    data, T_ee_cam = robot_noise_data
    # `jaxcal handeye`'s compiled solver at this cap (at 200, the rendered 16-frame captures' program).
    r = hand_eye_solver(max_steps)(data, True, False)
    stages = [
        bool(jax.tree.map(lambda x, i=i: x[i], r.stage_result) == optx.RESULTS.successful) for i in (0, 1)
    ]
    assert stages == [True, True] and int(r.num_steps) == int(np.sum(r.stage_steps))
    assert r.rejected_frames().tolist() == [3, 9]
    assert jaxcal.assess_hand_eye(r).status == "ok"


def test_a_stage_at_its_step_cap_is_suspect(robot_noise_data):
    data, _ = robot_noise_data
    r = jax.tree.map(
        np.asarray, eqx.filter_jit(jaxcal.calibrate_hand_eye)(data, options=jaxcal.LMOptions(1e-8, 1e-6, 3))
    )
    assert not bool(r.result == optx.RESULTS.successful)
    v = jaxcal.assess_hand_eye(r, max_steps=3)
    assert v.status == "suspect"
    assert any(
        "robust solve did not converge: it stopped at its step cap after 3 steps (max_steps=3)" in x
        for x in v.reasons
    )


def test_bad_fit_and_far_from_start_are_suspect():
    """A solve whose pixels are 30x the stated noise, and one that ends far from its closed form, are suspect."""
    rng = np.random.default_rng(6)
    data, _ = _pixel_data(rng, sigma=0.3)
    r = jax.tree.map(
        np.asarray, jax.jit(jaxcal.calibrate_hand_eye)(eqx.tree_at(lambda d: d.sigma_px, data, 0.01))
    )
    v = jaxcal.assess_hand_eye(r)
    assert v.status == "suspect" and any("times the detector's noise" in x for x in v.reasons)
    far = eqx.tree_at(
        lambda x: x.T_cam_robot_start, r, r.T_cam_robot_start @ _pose([0.0, 0.2, 0.0], [0.1, 0, 0])
    )
    assert any("from the closed-form start" in x for x in jaxcal.assess_hand_eye(far).reasons)
    # With frames left out predicted as a robot's noise allows, an exact-pose misfit is that noise (a
    # note, ok); predicted beyond any robot's, the poses do not belong to these images (suspect).
    noisy = he.HeldOut(rms_px=1.0, in_sample_px=0.3, sigma_px=0.01, scale_px=1.0, folds=8, frames=16)
    v = jaxcal.assess_hand_eye(r, held_out=noisy)
    assert v.status == "ok" and any(
        "the robot's poses are noisy at this level, about 1 mm" in x for x in v.notes
    )
    v = jaxcal.assess_hand_eye(r, held_out=dataclasses.replace(noisy, rms_px=6.0))
    assert v.status == "suspect" and any("do not belong to these images" in x for x in v.reasons), v.reasons
    # Views predicted from near or behind the camera: the bound in words, no absurd figure.
    v = jaxcal.assess_hand_eye(r, held_out=dataclasses.replace(noisy, rms_px=5.89e10))
    text = " ".join(v.reasons)
    assert "predicted from their reported robot poses to over 1e+05 px (far off the image) RMS" in text, text
    assert "over 1000 mm / 180 deg per axis" in text and "e+" not in text.replace("1e+05", ""), text


@pytest.mark.slow
def test_normalised_errors_and_kfold_spread_are_honest():
    """60 seeded trials of analytic corners (0.3 px noise): the errors over the reported std have RMS
    in 0.8-1.25 (translation and rotation), and the 8-fold spread matches the std within 2x on average."""
    solve = jax.jit(lambda d, reject: jaxcal.calibrate_hand_eye(d, reject_outliers=reject))
    rng = np.random.default_rng(7)
    z, ratio = [], []
    for trial in range(60):
        data, T_ee_cam = _pixel_data(rng, sigma=0.3)
        r = jax.tree.map(np.asarray, solve(data, True))
        trans, rot = _err(r.T_ee_cam[0], T_ee_cam)
        std = r.std_robot_cam[0]
        z.append([trans / np.linalg.norm(std[:3]), rot / np.linalg.norm(std[3:])])
        if trial < 6:
            kf = jaxcal.kfold_spread(lambda d: solve(d, False), data, r, folds=8)
            ratio.append(he.std_ratio(kf, r)[0])
    rms = np.sqrt(np.mean(np.square(z), axis=0))
    print(
        f"normalised error RMS (translation, rotation) {np.round(rms, 3)}, k-fold/std {np.round(np.mean(ratio, 0), 2)}"
    )
    assert np.all((0.8 < rms) & (rms < 1.25)), rms
    assert np.all((0.5 < np.mean(ratio, 0)) & (np.mean(ratio, 0) < 2.0))


def test_the_commands_folds_start_from_the_optimum_and_end_where_the_closed_form_ends():
    """`jaxcal handeye`'s k-fold spread re-solves each fold from the full data's optimum and robot
    noise (`kfold_from_optimum`): the spread equals the one from each fold's own closed form to the
    solver's tolerance (steps below 1e-8 relative, so well inside 1 % of a 0.01 mm spread), in fewer
    steps (here the robot noise estimate's re-solves dominate; on a clean capture a fold takes 4-6)."""
    from jaxcal.handeye import hand_eye_solver
    from jaxcal.handeye._solve import kfold_from_optimum

    rng = np.random.default_rng(11)
    data, _ = _pixel_data(rng, sigma=0.2, robot=he.ROBOT_SIGMA_START, robot_noise=5e-4)
    solve = hand_eye_solver(200)
    steps = []

    def counted(*args):
        out = solve(*args)
        steps.append(int(np.sum(out.stage_steps)))
        return out

    r = jax.tree.map(np.asarray, solve(data, True, True))
    cold = jaxcal.kfold_spread(lambda d: counted(d, False, True), data, r, folds=5)
    cold_steps, steps[:] = sum(steps), []
    warm = kfold_from_optimum(counted, data, r, True, 5)
    assert cold.converged.all() and warm.converged.all() and warm.fold_frames == cold.fold_frames
    np.testing.assert_allclose(warm.std_robot_cam, cold.std_robot_cam, rtol=0.01)
    np.testing.assert_allclose(warm.std_robot_board, cold.std_robot_board, rtol=0.01)
    assert sum(steps) < 0.9 * cold_steps, (sum(steps), cold_steps)


# --------------------------------------------------------------------------- robot pose noise, estimated


#: Robot pose noise per axis (m, rad) of the analytic and rendered captures below: 1 mm, 0.1 deg.
ROBOT_NOISE = (1e-3, np.radians(0.1))


def _noisy_robot_data(seed, frames=24, sigma_px=0.1, noise=ROBOT_NOISE, bad=()):
    """Analytic corners, every robot pose off by `noise` (m, rad per axis, base frame: the solver's
    convention), `bad` frames off by 2 deg / 5 mm more; the noise given as a start only."""
    rng = np.random.default_rng(seed)
    T_base_ee, A, T_ee_cam, _ = eye_in_hand_views(rng, CHESSBOARD, frames)
    uv = project(CHESSBOARD, A) + rng.normal(0.0, sigma_px, (frames, CHESSBOARD.num_points, 2))
    T_rec = T_base_ee.copy()
    for f in range(frames):
        T_rec[f, :3, :3] = cv2.Rodrigues(rng.normal(0.0, noise[1], 3))[0] @ T_rec[f, :3, :3]
        T_rec[f, :3, 3] += rng.normal(0.0, noise[0], 3)
    for f in bad:
        T_rec[f] = T_rec[f] @ _pose(np.radians(2.0) * np.array([0.0, 0.6, 0.8]), [0.005, 0.0, 0.0])
    data = jaxcal.make_hand_eye_pixels(
        T_rec,
        uv,
        K,
        CHESSBOARD.points(),
        eye_in_hand=True,
        sigma_px=sigma_px,
        robot_sigma_translation=2e-3,  # the start, twice the truth
        robot_sigma_rotation=np.radians(0.05),  # half the truth
    )
    return jaxcal.pad_hand_eye(data), T_ee_cam


@pytest.fixture(scope="module")
def estimating_solver():
    """`calibrate_hand_eye(data, estimate_robot_noise=e)` as `jaxcal handeye` compiles it (`hand_eye_solver`:
    the rendered 24-frame capture's program, one compile for both)."""
    from jaxcal.handeye import hand_eye_solver

    solve = hand_eye_solver(200)
    return lambda d, e: solve(d, True, e)


def test_robot_noise_estimate_is_unbiased_and_its_std_honest(estimating_solver):
    """Variance components on analytic corners (24 frames, 0.1 px, robot 1 mm / 0.1 deg per axis),
    10 seeds: the estimates average the truth within 10% (each is off by about 10%: a wrong
    leverage or a biased update would show), no frame is rejected, and the camera's error over
    its reported std has RMS near 1 (the covariance carries the estimated noise)."""
    ratio, z = [], []
    for seed in range(10):
        data, T_ee_cam = _noisy_robot_data(100 + seed)
        r = jax.tree.map(np.asarray, estimating_solver(data, True))
        assert bool(r.robot_sigma_estimated) and r.rejected_frames().tolist() == []
        ratio.append(r.robot_sigma[[0, 3]] / [1e-3, np.radians(0.1)])
        trans, rot = _err(r.T_ee_cam[0], T_ee_cam)
        z.append(
            [trans / np.linalg.norm(r.std_robot_cam[0, :3]), rot / np.linalg.norm(r.std_robot_cam[0, 3:])]
        )
        # Each group's redundancy is most of its 3 x 24 pseudo-observations.
        assert np.all((30 < r.robot_dof) & (r.robot_dof < 72))
    mean, rms = np.mean(ratio, 0), np.sqrt(np.mean(np.square(z), 0))
    print(
        f"estimated / true robot noise: mean {np.round(mean, 3)}, per seed {np.round(ratio, 2).tolist()}; z RMS {rms}"
    )
    assert np.all(np.abs(mean - 1.0) < 0.1), mean
    assert np.all((0.6 < rms) & (rms < 1.5)), rms
    # Given, the noise is used as given.
    r = estimating_solver(data, False)
    assert not bool(r.robot_sigma_estimated)
    np.testing.assert_allclose(r.robot_sigma, [2e-3] * 3 + [np.radians(0.05)] * 3)


def test_exact_robot_poses_estimate_no_noise(estimating_solver):
    """Robot poses exact: the estimate falls far below what the views resolve (a hundredth of a
    mm), and the camera is where the exact-pose solve puts it, within a fifth of its std."""
    data, T_ee_cam = _noisy_robot_data(7, noise=(0.0, 0.0))
    r = estimating_solver(data, True)
    assert float(r.robot_sigma[0]) < 2e-5 and float(r.robot_sigma[3]) < np.radians(2e-3)
    exact = jax.jit(jaxcal.calibrate_hand_eye)(eqx.tree_at(lambda d: d.robot_sigma, data, None))
    trans, rot = _err(r.T_ee_cam[0], np.asarray(exact.T_ee_cam[0]))
    assert trans < 0.2 * np.linalg.norm(exact.std_robot_cam[0, :3])
    assert rot < 0.2 * np.linalg.norm(exact.std_robot_cam[0, 3:])


def test_wrong_robot_poses_are_rejected_against_the_estimated_noise(estimating_solver):
    """Two of 24 poses off by 2 deg / 5 mm on top of 1 mm / 0.1 deg noise: the robust stage's
    median update keeps them from inflating the estimate, so exactly they are rejected and the
    estimate is within 30% of the truth."""
    data, _ = _noisy_robot_data(11, bad=(5, 17))
    r = jax.tree.map(np.asarray, estimating_solver(data, True))
    assert r.rejected_frames().tolist() == [5, 17]
    ratio = r.robot_sigma[[0, 3]] / [1e-3, np.radians(0.1)]
    assert np.all(np.abs(ratio - 1.0) < 0.3), ratio
    assert jaxcal.assess_hand_eye(r).status == "ok"


def test_a_poor_fit_names_robot_noise_by_how_it_was_set(estimating_solver):
    """The robot noise given far too small, or taken as exact: the reason says robot pose noise may
    explain it and how to estimate it; estimated: that it does not."""
    data, _ = _noisy_robot_data(12)
    small = eqx.tree_at(lambda d: d.robot_sigma, data, jnp.asarray([1e-5] * 3 + [1e-5] * 3))
    v = jaxcal.assess_hand_eye(jax.tree.map(np.asarray, estimating_solver(small, False)))
    assert v.status == "suspect"
    assert any("needed corrections of" in x and he.ROBOT_SIGMA_OPTIONS in x for x in v.reasons), v.reasons
    exact = eqx.tree_at(lambda d: d.robot_sigma, data, None)
    v = jaxcal.assess_hand_eye(jax.tree.map(np.asarray, jax.jit(jaxcal.calibrate_hand_eye)(exact)))
    assert any("taken as exact" in x and "estimate_robot_noise=True" in x for x in v.reasons), v.reasons
    # Estimated and still a misfit (the pixel noise stated 10x too small): not the robot's noise.
    tight = eqx.tree_at(lambda d: d.sigma_px, data, jnp.asarray(0.01))
    v = jaxcal.assess_hand_eye(jax.tree.map(np.asarray, estimating_solver(tight, True)))
    assert any("does not explain it" in x for x in v.reasons), v.reasons


def test_a_traced_noise_switch_with_exact_poses_is_refused():
    """`estimate_robot_noise` traced with exact robot poses (`robot_sigma` None) once solved with
    1 mm / 0.1 deg "as given" when False: whether to add corrections decides the program, so the
    flag must then be a Python bool, and a traced one is refused (at trace time: nothing compiles)."""
    data, _ = _noisy_robot_data(12)
    exact = eqx.tree_at(lambda d: d.robot_sigma, data, None)
    with pytest.raises(ValueError, match="estimate_robot_noise is traced but data.robot_sigma is None"):
        jax.jit(lambda d, e: jaxcal.calibrate_hand_eye(d, estimate_robot_noise=e))(exact, False)


# --------------------------------------------------------------------------- the robot-noise model, held out


def test_held_out_reprojection_and_the_robot_noise_it_reads_as():
    """At the true transforms, corners predicted from exact robot poses are off by the pixel noise
    (0.1 px); from poses off by 1 mm / 0.1 deg per axis, by what `robot_pixel_scale` says such noise
    moves them (a missing 1/2 per coordinate or a step in the wrong frame is 40 % or more off); and
    `HeldOut.level` reads the excess back in those units."""
    rng = np.random.default_rng(21)
    T_base_ee, A, X, Y = eye_in_hand_views(rng, CHESSBOARD, 24)
    uv = project(CHESSBOARD, A)
    noisy = uv + rng.normal(0.0, 0.1, uv.shape)
    data = jaxcal.make_hand_eye_pixels(
        T_base_ee, noisy, K, CHESSBOARD.points(), eye_in_hand=True, sigma_px=0.1
    )
    every = np.ones(24, bool)
    sq, n = he.reprojection_squares(np.linalg.inv(X)[None], Y, data, every)
    assert abs(np.sqrt(sq.sum() / n.sum()) / 0.1 - 1.0) < 0.05
    sigma = np.r_[np.full(3, 1e-3), np.full(3, np.radians(0.1))]
    ratios = []
    for _ in range(3):
        d = rng.normal(0.0, 1.0, (24, 6)) * sigma
        T = T_base_ee.copy()
        T[:, :3, :3] = np.stack([cv2.Rodrigues(w)[0] for w in d[:, 3:]]) @ T[:, :3, :3]
        T[:, :3, 3] += d[:, :3]
        moved = jaxcal.make_hand_eye_pixels(T, uv, K, CHESSBOARD.points(), eye_in_hand=True, sigma_px=0.1)
        sq, n = he.reprojection_squares(np.linalg.inv(X)[None], Y, moved, every)
        ratios.append(
            np.sqrt(sq.sum() / n.sum()) / he.robot_pixel_scale(np.linalg.inv(X)[None], Y, moved, every)
        )
    assert 0.85 < np.mean(ratios) < 1.15, ratios
    held = he.HeldOut(
        rms_px=float(np.hypot(0.1, 0.8)), in_sample_px=0.1, sigma_px=0.1, scale_px=0.4, folds=8, frames=24
    )
    assert abs(held.level - 2.0) < 1e-12 and held.noise_text() == "about 2 mm / 0.2 deg per axis"
    assert he.noise_explains_fit(held) and not he.noise_explains_fit(dataclasses.replace(held, scale_px=0.1))


def _fake_fit(model, frame_squares, rms):
    """A `NoiseModelFit` whose k-fold held out one frame per fold with these squared errors."""
    from jaxcal.handeye._noise import NoiseModelFit

    F = len(frame_squares)
    kfold = he.KFoldSpread(
        F, tuple((f,) for f in range(F)), np.zeros((1, 6)), np.zeros(6), np.ones(F, bool),
        np.asarray(frame_squares, float)[None], np.full((1, F), 96.0),
    )  # fmt: skip
    result = types.SimpleNamespace(
        robot_sigma=None if model == "exact" else np.r_[np.full(3, 1e-3), np.full(3, 1e-3)],
        robot_sigma_estimated=np.asarray(model == "estimate"),
        pixel_rms=0.2,
    )
    return NoiseModelFit(model, result, kfold, he.HeldOut(rms, 0.2, 0.2, 1.0, F, F))


def test_a_model_replaces_the_estimate_only_on_a_steady_gain():
    """`jaxcal._selection`'s rule, the one the tracker's terms are kept by (`CV_GAIN`), with the
    paired guard: exact poses 10 % better on every frame replace the estimate; 10 % better on average
    from one frame among eight (ViSP's capture: 5.05 against 5.90 px, 1.1 standard errors) do not;
    a steady gain under `CV_GAIN` does not; an asked model is kept as asked."""
    from jaxcal._selection import CV_GAIN, MIN_Z, improves, paired_z
    from jaxcal.handeye._noise import RobotNoiseSetting, choose

    assert improves(0.99, 1.0) and not improves(1.0 - CV_GAIN / 2, 1.0)
    base = np.array([40.0, 55.0, 38.0, 61.0, 47.0, 52.0, 44.0, 58.0])
    one_frame = base + 3.0
    one_frame[0] -= 8.0 * 3.0 + 0.2 * base.sum()
    assert one_frame.sum() < 0.9 * base.sum() and paired_z(base, one_frame) < MIN_Z
    auto = RobotNoiseSetting("auto")
    cases = [(0.9 * base, "exact"), (one_frame, "estimate"), ((1.0 - CV_GAIN / 2) * base, "estimate")]
    for exact_squares, kept in cases:
        fits = (
            _fake_fit("estimate", base, 1.0),
            _fake_fit("exact", exact_squares, np.sqrt(exact_squares.sum() / base.sum())),
        )
        k, basis = choose(fits, auto, folds=8)
        assert fits[k].model == kept and basis.startswith("chosen by held-out reprojection"), basis
    assert choose(fits[:1], RobotNoiseSetting("estimate"), folds=8) == (
        0,
        "as asked (robot_noise='estimate')",
    )
    # The estimate's frames left out far off the image (a misread capture): one frame dominates any
    # paired test, so the exact model, on the image, is kept without one.
    wild = base.copy()
    wild[0] = 1e22
    fits = (_fake_fit("estimate", wild, 5.89e10), _fake_fit("exact", 2 * base, 57.5))
    k, basis = choose(fits, auto, folds=8)
    assert (
        fits[k].model == "exact" and "kept: estimate predicts the frames left out far off the image" in basis
    )
    bare = tuple(dataclasses.replace(f, kfold=None, held_out=None) for f in fits)  # folds=0
    assert choose(bare, auto, folds=0) == (
        0,
        "the default, with nothing to compare the models on (no folds (folds=0))",
    )


# --------------------------------------------------------------------------- capture format


def _write_capture(root, fmt="xyz_quat", unit="m", rot_unit="rad", frames=4, images=True):
    rng = np.random.default_rng(8)
    T = np.stack([_pose(rng.normal(0.0, 0.5, 3), rng.normal(0.0, 0.3, 3)) for _ in range(frames)])
    names = [f"f{i}" for i in range(frames)]
    cams = [HandEyeCamera("cam0", 640, 480, K, DIST, "cam0_optical_frame")]  # K is a 640x480 camera's
    root.mkdir(parents=True, exist_ok=True)
    write_hand_eye_description(
        root,
        eye_in_hand=True,
        cameras=cams,
        target=CHESSBOARD,
        frames=names,
        T_base_ee=T,
        pose_format=fmt,
        translation_unit=unit,
        rotation_unit=rot_unit,
    )
    if images:
        (root / "images" / "cam0").mkdir(parents=True)
        for n in names:
            cv2.imwrite(str(root / "images" / "cam0" / f"{n}.png"), np.zeros((480, 640), np.uint8))
    return T


@pytest.mark.parametrize(
    "fmt, unit, rot_unit",
    [("matrix", "m", "rad"), ("xyz_quat", "mm", "rad"), ("xyz_rpy", "m", "deg"), ("xyz_rotvec", "mm", "rad")],
)
def test_pose_formats_round_trip(tmp_path, fmt, unit, rot_unit):
    T = _write_capture(tmp_path / "c", fmt, unit, rot_unit)
    cap = load_hand_eye_capture(tmp_path / "c")
    np.testing.assert_allclose(cap.T_base_ee, T, atol=1e-12)
    assert cap.frames == ("f0", "f1", "f2", "f3") and cap.eye_in_hand and cap.cameras[0].name == "cam0"
    header = (tmp_path / "c" / "poses.csv").read_text().splitlines()[0]
    assert header == "frame," + ",".join(POSE_COLUMNS[fmt])


def test_quaternion_helpers_agree():
    rng = np.random.default_rng(9)
    for _ in range(20):
        R = cv2.Rodrigues(rng.normal(0.0, 1.5, 3))[0]
        np.testing.assert_allclose(quaternion_to_matrix(matrix_to_quaternion(R)), R, atol=1e-12)


def _edit(path, fn):
    with open(path, newline="") as f:
        rows = list(csv.reader(f))
    fn(rows)
    with open(path, "w", newline="") as f:
        csv.writer(f).writerows(rows)


def _set(row, i, value):
    row[i] = value


@pytest.mark.parametrize(
    "breakage, match",
    [
        (
            lambda r, m: _edit(r / "poses.csv", lambda rows: _set(rows[2], 4, "0.3")),
            r"poses.csv line 3 \(frame f1\): quaternion norm",
        ),
        (
            lambda r, m: _edit(r / "poses.csv", lambda rows: _set(rows[1], 1, "x")),
            r"line 2 \(frame f0\): field 'x' = 'x' is not a number",
        ),
        (
            lambda r, m: _edit(r / "poses.csv", lambda rows: _set(rows[0], 4, "q_x")),
            r"line 1: header .* does not match format 'xyz_quat'",
        ),
        (
            lambda r, m: m["poses"].update(translation_unit="inch"),
            r"field 'translation_unit' must be one of \['m', 'mm'\], got 'inch'",
        ),
        (lambda r, m: m.update(arrangement="eye-on-hand"), r"field 'arrangement' must be one of"),
        (
            lambda r, m: m["target"].update(kind="checkerboard"),
            r"handeye.json: field 'target': target 'board': kind must be one of",
        ),
        (
            lambda r, m: m["cameras"][0].update(distortion=[0.1, 0.2, 0.3]),
            r"camera 'cam0' field 'distortion'",
        ),
        (  # the camera block is checked as the dataset's is (jaxcal.io._schema)
            lambda r, m: m["cameras"][0].update(
                K=[[600.0, 0.0, 9000.0], [0.0, 600.0, 240.0], [0.0, 0.0, 1.0]]
            ),
            r"camera 'cam0' field 'K': principal point \(9000, 240\) lies outside",
        ),
        (
            lambda r, m: (r / "images" / "cam0" / "f2.png").unlink(),
            r"no image for frame\(s\) \['f2'\] .* the folder holds f0.png, f1.png, f3.png\)",
        ),
        (  # the images' size against the camera's (its K is for that size)
            lambda r, m: cv2.imwrite(str(r / "images" / "cam0" / "f1.png"), np.zeros((600, 800), np.uint8)),
            r"cam0/f1.png: image is 800x600 pixels, handeye.json gives camera 'cam0' 640x480 \(fields 'width', "
            r"'height'\); 1 of 4 images differ$",
        ),
        (
            lambda r, m: m["cameras"][0].update(width=480, height=640),
            r"f0.png: image is 640x480 pixels, .* 480x640 .* 4 of 4 images differ; every image: a K calibrated",
        ),
        (lambda r, m: m.update(schema_version=7), r"unknown schema_version 7"),
        (  # a key jaxcal does not read is refused, not ignored; notes go under x_ keys
            lambda r, m: m.update(robot_noise_mm=1.0),
            r"handeye.json: unknown field 'robot_noise_mm'; known fields are 'arrangement', .* starting with 'x_'",
        ),
        (lambda r, m: m["cameras"][0].update(fx=600), r"handeye.json: cameras\[0\]: unknown field 'fx'"),
        (  # metres declared millimetres: a flange that never leaves the base
            lambda r, m: m["poses"].update(translation_unit="mm"),
            r"poses.csv: every frame's flange lies within 0.\d+ mm of the base, no arm's reach; .*'translation_unit' "
            r"\('mm'\) right \(metres declared millimetres\?\)",
        ),
        (  # a pose file is the capture's own: no name leaves its folder
            lambda r, m: m["poses"].update(file="../other/poses.csv"),
            r"handeye.json: field 'poses.file': expected a path relative to the dataset directory that stays "
            r"inside it, got '../other/poses.csv'",
        ),
        (
            lambda r, m: m["poses"].update(file=str(r / "poses.csv")),
            r"field 'poses.file': expected a path relative",
        ),
        (
            lambda r, m: (r / "poses.csv").write_bytes(
                (r / "poses.csv").read_bytes().replace(b"frame", b"fr\xe9me")
            ),
            r"poses.csv: not UTF-8 text \(invalid continuation byte at byte 2\)",
        ),
        (
            lambda r, m: m["target"].update(square_length=30),
            r"target 'board': square_length = 30 m; lengths are in metres \(millimetres given\?",
        ),
    ],
)
def test_bad_captures_name_file_field_and_value(tmp_path, breakage, match):
    root = tmp_path / "c"
    _write_capture(root)
    meta = json.loads((root / "handeye.json").read_text())
    breakage(root, meta)
    (root / "handeye.json").write_text(json.dumps(meta))
    with pytest.raises(DatasetError, match=match):
        load_hand_eye_capture(root)


def test_radians_declared_degrees_are_named(tmp_path):
    """Rotation vectors in radians, handeye.json saying `deg`: read as degrees the flange would
    barely turn (the pose checks would then ask for a second rotation axis); the unit is named,
    as it is for degrees declared radians (rotation vectors and Euler angles beyond a turn)."""
    root = tmp_path / "c"
    _write_capture(root, "xyz_rotvec", "m", "rad")
    meta = json.loads((root / "handeye.json").read_text())
    meta["poses"]["rotation_unit"] = "deg"
    (root / "handeye.json").write_text(json.dumps(meta))
    with pytest.raises(
        DatasetError, match=r"poses.csv: no rotation value exceeds .*'rotation_unit' \('deg'\) right"
    ):
        load_hand_eye_capture(root)
    # ... and the other way: degrees declared radians reach beyond a turn.
    for fmt in ("xyz_rotvec", "xyz_rpy"):
        _write_capture(tmp_path / fmt, fmt, "m", "deg")
        meta = json.loads((tmp_path / fmt / "handeye.json").read_text())
        meta["poses"]["rotation_unit"] = "rad"
        (tmp_path / fmt / "handeye.json").write_text(json.dumps(meta))
        with pytest.raises(
            DatasetError, match=r"poses.csv: a rotation value reaches .* \(degrees declared radians\?\)"
        ):
            load_hand_eye_capture(tmp_path / fmt)


def test_a_pose_file_with_a_byte_order_mark_and_crlf_reads_as_without(tmp_path):
    """Spreadsheets write a byte-order mark and CRLF line ends: the same poses as without them."""
    _write_capture(tmp_path / "c")
    plain = load_hand_eye_capture(tmp_path / "c")
    text = (tmp_path / "c" / "poses.csv").read_text()
    (tmp_path / "c" / "poses.csv").write_bytes(b"\xef\xbb\xbf" + text.replace("\n", "\r\n").encode())
    marked = load_hand_eye_capture(tmp_path / "c")
    assert marked.frames == plain.frames
    np.testing.assert_array_equal(marked.T_base_ee, plain.T_base_ee)


def test_images_no_pose_row_names_are_noted_not_used(tmp_path):
    _write_capture(tmp_path / "c")
    assert load_hand_eye_capture(tmp_path / "c").notes == ()
    assert repeated_poses(np.stack([np.eye(4), 2 * np.eye(4), np.eye(4), np.eye(4)])) == {2: 0, 3: 0}
    cam = tmp_path / "c" / "images" / "cam0"
    for name in ("f9.png", "g1.jpg", "readme.txt"):  # two images of frames poses.csv lacks, one other file
        (cam / name).write_bytes((cam / "f0.png").read_bytes())
    cap = load_hand_eye_capture(tmp_path / "c")
    assert cap.frames == ("f0", "f1", "f2", "f3") and [p.name for p in cap.images[0]] == [
        "f0.png",
        "f1.png",
        "f2.png",
        "f3.png",
    ]
    assert cap.notes == (
        f"{cam}: 2 image(s) not used, no row of poses.csv names their frame: f9.png, g1.jpg "
        "(a pose row missing, or files that do not belong to this capture?)",
    )


def test_millimetres_written_as_metres_are_caught(tmp_path):
    _write_capture(tmp_path / "c", unit="mm")
    meta = json.loads((tmp_path / "c" / "handeye.json").read_text())
    meta["poses"]["translation_unit"] = "m"
    (tmp_path / "c" / "handeye.json").write_text(json.dumps(meta))
    with pytest.raises(DatasetError, match=r"m from the base; is .*'translation_unit' \('m'\) right"):
        load_hand_eye_capture(tmp_path / "c")


def test_jaxcal_exposes_vision_and_the_cache_opt_out(monkeypatch):
    import jaxcal._cache as cache

    assert jaxcal.vision.hand_eye_from_detections is jaxcal.hand_eye_from_detections
    monkeypatch.delenv("JAX_COMPILATION_CACHE_DIR", raising=False)
    before = jax.config.jax_compilation_cache_dir
    threshold = jax.config.jax_persistent_cache_min_compile_time_secs
    try:
        jax.config.update("jax_compilation_cache_dir", None)
        monkeypatch.setenv("JAXCAL_NO_CACHE", "1")
        cache.enable_compilation_cache()
        assert jax.config.jax_compilation_cache_dir is None
        monkeypatch.setenv("JAXCAL_NO_CACHE", "0")
        cache.enable_compilation_cache()
        assert str(jax.config.jax_compilation_cache_dir).endswith("jaxcal/xla")
        # A user's cache keeps every program, however quick to compile.
        assert jax.config.jax_persistent_cache_min_compile_time_secs == 0.0
    finally:
        # Both settings back: with the threshold left at 0 every later compile of this
        # worker was serialised and written to the suite's cache.
        jax.config.update("jax_compilation_cache_dir", before)
        jax.config.update("jax_persistent_cache_min_compile_time_secs", threshold)


# --------------------------------------------------------------------------- rendered captures, end to end

RENDERED = {
    "chessboard": CHESSBOARD,
    "circles": TargetSpec(
        "circles", squares=(7, 6), square_length=0.03, marker_length=0.015, margin=0.02, name="board"
    ),
    "charuco": TargetSpec(
        "charuco", squares=(8, 6), square_length=0.03, marker_length=0.022, margin=0.02, name="board"
    ),
}


def _render(path, target, eye_in_hand, **kw):
    from jaxcal.sim.handeye import HandEyeSimConfig, simulate_hand_eye

    return simulate_hand_eye(
        HandEyeSimConfig(target=RENDERED[target], eye_in_hand=eye_in_hand, frames=16, **kw), path
    )


@pytest.mark.slow
@pytest.mark.parametrize(
    "target, eye_in_hand, seed",
    [("chessboard", True, 1), ("chessboard", False, 2), ("circles", False, 3), ("charuco", True, 4)],
)
def test_rendered_capture_calibrates_through_the_command(tmp_path, capsys, target, eye_in_hand, seed):
    """16 frames at 640x480 (MuJoCo): `jaxcal handeye` writes every output, the camera is within
    0.5 mm / 0.1 deg of the truth, and the reported std and the 10-fold spread agree within 2x."""
    capture = _render(tmp_path / "capture", target, eye_in_hand, seed=seed)
    assert main(["handeye", str(capture), "--out", str(tmp_path / "out"), "--quiet"]) == 0
    out = tmp_path / "out"
    names = {
        "result.json",
        "report.md",
        "residuals.png",
        "camera_cam0.yaml",
        "ros_cam0.launch.yaml",
        "ros_cam0.txt",
        "easy_handeye_cam0.yaml",
        ".jaxcal",  # the marker that lets --overwrite replace what jaxcal wrote, and only that
    }
    assert {p.name for p in out.iterdir()} == names
    s = json.loads((out / "result.json").read_text())
    assert s["run"]["command"] == f"jaxcal handeye {capture} --out {out} --quiet"  # how it was made
    assert s["run"]["options"]["folds"] == 10 and s["run"]["command"] in (out / "report.md").read_text()
    cam = s["cameras"]["cam0"]
    print(
        f"{target} eye_in_hand={eye_in_hand}: truth error {cam['truth_error']}, k-fold/std {cam['kfold_over_std']}"
    )
    assert s["status"] == "ok" and s["rejected_frames"] == [] and s["reasons"] == []
    assert cam["truth_error"]["translation_mm"] < 0.5 and cam["truth_error"]["rotation_deg"] < 0.1
    # Rendered robot poses are exact: the noise estimate rests on almost nothing, and says so.
    said = " ".join(capsys.readouterr().out.split())
    assert "noise rests on almost none" in said and "so its figure is only an upper bound" in said, said
    assert (
        0.5 <= cam["kfold_over_std"]["translation"] <= 2.0 and 0.5 <= cam["kfold_over_std"]["rotation"] <= 2.0
    )
    assert cam["parent_frame"] == ("tool0" if eye_in_hand else "base_link")
    fs = cv2.FileStorage(str(out / "camera_cam0.yaml"), cv2.FILE_STORAGE_READ)
    np.testing.assert_allclose(fs.getNode("T_robot_cam").mat(), cam["T_robot_cam"]["matrix"])
    fs.release()
    # The ROS files parse back to the same pose (round trip, issue 16 item 7).
    T = np.asarray(cam["T_robot_cam"]["matrix"])
    easy = read_easy_handeye(out / "easy_handeye_cam0.yaml")
    assert easy["eye_on_hand"] == eye_in_hand and easy["tracking_base_frame"] == cam["child_frame"]
    np.testing.assert_allclose(easy["T"], T, atol=1e-9)
    for f in ("ros_cam0.launch.yaml", "ros_cam0.txt"):
        T_ros, parent, child = read_static_transform(out / f)
        np.testing.assert_allclose(T_ros, T, atol=1e-9)
        assert (parent, child) == (cam["parent_frame"], cam["child_frame"])
    assert "status **ok**" in (out / "report.md").read_text()


@pytest.mark.slow
def test_a_lens_left_out_of_handeye_json_is_named(tmp_path, capsys):
    """Rendered through a lens (k1 -0.08, k2 0.05), the capture's handeye.json states it: the lens
    test finds nothing. The same images with the distortion left out: the camera's pose moves by
    a millimetre against a claimed 0.04 mm, which nothing else sees; the test names the lens and
    the k1 it points to, and the result is suspect."""
    from jaxcal.handeye._observe import observe
    from jaxcal.handeye._verdict import LENS_PX, LENS_SIGMAS, lens_tests

    capture = _render(tmp_path / "capture", "charuco", True, seed=7, distortion=(-0.08, 0.05, 0.0, 0.0, 0.0))
    quiet = dict(noise=None, sigma_px=None, workers=1, progress=False, log=lambda m: None)
    ((_, _, _, _, sigmas),) = lens_tests(observe(capture, **quiet))
    assert sigmas < LENS_SIGMAS, sigmas
    meta = json.loads((capture / "handeye.json").read_text())
    meta["cameras"][0]["distortion"] = [0.0] * 5
    (capture / "handeye.json").write_text(json.dumps(meta))
    ((_, k1, _, shift, sigmas),) = lens_tests(observe(capture, **quiet))
    assert sigmas > 2 * LENS_SIGMAS and shift > 5 * LENS_PX and -0.10 < k1 < -0.06, (k1, shift, sigmas)
    # A lens off by 0.01 in k1 (on such captures the camera moves 0.11 mm against a claimed 0.025).
    meta["cameras"][0]["distortion"] = [-0.07, 0.05, 0.0, 0.0, 0.0]
    (capture / "handeye.json").write_text(json.dumps(meta))
    ((_, k1_off, _, shift, sigmas),) = lens_tests(observe(capture, **quiet))
    assert sigmas > LENS_SIGMAS and shift > LENS_PX and -0.02 < k1_off < 0.0, (k1_off, shift, sigmas)
    meta["cameras"][0]["distortion"] = [0.0] * 5
    (capture / "handeye.json").write_text(json.dumps(meta))
    assert main(["handeye", str(capture), "--out", str(tmp_path / "out"), "--quiet"]) == 3
    s = json.loads((tmp_path / "out" / "result.json").read_text())
    assert any(
        "as a lens's radial distortion does" in r and "cameras[].distortion" in r for r in s["reasons"]
    )
    assert s["cameras"]["cam0"]["truth_error"]["translation_mm"] > 0.5  # what the reason is about


@pytest.mark.slow
def test_self_calibrated_intrinsics_make_the_result_suspect(tmp_path, capsys):
    """A capture without K (`"K": null`): the intrinsics are calibrated from the same 16 images,
    whose focal-length error moves the camera by millimetres that neither the standard deviations
    nor the k-fold spread see (both hold K exact). The result is suspect (exit 3), saying why."""
    capture = _render(tmp_path / "capture", "chessboard", False, seed=5, intrinsics_known=False)
    assert main(["handeye", str(capture), "--out", str(tmp_path / "out"), "--quiet"]) == 3
    s = json.loads((tmp_path / "out" / "result.json").read_text())
    cam = s["cameras"]["cam0"]
    assert cam["intrinsics"]["source"] == "self-calibrated" and s["status"] == "suspect"
    assert any("self-calibrated" in r and "separate intrinsics calibration" in r for r in s["reasons"])
    # What the reason is about: the error is many times the stated uncertainty (8 times here).
    assert cam["truth_error"]["translation_mm"] > 5.0 * max(cam["std"]["translation_mm"])


@pytest.mark.slow
def test_robot_pose_noise_is_estimated_by_default(tmp_path, capsys):
    """A rendered eye-in-hand capture (24 frames at 320x240) whose every robot pose is off by 1 mm /
    0.1 deg per axis, no --robot-sigma-* given: status ok, no frame rejected, the estimated noise
    within 30% of the truth (reported in result.json and on the console), and the std within
    x0.7-1.4 of the 10-fold spread (issue 31, item 9). Given far too small (0.05 mm / 0.005 deg),
    the result is suspect and the reason says the poses are noisier than given and names the options."""
    from jaxcal.sim.handeye import HandEyeSimConfig, simulate_hand_eye

    config = HandEyeSimConfig(
        target=CHESSBOARD,
        frames=24,
        seed=4,
        resolution=(320, 240),
        robot_noise_mm=1.0,
        robot_noise_deg=0.1,
    )
    capture = simulate_hand_eye(config, tmp_path / "capture")
    assert main(["handeye", str(capture), "--out", str(tmp_path / "out"), "--quiet"]) == 0
    console = capsys.readouterr().out
    s = json.loads((tmp_path / "out" / "result.json").read_text())
    noise, cam = s["robot_noise"], s["cameras"]["cam0"]
    print(
        f"estimated robot noise {noise}, k-fold/std {cam['kfold_over_std']}, truth error {cam['truth_error']}"
    )
    assert s["status"] == "ok" and s["rejected_frames"] == [] and s["reasons"] == []
    assert noise["estimated"] and "estimated from the data" in console and he.ROBOT_SIGMA_OPTIONS in console
    assert abs(noise["translation_mm"] / 1.0 - 1.0) < 0.3 and abs(noise["rotation_deg"] / 0.1 - 1.0) < 0.3
    assert (
        0.7 <= cam["kfold_over_std"]["translation"] <= 1.4 and 0.7 <= cam["kfold_over_std"]["rotation"] <= 1.4
    )
    # The default compared the models on frames left out and kept the estimate: exact poses predict
    # them worse, and the held-out error reads back as the robot's noise (at most: it also holds the fit's).
    model, held = s["robot_noise_model"], s["held_out"]
    assert (
        model["asked"] == "auto" and model["model"] == "estimate" and "chosen by held-out" in model["basis"]
    )
    rms = {m["model"]: m["held_out_rms_px"] for m in model["models"]}
    assert rms["exact"] > 1.05 * rms["estimate"] and held["rms_px"] == rms["estimate"]
    assert 0.9 <= held["robot_noise_level"]["translation_mm"] / 1.0 <= 1.5, held
    given = jaxcal.calibrate_hand_eye_capture(
        capture, robot_sigma_translation=5e-5, robot_sigma_rotation=np.radians(0.005), folds=0
    )
    assert given.verdict.status == "suspect"
    hint = [x for x in given.verdict.reasons if "noisier than given" in x]
    assert len(hint) == 1 and he.ROBOT_SIGMA_OPTIONS in hint[0], given.verdict.reasons
    assert any("needed corrections of" in x for x in given.verdict.reasons)
    print(hint[0])


@pytest.fixture(scope="module")
def corrupted_capture(tmp_path_factory):
    """A rendered eye-in-hand chessboard capture, clean and with 10% of its robot poses off by 2 deg / 5 mm."""
    root = tmp_path_factory.mktemp("corrupted")
    clean = _render(root / "clean", "chessboard", True, seed=11)
    bad = _render(root / "bad", "chessboard", True, seed=11, robot_error_fraction=0.1)
    first = sorted((bad / "images" / "cam0").iterdir())[0]
    shutil.copyfile(first, first.with_name("stray" + first.suffix))  # an image no pose row names
    # One corrupted frame's pose is its predecessor's, as a logger that wrote the previous pose again.
    frame = json.loads((bad / "truth.json").read_text())["corrupted_frames"][0]

    def copy_previous(rows):
        i = [r[0] for r in rows].index(frame)
        rows[i][1:] = rows[i - 1][1:]

    _edit(bad / "poses.csv", copy_previous)
    return clean, bad


@pytest.mark.slow
@pytest.mark.parametrize("robot_noise", [False, True])
def test_corrupted_robot_poses_are_flagged(corrupted_capture, robot_noise):
    """2 of 16 robot poses off by 2 deg / 5 mm: those frames are rejected (with reasons) and the
    camera pose is the clean capture's within its std, with robot noise off and on."""
    clean, bad = corrupted_capture
    kw = dict(robot_sigma_translation=2e-4, robot_sigma_rotation=np.radians(0.02)) if robot_noise else {}
    r_clean = jaxcal.calibrate_hand_eye_capture(clean, folds=0, **kw)
    r_bad = jaxcal.calibrate_hand_eye_capture(bad, folds=0, **kw)
    truth = json.loads((bad / "truth.json").read_text())
    assert r_clean.rejected == {} and r_clean.verdict.ok
    assert [r_bad.capture.frames[f] for f in r_bad.rejected] == truth["corrupted_frames"]
    assert all("robot pose does not fit" in why for why in r_bad.rejected.values())
    assert r_bad.verdict.ok and any("rejected as outliers" in n for n in r_bad.verdict.notes)
    frames = r_bad.capture.frames
    copied = frames.index(truth["corrupted_frames"][0])
    assert r_bad.rejected[copied].endswith(
        f"it repeats frame {frames[copied - 1]}'s pose exactly (a pose logged twice?)"
    ), r_bad.rejected
    assert r_bad.verdict.notes[0].endswith(
        f"poses.csv: 1 frame(s) repeat an earlier frame's pose exactly: {frames[copied]} = {frames[copied - 1]} "
        "(a robot that came back to a commanded pose, or a logger that wrote the previous pose again: the views "
        "will tell)"
    ) and r_bad.verdict.notes[1].endswith(
        "cam0: 1 image(s) not used, no row of poses.csv names their frame: stray.png (a pose row missing, or "
        "files that do not belong to this capture?)"
    ), r_bad.verdict.notes
    trans, rot = _err(r_bad.T_robot_cam[0], r_clean.T_robot_cam[0])
    std = np.asarray(r_bad.result.std_robot_cam[0])
    assert trans < np.linalg.norm(std[:3]) and rot < np.linalg.norm(std[3:])


@pytest.mark.slow
def test_the_robot_noise_model_asked_for_is_the_one_solved(corrupted_capture):
    """`robot_noise="exact"` and the previous release's `estimate_robot_noise=False` solve with the
    poses as reported (no corrections: the exact-pose optimum, no robot noise recorded), where
    the flag once reached a traced test and solved with 1 mm / 0.1 deg "as given"; `given` uses the
    noise given; contradictory or incomplete settings are refused before anything is read."""
    from jaxcal.handeye import hand_eye_solver
    from jaxcal.io.handeye_results import hand_eye_summary

    clean, _ = corrupted_capture
    exact = jaxcal.calibrate_hand_eye_capture(clean, robot_noise="exact", folds=0)
    legacy = jaxcal.calibrate_hand_eye_capture(clean, estimate_robot_noise=False, folds=0)
    # The exact-pose solve of the same data, without rejection (nothing is rejected on this capture).
    plain = jax.tree.map(np.asarray, hand_eye_solver(200)(exact.observations.data, False, False))
    assert plain.robot_sigma is None and exact.rejected == {}
    for run in (exact, legacy):
        assert (
            run.result.robot_sigma is None
            and run.noise.fit.model == "exact"
            and run.noise.setting.mode == "exact"
        )
        np.testing.assert_array_equal(run.result.T_base_ee, run.observations.data.T_base_ee)  # no corrections
        np.testing.assert_allclose(run.T_robot_cam, plain.T_robot_cam, atol=1e-8)
        summary = hand_eye_summary(run)
        assert summary["robot_noise"] is None and summary["robot_noise_model"]["model"] == "exact"
    sigma = (2e-4, np.radians(0.02))
    given = jaxcal.calibrate_hand_eye_capture(
        clean, robot_noise="given", robot_sigma_translation=sigma[0], robot_sigma_rotation=sigma[1], folds=0
    )
    np.testing.assert_allclose(given.result.robot_sigma, [sigma[0]] * 3 + [sigma[1]] * 3)
    assert not bool(given.result.robot_sigma_estimated)
    assert given.noise.basis == "as asked (robot_noise='given')"
    for kw, match in (
        (dict(robot_noise="given"), "robot_noise='given' needs robot_sigma_translation"),
        (dict(robot_noise="estimate", estimate_robot_noise=False), "disagree"),
        (
            dict(robot_noise="exact", robot_sigma_translation=1e-3, robot_sigma_rotation=1e-3),
            "takes no robot_sigma",
        ),
        (dict(robot_noise="sometimes"), "robot_noise must be one of"),
    ):
        with pytest.raises(ValueError, match=match):
            jaxcal.calibrate_hand_eye_capture(clean, **kw)


def test_jaxcal_check_takes_the_held_out_noise_of_an_exact_pose_result():
    """A result with exact robot poses records no robot noise; `jaxcal check` then takes the noise
    its frames left out read as (`held_out`), which a later capture's frames carry too."""
    from jaxcal.io.checks import hand_eye_reference

    doc = {
        "arrangement": "eye_in_hand",
        "cameras": {},
        "target": {"spec": CHESSBOARD.to_dict(), "T_robot_target": {"matrix": np.eye(4).tolist()}},
        "robot_noise": None,
        "held_out": {"robot_noise_level": {"translation_mm": 0.8, "rotation_deg": 0.08}},
        "solver": {"sigma_px": 0.2},
    }
    assert hand_eye_reference(doc, "result.json").robot_noise == (0.8, 0.08)
    assert hand_eye_reference({**doc, "held_out": None}, "result.json").robot_noise is None
    given = {"translation_mm": 1.0, "rotation_deg": 0.1, "estimated": False}
    assert hand_eye_reference({**doc, "robot_noise": given}, "result.json").robot_noise == (1.0, 0.1)


def test_the_command_refuses_robot_noise_options_that_do_not_go_together(tmp_path, capsys):
    for options, match in (
        (["--robot-noise", "given"], "--robot-noise given needs robot-sigma-mm"),
        (
            ["--robot-noise", "exact", "--config", "robot-sigma-mm=1"],
            "--robot-noise exact takes no robot-sigma-mm",
        ),
    ):
        assert main(["handeye", str(tmp_path / "none"), "--out", str(tmp_path / "out"), *options]) == 2
        assert match in capsys.readouterr().err


@pytest.mark.slow
def test_shuffled_capture_is_refused_by_the_command(corrupted_capture, tmp_path, capsys):
    """Robot poses shuffled among the frames: exit code 2 before any solve, naming the frames."""
    clean, _ = corrupted_capture
    shuffled = tmp_path / "shuffled"
    shutil.copytree(clean, shuffled)
    with open(shuffled / "poses.csv", newline="") as f:
        rows = list(csv.reader(f))
    perm = np.roll(np.arange(len(rows) - 1), 5)  # every frame gets another frame's pose
    values = [rows[1 + i][1:] for i in perm]
    with open(shuffled / "poses.csv", "w", newline="") as f:
        csv.writer(f).writerows([rows[0]] + [[rows[1 + k][0], *v] for k, v in enumerate(values)])
    assert main(["handeye", str(shuffled), "--out", str(tmp_path / "out"), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert "robot poses and images disagree" in err and "frames 0000" in err
    assert not (tmp_path / "out").exists()


def _rewrite_poses(path, fn):
    with open(path / "poses.csv", newline="") as f:
        rows = list(csv.reader(f))
    with open(path / "poses.csv", "w", newline="") as f:
        csv.writer(f).writerows([rows[0]] + [fn(rows[0], r) for r in rows[1:]])


@pytest.mark.slow
def test_a_misread_capture_is_named_with_its_fix(corrupted_capture, tmp_path):
    """Three mistakes the input check cannot see (every relative rotation angle is kept): the
    arrangement swapped, quaternions written w, x, y, z under a qx, qy, qz, qw header, and 4x4
    matrices' rotation blocks written by columns. Each is suspect (the robot noise estimated to
    absorb the misfit is beyond any robot's) with a first reason naming the field to fix, and read
    that way it fits as the clean capture does; the clean capture gets no such reason."""
    clean, _ = corrupted_capture
    r = jaxcal.calibrate_hand_eye_capture(clean, folds=0)
    assert r.verdict.ok and not any("the data fit if" in x for x in r.verdict.reasons)
    swapped = tmp_path / "swapped"
    shutil.copytree(clean, swapped)
    meta = json.loads((swapped / "handeye.json").read_text())
    assert meta["arrangement"] == "eye_in_hand"
    (swapped / "handeye.json").write_text(json.dumps(meta | {"arrangement": "eye_to_hand"}))
    wxyz = tmp_path / "wxyz"
    shutil.copytree(clean, wxyz)

    def as_wxyz(header, row):
        i = [header.index(c) for c in ("qx", "qy", "qz", "qw")]
        out = list(row)
        for j, v in zip(i, [row[i[3]], row[i[0]], row[i[1]], row[i[2]]]):
            out[j] = v
        return out

    _rewrite_poses(wxyz, as_wxyz)
    # 4x4 matrices whose rotation blocks are written by columns.
    transposed = tmp_path / "transposed"
    shutil.copytree(clean, transposed)
    T = np.asarray(load_hand_eye_capture(clean).T_base_ee).copy()
    T[:, :3, :3] = np.swapaxes(T[:, :3, :3], -1, -2)
    with open(clean / "poses.csv", newline="") as f:
        frames = [r[0] for r in list(csv.reader(f))[1:]]
    with open(transposed / "poses.csv", "w", newline="") as f:
        csv.writer(f).writerows(
            [["frame", *POSE_COLUMNS["matrix"]]] + [[n, *r] for n, r in zip(frames, pose_rows(T, "matrix"))]
        )
    meta = json.loads((clean / "handeye.json").read_text())
    meta["poses"] = {"file": "poses.csv", "format": "matrix", "translation_unit": "m"}
    (transposed / "handeye.json").write_text(json.dumps(meta))
    for capture, names in (
        (swapped, "field 'arrangement' is 'eye_in_hand'"),
        (wxyz, "hold w, x, y, z"),
        (transposed, "rotation blocks are transposed"),
    ):
        bad = jaxcal.calibrate_hand_eye_capture(capture, folds=0)
        # The robot noise, estimated, absorbs the misfit: it comes out beyond any robot's.
        assert bad.verdict.status == "suspect" and he.implausible_robot_noise(bad.result)
        assert any("more than any robot's pose error" in x for x in bad.verdict.reasons)
        found = [x for x in bad.verdict.reasons if "the data fit if" in x]
        assert len(found) == 1 and names in found[0], bad.verdict.reasons
        assert bad.verdict.reasons[0] == found[0]  # the cause first, then its symptoms
        assert not any("PnP's distances" in x for x in bad.verdict.reasons)  # no scale off misread poses
        rms = float(found[0].split("reprojection RMS ")[1].split(" px")[0])
        assert abs(rms - float(r.result.pixel_rms)) < 0.05 * float(r.result.pixel_rms)


@pytest.mark.slow
def test_rotations_read_in_another_convention_are_refused_naming_it(corrupted_capture, tmp_path):
    """Euler angles written intrinsic x-y-z (R = Rx Ry Rz) under xyz_rpy's fixed axes, and
    roll-pitch-yaw written under xyz_rotvec: the relative rotation angles change, so the input
    check refuses them; the refusal names the reading under which the poses and images agree."""
    clean, _ = corrupted_capture
    T = np.asarray(load_hand_eye_capture(clean).T_base_ee)
    with open(clean / "poses.csv", newline="") as f:
        frames = [r[0] for r in list(csv.reader(f))[1:]]
    meta = json.loads((clean / "handeye.json").read_text())
    intrinsic = -matrix_to_rpy(np.swapaxes(T[:, :3, :3], -1, -2))  # R = Rx(r) Ry(p) Rz(y)
    np.testing.assert_allclose(np.swapaxes(rpy_to_matrix(-intrinsic), -1, -2), T[:, :3, :3], atol=1e-12)
    for fmt, values, want in (
        ("xyz_rpy", intrinsic, "the angles are intrinsic x-y-z"),
        ("xyz_rotvec", matrix_to_rpy(T[:, :3, :3]), "the columns rx, ry, rz hold roll, pitch, yaw"),
    ):
        capture = tmp_path / fmt
        shutil.copytree(clean, capture)
        with open(capture / "poses.csv", "w", newline="") as f:
            csv.writer(f).writerows(
                [["frame", *POSE_COLUMNS[fmt]]]
                + [[n, *t, *v] for n, t, v in zip(frames, T[:, :3, 3].tolist(), values.tolist())]
            )
        spec = {"file": "poses.csv", "format": fmt, "translation_unit": "m", "rotation_unit": "rad"}
        (capture / "handeye.json").write_text(json.dumps(meta | {"poses": spec}))
        with pytest.raises(jaxcal.InconsistentPosesError, match="robot poses and images disagree") as e:
            jaxcal.calibrate_hand_eye_capture(capture, folds=0)
        assert f"They agree when read otherwise: {want}" in str(e.value), str(e.value)


@pytest.mark.slow
def test_matrices_written_by_columns_are_refused_naming_the_order(corrupted_capture, tmp_path):
    """4x4 matrices written column-major (the translation in the bottom row) are refused at
    load, line and frame named, with the order to write them in."""
    clean, _ = corrupted_capture
    T = np.asarray(load_hand_eye_capture(clean).T_base_ee)
    with open(clean / "poses.csv", newline="") as f:
        frames = [r[0] for r in list(csv.reader(f))[1:]]
    capture = tmp_path / "columns"
    shutil.copytree(clean, capture)
    with open(capture / "poses.csv", "w", newline="") as f:
        rows = [[n, *np.swapaxes(M, 0, 1).ravel().tolist()] for n, M in zip(frames, T)]
        csv.writer(f).writerows([["frame", *POSE_COLUMNS["matrix"]], *rows])
    meta = json.loads((clean / "handeye.json").read_text())
    meta["poses"] = {"file": "poses.csv", "format": "matrix", "translation_unit": "m"}
    (capture / "handeye.json").write_text(json.dumps(meta))
    with pytest.raises(DatasetError, match=r"poses.csv line 2 \(frame 0000\): bottom row") as e:
        load_hand_eye_capture(capture)
    assert "written by columns (column-major); write each row by row" in str(e.value)


def test_pose_rows_columns():
    T = _pose([0.1, 0.2, 0.3], [1.0, 2.0, 3.0])[None]
    assert pose_rows(T, "xyz_quat", "mm")[0][:3] == [1000.0, 2000.0, 3000.0]


def test_simulate_handeye_refuses_a_view_that_cannot_hold_the_target(tmp_path, capsys):
    """A camera distance of zero or less is refused by its option; a target that never fits the
    image (too close, too few pixels) by one line naming the resolution and the distance, exit 2,
    nothing written (it was a traceback advising a lower distance)."""
    with pytest.raises(SystemExit) as e:
        main(["simulate-handeye", "--out", str(tmp_path / "a"), "--distance", "-1"])
    assert e.value.code == 2 and "expected a number above zero, got '-1'" in capsys.readouterr().err
    for option, value in (("--resolution", "10x10"), ("--distance", "0.05")):
        assert main(["simulate-handeye", "--out", str(tmp_path / "b"), "--frames", "3", option, value]) == 2
        err = capsys.readouterr().err
        assert err.startswith("jaxcal: error: simulate_hand_eye: the whole target never fits a "), err
        assert ("10x10 image" if option == "--resolution" else "from 0.05 m") in err
        assert "raise the distance or the resolution" in err and "Traceback" not in err
        assert not (tmp_path / "b").exists()
