"""`jaxcal check` of a hand-eye result (jaxcal.handeye_check, jaxcal._drift_handeye).

On analytic corners: a fixed camera (or one on the flange) sees a chessboard at a few
recorded robot poses; the corners carry pixel noise, every pose the robot's noise and the
calibration its own error, drawn from the covariances the check's $R$ is built from. Then the
false-alarm rate at zero drift and the power against a move of known non-centrality match
the chi-square laws, and a detected move is estimated within its covariance. One small
rendered end-to-end run (`jaxcal handeye`, then `jaxcal check` of a later capture with and
without a moved camera; exit 0 / 3) and refusals of a capture of another camera or target.
"""

import json
import shutil
from dataclasses import replace

import cv2
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy import stats
from scipy.spatial.transform import Rotation

from jaxcal._drift_camera import GN_STEPS
from jaxcal._drift_handeye import COMPONENT_ROUNDS, VIEW_START, HandEyeCheckData, residuals
from jaxcal._geometry import se3_exp
from jaxcal._handeye.model import corrected_robot
from jaxcal.cli import main
from jaxcal.drift import check, hand_eye_verdict, power, threshold
from jaxcal.errors import DatasetError
from jaxcal.handeye_check import fit_check, larger_covariance
from jaxcal.io.checks import drift_check_json, product_json, read_product
from jaxcal.markers import TargetSpec
from jaxcal.sim.handeye import HandEyeSimConfig, simulate_hand_eye

BOARD = TargetSpec("chessboard", squares=(6, 5), square_length=0.03, name="board")
K = np.array([[500.0, 0.0, 319.5], [0.0, 500.0, 239.5], [0.0, 0.0, 1.0]])
SIGMA_PX = 0.1
ROBOT = np.r_[np.full(3, 2e-4), np.full(3, np.radians(0.01))]


def _exp(xi) -> np.ndarray:
    return np.asarray(se3_exp(jnp.asarray(xi, jnp.float64)))


def _rig(rng, frames=6, board=BOARD):
    """Eye-to-hand: `X` = T_cam_base, `Y` = T_ee_board, the true flange poses and a covariance."""
    X = _exp([0.1, -0.2, 0.9, 2.0, 0.3, -0.2])
    Y = _exp([0.0, 0.0, 0.05, 0.0, 0.0, 0.3])
    centre = np.asarray(board.points()).mean(0)
    B = []
    for _ in range(frames):  # the board 0.6 m in front of the camera, tilted up to 25 deg
        w = rng.uniform(-1, 1, 3) * np.radians(25)
        A = _exp(np.r_[rng.uniform(-0.05, 0.05, 2), 0.6, w]) @ _exp(np.r_[-centre, 0, 0, 0])
        B.append(np.linalg.inv(X) @ A @ np.linalg.inv(Y))
    G = rng.normal(0.0, 1.0, (12, 12)) * np.r_[np.full(3, 5e-5), np.full(3, 1e-4)].repeat(2)[:, None]
    return X, Y, np.stack(B), G @ G.T / 12


def _capture(rng, X, Y, B, cov, eps=(0.0,) * 6, board=BOARD) -> HandEyeCheckData:
    """Corners of a capture at the true poses `B` with the camera moved by `eps`; the recorded
    poses carry the robot's noise, and the calibration's `X`, `Y` its error, drawn from `cov`."""
    xi = np.linalg.cholesky(cov) @ rng.standard_normal(12)
    X_true, Y_true = X @ _exp(-xi[:6]), Y @ _exp(-xi[6:])  # the calibration is off by xi
    delta = ROBOT * rng.standard_normal((len(B), 6))
    recorded = np.asarray(corrected_robot(jnp.asarray(B), jnp.asarray(delta)))
    P = np.asarray(board.points(), np.float64)
    pix = []
    for Bf in B:
        A = _exp(-np.asarray(eps)) @ X_true @ Bf @ Y_true
        p = P @ A[:3, :3].T + A[:3, 3]
        pix.append(p[:, :2] / p[:, 2:] @ K[:2, :2].T + K[:2, 2])
    pix = np.stack(pix) + SIGMA_PX * rng.standard_normal((len(B), len(P), 2))
    return HandEyeCheckData(
        T_base_ee=jnp.asarray(recorded), pixels=jnp.asarray(pix), mask=jnp.ones(pix.shape[:2], bool),
        K=jnp.asarray(K), board_points=jnp.asarray(P), eye_in_hand=jnp.asarray(False),
    )  # fmt: skip


def _verdict(data, X, Y, cov):
    return hand_eye_verdict(fit_check(data, X, Y, cov, ROBOT, SIGMA_PX, eye_in_hand=False))


def test_hand_eye_false_alarms_and_power_match_the_chi_square_laws():
    rng = np.random.default_rng(0)
    X, Y, B, cov = _rig(rng)
    trials = 200
    null = [_verdict(_capture(rng, X, Y, B, cov), X, Y, cov) for _ in range(trials)]
    alarms = np.mean([c.detected for c in null])
    assert 0.015 <= alarms <= 0.095, alarms  # 5 % +- 2.9 binomial sigma
    # The statistic's law: its mean is the degrees of freedom (6 +- 3 standard errors).
    assert abs(np.mean([c.statistic for c in null]) - 6.0) < 3 * np.sqrt(12.0 / trials)
    # A move along the worst translation direction at the size of 50 % power, and the closed form.
    P = np.linalg.inv(null[0].cov)
    mu, U = np.linalg.eigh(P[:3, :3])
    lam = 8.0
    eps = np.r_[np.sqrt(lam / mu[0]) * U[:, 0], 0.0, 0.0, 0.0]
    moved = [_verdict(_capture(rng, X, Y, B, cov, eps), X, Y, cov) for _ in range(150)]
    hits = np.mean([c.detected for c in moved])
    expected = float(power(lam, 6, 0.05, null[0].dof_noise))  # the non-central F of the test
    assert abs(hits - expected) < 0.1, (hits, expected)
    # Detected moves are estimated within their covariance (chi-square of the error).
    z2 = [(c.theta - eps) @ np.linalg.solve(c.cov, c.theta - eps) for c in moved if c.detected]
    assert np.mean(np.array(z2) < stats.chi2.ppf(0.95, 6)) > 0.85


def test_a_larger_move_is_reported_with_the_camera_pose_now():
    rng = np.random.default_rng(1)
    X, Y, B, cov = _rig(rng)
    eps = np.r_[1e-3, -5e-4, 2e-4, 0.0, np.radians(0.05), 0.0]
    c = _verdict(_capture(rng, X, Y, B, cov, eps), X, Y, cov)
    assert c.detected and c.exit_code == 3 and "the camera moved by" in c.message
    assert abs(c.translation_mm[0] - 1e3 * np.linalg.norm(eps[:3])) < 4 * c.translation_mm[1]
    # T_base_cam now: the calibrated one moved by the twist in the camera's frame.
    T_now = drift_check_json(c)["T_base_cam_now"]
    assert np.allclose(T_now, np.linalg.inv(X) @ _exp(eps), atol=5 * np.sqrt(np.max(np.diag(c.cov))))


def test_larger_covariance_takes_the_larger_along_every_direction():
    rng = np.random.default_rng(2)
    a = (lambda G: G @ G.T)(rng.normal(size=(5, 5)))
    b = (lambda G: G @ G.T)(rng.normal(size=(5, 5)))
    m = larger_covariance(a, b)
    assert np.all(np.linalg.eigvalsh(m - a) > -1e-9) and np.all(np.linalg.eigvalsh(m - b) > -1e-9)
    assert np.allclose(larger_covariance(a, 0.5 * a), a)
    assert np.allclose(larger_covariance(a, 2.0 * a), 2.0 * a)


@jax.jit
def _dense_fit(X, Y, cov, robot_sigma, sigma_px, data):
    """The reference: `jaxcal._drift_handeye` before its Woodbury form, every m x m matrix formed
    ($R$ inverted each round, Cholesky-whitened Gauss-Newton). **Returns:** `(theta, C, T, rss,
    s, R)`."""
    F = data.T_base_ee.shape[0]
    zero6, zero12, zeroF = jnp.zeros(6), jnp.zeros(12), jnp.zeros((F, 6))
    r0 = residuals(zero6, zero12, zeroF, X, Y, data)
    A = jax.jacfwd(lambda e: residuals(e, zero12, zeroF, X, Y, data))(zero6)
    J = jax.jacfwd(lambda xi: residuals(zero6, xi, zeroF, X, Y, data))(zero12)
    G = jax.jacfwd(lambda d: residuals(zero6, zero12, d, X, Y, data))(zeroF)  # (m, F, 6): every block
    Gs = G * robot_sigma
    seen = jnp.repeat(data.mask.reshape(-1), 2).astype(r0.dtype)
    V_fixed = jnp.einsum("afk,bfk->ab", Gs, Gs) + J @ cov @ J.T + jnp.diag(1.0 - seen)
    Vs = (jnp.diag(seen), *(jnp.einsum("afk,bfk->ab", g, g) for g in (G[..., :3], G[..., 3:])))

    def step(s, _):
        Ri = jnp.linalg.inv(s[0] * Vs[0] + s[1] * Vs[1] + s[2] * Vs[2] + V_fixed)
        RiA = Ri @ A
        Q = Ri - RiA @ jnp.linalg.solve(A.T @ RiA, RiA.T)
        Qr = Q @ r0
        num = jnp.stack([Qr @ V @ Qr for V in Vs])
        return s * num / jnp.stack([jnp.sum(Q * V) for V in Vs]), None

    s0 = jnp.stack([sigma_px**2, jnp.asarray(VIEW_START**2), jnp.asarray(VIEW_START**2)])
    s, _ = jax.lax.scan(step, s0, None, length=COMPONENT_ROUNDS)
    R = s[0] * Vs[0] + s[1] * Vs[1] + s[2] * Vs[2] + V_fixed
    L = jnp.linalg.cholesky(R)

    def res(eps):
        return jax.scipy.linalg.solve_triangular(L, residuals(eps, zero12, zeroF, X, Y, data), lower=True)

    def step(theta, _):  # `fit_handeye_drift`'s Gauss-Newton, on the dense whitened residuals
        A = jax.jacfwd(res)(theta)
        return theta + jnp.linalg.solve(A.T @ A, -A.T @ res(theta)), None

    theta, _ = jax.lax.scan(step, jnp.zeros(6), None, length=GN_STEPS)
    A = jax.jacfwd(res)(theta)
    info, r = A.T @ A, res(theta)
    return theta, jnp.linalg.inv(info), theta @ info @ theta, r @ r, s, R


BOARD_42 = TargetSpec("chessboard", squares=(8, 7), square_length=0.025, name="board42")


@pytest.mark.parametrize(
    "frames, board, dropped",
    [(6, BOARD, 0.0), (6, BOARD, 0.15), (16, BOARD_42, 0.0)],
    ids=["rig", "rig-some-corners-unseen", "16x42"],
)
def test_the_woodbury_fit_matches_the_dense_one(frames, board, dropped):
    """`fit_check` on the factors of $R$ (diagonal + a rank-6 block per view + rank 12) gives the
    dense fit's theta, C, T, rss and variance components to round-off: a backward-stable solve's
    error, $\\sqrt{m}\\,\\epsilon\\,\\kappa(R)$, with a factor 10 of slack (m = 240, 1344;
    $\\kappa(R)$ ~ 1e2-1e3 here, so ~1e-11: a wrong term in $R$ or $Q$ is off by far more)."""
    rng = np.random.default_rng(3)
    X, Y, B, cov = _rig(rng, frames, board)
    data = _capture(rng, X, Y, B, cov, board=board)
    if dropped:  # undetected corners: zero pixels, masked out
        mask = np.asarray(data.mask) & (rng.uniform(size=data.mask.shape) > dropped)
        data = replace(data, mask=jnp.asarray(mask), pixels=jnp.where(mask[..., None], data.pixels, 0.0))
    f = fit_check(data, X, Y, cov, ROBOT, SIGMA_PX, eye_in_hand=False)
    theta, C, T, rss, s, R = (np.asarray(a) for a in _dense_fit(X, Y, cov, ROBOT, SIGMA_PX, data))
    w = np.linalg.eigvalsh(R)
    tol = 10 * np.sqrt(len(R)) * np.finfo(float).eps * w[-1] / w[0]
    assert tol < 1e-9, tol
    sd = np.sqrt(np.diag(C))
    assert np.all(np.abs(f.theta - theta) <= tol * (np.abs(theta) + sd))
    assert np.all(np.abs(f.C - C) <= tol * np.outer(sd, sd))
    assert f.T == pytest.approx(float(T), rel=tol) and f.rss == pytest.approx(float(rss), rel=tol)
    s_fit = np.r_[f.nu * SIGMA_PX**2, np.square(f.view_sigma)]
    assert np.allclose(s_fit, s, rtol=tol, atol=0.0), (s_fit, s)


# --------------------------------------------------------------------------- rendered, end to end

CONFIG = HandEyeSimConfig(frames=16, seed=5, resolution=(320, 240), eye_in_hand=False)
MOVE = ((1e-3, -1e-3, 0.5e-3), (0.0, np.radians(0.15), np.radians(0.1)))


@pytest.fixture(scope="module")
def rendered(tmp_path_factory):
    """A rendered eye-to-hand calibration (`jaxcal handeye`, 16 frames at 320x240) and two
    six-frame check captures of the same rig at other poses: the camera unmoved, and moved."""
    root = tmp_path_factory.mktemp("check_handeye")
    capture = simulate_hand_eye(CONFIG, root / "capture")
    assert main(
        ["handeye", str(capture), "--out", str(root / "result"), "--config", "folds=0", "--quiet"]
    ) in (0, 3)
    still = simulate_hand_eye(replace(CONFIG, frames=6, seed=11), root / "still")
    moved = simulate_hand_eye(replace(CONFIG, frames=6, seed=11, camera_move=MOVE), root / "moved")
    return root / "result", still, moved


@pytest.mark.slow
def test_a_moved_hand_eye_camera_is_detected_and_an_unmoved_one_is_not(rendered, tmp_path):
    res, still, moved = rendered
    doc = json.loads((res / "result.json").read_text())
    assert (
        doc["schema"] == "jaxcal.handeye_result" and len(doc["cameras"]["cam0"]["check"]["covariance"]) == 12
    )
    c0 = check(res, still)
    assert not c0.detected and c0.exit_code == 0 and c0.what == "camera" and c0.samples == 6
    assert c0.capture == str(still) and c0.result.endswith("result.json")  # a Path's own `.root` is "/"
    out = tmp_path / "drift.json"
    assert main(["check", str(res), str(moved), "--json", str(out), "--workers", "1"]) == 3
    d = json.loads(out.read_text())
    assert d["detected"] and d["test"] == "F" and "T_base_cam_now" in d
    back = read_product(out)  # the typed record, written again byte for byte
    assert back.frame == "T_base_cam" and back.residual.view_sigma_mm == d["residual"]["view_sigma_mm"]
    assert json.dumps(product_json(back), indent=1) == out.read_text()
    # The move's size against the truth, within 4 sigma (and the rendering's own bias).
    size_mm = 1e3 * np.linalg.norm(MOVE[0])
    assert abs(d["translation_mm"]["size"] - size_mm) < 4 * d["translation_mm"]["std"] + 0.1
    truth = json.loads((moved / "truth.json").read_text())["T_robot_cam"]["cam0"]
    assert np.linalg.norm(np.asarray(d["T_base_cam_now"])[:3, 3] - np.asarray(truth)[:3, 3]) < 1e-3


@pytest.mark.slow
def test_hand_eye_check_refuses_another_camera_or_target(rendered, tmp_path):
    res, still, _ = rendered

    def variant(name, edit):
        p = tmp_path / name
        shutil.copytree(still, p)
        meta = json.loads((p / "handeye.json").read_text())
        edit(meta)
        (p / "handeye.json").write_text(json.dumps(meta))
        return p

    def zoom(meta):
        meta["cameras"][0]["K"][0][0] *= 1.1

    with pytest.raises(DatasetError, match=r"handeye.json: cameras\[0\].K of 'cam0' differs.*another camera"):
        check(res, variant("zoomed", zoom))

    def bigger(meta):
        meta["target"]["square_length"] *= 1.2

    with pytest.raises(DatasetError, match="handeye.json: target .* differs .*another target"):
        check(res, variant("bigger", bigger))

    def resized(meta):
        meta["cameras"][0]["width"] *= 2

    wide = variant("resized", resized)
    for image in (wide / "images" / "cam0").iterdir():  # the images as wide as the camera now says
        cv2.imwrite(str(image), cv2.resize(cv2.imread(str(image)), (640, 240)))
    with pytest.raises(DatasetError, match="handeye.json: cameras\\[0\\] .* is 640x240.*another camera"):
        check(res, wide)
    # The JSON alone widened: the images are not the camera's it states, whatever was calibrated.
    with pytest.raises(
        DatasetError, match=r"0000.png: image is 320x240 pixels, handeye.json gives .* 640x240"
    ):
        check(res, variant("resized_json", resized))

    def flipped(meta):
        meta["arrangement"] = "eye_in_hand"

    with pytest.raises(DatasetError, match="handeye.json: arrangement 'eye_in_hand'"):
        check(res, variant("flipped", flipped))
    # Poses written inverted (T_ee_base) fit only with each view's pose centimetres off: no camera
    # "move" from them (it was 565 mm, and `re-register`), but the misreadings to look for.
    inverted = variant("inverted", lambda meta: None)
    rows = [line.split(",") for line in (inverted / "poses.csv").read_text().splitlines()]
    for row in rows[1:]:
        T = np.eye(4)
        T[:3, :3] = Rotation.from_quat([float(v) for v in row[4:8]]).as_matrix()
        T[:3, 3] = [float(v) for v in row[1:4]]
        Ti = np.linalg.inv(T)
        row[1:8] = [repr(float(v)) for v in (*Ti[:3, 3], *Rotation.from_matrix(Ti[:3, :3]).as_quat())]
    (inverted / "poses.csv").write_text("\n".join(",".join(r) for r in rows) + "\n")
    with pytest.raises(
        DatasetError, match=r"inverted: its robot poses and images fit .* mm / .* deg off .*inverted"
    ):
        check(res, inverted)


def test_the_f_law_of_an_estimated_noise_scale():
    """With the noise scale estimated on n degrees of freedom the threshold is k F(k, n), above
    the chi-square's and tending to it; the power at zero drift is the false-alarm rate."""
    k = 6
    thr = [threshold(k, 0.05, n) for n in (20, 100, 1000, 100000)]
    assert all(a > b for a, b in zip(thr, thr[1:])) and thr[-1] == pytest.approx(threshold(k), rel=1e-3)
    assert power(0.0, k, 0.05, 200) == pytest.approx(0.05, abs=1e-9)
    assert power(8.0, k, 0.05, 200) < power(8.0, k, 0.05)
