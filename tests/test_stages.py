"""The stages and their building blocks, without rendering or solving.

Capture kinds are resolved from copies of the shipped dataset with their
metadata edited (eye-in-hand, markers on every link, no encoder log, two
cameras); the synchronisation, the verdict's checks, the parameter layout,
the least-squares kit and the size buckets are checked on analytic inputs.
The solvers each stage calls are tested in their own files (test_arcfit,
test_axisfit, test_refine: exact recovery for every capture kind on analytic
corners), and one rendered capture per kind runs end to end (test_calibrate,
test_eye_in_hand, test_links).
"""

import dataclasses
import json
import re
import shutil
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from jaxcal import stages
from jaxcal._buckets import bucket, pad_log
from jaxcal._correction import ParameterLayout, physical_parameters, zero_correction
from jaxcal._kinematics import joint_axes
from jaxcal._lsq import closed_form_jvp, covariance, independent_columns
from jaxcal.errors import CalibrationError
from jaxcal.io.dataset import load_dataset
from jaxcal.robots import load_robot
from jaxcal.stages import kinds
from jaxcal.stages._axes_check import axis_spacing_ratio, reversed_joints
from jaxcal.stages._synchronise import assign_frames, usable
from jaxcal.stages._timing import interpolation_error, stamp_jitter_s
from jaxcal.stages._verdict import CAUSES, _Checks
from jaxcal.stages.kinds import Motion, Mount

DATA = Path(__file__).resolve().parents[1] / "data" / "ur5e_sweeps"
OPTIONS = stages.Options(progress=False, workers=1)


def _variant(tmp_path: Path, edit) -> Path:
    """A copy of the shipped dataset without its truth, `edit(metadata)` applied."""
    dst = tmp_path / "ds"
    shutil.copytree(DATA, dst, ignore=shutil.ignore_patterns("truth.*"))
    meta = json.loads((dst / "metadata.json").read_text())
    edit(meta, dst)
    (dst / "metadata.json").write_text(json.dumps(meta))
    return dst


def _eye_in_hand(meta, root):
    meta["cameras"][0]["mount"] = "flange"
    meta["targets"][0]["link"] = "world"


def _no_encoders(meta, root):
    (root / "encoders.csv").unlink()
    meta["encoders"] = None


def _two_cameras(meta, root):
    second = dict(meta["cameras"][0], name="cam1")
    meta["cameras"].append(second)


def _free_motion_without_link_plates(meta, root):
    meta["motion"] = [{"joint": None, "start": meta["motion"][0]["start"], "end": meta["motion"][-1]["end"]}]


# --------------------------------------------------------------------------- setup: capture kinds


@pytest.mark.parametrize(
    "edit, mount, motion, encoders, fixed",
    [
        (lambda m, r: None, Mount.EYE_TO_HAND, Motion.SWEEPS, True, "T_cam_base"),
        (_eye_in_hand, Mount.EYE_IN_HAND, Motion.SWEEPS, True, "T_board_base"),
        (_no_encoders, Mount.EYE_TO_HAND, Motion.SWEEPS, False, "T_cam_base"),
    ],
)
def test_setup_resolves_the_capture_kind(tmp_path, edit, mount, motion, encoders, fixed):
    s = stages.setup(_variant(tmp_path, edit), OPTIONS)
    kind = s.kind
    assert (kind.mount, kind.motion, kind.encoders) == (mount, motion, encoders)
    assert kind.fixed_frame == fixed and kind.inverts_poses == (mount is Mount.EYE_IN_HAND)
    assert kind.axis_fit_uses_poses == encoders and kind.per_view_angles == (not encoders)
    assert kind.identifiability_tol == (1e-6 if encoders else 1e-3)
    assert len(s.targets) == 1
    if mount is Mount.EYE_IN_HAND:
        # The board's pattern, named after the camera, rides on the flange in the fits.
        assert s.board.name == "plate0" and s.targets[0].name == "cam0" and s.targets[0].link == "flange"


#: The columns of the table in `jaxcal.stages.kinds`'s docstring: the kinds each stands for.
KIND_COLUMNS = {
    "eye-to-hand sweeps": [(Mount.EYE_TO_HAND, Motion.SWEEPS, True)],
    "eye-in-hand sweeps": [(Mount.EYE_IN_HAND, Motion.SWEEPS, True)],
    "markers on every link": [(Mount.EYE_TO_HAND, Motion.FREE, True)],
    "poses": [(Mount.EYE_TO_HAND, Motion.POSES, True), (Mount.EYE_IN_HAND, Motion.POSES, True)],
    "no encoder log": [(m, Motion.SWEEPS, False) for m in (Mount.EYE_TO_HAND, Mount.EYE_IN_HAND)],
    "tracker sweeps": [(Mount.DEVICE, Motion.SWEEPS, True)],
    "tracker poses": [(Mount.DEVICE, Motion.POSES, True)],
}


def test_every_yes_and_no_of_the_kinds_table_is_what_the_property_answers():
    """The table in `kinds.py` is the contract the stages read: each cell that says `yes`,
    `no`, a mount (`eye-in-hand`: yes for that mount, no for the other) or a value is checked."""
    rows = [
        [c.strip().strip("`") for c in line.strip().strip("|").split("|")]
        for line in kinds.__doc__.splitlines()
        if line.startswith("| ")
    ]
    header, body = rows[0], rows[2:]  # the second row is the rule under the header
    assert set(header[1:]) == set(KIND_COLUMNS)
    checked = 0
    for name, *cells in body:
        for column, cell in zip(header[1:], cells):
            for mount, motion, encoders in KIND_COLUMNS[column]:
                value = getattr(kinds.CaptureKind(mount, motion, encoders), name)
                if cell in ("yes", "no"):
                    expected = cell == "yes"
                elif cell in ("eye-in-hand", "eye-to-hand"):
                    expected = mount.value == cell.replace("-", "_")
                elif (
                    cell in ("camera", "device", "point", "target(s)")
                    or cell.startswith("T_")
                    or "frame," in cell
                ):
                    expected = cell
                elif cell.replace(".", "").replace("e-", "").isdigit():
                    expected = float(cell)
                else:
                    continue  # "(its mount)", "(no fit)", "not with device_is_base", blank: prose
                assert value == expected, (name, column, mount, cell, value)
                checked += 1
    assert checked > 100


def test_a_capture_the_method_cannot_calibrate_says_why():
    no_log = [kinds.CaptureKind(Mount.EYE_TO_HAND, m, False) for m in (Motion.POSES, Motion.FREE)]
    assert "pose-based capture" in no_log[0].unsupported and "sequential method" in no_log[1].unsupported
    assert kinds.CaptureKind(Mount.EYE_TO_HAND, Motion.SWEEPS, False).unsupported is None
    assert kinds.CaptureKind(Mount.DEVICE, Motion.POSES, False).unsupported is None


def test_setup_adds_further_fixed_cameras_only_where_the_kind_refines_them(tmp_path):
    s = stages.setup(_variant(tmp_path, _two_cameras), OPTIONS)
    assert [c.name for c in s.extra_cameras] == ["cam1"] and s.kind.refines_other_cameras
    assert any("the refinement adds ['cam1']" in n for n in s.notes)
    single = stages.setup(s.dataset, stages.Options(progress=False, other_cameras=False))
    assert single.extra_cameras == ()
    both = _variant(tmp_path / "b", lambda m, r: (_two_cameras(m, r), _no_encoders(m, r)))
    s2 = stages.setup(both, OPTIONS)
    assert s2.extra_cameras == () and any("uses camera 'cam0' only" in n for n in s2.notes)


def test_free_motion_with_the_plate_on_the_flange_only_is_pose_based(tmp_path):
    s = stages.setup(_variant(tmp_path, _free_motion_without_link_plates), OPTIONS)
    assert s.kind.motion is Motion.POSES and not s.kind.has_arcs and not s.kind.keeps_two_stage_gauge
    assert any("pose-based capture" in n for n in s.notes)


def test_free_motion_needs_a_plate_on_every_link_once_links_carry_plates(tmp_path):
    def edit(meta, root):
        _free_motion_without_link_plates(meta, root)
        meta["targets"].append(dict(meta["targets"][0], name="plate1", link="upper_arm_link", first_id=20))

    with pytest.raises(CalibrationError, match="no target on link 'shoulder_link'"):
        stages.setup(_variant(tmp_path, edit), OPTIONS)


def test_an_unknown_camera_is_named(tmp_path):
    with pytest.raises(CalibrationError, match="camera 'cam9' is not in"):
        stages.setup(DATA, stages.Options(camera="cam9"))


# --------------------------------------------------------------------------- synchronise


def test_frames_are_assigned_from_the_motion_segments_or_the_encoder_log():
    ds = load_dataset(DATA)
    t = np.array([s[1] + 0.5 * (s[2] - s[1]) for s in ds.segments] + [ds.segments[-1][2] + 10.0])
    assert assign_frames(ds, t, None, 6).tolist() == [0, 1, 2, 3, 4, 5, -1]
    # Without segments: the one joint away from zero while the others stay at zero.
    q = np.zeros((4, 6))
    q[0, 2] = 0.3  # elbow alone
    q[1, [1, 2]] = 0.3  # two joints: no sweep
    q[2, 4] = 0.001  # below MOVING_DEG
    q[3, 5] = -1.0
    no_segments = dataclasses.replace(ds, segments=())
    assert assign_frames(no_segments, np.zeros(4), q, 6).tolist() == [2, -1, -1, 5]


def test_frames_in_an_encoder_glitch_are_not_usable():
    ds = load_dataset(DATA)
    t = ds.encoder_t[[5, 50, 100]]
    inside, glitched = usable(ds, t, (ds.encoder_t, ds.encoder_motor))
    assert inside.all() and not glitched.any()
    outside, _ = usable(ds, np.array([ds.encoder_t[0] - 1.0, ds.encoder_t[-1] + 1.0]), (ds.encoder_t, None))
    assert not outside.any()


# --------------------------------------------------------------------------- verdict


class _Arcs:
    def __init__(self, point, direction):
        self.point, self.direction = point, direction


def test_a_joint_logged_the_other_way_is_named_by_its_parallel_neighbours():
    """The UR5e's shoulder lift, elbow and wrist 1 are parallel: an axis measured (in the encoder
    log's sense) against both others is that joint's log reversed; trial 14 found a reversed elbow
    blamed on three other joints' reduction ratios. The measured axes may be turned as a whole."""
    s = stages.setup(DATA, OPTIONS)
    p, d = (np.asarray(a) for a in joint_axes(s.nominal, jnp.zeros(6)))
    R = Rotation.from_rotvec([0.3, -0.2, 0.1]).as_matrix()
    assert reversed_joints(s, _Arcs(p @ R.T, d @ R.T)) == []
    for j in (1, 2, 3):
        flipped = d.copy()
        flipped[j] *= -1.0
        assert reversed_joints(s, _Arcs(p @ R.T, flipped @ R.T)) == [(j, [k for k in (1, 2, 3) if k != j])]
    flipped = d.copy()
    flipped[0] *= -1.0  # the base has no parallel neighbour: nothing to tell it by
    assert reversed_joints(s, _Arcs(p, flipped)) == []
    from types import SimpleNamespace

    from jaxcal.stages._verdict import _axes
    from jaxcal.stages.limits import Limits

    c = _Checks()
    flipped = d.copy()
    flipped[2] *= -1.0
    two = SimpleNamespace(arc_rows=(), fit=SimpleNamespace(residual_rms=1.0), arcs=_Arcs(p, flipped))
    _axes(c, s, two, Limits(), None)
    assert c.reasons[0].startswith("joint 'elbow_joint' turns the other way than the robot file's axis")


def test_the_axes_spacing_measures_a_mis_sized_target():
    s = stages.setup(DATA, OPTIONS)
    p, d = (np.asarray(a) for a in joint_axes(s.nominal, jnp.zeros(6)))
    R = Rotation.from_rotvec([0.3, -0.2, 0.1]).as_matrix()
    for scale in (1.0, 1.1, 0.95):
        # The camera sees the axes through the target: every length times `scale`.
        ratio, pairs = axis_spacing_ratio(s, _Arcs(scale * p @ R.T + [0.1, 0.2, 0.9], d @ R.T))
        assert ratio == pytest.approx(scale, rel=1e-9) and len(pairs) == 2  # the two long parallel pairs


def test_a_rolling_shutters_spacing_is_judged_on_the_refined_robot():
    """With the line delay estimated the two-stage arcs know nothing of the rolling shutter
    and bend (a render's axes at 56 % of the nominal spacing: `suspect` for a target of the
    wrong size, on a result as good as the ideal capture's); once the refinement timed every
    corner at its row the spacing is the refined robot's, which a mis-sized target still scales."""
    from types import SimpleNamespace

    import equinox as eqx

    from jaxcal.stages._verdict import _axes, _Checks
    from jaxcal.stages.limits import Limits

    s = stages.setup(DATA, OPTIONS)
    p, d = (np.asarray(a) for a in joint_axes(s.nominal, jnp.zeros(6)))
    two = SimpleNamespace(arc_rows=(), fit=SimpleNamespace(residual_rms=1.0), arcs=_Arcs(0.56 * p, d))

    def board(refined, notes=None):
        c = _Checks()
        _axes(c, s, two, Limits(), refined)
        (row,) = [r for r in c.rows if r.check == "board_scale"]
        return (row, c.reasons) if notes is None else (row, c.notes)

    row, reasons = board(None)
    assert not row.passed and "measured through the target are 56.0 %" in reasons[0]
    for scale, passed in ((1.0, True), (1.003, True), (1.005, False), (1.1, False)):
        # Every length of the robot times `scale` (a target printed 10 % larger than stated).
        T = s.nominal.T_parent_joint
        model = eqx.tree_at(lambda m: m.T_parent_joint, s.nominal, T.at[:, :3, 3].multiply(scale))
        row, reasons = board(SimpleNamespace(fit=SimpleNamespace(model=model)))
        assert row.passed == passed and row.value == pytest.approx(100 * abs(scale - 1), abs=1e-9)
        assert passed or "the refined robot's joint axes (every corner timed at its row) are 1" in reasons[0]
        # Within the limit but further off than a real arm's own spacing (trial 14: a target printed
        # 0.3 % large read 0.24 %, the tool point 3 times its claim under `ok`): a note, with the move.
        _, notes = board(SimpleNamespace(fit=SimpleNamespace(model=model)), notes=True)
        said = [n for n in notes if "printed size that far off" in n]
        assert bool(said) == (scale == 1.003), notes
        if said:  # 0.3 % of the flange's RMS reach over the workspace (about 0.6 m): about 2 mm
            assert 1.0 < float(re.search(r"would lie ([0-9.]+) mm RMS off", said[0]).group(1)) < 3.5, said


# --------------------------------------------------------------------------- parameter layout and least squares


def test_the_layout_names_every_parameter_once_in_solver_order():
    model = load_robot("ur5e")
    lay = ParameterLayout.of(model, 2, other_cameras=("side",), angles=("a", "b"))
    names = lay.names()
    assert len(names) == lay.size == len(set(names))
    idx = lay.indices()
    assert sorted(np.concatenate(list(idx.values())).tolist()) == list(range(lay.size))
    assert (
        names[idx["zero"][2]] == "elbow_joint.zero_offset" and names[idx["others"][0]] == "side.T_cam_base.tx"
    )
    assert lay.names(refine=False) == names[: lay.axis_size]
    assert sorted(lay.priority().tolist()) == list(range(lay.size))
    eih = ParameterLayout.of(model, 1, eye_in_hand=True).names(refine=False)
    assert eih[0] == "T_board_base.tx" and eih[-1] == "camera.mount.rz"


def test_the_physical_table_is_the_nominal_at_zero_correction():
    model = load_robot("ur5e")
    lay = ParameterLayout.of(model, 1)
    T0, mount = np.eye(4), np.eye(4)[None]
    n = lay.axis_size
    rows = physical_parameters(
        lay,
        model,
        mount,
        T0,
        jnp.zeros(6),
        zero_correction(6, 1),
        np.eye(n) * 1e-6,
        np.ones(n, bool),
        ["plate"],
    )
    assert all(r["estimate"] == pytest.approx(r["nominal"], abs=1e-15) for r in rows)
    assert all(r["std"] > 0 for r in rows if r["free"])
    assert rows[-1]["name"] == "plate.mount.yaw"


def test_independent_columns_follow_the_priority_order():
    rng = np.random.default_rng(0)
    A = rng.normal(size=(20, 3))
    J = jnp.asarray(np.column_stack([A, A[:, 0] + A[:, 1], A[:, 2] * 3.0]))  # columns 3, 4 depend on 0-2
    keep, _ = independent_columns(J, np.arange(5), tol=1e-8)
    assert keep.tolist() == [True, True, True, False, False]
    keep, _ = independent_columns(J, np.array([4, 3, 2, 1, 0]), tol=1e-8)
    assert keep.tolist() == [False, True, False, True, True]
    cov, sv, _ = covariance(J, jnp.asarray([True, True, True, False, False]), 2.0)
    np.testing.assert_allclose(cov[:3, :3], 2.0 * np.linalg.inv(A.T @ A), rtol=1e-9)
    assert np.all(np.asarray(cov)[3:] == 0.0)


def test_a_closed_form_jacobian_is_used_for_parameters_and_autodiff_for_data():
    def f(x, a):
        return jnp.sin(x) * a

    def terms(x, a):
        return f(x, a), jnp.diag(jnp.cos(x) * a)

    g = closed_form_jvp(f, terms, f)
    x, a = jnp.array([0.1, 0.7]), jnp.array([2.0, 3.0])
    np.testing.assert_allclose(jax.jacfwd(g)(x, a), jax.jacfwd(f)(x, a), rtol=1e-12)
    np.testing.assert_allclose(jax.jacfwd(g, argnums=1)(x, a), jax.jacfwd(f, argnums=1)(x, a), rtol=1e-12)


# --------------------------------------------------------------------------- size buckets


def test_buckets_grow_by_at_most_half_and_logs_pad_without_changing_interpolation():
    sizes = [bucket(n) for n in range(1, 5000)]
    assert all(s >= n for n, s in zip(range(1, 5000), sizes))
    ladder = sorted(set(sizes))
    assert all(b / a <= 1.5 for a, b in zip(ladder, ladder[1:]))
    t = np.linspace(0.0, 2.0, 11)
    q = np.stack([np.sin(t), t**2], -1)
    tp, qp = pad_log(t, q, bucket(len(t)))
    assert len(tp) == 12 and np.all(np.diff(tp) > 0)
    probe = np.linspace(-1.0, 5.0, 97)
    for j in range(2):
        np.testing.assert_array_equal(np.interp(probe, tp, qp[:, j]), np.interp(probe, t, q[:, j]))


def test_a_joint_origin_far_past_its_limit_asks_for_the_robot_model():
    """A joint origin a few mm past its limit is a worn or bent arm; tens of mm (the UR5's data
    calibrated as a UR5e) is the wrong model, and the reason says so."""
    from jaxcal.records import ParameterRow
    from jaxcal.stages._verdict import WRONG_MODEL_FACTOR, _Checks, _corrections
    from jaxcal.stages.limits import Limits

    limits = Limits()
    for mm, asks in ((1.5 * limits.origin_mm, False), (1.01 * WRONG_MODEL_FACTOR * limits.origin_mm, True)):
        rows = tuple(
            ParameterRow(f"shoulder_pan_joint.origin.{k}", "m", "correction", 0.0, v, 1e-5, True)
            for k, v in (("x", mm * 1e-3), ("y", 0.0), ("z", 0.0))
        )
        c = _Checks()
        _corrections(c, rows, limits, set())
        (reason,) = c.reasons
        assert "moved" in reason and ("is the robot model" in reason) == asks, reason
        assert "--device-is-base" not in reason
        # With the device's frame given as the base, the first joint's origin far off also asks that.
        c = _Checks()
        _corrections(c, rows, limits, set(), "shoulder_pan_joint.origin")
        (reason,) = c.reasons
        assert ("Or is the device's frame not its base? Calibrate without --device-is-base" in reason) == asks


def test_a_pose_captures_gauge_moves_the_fixed_frame_by_the_truths_held_perturbations():
    """A truth that differs from the nominal UR5e only by 1 mm of joint 2's origin along joint 1's
    axis (`shoulder_lift_joint.origin.ty`, which a pose capture's refinement holds at nominal):
    the estimator can only move its base frame 1 mm along that axis instead, and the gauge fit
    finds exactly that (so a perfect estimate scores zero, not 1 mm). A truth off in a parameter
    the estimator frees leaves the gauge at the truth's own pose."""
    from jaxcal._correction import apply_correction, zero_correction
    from jaxcal._uncertainty import joint_travel
    from jaxcal.stages._validate import _pose_gauge

    nominal = load_robot("ur5e")
    n = nominal.num_joints
    corr = zero_correction(n, 1)
    corr = type(corr)(origin=corr.origin.at[1, 1].set(1e-3), zero_offset=corr.zero_offset, tool=corr.tool)
    true, _ = apply_correction(nominal, np.eye(4)[None], corr)
    T_cb = np.array([[1.0, 0, 0, 0.9], [0, 0.26, -0.97, 0.2], [0, 0.97, 0.26, 1.1], [0, 0, 0, 1.0]])
    T_cb[:3, :3] = np.linalg.qr(T_cb[:3, :3])[0] * np.sign(np.diag(np.linalg.qr(T_cb[:3, :3])[1]))
    mount = np.eye(4)
    mount[:3, 3] = [0.0, 0.05, 0.1]
    free = np.ones(7 * n + 12, bool)
    free[6:12] = False  # joint 1's origin
    free[6 + 6 * n] = False  # and its zero offset: the base frame is the camera's to place
    travel = joint_travel(nominal)
    held = free.copy()
    held[12 + 1] = held[12 + 4] = held[12 + 5] = False  # shoulder_lift_joint.origin.ty, ry, rz
    dT = np.linalg.inv(T_cb) @ np.asarray(_pose_gauge(nominal, true, held, T_cb, mount, travel)[0])
    np.testing.assert_allclose(np.abs(dT[:3, 3]), [0.0, 0.0, 1e-3], atol=1e-9)  # 1 mm along joint 1's axis
    np.testing.assert_allclose(dT[:3, :3], np.eye(3), atol=1e-9)
    # A truth off in a parameter the estimator frees (elbow_joint.origin.tx): the gauge is its own pose.
    corr = type(corr)(
        origin=corr.origin.at[1, 1].set(0.0).at[2, 0].set(1e-3), zero_offset=corr.zero_offset, tool=corr.tool
    )
    true, _ = apply_correction(nominal, np.eye(4)[None], corr)
    dT = np.linalg.inv(T_cb) @ np.asarray(_pose_gauge(nominal, true, held, T_cb, mount, travel)[0])
    np.testing.assert_allclose(dT, np.eye(4), atol=1e-9)


@pytest.mark.parametrize(
    ("unit", "span_deg", "kind", "named"),
    [
        ("deg", 1.16, "revolute", True),  # a log in radians (66 deg) labelled degrees
        ("deg", 0.05, "revolute", False),  # 3 deg even in radians: too short either way
        ("deg", 20.0, "revolute", False),  # a sweep: nothing to name
        ("rad", 1.16, "revolute", False),
        ("deg", 1.16, "prismatic", False),
    ],
)
def test_a_log_in_radians_labelled_degrees_is_named(unit, span_deg, kind, named):
    """A sweep too short to fit, from a log whose `encoders.unit` says deg, is named as a log
    in radians when its values, read as radians, sweep a plausible angle."""
    from types import SimpleNamespace

    from jaxcal._arcdata import make_arc_data
    from jaxcal.stages._two_stage import _radians_read_as_degrees

    angle = np.radians(np.linspace(0.0, span_deg, 12))
    positions = np.stack([np.cos(angle), np.sin(angle), np.zeros(12)], axis=-1)[None]
    data = jax.device_get(make_arc_data(positions, encoder=angle))
    assert _radians_read_as_degrees(SimpleNamespace(encoder_unit=unit), data, kind) is named


def test_the_causes_lead_the_reasons():
    """A failed check naming a cause (a rolling shutter, a lens, blur, errors that repeat) comes
    before the symptoms it explains, the causes in `CAUSES`' order whatever order they ran in."""
    c = _Checks()
    c.add("origin.mm", 60.0, 15.0, "origin moved")
    c.add("correlated_errors_sigmas", 7.0, 5.0, "errors repeat", cause="correlated_errors")
    c.add("axis_residual", 1.0, 5.0, "passes")
    c.add("cam0.rolling_shutter_sigmas", 41.0, 10.0, "rolling shutter", cause="rolling_shutter")
    c.add("cam0.lens_sigmas", 12.0, 10.0, "lens", cause="camera_model")
    c.add("encoder_interpolation", 1.7, 0.5, "log too slow", cause="timing")
    assert c.reasons == ["rolling shutter", "lens", "log too slow", "errors repeat", "origin moved"]
    assert [r.passed for r in c.rows] == [False, False, True, False, False, False]
    assert CAUSES == (
        "encoder_sense",
        "rolling_shutter",
        "camera_model",
        "timing",
        "blur",
        "arm",
        "correlated_errors",
    )
    # An arm's reason after a timing cause says the timing makes its signs too.
    c.add("arm_clock_sigmas", 6.7, 2.58, "sags", cause="arm")
    c.also_from("timing", "arm", "see the timing: ")
    assert c.reasons[:4] == ["rolling shutter", "lens", "log too slow", "see the timing: sags"]


def test_the_interpolation_error_of_a_log():
    """Linear interpolation of $t^2$ between samples $h$ apart misses by $h^2 s(1 - s)$ at the
    fraction $s$ of an interval (the formula is exact on a parabola, unevenly sampled too), and
    nothing on a line."""
    t = np.array([0.0, 0.1, 0.3, 0.35, 0.5])
    at = np.array([0.05, 0.2, 0.31, 0.45])
    k = np.searchsorted(t, at) - 1
    h, s = t[k + 1] - t[k], (at - t[k]) / (t[k + 1] - t[k])
    np.testing.assert_allclose(interpolation_error(t, t**2, at), h**2 * s * (1 - s), rtol=1e-12)
    np.testing.assert_allclose(interpolation_error(t, 3.0 * t + 1.0, at), 0.0, atol=1e-12)


def test_the_jitter_of_a_cameras_stamps():
    """Stamps at 30 fps with 2 ms of jitter and every tenth frame dropped: the jitter within 10 %
    (2000 frames), the drops ignored; steady stamps have none."""
    t = np.arange(2000) / 30.0
    keep = np.arange(2000) % 10 != 5
    noisy = t + 0.002 * np.random.default_rng(0).standard_normal(t.size)
    assert abs(stamp_jitter_s(noisy[keep]) / 0.002 - 1.0) < 0.1
    assert stamp_jitter_s(t[keep]) < 1e-12
