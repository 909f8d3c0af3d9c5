"""Capture planning (`jaxcal.plan`, `jaxcal.evaluate_plan`, `jaxcal plan`, `simulate-plan`).

Small cases: the Fisher information against the refinement's own Cramer-Rao
bound, its gradient against finite differences, the feasibility checks'
named reasons and seed 002's correction, the JAX collision capsules against
MuJoCo's contacts, the greedy selection against brute force, plan files
(round trip, unknown fields, wrong types), the refused inputs (exit code 2,
nothing written), and one small rendered eye-in-hand plan end to end.
"""

import json
import os
import re
import shutil
from dataclasses import replace
from itertools import combinations
from pathlib import Path

import cv2
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxcal
from jaxcal._refine import fisher_std, identifiable_mask, zero_params
from jaxcal._uncertainty import random_configurations
from jaxcal.cli import main
from jaxcal.errors import BudgetTooSmallError, CameraViewError, PlanFileError, UnreachableRegionError
from jaxcal.io.plan_inputs import parse_region, read_camera
from jaxcal.planning import (
    CHECKS,
    CapturePlan,
    FeasibilityLimits,
    PoseSet,
    Robot,
    default_layout,
    evaluate_views,
    load_plan,
    plan_from_dict,
    plan_robot,
    plan_to_dict,
    save_plan,
    scene_of,
    sweep_plan,
)
from jaxcal.planning._evaluate import (
    corner_problem,
    design,
    ee_gram,
    ee_jacobians,
    ee_mean_square,
    free_jacobian,
)
from jaxcal.planning._optimise import all_margins, correct_toward, greedy_d_optimal, view_blocks
from jaxcal.robots import robot_path

#: Twelve poses about the UR5e's zero that the demo's camera sees well (rad).
POSES = np.radians(
    [
        [10, -15, 20, -10, 15, 30],
        [-15, 10, -20, 15, -10, -30],
        [20, 5, 10, 20, -20, 60],
        [-20, -5, -10, -20, 20, -60],
        [5, 20, -25, 5, 25, 0],
        [-5, -20, 25, -5, -25, 90],
        [25, -10, 5, -25, 10, -90],
        [-25, 10, -5, 25, -15, 45],
        [0, 15, 15, -15, 5, -45],
        [15, -20, -15, 10, -5, 120],
        [-10, 0, 30, 0, 10, -120],
        [30, 10, -30, -5, 0, 15],
    ]
)


@pytest.fixture(scope="module")
def ur5e():
    robot = Robot.load("ur5e")
    camera, target = default_layout(robot.model, np.zeros(6))
    return robot, camera, target, scene_of(robot, camera, target, -0.6)


def _plan(ur5e, poses=POSES) -> CapturePlan:
    robot, camera, target, _ = ur5e
    return CapturePlan(
        "ur5e", tuple(robot.model.joint_names), camera, target, np.zeros(6), (PoseSet(poses),), -0.6
    )


def test_default_layout_is_the_demos(ur5e):
    from jaxcal.sim.simulate import SimConfig, scene_layout

    robot, camera, target, _ = ur5e
    for eye_in_hand, distance in ((False, 0.9), (True, 0.6)):
        cfg = SimConfig(resolution=(1280, 960), eye_in_hand=eye_in_hand, camera_distance=distance)
        plates, _, cams, _ = scene_layout(robot.model, robot.model, cfg, np.random.default_rng(0))
        c, t = default_layout(robot.model, np.zeros(6), distance=distance, eye_in_hand=eye_in_hand)
        assert np.allclose(c.T_mount_cam, cams[0].T_mount_cam, atol=1e-12) and c.mount == cams[0].mount
        assert np.allclose(c.K, cams[0].K) and np.allclose(
            t.T_link_target, plates[0].T_link_target, atol=1e-12
        )
        assert t.spec == plates[0].target and t.link == plates[0].link


def test_fisher_information_is_the_refinements_cramer_rao_bound(ur5e):
    *_, scene = ur5e
    t = np.arange(len(POSES), dtype=float)
    configs = np.asarray(random_configurations(jax.random.key(0), 200, 6))
    ev = evaluate_views(scene, POSES, t, configs, sweeps=False, sigma_px=0.05)
    problem = corner_problem(scene, jnp.asarray(POSES), jnp.asarray(t))
    d = design(scene, False)
    free, _ = jax.jit(identifiable_mask, static_argnames="tol")(
        problem, zero_params(6, 1), jnp.asarray(d.candidates), tol=d.tol
    )
    assert np.array_equal(np.asarray(free), ev.free) and ev.free.sum() == 36
    oracle = np.asarray(fisher_std(problem, zero_params(6, 1), np.asarray(free), 0.05))
    assert np.allclose(ev.std, oracle, rtol=1e-6, atol=1e-15)
    # The same EE figure through the planner's objective (Cholesky, Jacobi-scaled, no SVD).
    idx = np.flatnonzero(ev.free)
    M = ee_gram(ee_jacobians(scene, jnp.asarray(configs)), idx, d.layout.size)
    ms = ee_mean_square(free_jacobian(problem, idx), M, 0.05)
    assert np.isclose(np.sqrt(float(ms)), ev.ee_rms, rtol=1e-4)  # the ridge of 1e-9
    # Held parameters here are exact reparametrisations: no EE effect left.
    assert len(ev.held) == 24 and ev.unidentifiable == [] and max(ev.held_effect.values()) < 1e-12
    lo, hi = ev.ratio_interval
    assert 0.2 < lo < 1.0 < hi < 2.5 and ev.effective_dof >= 1.0
    # The percentile and band probability read the distribution the interval came from.
    assert abs(ev.ratio_percentile(lo * ev.ee_rms) - 0.05) < 0.002
    assert abs(ev.ratio_percentile(hi * ev.ee_rms) - 0.95) < 0.002
    assert abs(ev.outside_probability(lo, hi) - 0.10) < 0.003
    assert ev.ratio_percentile(0.0) == 0.0 and ev.ratio_percentile(1e3) == 1.0
    # No rescaled prediction keeps more of one capture's ratio inside a band than the best scale:
    # scanning scales by brute force finds the same optimum, and it is at least the RMS's own.
    best, scale = ev.best_band_probability(0.6, 1.5)
    scan = [1.0 - ev.outside_probability(0.6 * c, 1.5 * c) for c in np.linspace(0.5, 1.5, 201)]
    assert abs(best - max(scan)) < 0.002 and best >= 1.0 - ev.outside_probability(0.6, 1.5) - 1e-12
    inside = 1.0 - ev.outside_probability(0.6 * scale, 1.5 * scale)
    assert abs(inside - best) < 2e-4  # round-off may move the two draws on its ends
    assert 0.5 < scale < 1.2 and best < 0.999
    # Its mean square is the prediction's: E[sum(lam z^2)] = ee_rms^2.
    assert np.isclose(ev.error_eigenvalues.sum(), ev.ee_rms**2, rtol=1e-6)


def test_the_objective_gradient_matches_finite_differences(ur5e):
    *_, scene = ur5e
    configs = random_configurations(jax.random.key(0), 100, 6)
    q = jnp.asarray(POSES)
    t = jnp.arange(len(POSES), dtype=float)
    idx = np.flatnonzero(evaluate_views(scene, POSES, np.asarray(t), np.asarray(configs), sweeps=False).free)
    M = ee_gram(ee_jacobians(scene, configs), idx, design(scene, False).layout.size)

    @jax.jit
    def f(q):
        return jnp.log(ee_mean_square(free_jacobian(corner_problem(scene, q, t), idx), M, 0.05))

    g = jax.jit(jax.grad(f))(q)
    h = 1e-6
    for v, j in ((0, 1), (3, 4), (7, 5), (11, 2)):
        e = np.zeros(q.shape)
        e[v, j] = h
        fd = (f(q + e) - f(q - e)) / (2 * h)
        assert np.isclose(float(g[v, j]), float(fd), rtol=1e-4, atol=1e-7)


def test_feasibility_names_the_failing_check_and_corrects_toward_the_taught_pose(ur5e):
    robot, _, _, scene = ur5e
    lim = FeasibilityLimits()
    bad = np.array(
        [
            [0.0, 0.0, 0.0, 0.0, 0.0, 7.0],  # beyond the URDF limit of 2 pi
            [0.0, 0.0, 0.0, 0.0, np.radians(80), 0.0],  # the plate turned away: 80 deg view angle
            [0.0, np.radians(-60), 0.0, 0.0, 0.0, 0.0],  # the plate lifted out of the image
            [0.0, np.radians(90), 0.0, 0.0, 0.0, 0.0],  # the arm through the floor
        ]
    )
    m = np.asarray(all_margins(scene, lim, jnp.asarray(bad)))
    first = [CHECKS[int(np.argmax(row <= 0))] for row in m]
    assert first[:3] == ["joint_limits", "view_angle", "in_image"] and first[3] == "scene_collision"
    q, frac, why = correct_toward(scene, lim, np.zeros(6), bad)
    assert why == first
    assert np.all((frac > 0) & (frac < 1))  # each moved part of the way back, then passed
    assert np.all(np.asarray(all_margins(scene, lim, jnp.asarray(q))) > 0)
    assert np.allclose(q, frac[:, None] * bad)  # along the line to the taught pose (zero)
    fixed, _, _ = correct_toward(scene, lim, np.zeros(6), POSES)
    again, frac_ok, why_ok = correct_toward(
        scene, lim, np.zeros(6), fixed
    )  # feasible frames stay as they are
    assert np.all(frac_ok == 1.0) and why_ok == [None] * len(POSES) and np.array_equal(again, fixed)


def test_capsules_are_conservative_against_mujoco_contacts(ur5e):
    from jaxcal.sim.plan import MujocoChecker

    robot, _, _, scene = ur5e
    q = np.asarray(jax.random.uniform(jax.random.key(3), (300, 6), minval=-np.pi, maxval=np.pi))
    m = np.asarray(all_margins(scene, FeasibilityLimits(clearance=0.0), jnp.asarray(q)))
    jax_hits = (m[:, CHECKS.index("self_collision")] <= 0) | (m[:, CHECKS.index("scene_collision")] <= 0)
    mj_hits = np.array([r is not None for r in MujocoChecker(_plan(ur5e))(q, path=True)])
    assert mj_hits.sum() > 50  # the sample does collide
    assert not np.any(mj_hits & ~jax_hits)  # whatever MuJoCo finds, the capsules found
    assert (jax_hits & ~mj_hits).mean() < 0.1  # and not much more


def test_greedy_selection_matches_brute_force_for_two_frames(ur5e):
    *_, scene = ur5e
    ev = evaluate_views(scene, POSES, np.arange(12.0), np.zeros((1, 6)), sweeps=False)
    idx = np.flatnonzero(ev.free)[:10]  # a few parameters: two frames identify them
    B = np.asarray(view_blocks(scene, jnp.asarray(POSES[:6]), idx))
    s = np.sqrt(np.einsum("mrf,mrf->f", B, B) / len(B))
    Bs = B / s
    prior = 1e-6 * B.shape[1] * np.eye(len(idx))
    first = max(range(6), key=lambda v: np.linalg.slogdet(prior + Bs[v].T @ Bs[v])[1])
    sel = np.asarray(greedy_d_optimal(jnp.asarray(B), 2))
    assert sel[0] == first
    second = max((v for v in range(6) if v != first),
                 key=lambda v: np.linalg.slogdet(prior + Bs[first].T @ Bs[first] + Bs[v].T @ Bs[v])[1])  # fmt: skip
    assert sel[1] == second
    best_pair = max(combinations(range(6), 2),
                    key=lambda p: np.linalg.slogdet(prior + sum(Bs[v].T @ Bs[v] for v in p))[1])  # fmt: skip
    assert set(sel) == set(best_pair)


def test_plan_files_round_trip_and_refuse_unknown_fields_and_wrong_types(ur5e, tmp_path):
    p = _plan(ur5e)
    path = save_plan(p, tmp_path / "plan.json")
    back = load_plan(path)
    assert plan_to_dict(back) == plan_to_dict(p)
    q, t, seg = back.views()
    assert np.array_equal(q, POSES) and np.all(np.diff(t) > 0) and np.all(seg == 0)
    d = plan_to_dict(p)
    d["segments"][0]["pose"] = d["segments"][0]["poses"][0]
    with pytest.raises(PlanFileError, match=r"segments\[0\]: unknown field 'pose'"):
        plan_from_dict(d)
    d = plan_to_dict(p)
    d["segments"][0]["pose"] = d["segments"][0].pop("poses")  # a typo: missing and unknown, both said
    with pytest.raises(PlanFileError, match=r"segments\[0\]: missing field 'poses' \(unknown field 'pose'\)"):
        plan_from_dict(d)
    d = plan_to_dict(p)
    d["target"]["spec"]["squares"] = [5]
    with pytest.raises(
        PlanFileError, match=r"squares: expected two whole numbers \[columns, rows\], got \[5\]"
    ):
        plan_from_dict(d)
    d = plan_to_dict(p)
    d["camera"]["width"] = "wide"
    with pytest.raises(Exception, match=r"camera.width: expected an integer"):
        plan_from_dict(d)
    d = plan_to_dict(p)
    d["segments"][0]["poses"][3] = [0.0] * 5
    (tmp_path / "bad.json").write_text(json.dumps(d))
    with pytest.raises(PlanFileError, match=r"bad.json: segments\[0\].poses"):
        load_plan(tmp_path / "bad.json")
    # A URDF path that does not resolve from the plan file's folder: the file, the field, where it looked.
    d = plan_to_dict(p)
    d["robot"] = "../../robots/ur5e.urdf"
    (tmp_path / "moved.json").write_text(json.dumps(d))
    with pytest.raises(
        PlanFileError, match=r"moved.json: field 'robot': '../../robots/ur5e.urdf' .* \(looked for "
    ):
        load_plan(tmp_path / "moved.json")


def test_sweep_plans_film_what_the_simulator_films():
    from jaxcal.sim.motion import joint_sweeps

    p = sweep_plan("ur5e", frames_per_joint=10, range_deg=60.0)
    q, t, seg = p.views()
    m = p.motion()
    traj = joint_sweeps(p.joints, 60.0, sweep_s=10 / 30.0)
    assert [s[0] for s in m.segments] == list(p.joints) and len(q) == 60
    for k in range(6):  # the same configurations at the same place in each sweep
        a = q[seg == k]
        s0 = traj.segments[k]
        b = traj(s0.start + (s0.end - s0.start) / 10 * (np.arange(10) + 0.5))
        assert np.allclose(a, b, atol=1e-12)


def test_bad_input_is_refused_with_exit_code_2_and_nothing_written(ur5e, tmp_path, capsys):
    out = tmp_path / "plan.json"
    assert main(["plan", "--frames", "1", "--out", str(out), "--config", "no-mujoco=true"]) == 2
    assert "too few to identify anything" in capsys.readouterr().err and not out.exists()
    assert (
        main(
            [
                "plan",
                "--region",
                "3,3,3,4,4,4",
                "--frames",
                "24",
                "--out",
                str(out),
                "--config",
                "no-mujoco=true",
            ]
        )
        == 2
    )
    assert "give a region the arm can reach" in capsys.readouterr().err and not out.exists()
    bad = plan_to_dict(_plan(ur5e))
    bad["segments"][0]["speed_rad"] = 1.0
    (tmp_path / "bad.json").write_text(json.dumps(bad))
    assert main(["plan", "--evaluate", str(tmp_path / "bad.json"), "--json", str(out)]) == 2
    assert "unknown field 'speed_rad'" in capsys.readouterr().err and not out.exists()
    robot, camera, target, _ = ur5e
    away = camera.T_mount_cam.copy()
    away[:3, :3] = away[:3, :3] @ np.diag([-1.0, 1.0, -1.0])  # turned round: looks away from the arm
    blind = type(camera)(camera.name, camera.width, camera.height, camera.K, camera.distortion, "world", away)
    with pytest.raises(CameraViewError, match="taught pose"):
        jaxcal.plan("ur5e", camera=blind, target=target, frames=24)
    with pytest.raises(BudgetTooSmallError):
        jaxcal.plan("ur5e", frames=2)
    with pytest.raises(UnreachableRegionError):
        jaxcal.evaluate_plan(_plan(ur5e), region=([2.0, 2.0, 2.0], [3.0, 3.0, 3.0]))
    with pytest.raises(UnreachableRegionError, match="wholly below the floor at z = -0.6 m"):
        jaxcal.evaluate_plan(_plan(ur5e), region=([-0.5, -0.5, -0.9], [0.5, 0.5, -0.7]))
    assert (
        main(["plan", "--robot", "scara", "--frames", "24", "--out", str(out), "--config", "no-mujoco=true"])
        == 2
    )
    assert "['joint3'] are prismatic" in capsys.readouterr().err and not out.exists()


CAMERA_YAML = """camera_name: side
camera_matrix: [[1400, 0, 959.5], [0, 1400, 539.5], [0, 0, 1]]
distortion_coefficients: {rows: 1, cols: 5, data: [-0.05, 0.01, 0, 0, 0]}
image_width: 1920
image_height: 1080
T_base_cam: [[1, 0, 0, 0.1], [0, 1, 0, 0.2], [0, 0, 1, 0.3], [0, 0, 0, 1]]
"""


def test_camera_files_plain_yaml_ros_or_opencv_every_field_checked(tmp_path):
    """A camera file as a user writes it (plain YAML lists, ROS camera_info's {rows, cols, data})
    reads as OpenCV's own format does; a value the plan file would refuse is refused here,
    naming the file and the field (a traceback or a plan written and refused later, before)."""
    plain = tmp_path / "plain.yaml"
    plain.write_text(CAMERA_YAML)
    cam = read_camera(plain, "flange")
    fs = cv2.FileStorage(str(tmp_path / "cv.yaml"), cv2.FILE_STORAGE_WRITE)
    fs.write("camera_matrix", np.array([[1400, 0, 959.5], [0, 1400, 539.5], [0, 0, 1]]))
    fs.write("distortion_coefficients", np.array([[-0.05, 0.01, 0, 0, 0]]))
    fs.write("T_base_cam", np.array([[1, 0, 0, 0.1], [0, 1, 0, 0.2], [0, 0, 1, 0.3], [0, 0, 0, 1.0]]))
    fs.write("image_width", 1920)
    fs.write("image_height", 1080)
    fs.write("camera_name", "side")
    fs.release()
    opencv = read_camera(tmp_path / "cv.yaml", "flange")
    assert cam.mount == opencv.mount == "world" and (cam.width, cam.height) == (1920, 1080)
    assert np.array_equal(cam.K, opencv.K) and np.array_equal(cam.distortion, opencv.distortion)
    assert np.array_equal(cam.T_mount_cam, opencv.T_mount_cam) and cam.distortion[0] == -0.05
    bad = {
        "camera_matrix: [[1400, 0, 959.5], [0, 1400, 539.5], [0, 0, 0]]": "'camera_matrix': expected a pinhole",
        "camera_matrix: [1400, 0, 959.5, 0, 1400, 539.5, 0, 0, 1]": "'camera_matrix': expected a 3x3 matrix",
        "camera_matrix: [[-1400, 0, 959.5], [0, 1400, 539.5], [0, 0, 1]]": "fx, fy > 0",
        "image_width: wide": "'image_width': expected a whole number of pixels, got 'wide'",
        "image_width: 1920.7": "'image_width': expected a whole number",
        "image_width: 0": "'image_width': expected 1 to 65535",
        "T_flange_cam: [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]": "give one camera pose",
        "T_base_cam: [[2, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]": "'T_base_cam': not a rigid",
        "distortion_coefficients: [0, 0, 0, 0, 0, 0, 0, 0]": "expected 5 numbers",
        "T_base_cam: [[1, 0, 0, 100], [0, 1, 0, 200], [0, 0, 1, 300], [0, 0, 0, 1]]": "millimetres given as metres",
        "camera_matrix: [[1400, 0, 959.5], [0, 1400, .nan], [0, 0, 1]]": "not finite",
    }
    for i, (line, match) in enumerate(bad.items()):
        key = line.split(":")[0]
        text = (
            "\n".join(x for x in CAMERA_YAML.splitlines() if not x.startswith(key + ":")) + "\n" + line + "\n"
        )
        path = tmp_path / f"bad{i}.yaml"
        path.write_text(text)
        with pytest.raises(PlanFileError, match=re.escape(match)) as e:
            read_camera(path, "flange")
        assert str(path) in str(e.value)
    (tmp_path / "prose.yaml").write_text("This is: not: a camera\n")
    (tmp_path / "broken.yaml").write_text("%YAML:1.0\ncamera_matrix: [[1, 2], oops\n")
    for name in ("prose.yaml", "broken.yaml"):
        with pytest.raises(PlanFileError, match=name):
            read_camera(tmp_path / name, "flange")


def test_plan_command_never_writes_over_inputs_or_existing_files(ur5e, tmp_path, capsys):
    """`--evaluate P --json P` replaced the plan, `--plot` any file, and `plan --overwrite --out`
    its own camera or target file; each is now exit 2 with the input unchanged. A plan's joint
    values outside the robot's limits are refused (they were evaluated and rendered), and a
    URDF path in a plan is read relative to the plan file."""
    plan_path, other = tmp_path / "plan.json", tmp_path / "notes.txt"
    save_plan(_plan(ur5e), plan_path)
    other.write_text("keep me")
    before = plan_path.read_bytes()
    for argv in (
        ["--json", str(plan_path)],
        ["--plot", str(plan_path), "--overwrite"],
        ["--plot", str(other)],
        ["--out", str(tmp_path / "new.json")],
    ):
        assert main(["plan", "--evaluate", str(plan_path), *argv]) == 2, argv
        err = capsys.readouterr().err
        assert "never writes over its inputs" in err or "exists" in err or "--out writes a new plan" in err
    assert plan_path.read_bytes() == before and other.read_text() == "keep me"
    assert not (tmp_path / "new.json").exists()
    camera = tmp_path / "camera.yaml"
    camera.write_text(CAMERA_YAML)
    cam_before = camera.read_bytes()
    argv = [
        "plan",
        "--camera-file",
        str(camera),
        "--frames",
        "24",
        "--config=no-mujoco=true",
        "--overwrite",
        "--out",
        str(camera),
    ]
    assert main(argv) == 2 and "never writes over its inputs" in capsys.readouterr().err
    assert camera.read_bytes() == cam_before
    argv = [
        "plan",
        "--camera-file",
        str(camera),
        "--eye-in-hand",
        "--frames",
        "24",
        "--out",
        str(tmp_path / "e.json"),
    ]
    assert main(argv) == 2 and "places a fixed camera" in capsys.readouterr().err
    # Joint values outside the limits: a pose, and the taught pose.
    d = plan_to_dict(_plan(ur5e))
    d["segments"][0]["poses"][4][1] = 7.5
    (tmp_path / "outside.json").write_text(json.dumps(d))
    assert main(["plan", "--evaluate", str(tmp_path / "outside.json")]) == 2
    err = capsys.readouterr().err
    assert (
        "outside.json: segments[0] frame 4: joint shoulder_lift_joint = 7.5000 rad is outside its limits"
        in err
    )
    with pytest.raises(PlanFileError, match=r"taught: joint wrist_3_joint"):
        jaxcal.evaluate_plan(replace(_plan(ur5e), taught=np.array([0, 0, 0, 0, 0, 9.0])))
    # A URDF given by a relative path: the plan records it relative to itself and reads it so.
    sub = tmp_path / "plans"
    sub.mkdir()
    urdf = tmp_path / "arm.urdf"
    shutil.copy(robot_path("ur5e"), urdf)
    saved = save_plan(replace(_plan(ur5e), robot=os.path.relpath(urdf)), sub / "p.json")
    assert json.loads(saved.read_text())["robot"] == "../arm.urdf"
    assert Path(load_plan(saved).robot) == urdf.resolve()
    assert plan_robot(load_plan(saved)).model.num_joints == 6


def test_simulate_plan_refuses_options_the_plan_fixes(ur5e, tmp_path, capsys):
    plan_path = save_plan(_plan(ur5e), tmp_path / "plan.json")
    argv = ["simulate-plan", str(plan_path), "--robot", "panda", "--resolution", "640x480"]
    assert main([*argv, "--out", str(tmp_path / "ds")]) == 2
    err = capsys.readouterr().err
    assert f"jaxcal simulate-plan {plan_path}: --robot, --resolution cannot change a plan" in err
    # The camera and arm models are the capture's, not the plan's: they go with it.
    argv = ["simulate-plan", str(plan_path), "--camera-model", "global-shutter", "--arm", "realistic"]
    assert main([*argv, "--robot", "panda", "--out", str(tmp_path / "ds")]) == 2
    assert "--robot cannot change a plan" in capsys.readouterr().err
    assert not (tmp_path / "ds").exists()


def test_simulate_kinds_are_commands_and_the_old_spellings_are_gone(tmp_path, capsys):
    """`simulate --kind tracker` and `simulate --plan` were replaced by `simulate-tracker` and
    `simulate-plan PLAN` (and worked one release more); an image option given to tracker data is
    refused by name, not ignored."""
    for old in (["--kind", "tracker"], ["--plan", str(tmp_path / "plan.json")]):
        with pytest.raises(SystemExit):
            main(["simulate", *old, "--out", str(tmp_path / "a")])
        assert f"takes no option {old[0]}" in capsys.readouterr().err
    assert main(["simulate-tracker", "--out", str(tmp_path / "c"), "--resolution", "640x480"]) == 2
    assert "--resolution: not options of tracker data" in capsys.readouterr().err
    assert not (tmp_path / "a").exists() and not (tmp_path / "c").exists()


def test_negative_numbers_start_a_region_or_a_taught_pose():
    with pytest.raises(PlanFileError, match="millimetres"):
        parse_region("-500,-500,0,500,500,500")
    lo, hi = parse_region("0.5,0.5,0.5,-0.5,-0.5,0")
    assert np.array_equal(lo, [-0.5, -0.5, 0.0]) and np.array_equal(hi, [0.5, 0.5, 0.5])
    from jaxcal.cli import _join_negative_lists

    argv = ["plan", "--region", "-0.5,-0.5,0,0.5,0.5,0.5", "--taught", "-1.2,0,0,0,0,0", "--frames", "-5"]
    assert _join_negative_lists(argv) == [
        "plan", "--region=-0.5,-0.5,0,0.5,0.5,0.5", "--taught=-1.2,0,0,0,0,0", "--frames", "-5"
    ]  # fmt: skip


@pytest.mark.slow
def test_cli_evaluates_a_plan_file_with_the_spread_of_one_capture(ur5e, tmp_path, capsys):
    plan_path, out, png = tmp_path / "plan.json", tmp_path / "prediction.json", tmp_path / "ee.png"
    save_plan(_plan(ur5e), plan_path)
    before = plan_path.read_bytes()
    assert main(["plan", "--evaluate", str(plan_path), "--json", str(out), "--plot", str(png)]) == 0
    assert plan_path.read_bytes() == before and png.stat().st_size > 10_000
    text = capsys.readouterr().out
    figures = json.loads(out.read_text())
    ev = jaxcal.evaluate_plan(_plan(ur5e))
    assert (
        figures["ee_rms_mm"] == pytest.approx(1e3 * ev.ee_rms, rel=1e-9) and figures["unidentifiable"] == []
    )
    lo, hi = figures["one_capture_ee_rms_mm_90"]
    median = figures["one_capture_ee_rms_mm_median"]
    # The median capture comes out below the RMS (the distribution is skewed to small errors).
    assert lo < median < figures["ee_rms_mm"] < hi
    assert median == pytest.approx(1e3 * ev.ee_rms * ev.ratio_quantile(0.5))
    assert abs(ev.ratio_percentile(1e-3 * median) - 0.5) < 0.002
    assert "one capture's EE RMS mm" in text and f"{median:.4f} median" in text
    assert 0.1 < figures["outside_0.6_1.5_probability"] < 0.4
    # Frames that fail the checks are counted and the first's reason named, on the console and in the
    # JSON, not silently dropped: 4 of these 12 (the demo's camera does not see them whole) ...
    assert figures["frames_infeasible"] == len(POSES) - figures["frames"] > 0
    assert "frames left out" in text and figures["infeasible_note"].startswith("4 of its 12 frames fail")
    # ... and more of them on a UR3 (same joint names, a smaller arm).
    d = plan_to_dict(_plan(ur5e))
    d["robot"] = "ur3"
    (tmp_path / "ur3.json").write_text(json.dumps(d))
    ev3 = jaxcal.evaluate_plan(tmp_path / "ur3.json")
    assert (
        ev3.frames + ev3.frames_infeasible == len(POSES)
        and ev3.frames_infeasible > figures["frames_infeasible"]
    )
    assert ev3.infeasible_note.startswith(f"{ev3.frames_infeasible} of its {len(POSES)} frames fail")
    assert "robot 'ur3'" in ev3.infeasible_note and "planned for this robot" in ev3.infeasible_note
    counts = re.findall(r"(joint_limits|self_collision|scene_collision|distance|view_angle|[a-z_]+) (\d+)[,;]",
                        ev3.infeasible_note)  # fmt: skip
    assert sum(int(n) for _, n in counts) == ev3.frames_infeasible, (
        ev3.infeasible_note
    )  # every frame, per check
    # Most of a plan's frames left out: the figures are another capture's, and the exit status says so.
    away = [[3.0, -0.2 * k, 0.1 * k, 0.0, 0.0, 0.0] for k in range(7)]  # the target turned from the camera
    d["robot"], d["segments"][0]["poses"] = "ur5e", d["segments"][0]["poses"] + away
    (tmp_path / "folded.json").write_text(json.dumps(d))
    capsys.readouterr()
    assert main(["plan", "--evaluate", str(tmp_path / "folded.json")]) == 3
    assert "most of the plan's frames fail the feasibility checks" in capsys.readouterr().out


def test_an_eye_in_hand_plan_is_rendered_and_calibrated(tmp_path):
    """Pose-based eye-in-hand (item 2): planned, rendered, calibrated from the nominal robot."""
    from jaxcal.sim.plan import MujocoChecker, render_plan

    res = jaxcal.plan("ur5e", eye_in_hand=True, frames=40, steps=10, candidates=300, resolution=(640, 480),
                      checker_factory=MujocoChecker)  # fmt: skip
    p = res.plan
    assert p.eye_in_hand and p.frames >= 38 and res.evaluation.unidentifiable == []
    ds = render_plan(p, tmp_path / "ds", seed=2, progress=False)
    meta = json.loads((ds / "metadata.json").read_text())
    assert meta["x_plan"] == "plan.json" and plan_to_dict(load_plan(ds / "plan.json")) == plan_to_dict(p)
    assert all(m["joint"] is None and m["x_plan_kind"] == "poses" for m in meta["motion"])
    r = jaxcal.calibrate(ds, progress=False, workers=1)
    v = r.validation
    assert r.kind.eye_in_hand and not r.kind.has_arcs and r.status == "ok"
    assert r.frames["target_found"] >= 0.95 * r.frames["images"]
    predicted = 1e3 * res.evaluation.ee_rms
    assert v["ee_rms_mm_before"] > 3.0 and v["ee_rms_mm_after"] < 3.0 * predicted
    # Its tables: no empty sweeps table, and the middle column is what it is, the closed-form start.
    from rich.console import Console

    from jaxcal.cli._calibrate_run import _calibration_tables

    console = Console(record=True, width=160)
    _calibration_tables(console, r)
    text = console.export_text()
    assert "Joint sweeps" not in text and "start (closed form)" in text and "two-stage" not in text
