"""The non-geometric terms (`jaxcal._terms`): one vocabulary and basis for every capture, their
coefficients in the refinement, the cross-validation that keeps them (`jaxcal.stages._terms`) and
the compensation a robot applies (`jaxcal.compensate`). Analytic data only."""

import dataclasses
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax.flatten_util import ravel_pytree

import jaxcal
from jaxcal import _terms
from jaxcal._correction import ParameterLayout
from jaxcal._montecarlo import default_setup
from jaxcal._pointfit import PointLayout
from jaxcal._refine import (
    RefineProblem,
    grid_points,
    projected_corners,
    reprojection_residuals,
    sweep_corner_data,
    zero_params,
)
from jaxcal.robots import link_inertials, load_robot
from jaxcal.stages._terms import CV_SANE, _compare, _Linear, fold_of_views

NOMINAL = load_robot("ur5e")
N = NOMINAL.num_joints
MASSES, COMS = link_inertials("ur5e")


def test_the_approach_flank_is_where_the_last_move_came_from():
    """+1 once a joint has moved up by the play, -1 once down, 0 before it moves; a reversal
    smaller than the play keeps the flank; the log's rows and times between them agree."""
    w = _terms.APPROACH_WIDTH_RAD
    q = np.array([0.0, 0.0, 0.01, 0.02, 0.02 - 0.4 * w, 0.015, 0.015])[:, None]
    a = _terms.approach(q)[:, 0]
    np.testing.assert_allclose(a, [0, 0, 1, 1, 0.2, -1, -1], atol=1e-12)
    t = np.arange(len(q), dtype=float)
    np.testing.assert_allclose(_terms.approach_at(t, q, t)[:, 0], a, atol=1e-12)
    mid = _terms.approach_at(t, q, np.array([2.5]))  # moving up between rows 2 and 3
    np.testing.assert_allclose(mid, [[1.0]], atol=1e-12)


def test_one_vocabulary_for_the_point_fit_and_the_refinement():
    """The point fit and the refinement name and lay out the same coefficients, and the
    flattened vector reads back as the per-joint matrix the basis multiplies."""
    terms = ("compliance", "backlash", "harmonic1")
    names = _terms.names(terms, NOMINAL.joint_names)
    base = ParameterLayout.of(NOMINAL, 1, fixed_name="T_device_base")
    assert PointLayout(base, terms).term_names() == names
    lay = ParameterLayout.of(NOMINAL, 1, terms=terms)
    assert lay.names()[-len(names) :] == names and lay.index("terms").size == len(names) == 5 * N
    assert names[N] == "shoulder_pan_joint.backlash.approach_rad"
    x = np.arange(len(names), dtype=float)
    e = np.asarray(_terms.coefficients(terms, jnp.asarray(x), N))
    np.testing.assert_array_equal(_terms.flatten(terms, e), x)
    joint, col = _terms.column_map(terms, N)
    np.testing.assert_array_equal(e[joint, col], x)
    with pytest.raises(ValueError, match="unknown non-geometric terms"):
        ParameterLayout.of(NOMINAL, 1, terms=("sag",))


def test_the_basis_is_the_gravity_torque_with_the_payload_the_flank_and_the_harmonics():
    rng = np.random.default_rng(0)
    q = rng.uniform(-1.0, 1.0, (5, N))
    a = np.sign(rng.standard_normal((5, N)))
    terms = ("compliance", "backlash", "harmonic2")
    b = np.asarray(_terms.term_basis(terms, NOMINAL, jnp.asarray(q), MASSES, COMS, jnp.asarray(a)))
    tau = np.asarray(jax.vmap(lambda qq: _terms.gravity_torques(NOMINAL, qq, MASSES, COMS))(jnp.asarray(q)))
    np.testing.assert_allclose(b[..., 0], tau / 1000.0, rtol=1e-12)
    np.testing.assert_allclose(b[..., 1], a)
    np.testing.assert_allclose(b[..., 2], np.tanh(tau / _terms.PRELOAD_NM), rtol=1e-12)
    np.testing.assert_allclose(b[..., 3:], np.stack([np.sin(2 * q), np.cos(2 * q)], -1), rtol=1e-12)
    # A 2 kg payload 0.1 m out on the flange: its torque about each joint adds to the links'.
    com = np.array([0.0, 0.0, 0.1])
    m2, c2 = _terms.with_payload(NOMINAL, MASSES, COMS, 2.0, com)
    with_p = jax.vmap(lambda qq: _terms.gravity_torques(NOMINAL, qq, m2, c2))(jnp.asarray(q))
    T = jax.vmap(lambda qq: jaxcal.forward_kinematics(NOMINAL, qq))(jnp.asarray(q))
    p = np.einsum("vab,b->va", np.asarray(T[:, -1]), np.r_[com, 1.0])[:, :3]
    o, z = (
        np.asarray(T[:, 1:-1, :3, 3]),
        np.einsum("vjab,jb->vja", np.asarray(T[:, 1:-1, :3, :3]), NOMINAL.axis),
    )
    extra = np.einsum("vja,vja->vj", z, np.cross(p[:, None] - o, [0.0, 0.0, -2.0 * _terms.GRAVITY]))
    np.testing.assert_allclose(np.asarray(with_p) - tau, extra, atol=1e-9)


SETUP = default_setup(NOMINAL)
TERMS = ("compliance", "backlash")


@pytest.fixture(scope="module")
def problem():
    """A UR5e's sweeps (8 frames per joint) seen 1.5 m away, every view's basis from its log."""
    data = sweep_corner_data(grid_points(), N, 8, 60.0)
    q, t = np.asarray(data.enc_q), np.asarray(data.enc_t)
    basis = np.asarray(_terms.term_basis(TERMS, NOMINAL, jnp.asarray(q), MASSES, COMS, _terms.approach(q)))
    data = dataclasses.replace(data, term_basis=jnp.asarray(basis))
    assert np.allclose(np.asarray(data.t_cam), t)
    return RefineProblem(
        nominal=NOMINAL, T_flange_marker0=SETUP.T_flange_marker, T_cam_base0=SETUP.T_cam_base,
        K0=jnp.array([[1000.0, 0, 640], [0, 1000, 480], [0, 0, 1]]), dist0=jnp.zeros(5),
        offset0_s=jnp.zeros(()), data=data, terms=TERMS,
    )  # fmt: skip


def test_a_terms_column_is_its_joints_angle_column_times_the_basis(problem):
    """Every view's joint angles gain the terms' correction over its basis (`_chain_at`): the
    residuals' derivative in a coefficient is its joint's angle column (the zero offset's, which
    `refine(..., jacobian=True)` hands over as `angle_jacobian`) times the coefficient's basis in
    that view, the columns the cross-validation takes; and the correction moves the corners as
    the joints turned by it would."""
    k = N * _terms.per_joint(TERMS)
    rng = np.random.default_rng(4)
    p = dataclasses.replace(zero_params(N, 1), terms=jnp.asarray(1e-3 * rng.standard_normal(k)))
    lay = ParameterLayout.of(NOMINAL, 1, terms=TERMS)
    flat, unravel = ravel_pytree(p)
    t_idx, z_idx = lay.index("terms"), lay.index("zero")

    def residuals(x):
        return reprojection_residuals(unravel(x), problem).reshape(-1)

    J = np.asarray(jax.jit(jax.jacfwd(residuals))(flat))
    basis = np.asarray(problem.data.term_basis)
    joint, col = _terms.column_map(TERMS, N)
    V, P = np.asarray(problem.data.mask).shape
    view = np.repeat(np.arange(V), 2 * P)
    J_cv = J[:, z_idx][:, joint] * basis[view][:, joint, col]
    np.testing.assert_allclose(J_cv, J[:, t_idx], atol=1e-9 * np.abs(J).max())
    # The same corners with the terms as zero-offset changes per view (one view at a time).
    delta = np.asarray(_terms.correction(TERMS, p.terms, problem.data.term_basis))  # (V, joints)
    v = int(np.argmax(np.abs(delta).sum(1)))
    moved = dataclasses.replace(
        p, terms=jnp.zeros(k), correction=dataclasses.replace(p.correction, zero_offset=jnp.asarray(delta[v]))
    )
    np.testing.assert_allclose(
        np.asarray(projected_corners(moved, problem))[v],
        np.asarray(projected_corners(p, problem))[v],
        atol=1e-9,
    )


def test_the_held_out_fit_is_least_squares_on_the_other_folds():
    """`_Linear.held_out` against an explicit least-squares fit per fold (a linear model: the
    refinement's linearisation is exact there), blocks of consecutive frames dealt round the
    folds."""
    rng = np.random.default_rng(1)
    frames = np.repeat(np.arange(20), 2)  # two views per frame
    fold = fold_of_views(frames, frames.astype(float), np.ones(40, bool), 3)
    assert np.all(fold[::2] == fold[1::2]) and np.all(np.diff(fold[::12]) != 0)
    rows = np.repeat(fold, 4)  # two corners per view, (u, v) each
    J = rng.standard_normal((160, 5))
    r = rng.standard_normal(160)
    lin = _Linear(
        A=J, b=r, scale=np.linalg.norm(J, axis=0), raw_r=r, raw_J=J, used=np.ones(160, bool), fold=rows,
        n_geo=3, family=np.array([0, 1]), sign=np.zeros(2, int), b_rms=np.ones(2),
    )  # fmt: skip
    got = lin.held_out(np.array([1]), 3)
    want = []
    for f in range(3):
        tr, te = rows != f, rows == f
        cols = [0, 1, 2, 4]
        d = np.linalg.lstsq(J[tr][:, cols], -r[tr], rcond=None)[0]
        e = r[te] + J[te][:, cols] @ d
        want.append(np.linalg.norm(e.reshape(-1, 2), axis=1))
    np.testing.assert_allclose(got, np.concatenate(want), rtol=1e-10)


def test_a_family_is_kept_when_held_out_views_improve():
    """A family whose columns made the data is kept; one of pure noise is not (and is named, why)."""
    rng = np.random.default_rng(2)
    n_rows = 4000
    G = rng.standard_normal((n_rows, 6))
    T = rng.standard_normal((n_rows, 2))  # family 0: real; family 1: noise
    U = rng.standard_normal((n_rows, 2))
    r = 0.05 * rng.standard_normal(n_rows) + T @ np.array([0.02, -0.01])  # at the rigid fit: G^T r ~ 0
    r = r - G @ np.linalg.lstsq(G, r, rcond=None)[0]
    A = np.concatenate([G, T, U], axis=1)
    fold = np.repeat(np.arange(n_rows // 40) % 5, 40)
    block = np.repeat(np.arange(n_rows // 40), 40)  # 100 blocks of consecutive frames
    lin = _Linear(
        A=A, b=r, scale=np.linalg.norm(A, axis=0), raw_r=r, raw_J=A, used=np.ones(n_rows, bool), fold=fold,
        n_geo=6, family=np.array([0, 0, 1, 1]), sign=np.zeros(4, int), b_rms=np.full(4, 1e-3), block=block,
    )  # fmt: skip
    models, cols, kept = _compare(lin, ("first", "second"), 5, 1e-6)
    assert kept == ["first"] and list(cols) == [0, 1]
    assert models[1]["kept"] and not models[2].get("kept") and "held-out" in models[2]["why"]
    assert "standard errors over 100 blocks of frames" in models[1]["why"]  # the paired test's figure
    # A family tried first that takes part of a later one's pattern is left out again.
    mimic = 0.7 * T[:, :1] + 0.7 * rng.standard_normal((n_rows, 1))
    A = np.concatenate([G, mimic, T], axis=1)
    lin = _Linear(
        A=A, b=r, scale=np.linalg.norm(A, axis=0), raw_r=r, raw_J=A, used=np.ones(n_rows, bool), fold=fold,
        n_geo=6, family=np.array([0, 1, 1]), sign=np.zeros(3, int), b_rms=np.full(3, 1e-3), block=block,
    )  # fmt: skip
    models, cols, kept = _compare(lin, ("mimic", "real"), 5, 1e-6)
    assert kept == ["real"] and list(cols) == [1, 2], [m.get("why") for m in models]
    assert [m["terms"] for m in models if m.get("kept")] == [("real",)]
    assert "left out again" in models[-2]["why"]


def test_no_term_is_judged_by_folds_that_leave_the_geometry_unseen():
    """A geometric column seen almost only by one fold's frames (a joint swept within one block):
    that fold's fit, from the others' faint trace, predicts its views thousands of times off, and
    whatever the terms do, no family is kept on such figures; each says why."""
    rng = np.random.default_rng(4)
    n_rows = 2000
    fold = np.repeat(np.arange(n_rows // 40) % 5, 40)
    G = rng.standard_normal((n_rows, 3))
    G[:, 2] = np.where(fold == 0, 1.0, 1e-6 * rng.standard_normal(n_rows))  # seen by fold 0 alone
    T = rng.standard_normal((n_rows, 1))
    r = 0.05 * rng.standard_normal(n_rows) + 0.02 * T[:, 0]
    r = r - G @ np.linalg.lstsq(G, r, rcond=None)[0]
    A = np.concatenate([G, T], axis=1)
    lin = _Linear(
        A=A, b=r, scale=np.linalg.norm(A, axis=0), raw_r=r, raw_J=A, used=np.ones(n_rows, bool), fold=fold,
        n_geo=3, family=np.array([0]), sign=np.zeros(1, int), b_rms=np.full(1, 1e-3),
        block=np.repeat(np.arange(n_rows // 40), 40),
    )  # fmt: skip
    models, cols, kept = _compare(lin, ("compliance",), 5, 1e-6)
    assert models[0]["cv_mean_px"] > CV_SANE * lin.in_sample_px(np.zeros(0, int))
    assert kept == [] and len(cols) == 0 and models[0]["kept"]
    assert models[1]["why"].startswith("compliance: not tried: the views left out are predicted")


def test_a_family_left_out_is_counted_by_the_geometry_it_would_move():
    """A sag the geometry nearly absorbs (its column 95 % in the geometry's span) biases the rigid
    fit; `unresolved` returns the shift the family would make, which is the exact difference of the two
    least-squares fits and takes the rigid geometry back to the truth (its bias removed to within
    the wider fit's noise). Of a sign no arm has, the family is held and nothing is counted."""
    from jaxcal.stages._terms import unresolved

    rng = np.random.default_rng(5)
    n_rows = 4000
    G = rng.standard_normal((n_rows, 6))
    w = np.array([0.8, -0.5, 0.3, 0.0, 0.6, -0.2])
    T = (G @ w + 0.05 * rng.standard_normal(n_rows))[:, None]
    theta, c = rng.standard_normal(6), 0.5
    y = G @ theta + c * T[:, 0] + 0.05 * rng.standard_normal(n_rows)
    theta_rigid = np.linalg.lstsq(G, y, rcond=None)[0]
    b = G @ theta_rigid - y  # the residuals at the rigid solution
    A = np.concatenate([G, T], axis=1)

    def linear(sign):
        return _Linear(
            A=A, b=b, scale=np.linalg.norm(A, axis=0), raw_r=b, raw_J=A, used=np.ones(n_rows, bool),
            fold=np.repeat(np.arange(n_rows // 40) % 5, 40), n_geo=6, family=np.array([0]),
            sign=np.array([sign]), b_rms=np.full(1, 1e-3),
        )  # fmt: skip

    shifts, of = unresolved(linear(1), ("compliance",), (), np.zeros(0, int), 1e-6)
    assert of == ("compliance",) and shifts.shape == (6, 1)
    shift = shifts[:, 0]
    both = np.linalg.lstsq(A, y, rcond=None)[0][:6]
    np.testing.assert_allclose(shift, both - theta_rigid, atol=1e-9)
    bias = np.linalg.norm(theta_rigid - theta)
    assert bias > 0.3  # the rigid fit took most of the sag into the geometry
    assert np.linalg.norm(theta_rigid + shift - theta) < 0.15 * bias
    assert unresolved(linear(-1), ("compliance",), (), np.zeros(0, int), 1e-6) == (None, ())


def test_compensate_puts_each_joint_where_the_rigid_model_does():
    """$q_c + \\Delta(q_c, a) = q_t$: the commanded joints, sagged and lost in the play, stand
    where the rigid model puts the target (a path: each row approached from the one before)."""
    terms = ("compliance", "backlash")
    x = np.r_[[0.0, 0.03, 0.03, 0.2, 0.2, 0.2], np.tile([-1.5e-4, 2e-4], N)]
    q_t = np.random.default_rng(3).uniform(-1.5, 1.5, (7, N))
    q_c = _terms.compensate(terms, x, NOMINAL, MASSES, COMS, q_t)
    a = _terms.approach(q_t)
    delta = np.asarray(
        _terms.correction(
            terms, jnp.asarray(x), _terms.term_basis(terms, NOMINAL, jnp.asarray(q_c), MASSES, COMS, a)
        )
    )
    np.testing.assert_allclose(q_c + delta, q_t, atol=1e-12)
    assert np.abs(q_c - q_t).max() > 1e-3  # the shoulder's sag is milliradians


def test_compensate_refuses_what_no_robot_could_mean(tmp_path):
    """`jaxcal.compensate` from a compensation.json as the robot side reads it: the same commands
    as the terms give; joints or an approach that are not finite, of another arm, in degrees or
    off the flanks refused by name; a file whose coefficient is NaN refused naming it; a result
    of no kind it knows refused, not taken for "no terms"."""
    import json

    from jaxcal.errors import DatasetError
    from jaxcal.io.compensation import Compensation, compensation_json
    from jaxcal.io.dataset import finite_json, write_json

    terms = ("compliance", "backlash")
    x = np.r_[[0.0, 0.03, 0.03, 0.2, 0.2, 0.2], np.tile([-1.5e-4, 2e-4], N)]
    std = np.full(len(x), np.nan)  # unknown: written as null, read back as NaN
    path = tmp_path / "compensation.json"
    write_json(
        path, finite_json(compensation_json(Compensation(terms, x, std, NOMINAL, MASSES, COMS, np.ones(N))))
    )
    json.loads(path.read_text(), parse_constant=lambda c: pytest.fail(f"{c} in strict JSON"))
    q = np.random.default_rng(4).uniform(-1.5, 1.5, (3, N))
    np.testing.assert_array_equal(
        jaxcal.compensate(path, q), _terms.compensate(terms, x, NOMINAL, MASSES, COMS, q)
    )
    bad = q.copy()
    bad[1, 5] = np.nan
    for joints, approach, match in [
        (bad, None, r"joints\[1, 5\] is nan"),
        (q[:, :5], None, "this arm has 6 joints"),
        (np.degrees(q), None, r"joints\[0, \d\] = .* more than two turns: joints are radians"),
        (q, np.full(N, 2.0), "from -1 to \\+1"),
        (q, np.ones(N - 1), r"approach of shape \(5,\)"),
        (q, np.r_[np.ones(N - 1), np.inf], r"approach\[5\] is inf"),
    ]:
        with pytest.raises(ValueError, match=match):
            jaxcal.compensate(path, joints, approach=approach)
    for result in (None, {}, q):
        with pytest.raises(TypeError, match="give a CalibrationResult"):
            jaxcal.compensate(result, q)
    doc = json.loads(path.read_text())
    doc["coefficients"]["shoulder_lift_joint.compliance.rad_per_kNm"] = float("nan")
    path.write_text(json.dumps(doc))
    with pytest.raises(
        DatasetError, match="'shoulder_lift_joint.compliance.rad_per_kNm' is not a finite number"
    ):
        jaxcal.compensate(path, q)


DESIGN = Path(__file__).resolve().parents[1] / "data" / "ur5e_sweeps"


@pytest.fixture(scope="module")
def design_like():
    """`data/ur5e_sweeps`' corners as its images show them (the ids a detector finds per frame)."""
    from jaxcal.io.dataset import load_dataset
    from jaxcal.vision import detect_frames

    ds = load_dataset(DESIGN)
    rows = np.flatnonzero(ds.frames.camera == "cam0")
    return detect_frames(
        [ds.image_path(int(r)) for r in rows], [ds.targets[0].spec], K=ds.cameras[0].K, progress=False
    )


def _calibrated_on_design(like, arm, seed: int = 0):
    """`jaxcal.calibrate` of `data/ur5e_sweeps` on analytic corners where `arm` puts them, with
    0.054 px of noise drawn from `seed`."""
    from jaxcal.io.dataset import load_dataset
    from jaxcal.sim.corners import analytic_detections, capture_truth
    from jaxcal.stages import _observe

    truth = capture_truth(load_dataset(DESIGN), arm=arm)
    dets = analytic_detections(truth, "cam0", like=like, noise_px=0.054, rng=np.random.default_rng(seed))
    real = _observe.observe
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(
            "jaxcal.stages.observe",
            lambda setup, options, detections=None: real(setup, options, {"cam0": dets}),
        )
        return jaxcal.calibrate(DESIGN, progress=False)


@pytest.mark.slow
def test_a_compliance_at_one_speed_counts_its_lag(design_like):
    """The `realistic` arm's compliance alone on analytic corners of `data/ur5e_sweeps`' sweeps, at
    one speed: compliance is kept with gravity's torques, and the reduction ratios absorb its lag
    while the arm speeds up. The claim counts what the lag would move (`stages._terms.unresolved`),
    and covers the tool error (1.31 mm against 1.25 claimed when written), which the kept model's
    own claim (1.05 mm) did not; the note names the lag and the capture that would resolve it."""
    import re

    from jaxcal.sim.arm import ARM_PRESETS, ArmModel

    fit = _calibrated_on_design(
        design_like, ArmModel(name="sag", compliance=ARM_PRESETS["realistic"].compliance)
    )
    claim = next(c.value for c in fit.verdict.checks if c.check == "ee_sigma_mm")
    measured = fit.validation.ee_rms_mm_after
    note = next(n for n in fit.verdict.notes if "counts what the model cannot tell" in n)
    alone = float(re.search(r"the model alone would claim ([0-9.]+) mm", note).group(1))
    assert "compliance" in fit.terms.kept and "lag under the arm's own acceleration" in note
    assert "each sweep filmed both ways, the second at another speed" in note
    assert measured < 1.15 * claim and measured > 1.2 * alone, (measured, claim, alone)
    # The arm test still weighs the refinement's clock in the noise, not in what the claim considers
    # (counted there, the clock's std passed the arcs' and the test of their gap did not run).
    assert any(c.check == "arm_clock_z" for c in fit.verdict.checks), [c.check for c in fit.verdict.checks]


@pytest.mark.slow
def test_a_sagging_arm_with_lost_motion_is_calibrated_with_its_terms(tmp_path, design_like):
    """The realistic arm's sag, lost motion and late encoder stamps on analytic corners of
    `data/ur5e_sweeps`' design (without terms: 1.87 mm and suspect, naming gravity sag and backlash,
    as `tests/test_armcheck.py` checks): by default the lost motion is kept (held-out views improve
    by 10 %), the arcs and axes fitted again on the corrected log pass the rigidity tests, the result
    is ok with a tool error within 1.3x the rigid arm's on the same corners (1.00 mm: the issue's
    bound), and its terms are in `result.json` and `compensation.json`."""
    import json

    from jaxcal.errors import DatasetError
    from jaxcal.io.result import read_result
    from jaxcal.sim.arm import ARM_PRESETS

    fit = _calibrated_on_design(design_like, ARM_PRESETS["realistic"])
    assert "backlash" in fit.terms.kept and fit.status == "ok", fit.reasons
    assert not [w for w in fit.warnings if "home configuration" in w], fit.warnings  # swept from zero
    assert fit.validation.ee_rms_mm_after < 1.3 * 1.00
    # The lost motion recovered: the approach coefficients are minus half an arc minute, within 4 std.
    approach = [c for c in fit.terms.coefficients if c.free and c.name.endswith("approach_rad")]
    assert len(approach) >= 4, fit.terms.coefficients
    for c in approach:
        assert abs(c.estimate + 0.5 * np.radians(1 / 60)) < 4 * c.std, c
    out = jaxcal.write_outputs(fit, tmp_path / "out")
    saved = json.loads((out / "result.json").read_text())
    assert saved["terms"]["kept"] == list(fit.terms.kept)
    q = np.zeros((2, N))
    q[1, 1] = 0.3
    np.testing.assert_allclose(jaxcal.compensate(out, q), jaxcal.compensate(fit, q), atol=1e-15)
    # Strict JSON (a check without a limit is null, not Infinity); read back, the result names
    # what compensation needs; a folder whose calibration kept no term compensates nothing.
    for name in ("result.json", "compensation.json"):
        json.loads((out / name).read_text(), parse_constant=lambda c: pytest.fail(f"{c} in {name}"))
    with pytest.raises(ValueError, match="give its folder or its compensation.json"):
        jaxcal.compensate(read_result(out), q)  # the folder read as its result.json
    (out / "compensation.json").unlink()
    with pytest.raises(DatasetError, match="compensation.json: no such file, though the calibration kept"):
        jaxcal.compensate(out, q)
    saved["terms"]["kept"] = []
    (out / "result.json").write_text(json.dumps(saved))
    np.testing.assert_array_equal(jaxcal.compensate(out, q), q)
