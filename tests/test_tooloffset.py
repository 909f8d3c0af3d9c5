"""Tool offset by arc fitting (seed 2): circle fits, the iterative axis correction, MuJoCo rig."""

import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx
import pytest

from jaxcal import _tooloffset as to
from jaxcal._geometry import orthonormal_basis
from jaxcal.sim.tool import ToolScene

_fit = jax.jit(to.fit_circle)
N = 12  # points per arc everywhere: one compilation per dimension


def _arc_3d(rng, span_deg, noise=0.0):
    n = rng.normal(size=3)
    n /= np.linalg.norm(n)
    B = np.asarray(orthonormal_basis(jnp.asarray(n)))
    c, r = rng.normal(0.0, 0.3, 3), 0.07
    t = np.radians(np.linspace(0.0, span_deg, N)) + 0.4
    P = c + r * (np.cos(t)[:, None] * B[:, 0] + np.sin(t)[:, None] * B[:, 1])
    return P + rng.normal(0.0, noise, P.shape), c, n, r


@pytest.mark.parametrize("span_deg", [90.0, 330.0])
def test_fit_circle_3d_exact(span_deg):
    P, c, n, r = _arc_3d(np.random.default_rng(0), span_deg)
    fit = _fit(jnp.asarray(P), jnp.ones(N, bool))  # the compilation the masked fits share
    assert fit.result == optx.RESULTS.successful
    np.testing.assert_allclose(fit.centre, c, atol=1e-10)
    np.testing.assert_allclose(abs(float(jnp.dot(fit.normal, n))), 1.0, atol=1e-12)
    np.testing.assert_allclose(fit.radius, r, atol=1e-10)
    assert float(fit.rms) < 1e-10


def test_fit_circle_noise_and_mask():
    """0.1 mm noise on a 90 deg arc; a masked wild point is ignored."""
    rng = np.random.default_rng(1)
    errs = []
    for _ in range(20):
        P, c, _, r = _arc_3d(rng, 90.0, noise=1e-4)
        P[3] = 10.0
        mask = np.ones(N, bool)
        mask[3] = False
        fit = _fit(jnp.asarray(P), jnp.asarray(mask))
        errs.append([np.linalg.norm(np.asarray(fit.centre) - c), abs(float(fit.radius) - r)])
        assert 0.7e-4 < float(fit.rms) < 2e-4  # sqrt(2) x 0.1 mm: two residuals per point
    errs = np.array(errs)
    # A 90 deg arc of radius 70 mm with 0.1 mm noise: centre and radius to well under a millimetre.
    assert errs[:, 0].mean() < 5e-4 and errs[:, 1].mean() < 4e-4
    assert errs[:, 0].mean() > 1e-5  # the noise is really there


def _synthetic_measure(tip, roll, handedness, scale):
    """An analytic rig: the tip's image when rotating about the axis through `tcp`."""

    def measure(tcp):
        angles = np.radians(np.arange(0.0, 360.0, 30.0))
        d = np.asarray(tip) - tcp
        phi = np.arctan2(d[1], d[0]) + angles
        psi = roll + handedness * phi
        r = np.linalg.norm(d) / scale
        return np.stack([200.0 + r * np.cos(psi), 150.0 + r * np.sin(psi)], 1), angles, None

    return measure


@pytest.mark.parametrize("handedness", [1.0, -1.0])
def test_estimate_offset_exact(handedness):
    tip, roll, scale = np.array([0.004, -0.007]), 0.3, 5e-4
    px, angles, _ = _synthetic_measure(tip, roll, handedness, scale)(np.zeros(2))
    est = to._estimate(  # the loop's compiled estimator
        jnp.asarray(px), jnp.asarray(angles), metres_per_unit=scale, camera_roll=roll
    )
    assert float(est.handedness) == handedness
    np.testing.assert_allclose(est.offset, tip, atol=1e-12)
    np.testing.assert_allclose(est.radius, np.linalg.norm(tip), atol=1e-12)


def _synthetic_measure_3d(tip, roll, handedness, depth=0.2):
    """The tip in the camera frame (m), e.g. from stereo: the camera rolled and facing along or against the axis."""

    def measure(tcp):
        angles = np.radians(np.arange(0.0, 360.0, 30.0))
        d = np.asarray(tip) - tcp
        c, s = np.cos(angles), np.sin(angles)
        p_axis = np.stack([c * d[0] - s * d[1], s * d[0] + c * d[1], np.zeros_like(c)], 1)
        cr, sr = np.cos(roll), np.sin(roll)
        R = np.array([[cr, -sr, 0.0], [sr, cr, 0.0], [0.0, 0.0, 1.0]]) @ np.diag(
            [1.0, handedness, handedness]
        )
        return p_axis @ R.T + [0.01, -0.02, depth], angles, None

    return measure


@pytest.mark.parametrize("handedness", [1.0, -1.0])
def test_estimate_offset_exact_3d(handedness):
    """3D tip positions: the circle in space, the offset in the axis frame, and the loop in one step."""
    tip, roll = np.array([0.004, -0.007]), 0.3
    measure = _synthetic_measure_3d(tip, roll, handedness)
    P, angles, _ = measure(np.zeros(2))
    est = to._estimate(jnp.asarray(P), jnp.asarray(angles), camera_roll=roll)
    assert float(est.handedness) == handedness
    np.testing.assert_allclose(est.offset, tip, atol=1e-12)
    np.testing.assert_allclose(est.radius, np.linalg.norm(tip), atol=1e-12)
    r = to.calibrate_tool_offset(measure, np.zeros(2), metres_per_unit=1.0, camera_roll=roll, tol=1e-9)
    assert r.converged and r.iterations == 2  # one correction, then a radius of ~0
    np.testing.assert_allclose(r.tcp, tip, atol=1e-12)


def _synthetic_pointer(target, roll, handedness, scale, centre=(160.0, 120.0)):
    """The stylus axis's image: the principal point when the stylus is at `target` (m)."""

    def measure(xy):
        cr, sr = np.cos(roll), np.sin(roll)
        R = np.array([[cr, -sr], [sr, cr]])
        return np.asarray(centre) + R @ np.diag([1.0, handedness]) @ (np.asarray(xy) - target) / scale

    return measure


@pytest.mark.parametrize("roll_error_deg, scale_error", [(0.0, 1.0), (25.0, 1.0), (135.0, 2.5)])
def test_align_to_principal_point_exact(roll_error_deg, scale_error):
    """The second offset: one move with the exact roll; with a roll 25 or 135 deg off (and a scale
    2.5x off), the first move's error (2 sin(12.5 deg) of the start, or more) is learned from the
    second measurement, and the next move lands: three measurements."""
    target, roll, scale = np.array([0.012, -0.005]), 0.3, 4e-4
    measure = _synthetic_pointer(target, roll + np.radians(roll_error_deg), -1.0, scale * scale_error)
    al = to.align_to_principal_point(
        measure,
        np.zeros(2),
        (160.0, 120.0),
        metres_per_px=scale,
        camera_roll=roll,
        handedness=-1.0,
        tol_px=1e-6,
        max_iter=30,
    )
    assert al.converged
    np.testing.assert_allclose(al.position, target, atol=1e-9)
    np.testing.assert_allclose(al.offset, target)
    assert al.iterations == (2 if roll_error_deg == 0.0 else 3)
    if roll_error_deg == 25.0:
        assert al.errors_px[1] / al.errors_px[0] == pytest.approx(2 * np.sin(np.radians(12.5)), rel=1e-6)


@pytest.mark.parametrize("handedness", [1.0, -1.0])
@pytest.mark.parametrize(
    "roll_error_deg, scale_error", [(25.0, 1.0), (57.0, 1.0), (120.0, 1.0), (-170.0, 3.0)]
)
def test_iteration_learns_a_wrong_roll_and_scale(handedness, roll_error_deg, scale_error):
    """The camera's roll off by 25 to 170 deg (each move alone would shrink the error by 2 sin(eps/2):
    0.43 for 25 deg, ten rotations to a micrometre; 0.95 for 57 deg; growing beyond 60 deg), the
    image scale up to 3x off: the second arc shows what the first move did, and the third rotation
    is on the tip. The roll and scale the loop found are the rig's."""
    tip, roll = np.array([0.004, -0.007]), 0.3
    measure = _synthetic_measure(tip, roll + np.radians(roll_error_deg), handedness, 5e-4 * scale_error)
    r = to.calibrate_tool_offset(measure, np.zeros(2), metres_per_unit=5e-4, camera_roll=roll, tol=1e-6)
    assert r.converged and r.iterations == 3 and np.linalg.norm(r.tcp - tip) < 1e-12
    wrapped = np.angle(np.exp(1j * (r.camera_roll_found - roll - np.radians(roll_error_deg))))
    assert abs(wrapped) < 1e-9 and r.metres_per_unit_found == pytest.approx(5e-4 * scale_error, rel=1e-9)
    # Stopping when the radius stops changing (here: at most two rotations).
    r2 = to.calibrate_tool_offset(measure, np.zeros(2), metres_per_unit=5e-4, tol=0.0, tol_change=1.0)
    assert r2.converged and r2.iterations == 2


@pytest.mark.slow
def test_mujoco_rig_tool_offset_and_principal_point():
    """Rendered: a stylus 7.2 mm off the preset axis, the camera rolled 8 deg (not known to the loop)."""
    with ToolScene(tip_xy=(0.006, -0.004), camera_roll=np.radians(8.0), width=320, height_px=240) as rig:
        # The roll not given (8 deg off): converging, a few rotations; given as the image sees it
        # (`image_roll`, the axis frame's +x at -8 deg in the image): two.
        r0 = to.calibrate_tool_offset(rig.measure_arc, np.zeros(2), metres_per_unit=rig.metres_per_px)
        assert r0.converged and 3 <= r0.iterations <= 6
        r = to.calibrate_tool_offset(
            rig.measure_arc, np.zeros(2), metres_per_unit=rig.metres_per_px, camera_roll=rig.image_roll
        )
        assert r.converged and r.iterations <= 3
        np.testing.assert_allclose(r.radii[0], np.linalg.norm(rig.tip_xy), rtol=0.02)
        assert np.all(np.diff(r.radii) < 0)
        assert np.linalg.norm(r.tcp - rig.tip_xy) < 1e-4  # 0.1 mm, about 0.16 px at 320x240
        # Second offset: bring the stylus axis onto the principal point.
        start = np.array([0.01, -0.006])
        al = to.align_to_principal_point(
            lambda xy: rig.measure_point(xy, tcp=r.tcp),
            start,
            rig.K[:2, 2],
            metres_per_px=rig.metres_per_px,
            camera_roll=rig.image_roll,
        )
        assert al.converged and al.iterations <= 3 and al.errors_px[-1] < 0.05
        # Aligned when the tip is on the camera's axis (world xy = 0): axis_xy = tcp - tip.
        np.testing.assert_allclose(al.position, r.tcp - rig.tip_xy, atol=1.5e-4)
        np.testing.assert_allclose(al.offset, al.position - start)


@pytest.mark.parametrize(
    "points, angles, mask, match",
    [
        (np.zeros((2, 2)), np.array([0.0, 1.0]), None, "only 2 points"),
        (np.zeros((5, 2)), np.zeros(4), None, "5 points but angles"),
        (np.zeros((5, 4)), np.zeros(5), None, r"shape \(n, 2\) or \(n, 3\)"),
        (np.array([[0.0, 0.0], [1.0, np.nan], [0.0, 1.0], [1.0, 1.0]]), np.arange(4.0), None, "index 1"),
        (np.zeros((5, 2)), np.radians(np.arange(5.0) * 5.0), None, "spans 20.0 deg"),
        (np.zeros((5, 2)), np.arange(5.0), np.array([1, 1, 0, 0, 0], bool), "only 2 points"),
    ],
)
def test_bad_input(points, angles, mask, match):
    with pytest.raises(to.ToolOffsetInputError, match=match) as info:
        to.validate_arc_points(points, angles, mask)
    assert isinstance(info.value, ValueError)


def test_lost_tip_is_an_error():
    with pytest.raises(to.ToolOffsetInputError, match="measure returned"):
        to.align_to_principal_point(
            lambda xy: np.full(2, np.nan), np.zeros(2), (160.0, 120.0), metres_per_px=1e-3
        )


def test_a_circle_through_two_points_is_not_a_success():
    fit = to.fit_circle(jnp.asarray([[0.0, 0.0], [1.0, 0.0], [5.0, 5.0]]), jnp.asarray([True, True, False]))
    assert fit.result == optx.RESULTS.singular
    assert to.fit_circle(jnp.asarray([[1.0, 0.0], [0.0, 1.0], [-1.0, 0.0]])).result == optx.RESULTS.successful


def test_points_on_a_line_are_not_a_circle():
    """Collinear points, in the image or in space, are no success (the solver's radius grows
    without end); a short arc of 2 degrees, exact or with noise well under its 38 um sagitta, is."""
    t = np.linspace(0.0, 1.0, 12)
    for pts in (
        np.stack([3.0 * t, 1.0 - 2.0 * t], axis=1),
        np.stack([3.0 * t, 1.0 - 2.0 * t, 0.5 * t], axis=1),
    ):
        assert to.fit_circle(jnp.asarray(pts)).result != optx.RESULTS.successful
    a = np.radians(np.linspace(0.0, 2.0, 12))
    arc = 0.5 * np.stack([np.cos(a), np.sin(a)], axis=1)
    fit = to.fit_circle(jnp.asarray(arc))
    assert fit.result == optx.RESULTS.successful and abs(float(fit.radius) - 0.5) < 1e-6
    noisy = to.fit_circle(jnp.asarray(arc + 2e-6 * np.random.default_rng(0).standard_normal(arc.shape)))
    assert noisy.result == optx.RESULTS.successful and abs(float(noisy.radius) - 0.5) < 0.05


def test_a_roll_in_degrees_or_a_slipping_tool_is_named():
    """`camera_roll` in degrees is refused before any rotation; a tip that is not where the moves
    put it (a tool slipping 6 mm further at every rotation) makes the arc grow in spite of what the
    loop learns: it stops when the arc grows twice, naming the scale and the tip."""
    tip = np.array([0.004, -0.007])
    measure = _synthetic_measure(tip, 0.3, 1.0, 5e-4)
    with pytest.raises(to.ToolOffsetInputError, match=r"camera_roll: .* got 17.2 \(degrees\? 0.3002 rad\)"):
        to.calibrate_tool_offset(measure, np.zeros(2), metres_per_unit=5e-4, camera_roll=17.2)
    with pytest.raises(to.ToolOffsetInputError, match=r"camera_roll: .* got nan"):
        to.align_to_principal_point(
            lambda xy: xy, np.zeros(2), np.zeros(2), metres_per_px=1.0, camera_roll=np.nan
        )
    calls = []

    def slipping(tcp):
        calls.append(1)
        return _synthetic_measure(tip + 0.006 * len(calls), 0.3, 1.0, 5e-4)(tcp)

    with pytest.raises(
        to.ToolOffsetInputError,
        match=r"rotation \d+: the arc's radius grew .* the tip is not where the moves put",
    ):
        to.calibrate_tool_offset(slipping, np.zeros(2), metres_per_unit=5e-4, camera_roll=0.3)


def test_the_loop_refuses_an_impossible_scale_or_start_and_names_a_lost_tip():
    """A scale of zero or below, or a start that is not a point, is refused before any rotation (it
    once came back `converged` at the start); a scale 1000x too large moves the axis so far that the
    tip leaves the view, named as such with the move, not only as "0 points"."""
    tip = np.array([0.004, -0.007])
    measure = _synthetic_measure(tip, 0.3, 1.0, 5e-4)
    for scale in (0.0, -5e-4, np.nan):
        with pytest.raises(to.ToolOffsetInputError, match="metres_per_unit: the length of one unit"):
            to.calibrate_tool_offset(measure, np.zeros(2), metres_per_unit=scale)
    with pytest.raises(to.ToolOffsetInputError, match=r"tcp0: the start's x, y"):
        to.calibrate_tool_offset(measure, np.array([np.nan, 0.0]), metres_per_unit=5e-4)

    def in_view(tcp):  # the camera sees 400 x 300 px: beyond, the tip is lost
        points, angles, _ = measure(tcp)
        return points, angles, np.all((points >= 0) & (points <= [400.0, 300.0]), axis=1)

    with pytest.raises(
        to.ToolOffsetInputError,
        match=r"rotation 2, after the axis moved 8\.06e\+03 mm .* is metres_per_unit right",
    ):
        to.calibrate_tool_offset(in_view, np.zeros(2), metres_per_unit=0.5)
