"""Hand-eye calibration: eye-to-hand, eye-in-hand, several cameras, outliers, TCP touch, OpenCV."""

import cv2
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx
import pytest
from jax.flatten_util import ravel_pytree

from jaxcal import _handeye as he
from jaxcal._handeye import blocks
from jaxcal._handeye.jacobian import pixel_normal, pixel_terms
from jaxcal._handeye.model import HandEyeParams, HandEyeReference, robust_residuals
from jaxcal._linalg import concurrent_decompositions

# --------------------------------------------------------------------------- synthetic problems


def _pose(rotvec, t) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = cv2.Rodrigues(np.asarray(rotvec, np.float64))[0]
    T[:3, 3] = t
    return T


def _inv(T):
    return np.linalg.inv(T)


K = np.array([[600.0, 0.0, 319.5], [0.0, 600.0, 239.5], [0.0, 0.0, 1.0]])
BOARD = np.concatenate(
    [np.stack(np.meshgrid(np.arange(5), np.arange(4)), -1).reshape(-1, 2) * 0.04, np.zeros((20, 1))], axis=1
)


def pixel_problem(seed: int, *, frames: int = 10, eye_in_hand: bool = False):
    """Two cameras (a stereo pair) viewing a 5x4 board over `frames` robot poses, noise-free.

    Returns `(T_base_ee, pixels, X, Y)`: `X` `(2, 4, 4)` = T_cam_base (eye-to-hand)
    or T_cam_ee (eye-in-hand), `Y` = T_ee_board or T_base_board.
    """
    rng = np.random.default_rng(seed)
    X0 = _pose([0.4, -0.3, 0.2], [0.1, -0.05, 0.9])
    X = np.stack([X0, _pose([0.0, 0.12, 0.02], [-0.12, 0.0, 0.01]) @ X0])
    Y = _pose([0.3, -0.2, 0.1], [0.02, 0.03, 0.1])
    centre = _pose([0.0, 0.0, 0.0], -BOARD.mean(0))
    A0 = np.stack(
        [
            _pose(rng.normal(0.0, 0.3, 3), [*rng.normal(0.0, 0.04, 2), 0.75 + rng.normal(0.0, 0.05)]) @ centre
            for _ in range(frames)
        ]
    )
    B = np.stack([_inv(X[0]) @ a @ _inv(Y) for a in A0])  # A = X B Y
    A = np.einsum("cij,fjk,kl->cfil", X, B, Y)
    p = np.einsum("cfij,pj->cfpi", A[..., :3, :3], BOARD) + A[..., None, :3, 3]
    uv = np.einsum("ij,cfpj->cfpi", K, p)
    uv = uv[..., :2] / uv[..., 2:]
    assert np.all((uv > 0) & (uv < [640, 480]))
    T_base_ee = np.linalg.inv(B) if eye_in_hand else B
    return T_base_ee, uv, X, Y


def opencv_protocol(rng, n: int, scale: float):
    """OpenCV's own hand-eye test data (calib3d/test/test_hand_eye_calibration.cpp), eye-in-hand.

    Returns `(T_gripper_cam, T_base_gripper (n,4,4), T_cam_target (n,4,4))`, with
    Gaussian noise of `scale` times (2 mrad, 5 mm) on the board poses and
    (1 mrad, 1 mm) on the robot poses (on the rotation vector and the translation).
    """

    def gen(th, tr):
        axis = rng.uniform(-1.0, 1.0, 3)
        theta = rng.uniform(*np.radians(th)) * np.sign(rng.uniform(-1.0, 1.0))
        t = rng.uniform(*tr, 3) * np.sign(rng.uniform(-1.0, 1.0, 3))
        return _pose(theta * axis, t)

    def noisy(T, sr, st):
        out = _pose(cv2.Rodrigues(T[:3, :3])[0].ravel() + rng.normal(0.0, sr, 3), T[:3, 3])
        out[:3, 3] += rng.normal(0.0, st, 3)
        return out

    T_gc = gen((10, 50), (0.05, 0.5))
    T_bt = gen((5, 85), (0.5, 3.5))
    Tg, Tc = [], []
    for _ in range(n):
        T_bg = gen((5, 45), (0.5, 1.5))
        Tc.append(noisy(_inv(T_gc) @ _inv(T_bg) @ T_bt, 0.002 * scale, 0.005 * scale))
        Tg.append(noisy(T_bg, 0.001 * scale, 0.001 * scale))
    return T_gc, np.stack(Tg), np.stack(Tc)


def _err(T_est, T_true):
    """(rotation error rad, translation error m)."""
    dR = np.asarray(T_est)[:3, :3] @ T_true[:3, :3].T
    return np.linalg.norm(cv2.Rodrigues(dR)[0]), np.linalg.norm(np.asarray(T_est)[:3, 3] - T_true[:3, 3])


def _succeeded(result) -> bool:
    return bool(result.result == optx.RESULTS.successful)


# One compiled solver per data structure, shared by the tests below.
_calibrate_jit = jax.jit(lambda data, reject: he.calibrate_hand_eye(data, reject_outliers=reject))


def _calibrate(data, reject_outliers: bool = True):
    """The default solve; `reject_outliers` is traced, so both settings share one compilation."""
    return _calibrate_jit(data, jnp.asarray(reject_outliers))


_calibrate_batch = eqx.filter_jit(eqx.filter_vmap(he.calibrate_hand_eye))


# --------------------------------------------------------------------------- image features


@pytest.fixture(scope="module")
def eye_to_hand():
    return pixel_problem(0)


def test_pixels_eye_to_hand_two_cameras_exact(eye_to_hand):
    T_base_ee, uv, X, Y = eye_to_hand
    data = he.make_hand_eye_pixels(T_base_ee, uv, K, BOARD)
    X0, Y0 = jax.jit(he.initialise_hand_eye)(data)  # the closed form alone is exact too
    np.testing.assert_allclose(X0, X, atol=1e-9)
    np.testing.assert_allclose(Y0, Y, atol=1e-9)
    r = _calibrate(data)
    assert _succeeded(r) and int(r.num_rejected) == 0
    np.testing.assert_allclose(r.T_cam_base, X, atol=1e-9)
    np.testing.assert_allclose(r.T_base_cam, np.linalg.inv(X), atol=1e-9)
    np.testing.assert_allclose(r.T_ee_board, Y, atol=1e-9)
    assert float(r.pixel_rms) < 1e-8
    with pytest.raises(AttributeError, match="eye-to-hand"):
        _ = r.T_ee_cam


def test_pixels_noise_and_outlier_rejected(eye_to_hand):
    """0.3 px noise, one robot pose off by 3 deg and 1 cm: that frame is rejected, the rest is ML."""
    T_base_ee, uv, X, Y = eye_to_hand
    rng = np.random.default_rng(1)
    bad = T_base_ee.copy()
    bad[4] = bad[4] @ _pose([0.0, np.radians(3.0), 0.0], [0.01, 0.0, 0.0])
    data = he.make_hand_eye_pixels(bad, uv + rng.normal(0.0, 0.3, uv.shape), K, BOARD, sigma_px=0.3)
    r = _calibrate(data)
    assert _succeeded(r)
    assert r.rejected_frames().tolist() == [4]
    assert np.asarray(r.rejected).sum() == 2  # both cameras' views of that pose
    assert 0.8 < float(r.residual_rms) < 1.2  # the noise model is honest on the kept frames
    np.testing.assert_allclose(float(r.pixel_rms), 0.3 * float(r.residual_rms))
    for c in range(2):
        rot, trans = _err(r.T_base_cam[c], np.linalg.inv(X[c]))
        std = np.asarray(r.std_robot_cam[c])
        assert trans < 4.0 * np.linalg.norm(std[:3]) and trans < 2e-3
        assert rot < 4.0 * np.linalg.norm(std[3:]) and rot < np.radians(0.1)
    # Without rejection the bad pose drags the solution far off (the same compiled solver).
    r_all = _calibrate(data, reject_outliers=False)
    assert int(r_all.num_rejected) == 0
    assert (
        _err(r_all.T_base_cam[0], np.linalg.inv(X[0]))[1] > 3 * _err(r.T_base_cam[0], np.linalg.inv(X[0]))[1]
    )


def test_pixels_eye_in_hand():
    T_base_ee, uv, X, Y = pixel_problem(2, eye_in_hand=True)
    r = _calibrate(he.make_hand_eye_pixels(T_base_ee, uv, K, BOARD, eye_in_hand=True))
    assert _succeeded(r)
    np.testing.assert_allclose(r.T_cam_ee, X, atol=1e-9)
    np.testing.assert_allclose(r.T_base_board, Y, atol=1e-9)
    rng = np.random.default_rng(3)
    noisy = he.make_hand_eye_pixels(
        T_base_ee, uv + rng.normal(0.0, 0.5, uv.shape), K, BOARD, eye_in_hand=True, sigma_px=0.5
    )
    r = _calibrate(noisy)
    assert _succeeded(r) and int(r.num_rejected) == 0
    rot, trans = _err(r.T_ee_cam[0], np.linalg.inv(X[0]))
    assert trans < 4.0 * np.linalg.norm(np.asarray(r.std_robot_cam[0, :3])) and trans < 3e-3
    assert rot < 4.0 * np.linalg.norm(np.asarray(r.std_robot_cam[0, 3:]))


def test_pixels_noisy_robot_poses():
    """Robot poses off by 2 mrad / 2 mm, 0.05 px corners: with `robot_sigma` the robot poses are corrected."""
    T_base_ee, uv, X, Y = pixel_problem(11, frames=8)
    data = he.make_hand_eye_pixels(
        T_base_ee, uv, K, BOARD, robot_sigma_translation=2e-3, robot_sigma_rotation=2e-3
    )
    r = _calibrate(data)  # noise-free: exact, no correction
    assert _succeeded(r)
    np.testing.assert_allclose(r.T_cam_base, X, atol=1e-9)
    np.testing.assert_allclose(r.T_ee_board, Y, atol=1e-9)
    np.testing.assert_allclose(r.T_base_ee, T_base_ee, atol=1e-9)
    rng = np.random.default_rng(12)
    noisy = np.stack(
        [T @ _pose(rng.normal(0.0, 2e-3, 3), rng.normal(0.0, 2e-3, 3)) for T in T_base_ee]
    )  # the true poses are T_base_ee
    data = he.make_hand_eye_pixels(
        noisy,
        uv + rng.normal(0.0, 0.05, uv.shape),
        K,
        BOARD,
        sigma_px=0.05,
        robot_sigma_translation=2e-3,
        robot_sigma_rotation=2e-3,
    )
    r = _calibrate(data)
    assert _succeeded(r) and int(r.num_rejected) == 0
    before = np.array([_err(n, t) for n, t in zip(noisy, T_base_ee)])
    after = np.array([_err(c, t) for c, t in zip(np.asarray(r.T_base_ee), T_base_ee)])
    # Eight poses carry 48 unknown corrections and 12 shared unknowns: the
    # corrections recover most of the robot error (up to the gauge the
    # shared transforms absorb).
    assert after[:, 0].mean() < 0.5 * before[:, 0].mean() and after[:, 1].mean() < 0.5 * before[:, 1].mean()
    assert 0.7 < float(r.residual_rms) < 1.3


def _noisy_robot_pixels(seed, frames, *, eye_in_hand=False):
    """`pixel_problem` with robot poses off by 2 mrad / 2 mm and 0.05 px corner noise."""
    T_base_ee, uv, X, Y = pixel_problem(seed, frames=frames, eye_in_hand=eye_in_hand)
    rng = np.random.default_rng(seed + 1)
    noisy = np.stack([T @ _pose(rng.normal(0.0, 2e-3, 3), rng.normal(0.0, 2e-3, 3)) for T in T_base_ee])
    uv = uv + rng.normal(0.0, 0.05, uv.shape)
    kw = dict(sigma_px=0.05, robot_sigma_translation=2e-3, robot_sigma_rotation=2e-3, eye_in_hand=eye_in_hand)
    return he.make_hand_eye_pixels(noisy, uv, K, BOARD, **kw)


_calibrate_dense = jax.jit(lambda data: he.calibrate_hand_eye(data, by_blocks=False))


def test_noisy_robot_pixels_by_blocks_equal_the_dense_solve():
    """The Schur-complement solve (`blocks`, the default) and optimistix's dense
    LM over every robot correction: the same optimum, covariance and summary."""
    for eye_in_hand in (False, True):  # a traced flag: one compilation each
        data = _noisy_robot_pixels(21, 8, eye_in_hand=eye_in_hand)
        a, b = _calibrate(data), _calibrate_dense(data)
        assert _succeeded(a) and _succeeded(b)
        np.testing.assert_array_equal(a.rejected, b.rejected)
        for name in ("T_cam_robot", "T_robot_board", "T_base_ee"):
            np.testing.assert_allclose(getattr(a, name), getattr(b, name), rtol=0, atol=1e-8)
        for name in ("cov", "cov_frames"):
            scale = float(np.max(np.abs(getattr(b, name))))
            np.testing.assert_allclose(getattr(a, name), getattr(b, name), rtol=0, atol=1e-8 * scale)
        for name in ("std_cam_robot", "std_robot_board", "variance_factor", "robot_rms", "group_rms"):
            np.testing.assert_allclose(getattr(a, name), getattr(b, name), rtol=1e-8, atol=1e-14)


_calibrate_autodiff = jax.jit(lambda data: he.calibrate_hand_eye(data, closed_form_jacobian=False))


def test_closed_form_pixel_jacobian_equals_autodiff(eye_to_hand):
    """The hand-written Jacobian of the robust pixel residuals (exact robot poses)
    against autodiff away from the optimum, robust and plain, and the solve on it
    (`jacobian.solve_pixels`) against optimistix's on autodiff's: the same steps,
    optimum, covariance and summary."""
    T_base_ee, uv, X, Y = eye_to_hand
    rng = np.random.default_rng(3)
    bad = T_base_ee.copy()
    bad[2] = bad[2] @ _pose([0.0, np.radians(2.0), 0.0], [0.005, 0.0, 0.0])  # a group the loss down-weights
    mask = rng.random(uv.shape[:3]) > 0.2
    data = he.make_hand_eye_pixels(bad, uv + rng.normal(0.0, 0.2, uv.shape), K, BOARD, mask, sigma_px=0.2)
    X0, Y0 = jax.jit(he.initialise_hand_eye)(data)
    active = jnp.ones(data.mask.shape[:2], bool).at[1, 5].set(False)
    ref = HandEyeReference(X0=X0, Y0=Y0, active=active)
    params = HandEyeParams(
        cam_robot=jnp.asarray(rng.normal(0.0, 0.02, (2, 6))), robot_board=jnp.asarray(rng.normal(0.0, 0.02, 6)),
        robot=None,
    )  # fmt: skip
    flat, unravel = ravel_pytree(params)
    for robust in (True, False):
        args = (ref, data, 2.0, jnp.asarray(robust))
        r, J = jax.jit(pixel_terms)(params, args)
        auto = jax.jit(jax.jacfwd(lambda x, a=args: robust_residuals(unravel(x), a)[0]))(flat)
        np.testing.assert_allclose(
            r, robust_residuals(params, args)[0], rtol=0, atol=1e-12 * float(jnp.abs(r).max())
        )
        np.testing.assert_allclose(J, auto, rtol=0, atol=1e-9 * float(jnp.abs(auto).max()))
        assert float(jnp.abs(J[1, 5]).max()) == 0.0 and float(jnp.abs(auto).max()) > 10.0
        # The solver's normal equations, formed group by group with the loss's rank-one terms.
        r_n, normal = pixel_normal(params, args)
        np.testing.assert_allclose(r_n, r, rtol=0, atol=1e-12 * float(jnp.abs(r).max()))
        Jf = np.asarray(J).reshape(-1, J.shape[-1])
        H = Jf.T @ Jf
        np.testing.assert_allclose(normal.H, H, rtol=0, atol=1e-10 * np.abs(H).max())
        G = np.einsum("cfkn,cfk->cfn", J, r)
        np.testing.assert_allclose(normal.aux, G, rtol=0, atol=1e-10 * np.abs(G).max())
        np.testing.assert_allclose(normal.e, G.sum((0, 1)), rtol=0, atol=1e-10 * np.abs(G).max())
    a, b = _calibrate(data), _calibrate_autodiff(data)
    assert _succeeded(a) and _succeeded(b) and a.rejected_frames().tolist() == [2]
    np.testing.assert_array_equal(a.rejected, b.rejected)
    # `solve_pixels` runs optimistix's iteration on the normal equations: the same steps.
    np.testing.assert_array_equal(a.stage_steps, b.stage_steps)
    for name in ("T_cam_robot", "T_robot_board"):
        np.testing.assert_allclose(getattr(a, name), getattr(b, name), rtol=0, atol=1e-8)
    for name in ("cov", "cov_frames"):
        scale = float(np.max(np.abs(getattr(b, name))))
        np.testing.assert_allclose(getattr(a, name), getattr(b, name), rtol=0, atol=1e-8 * scale)
    for name in ("std_cam_robot", "std_robot_board", "variance_factor", "group_rms"):
        np.testing.assert_allclose(getattr(a, name), getattr(b, name), rtol=1e-8, atol=1e-14)


def test_block_linearisation_equals_forward_mode():
    """`blocks.linearise` (chain rule through the board poses) against n_g + 6
    forward-mode products of the frame residuals, plain and robust, both mounts."""
    for eye_in_hand in (False, True):
        data = _noisy_robot_pixels(22, 6, eye_in_hand=eye_in_hand)
        X0, Y0 = jax.jit(he.initialise_hand_eye)(data)
        rng = np.random.default_rng(23)
        g = jnp.asarray(rng.normal(0.0, 1e-2, 18))
        l = jnp.asarray(rng.normal(0.0, 2e-3, (6, 6)))
        ref = HandEyeReference(X0=X0, Y0=Y0, active=jnp.ones((2, 6), bool).at[1, 2].set(False))
        for robust in (False, True):
            args = (ref, data, jnp.asarray(0.5), jnp.asarray(robust))
            ours = jax.jit(blocks.linearise)(g, l, args)
            ref_ = jax.jit(blocks.linearise_by_jvp)(g, l, args)
            for x, y in zip(ours, ref_):
                np.testing.assert_allclose(x, y, rtol=0, atol=1e-12 * float(np.max(np.abs(y))))
    assert blocks.join(*blocks.split(HandEyeParams(jnp.ones((2, 6)), jnp.zeros(6), l))).robot is l


def test_poses_two_cameras_noisy_robot():
    """Pose-level, two cameras, robot noise marginalised: trial 0 noise-free (exact), 12 noisy (calibrated)."""
    T_base_ee, _, X, Y = pixel_problem(13, frames=12)
    A = np.einsum("cij,fjk,kl->cfil", X, T_base_ee, Y)
    kw = dict(
        sigma_translation=1e-3, sigma_rotation=1e-3, robot_sigma_translation=1e-3, robot_sigma_rotation=1e-3
    )
    rng = np.random.default_rng(14)
    trials = [he.make_hand_eye_poses(T_base_ee, A, **kw)]
    for _ in range(12):
        Tr = np.stack([T @ _pose(rng.normal(0.0, 1e-3, 3), np.zeros(3)) for T in T_base_ee])
        Tr[:, :3, 3] += rng.normal(0.0, 1e-3, (len(Tr), 3))
        An = np.einsum("cfij,cfjk->cfik", A, _noise_poses(rng, A.shape[:2], 1e-3, 1e-3))
        trials.append(he.make_hand_eye_poses(Tr, An, **kw))
    # A loop of jitted solves: one compilation, cheaper than the vmapped one (tested below).
    r = jax.tree.map(lambda *x: jnp.stack(x), *[_calibrate(d) for d in trials])
    assert bool(jnp.all(r.result == optx.RESULTS.successful))
    np.testing.assert_allclose(r.T_cam_base[0], X, atol=1e-9)
    np.testing.assert_allclose(r.T_ee_board[0], Y, atol=1e-9)
    np.testing.assert_allclose(r.T_base_ee[0], T_base_ee, atol=1e-9)  # no correction needed
    # Normalised errors of both cameras' poses: RMS about 1 if the marginalised covariance is right.
    z = []
    for i in range(1, len(trials)):
        for c in range(2):
            rot, trans = _err(r.T_base_cam[i, c], np.linalg.inv(X[c]))
            std = np.asarray(r.std_robot_cam[i, c])
            z += [trans / np.linalg.norm(std[:3]), rot / np.linalg.norm(std[3:])]
    assert 0.6 < np.sqrt(np.mean(np.square(z))) < 1.4


def _noise_poses(rng, shape, sigma_t, sigma_r):
    """Right-multiplied pose noise `(..., 4, 4)`: small rotations and translations."""
    out = np.broadcast_to(np.eye(4), (*shape, 4, 4)).copy()
    for idx in np.ndindex(*shape):
        out[idx] = _pose(rng.normal(0.0, sigma_r, 3), rng.normal(0.0, sigma_t, 3))
    return out


@pytest.mark.slow
def test_rendered_eye_to_hand():
    """MuJoCo-rendered ChArUco frames (UR5e, fixed 640x480 camera): corners beat OpenCV on PnP poses."""
    from jaxcal.sim.handeye import render_eye_to_hand

    d = render_eye_to_hand(10, seed=3)
    T_base_cam = d["T_base_cam"]
    r = _calibrate(
        he.make_hand_eye_pixels(d["T_base_ee"], d["pixels"], d["K"], d["points"], d["mask"], sigma_px=0.3)
    )
    assert _succeeded(r) and int(r.num_rejected) == 0
    assert float(r.pixel_rms) < 0.3
    rot, trans = _err(r.T_base_cam[0], T_base_cam)
    assert rot < np.radians(0.1) and trans < 1e-3
    _, trans_board = _err(r.T_ee_board, d["T_ee_board"])
    assert trans_board < 1e-3
    # OpenCV's seven solvers on the PnP poses of the same frames (eye-to-hand through the
    # eye-in-hand API: base2gripper in, cam2base out).
    theirs = np.array(
        [_err(T, T_base_cam) for T in _opencv(np.linalg.inv(d["T_base_ee"]), d["T_cam_board"]).values()]
    )
    assert rot < theirs[:, 0].min() and trans < theirs[:, 1].min()


# --------------------------------------------------------------------------- pose level, against OpenCV

_OPENCV_HAND_EYE = ("TSAI", "PARK", "HORAUD", "ANDREFF", "DANIILIDIS")
_OPENCV_ROBOT_WORLD = ("SHAH", "LI")


def _opencv(Tg, Tc):
    """Every OpenCV method's T_gripper_cam on eye-in-hand pose pairs."""
    out = {}
    for name in _OPENCV_HAND_EYE:
        R, t = cv2.calibrateHandEye(
            Tg[:, :3, :3],
            Tg[:, :3, 3],
            Tc[:, :3, :3],
            Tc[:, :3, 3],
            method=getattr(cv2, f"CALIB_HAND_EYE_{name}"),
        )
        out[name] = _pose(cv2.Rodrigues(R)[0].ravel(), t.ravel())
    Tgb = np.linalg.inv(Tg)
    for name in _OPENCV_ROBOT_WORLD:
        _, _, R, t = cv2.calibrateRobotWorldHandEye(
            Tc[:, :3, :3],
            Tc[:, :3, 3],
            Tgb[:, :3, :3],
            Tgb[:, :3, 3],
            method=getattr(cv2, f"CALIB_ROBOT_WORLD_HAND_EYE_{name}"),
        )
        out[name] = np.linalg.inv(_pose(cv2.Rodrigues(R)[0].ravel(), t.ravel()))
    return out


def _pose_data(Tg, Tc, scale):
    return he.make_hand_eye_poses(
        Tg,
        Tc,
        eye_in_hand=True,
        sigma_translation=0.005 * scale,
        sigma_rotation=0.002 * scale,
        robot_sigma_translation=0.001 * scale,
        robot_sigma_rotation=0.001 * scale,
    )


def test_poses_against_opencv():
    """OpenCV's own protocol, 10 poses: trial 0 noise-free, 15 seeded noisy trials, vmapped.

    Noise-free: every OpenCV method, jaxcal's closed form and its solve recover
    T_gripper_cam. Noisy: jaxcal (pose-level ML with the protocol's noise model)
    beats the best OpenCV method on average, and its standard deviations match
    its actual errors.
    """
    rng = np.random.default_rng(5)
    trials = [opencv_protocol(rng, 10, 0.0 if i == 0 else 1.0) for i in range(16)]
    data = jax.tree.map(lambda *x: jnp.stack(x), *[_pose_data(Tg, Tc, 1.0) for _, Tg, Tc in trials])
    X0, _ = jax.jit(jax.vmap(he.initialise_hand_eye))(data)
    r = _calibrate_batch(data)
    assert bool(jnp.all(r.result == optx.RESULTS.successful))
    assert int(jnp.sum(r.num_rejected)) == 0

    T_gc, Tg, Tc = trials[0]
    for name, T in _opencv(Tg, Tc).items():
        rot, trans = _err(T, T_gc)
        assert rot < 1e-7 and trans < 1e-7, name
    np.testing.assert_allclose(np.linalg.inv(X0[0, 0]), T_gc, atol=1e-9)  # the closed form alone
    np.testing.assert_allclose(r.T_ee_cam[0, 0], T_gc, atol=1e-9)
    np.testing.assert_allclose(r.T_base_ee[0], Tg, atol=1e-9)  # no robot correction needed

    ours = np.array([_err(r.T_ee_cam[i, 0], t[0]) for i, t in enumerate(trials)])[1:]
    theirs = {k: [] for k in _OPENCV_HAND_EYE + _OPENCV_ROBOT_WORLD}
    for T_gc, Tg, Tc in trials[1:]:
        for name, T in _opencv(Tg, Tc).items():
            theirs[name].append(_err(T, T_gc))
    best = np.min([np.mean(v, axis=0) for v in theirs.values()], axis=0)
    mean = ours.mean(0)
    assert mean[0] < 0.85 * best[0] and mean[1] < 0.85 * best[1], (mean, best)
    # Normalised errors: |error| / sqrt(trace of the 3x3 block) has RMS 1 for a calibrated covariance.
    std = np.asarray(r.std_robot_cam[1:, 0])
    z_t = ours[:, 1] / np.linalg.norm(std[:, :3], axis=1)
    z_r = ours[:, 0] / np.linalg.norm(std[:, 3:], axis=1)
    assert 0.7 < np.sqrt(np.mean(z_t**2)) < 1.35
    assert 0.7 < np.sqrt(np.mean(z_r**2)) < 1.35


# --------------------------------------------------------------------------- bad input


def test_batched_solves_keep_lapack_calls_ordered(eye_to_hand):
    """No two LAPACK calls of a vmapped solve can run side by side: on a
    two-core machine that deadlocks jaxlib's CPU thread pool (see jaxcal._linalg).
    Pose data with noisy robot poses (whitening) and pixel data (homographies)."""
    rng = np.random.default_rng(5)
    trials = [opencv_protocol(rng, 10, 1.0) for _ in range(2)]
    poses = jax.tree.map(lambda *x: jnp.stack(x), *[_pose_data(Tg, Tc, 1.0) for _, Tg, Tc in trials])
    T_base_ee, uv, _, _ = eye_to_hand
    pixels = he.make_hand_eye_pixels(T_base_ee, uv, K, BOARD)
    pixels = jax.tree.map(lambda x: jnp.stack([x, x]) if eqx.is_array(x) else x, pixels)
    noisy = _noisy_robot_pixels(24, 8)  # solved by blocks
    noisy = jax.tree.map(lambda x: jnp.stack([x, x]) if eqx.is_array(x) else x, noisy)
    for data in (poses, pixels, noisy):
        assert concurrent_decompositions(eqx.filter_vmap(he.calibrate_hand_eye), data) == []


def _good_poses():
    _, Tg, Tc = opencv_protocol(np.random.default_rng(6), 6, 0.0)
    return Tg, Tc


def _one_axis(n, axis=(0.0, 0.0, 1.0), step_deg=10.0):
    return np.stack(
        [_pose(np.radians(step_deg * i) * np.asarray(axis), [0.1 * i, 0.0, 0.5]) for i in range(n)]
    )


@pytest.mark.parametrize(
    "case, error, match",
    [
        ("too_few", he.TooFewPosesError, "only 2 frames"),
        ("one_axis", he.DegenerateMotionError, "second, non-parallel axis"),
        ("small", he.DegenerateMotionError, "at least 5 deg"),
        ("lengths", he.LengthMismatchError, "6 robot poses .* 5 board poses"),
        ("robot_not_rotation", he.NotARotationError, r"T_base_ee: pose \(3,\) is not a rotation"),
        ("board_not_rotation", he.NotARotationError, r"T_cam_board: pose \(0, 2\) is not a rotation"),
        ("bottom_row", he.NotARotationError, "bottom row"),
        ("nan_robot", he.NonFiniteError, "T_base_ee: non-finite"),
        ("shape", he.ShapeError, "T_cam_board must have shape"),
    ],
)
def test_bad_pose_input(case, error, match):
    Tg, Tc = _good_poses()
    if case == "too_few":
        Tg, Tc = Tg[:2], Tc[:2]
    elif case == "one_axis":
        Tg = _one_axis(6)
    elif case == "small":
        Tg = _one_axis(6, axis=(0.6, 0.8, 0.0), step_deg=0.5)
    elif case == "lengths":
        Tc = Tc[:5]
    elif case == "robot_not_rotation":
        Tg[3, :3, :3] *= 1.01
    elif case == "board_not_rotation":
        Tc[2, :3, :3] = Tc[2, :3, :3] @ np.diag([1.0, 1.0, -1.0])  # a reflection: det = -1
    elif case == "bottom_row":
        Tg[1, 3, 0] = 0.5
    elif case == "nan_robot":
        Tg[0, 0, 3] = np.nan
    elif case == "shape":
        Tc = Tc[:, :3]
    with pytest.raises(error, match=match) as info:
        he.make_hand_eye_poses(Tg, Tc, eye_in_hand=True)
    assert isinstance(info.value, ValueError)


def test_bad_pixel_input():
    T_base_ee, uv, _, _ = pixel_problem(0, frames=4)
    with pytest.raises(he.LengthMismatchError, match="4 robot poses .* 3 frames of pixels"):
        he.make_hand_eye_pixels(T_base_ee, uv[:, :3], K, BOARD)
    bad = uv.copy()
    bad[1, 2, 5] = np.nan
    with pytest.raises(he.NonFiniteError, match="camera 1, frame 2, point 5"):
        he.make_hand_eye_pixels(T_base_ee, bad, K, BOARD, mask=np.ones(uv.shape[:3], bool))
    mask = np.ones(uv.shape[:3], bool)
    mask[1] = False
    with pytest.raises(he.TooFewPosesError, match="camera 1 has no usable view"):
        he.make_hand_eye_pixels(T_base_ee, uv, K, BOARD, mask=mask)
    with pytest.raises(he.ShapeError, match="K has shape"):
        he.make_hand_eye_pixels(T_base_ee, uv, np.stack([K, K, K]), BOARD)
    # Every frame but one rotates about the same axis: too little diversity even though 4 poses.
    with pytest.raises(he.DegenerateMotionError, match="non-parallel"):
        he.make_hand_eye_pixels(_one_axis(4, axis=(1.0, 0.0, 0.0)), uv, K, BOARD)
    # Camera matrices that are not a pinhole's: a negative focal length would turn the camera round.
    flipped = K.copy()
    flipped[0, 0] = flipped[1, 1] = -600.0
    with pytest.raises(he.IntrinsicsError, match="camera 0: focal lengths must be positive"):
        he.make_hand_eye_pixels(T_base_ee, uv, flipped, BOARD)
    with pytest.raises(he.IntrinsicsError, match="camera 1: .*transposed"):
        he.make_hand_eye_pixels(T_base_ee, uv, np.stack([K, K.T]), BOARD)
    with pytest.raises(he.NonFiniteError, match="K of camera 0"):
        he.make_hand_eye_pixels(T_base_ee, uv, np.where(np.eye(3) > 0, np.nan, K), BOARD)
    with pytest.raises(he.ShapeError, match=r"K must have shape \(3, 3\) or \(cameras, 3, 3\), got \(3, 4\)"):
        he.make_hand_eye_pixels(T_base_ee, uv, np.c_[K, np.zeros(3)], BOARD)
    # Noise levels must be finite and positive.
    for sigma in (0.0, -0.2, np.nan):
        with pytest.raises(he.NoiseLevelError, match="sigma_px must be finite and positive"):
            he.make_hand_eye_pixels(T_base_ee, uv, K, BOARD, sigma_px=sigma)
    with pytest.raises(he.NoiseLevelError, match="robot_sigma_translation and robot_sigma_rotation"):
        he.make_hand_eye_pixels(
            T_base_ee, uv, K, BOARD, robot_sigma_translation=-1e-3, robot_sigma_rotation=1e-3
        )


def test_a_view_of_one_row_of_corners_stays_out_of_the_closed_form_start(eye_to_hand):
    """A view whose corners lie on one line (one row of the board) has no homography: it is
    left out of the closed-form start (which it would wreck) and of the rotation-angle check,
    and its corners still count in the solve."""
    T_base_ee, uv, X, Y = eye_to_hand
    mask = np.ones(uv.shape[:3], bool)
    mask[0, 3] = False
    mask[0, 3, :5] = True  # the board's first row of five corners only
    data = he.make_hand_eye_pixels(T_base_ee, uv, K, BOARD, mask=mask)
    _, ok = jax.jit(he.board_poses_from_pixels)(data)
    assert not bool(ok[0, 3]) and bool(np.asarray(ok).sum() == ok.size - 1)
    X0, Y0 = jax.jit(he.initialise_hand_eye)(data)
    np.testing.assert_allclose(X0, X, atol=1e-9)
    np.testing.assert_allclose(Y0, Y, atol=1e-9)
    r = _calibrate(data)
    assert _succeeded(r) and int(r.num_rejected) == 0
    np.testing.assert_allclose(r.T_cam_base, X, atol=1e-9)
    assert float(r.group_rms[0, 3]) < 1e-6  # its five corners were solved with the rest


# --------------------------------------------------------------------------- TCP touch


def touch_problem(seed: int, *, eye_in_hand: bool, n: int = 8):
    """Board points seen by the camera and touched by the TCP with varied tool orientations."""
    rng = np.random.default_rng(seed)
    tcp = np.array([0.01, -0.02, 0.15])
    T_base_board = _pose([0.05, -0.1, 0.3], [0.6, 0.1, 0.05])
    X = (
        _pose([2.5, 0.3, -0.4], [0.05, 0.02, 0.08])
        if eye_in_hand
        else _pose([2.2, 0.5, 0.2], [1.2, 0.3, 0.8])
    )
    pts_board = BOARD[rng.choice(len(BOARD), n, replace=False)]
    pts_base = pts_board @ T_base_board[:3, :3].T + T_base_board[:3, 3]
    D = []
    for p in pts_base:  # touch: the TCP at p, the tool tilted at random
        R = cv2.Rodrigues(np.array([np.pi, 0.0, 0.0]) + rng.normal(0.0, 0.3, 3))[0]
        D.append(_pose(cv2.Rodrigues(R)[0].ravel(), p - R @ tcp))
    D = np.stack(D)
    if eye_in_hand:  # the camera looks from one end-effector pose
        C = T_base_board @ _pose([np.pi, 0.0, 0.0], [0.08, 0.06, 0.5]) @ _inv(X)  # C X = T_base_cam
        points_cam = np.einsum("ij,kj->ki", _inv(C @ X), np.concatenate([pts_base, np.ones((n, 1))], 1))[
            :, :3
        ]
        return points_cam, D, C, tcp, X
    points_cam = np.einsum("ij,kj->ki", _inv(X), np.concatenate([pts_base, np.ones((n, 1))], 1))[:, :3]
    return points_cam, D, None, tcp, X


_calibrate_touch = eqx.filter_jit(he.calibrate_touch)


@pytest.mark.parametrize("eye_in_hand", [False, True])
def test_touch_exact_and_noisy(eye_in_hand):
    """The TCP offset unknown: exact on noise-free points; 0.2 mm point noise within the reported std."""
    P, D, C, tcp, X = touch_problem(7, eye_in_hand=eye_in_hand)
    r = _calibrate_touch(he.make_touch_data(P, D, C))  # TCP offset unknown
    assert _succeeded(r) and r.eye_in_hand == eye_in_hand
    np.testing.assert_allclose(r.T_robot_cam, X, atol=1e-9)
    np.testing.assert_allclose(r.tcp, tcp, atol=1e-9)
    rng = np.random.default_rng(8)
    sigma = 2e-4
    noisy = he.make_touch_data(P + rng.normal(0.0, sigma, P.shape), D, C, sigma=sigma)
    r = _calibrate_touch(noisy)
    assert _succeeded(r)
    assert np.linalg.norm(np.asarray(r.tcp) - tcp) < 4.0 * np.linalg.norm(np.asarray(r.std_tcp))
    rot, trans = _err(r.T_robot_cam, X)
    std = np.asarray(r.std_robot_cam)
    assert trans < 4.0 * np.linalg.norm(std[:3]) and np.linalg.norm(std[:3]) < 3e-3
    assert rot < 4.0 * np.linalg.norm(std[3:]) and np.linalg.norm(std[3:]) < np.radians(0.5)
    assert 0.3 * sigma < float(r.rms) < 2.0 * sigma


@pytest.mark.parametrize("eye_in_hand", [False, True])
def test_touch_known_tcp(eye_in_hand):
    P, D, C, tcp, X = touch_problem(10, eye_in_hand=eye_in_hand)
    r = _calibrate_touch(he.make_touch_data(P[:3], D[:3], C, tcp=tcp))  # three points suffice
    assert _succeeded(r)
    np.testing.assert_allclose(r.T_robot_cam, X, atol=1e-9)
    np.testing.assert_allclose(r.tcp, tcp)
    assert np.all(np.asarray(r.std_tcp) == 0.0)


def test_touch_bad_input():
    P, D, _, tcp, _ = touch_problem(9, eye_in_hand=False)
    with pytest.raises(he.LengthMismatchError, match="8 camera points but T_base_ee_touch"):
        he.make_touch_data(P, D[:7])
    with pytest.raises(he.TooFewPosesError, match="only 4 touched points, at least 5"):
        he.make_touch_data(P[:4], D[:4])
    line = np.outer(np.arange(8), [0.01, 0.02, 0.0])
    with pytest.raises(he.DegenerateMotionError, match="collinear"):
        he.make_touch_data(line, D, tcp=tcp)
    same = np.broadcast_to(D[0], D.shape).copy()
    same[:, :3, 3] = D[:, :3, 3]
    with pytest.raises(he.DegenerateMotionError, match="unknown TCP offset"):
        he.make_touch_data(P, same)
    bent = D.copy()
    bent[2, :3, :3] *= 2.0
    with pytest.raises(he.NotARotationError, match=r"T_base_ee_touch: pose \(2,\)"):
        he.make_touch_data(P, bent, tcp=tcp)


def _scaled_capture(eye_in_hand: bool, scale: float, frames: int = 12, seed: int = 0):
    """The `image_scale` inputs of a synthetic capture: robot poses, the PnP poses they imply with
    the translations `scale` times too long (a target printed or declared that much smaller),
    robot pose noise of 0.3 mm / 0.03 deg."""
    from types import SimpleNamespace

    from jaxcal._npgeom import pose, rotvec_to_matrix

    rng = np.random.default_rng(seed)
    X = pose(rotvec_to_matrix([0.1, -0.2, 1.5]), [0.05, -0.03, 0.08])  # the camera on the robot
    Y = pose(rotvec_to_matrix([3.0, 0.1, 0.2]), [0.6, 0.1, 0.0])  # the board
    T_be, poses = [], []
    for _ in range(frames):
        A = pose(rotvec_to_matrix(rng.normal(0, 0.35, 3)), [0.45, 0.0, 0.4] + rng.normal(0, 0.08, 3))
        if eye_in_hand:  # the camera looks down at the board in the base frame
            A = pose(rotvec_to_matrix([np.pi, 0, 0]) @ A[:3, :3], A[:3, 3])
            T_cb = np.linalg.inv(X) @ np.linalg.inv(A) @ Y
        else:
            T_cb = np.linalg.inv(X) @ A @ Y
        T_cb[:3, 3] *= scale
        noisy = pose(rotvec_to_matrix(rng.normal(0, 5e-4, 3)) @ A[:3, :3], A[:3, 3] + rng.normal(0, 3e-4, 3))
        T_be.append(noisy)
        poses.append(SimpleNamespace(T_cam_target=T_cb))
    observed = SimpleNamespace(
        observations=SimpleNamespace(
            data=SimpleNamespace(T_base_ee=np.stack(T_be)), frames=frames, poses=[poses]
        ),
        capture=SimpleNamespace(cameras=[SimpleNamespace(name="cam0")], eye_in_hand=eye_in_hand),
    )
    solved = SimpleNamespace(result=SimpleNamespace(T_robot_cam=X[None]), rejected={})
    return observed, solved


@pytest.mark.parametrize("eye_in_hand", [True, False])
def test_the_images_scale_against_the_robots_names_a_wrong_target_size(eye_in_hand):
    """A target 3 % smaller than declared (or a focal length 3 % long) makes every PnP translation 3 %
    long: the solve cannot see it, the scale fit against the robot's motion can. Right sizes pass."""
    from jaxcal.handeye._verdict import SCALE_TOLERANCE, image_scale, scale_reasons

    ((name, s, std, distance),) = image_scale(*_scaled_capture(eye_in_hand, 1.0))
    assert name == "cam0" and abs(s - 1.0) < 4 * std and std < SCALE_TOLERANCE / 5
    assert scale_reasons([(name, s, std, distance)], {"cam0": 0.05}) == ()
    ((_, s, std, distance),) = image_scale(*_scaled_capture(eye_in_hand, 1.03))
    assert abs(s - 1.03) < 4 * std
    (reason,) = scale_reasons([(name, s, std, distance)])
    assert "cam0" in reason and "+3.0 %" in reason and "square_length" in reason and "unit" not in reason
    # Ten times off is a unit (centimetres declared millimetres), not a size.
    (reason,) = scale_reasons([(name, 9.9, 0.01, distance)])
    assert "a factor of 10: a unit, not a size, is wrong" in reason and "translation_unit" in reason
    # Below the 0.5 % tolerance, a scale many standard errors off is named where the camera's move
    # it implies is past twice the claimed standard deviation, not where the claim covers it.
    ((_, s, std, distance),) = image_scale(*_scaled_capture(eye_in_hand, 1.004, frames=48))
    move = 1e3 * abs(s - 1.0) * distance
    assert abs(s - 1.0) > 5 * std and move > 1.0, (s, std, move)
    (reason,) = scale_reasons([(name, s, std, distance)], {"cam0": move / 4})
    assert f"{move:.1f} mm at {distance:.2f} m, against a claimed {move / 4:.2f} mm" in reason, reason
    assert scale_reasons([(name, s, std, distance)], {"cam0": move}) == ()
    # Too few frames for a scale and a jackknife: nothing said.
    assert image_scale(*_scaled_capture(eye_in_hand, 1.03, frames=5)) == []


def test_a_noise_model_worse_on_the_frames_left_out_is_said_to_be_worse():
    """The default's choice between robot-noise models names a model that predicts the frames left
    out worse as worse (it read "better than estimate by 0 standard errors")."""
    from types import SimpleNamespace

    from jaxcal.handeye._noise import RobotNoiseSetting, choose

    def fit(model, squares):
        squares = np.asarray(squares, float)
        return SimpleNamespace(
            model=model,
            held_out=SimpleNamespace(rms_px=float(np.sqrt(squares.mean()))),
            kfold=SimpleNamespace(frame_squares=lambda: squares),
        )

    rng = np.random.default_rng(0)
    base = rng.uniform(0.5, 1.5, 12)
    worse, better = fit("exact", 1.3 * base), fit("exact", 0.5 * base)
    index, basis = choose((fit("estimate", base), worse), RobotNoiseSetting("auto"), folds=12)
    assert index == 0 and "exact 1.16 px, not kept: worse than estimate on the frames left out" in basis, (
        basis
    )
    index, basis = choose((fit("estimate", base), better), RobotNoiseSetting("auto"), folds=12)
    assert index == 1 and "kept: better than estimate by" in basis, basis
