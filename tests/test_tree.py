"""Kinematic trees (issue 51): branched robot files with coupled joints, their forward kinematics,
and the calibration of a humanoid upper body from both hands measured at once.

The forward kinematics is checked against yourdfpy (which implements `<mimic>`) on a robot
file written by others (`data/robots/trees/panda_arm_hand.urdf`) and on the synthetic upper
body; the hand-written Jacobian of the tree fit against autodiff; the fit against a simulated
body bent by gravity, whose truth it must recover within its standard deviations.
"""

import dataclasses
import json
import re
import shutil
import xml.etree.ElementTree as ET
from pathlib import Path

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
import yourdfpy

from jaxcal import _treefit as tf
from jaxcal import trees
from jaxcal._dh import dh_table, table_forward_kinematics
from jaxcal._kinematics import forward_kinematics
from jaxcal._npgeom import rotvec_to_matrix
from jaxcal._tree import branch, tip_poses, tree_frames
from jaxcal._treefit import TreeSamples
from jaxcal._treelayout import tree_layout
from jaxcal.cli import main
from jaxcal.io.tree_dataset import load_tree_dataset, write_tree_dataset
from jaxcal.io.urdf import load_urdf
from jaxcal.io.urdf_tree import actuated_limits, load_urdf_tree, save_urdf_tree
from jaxcal.sim.humanoid import (
    compliance_z,
    elastic_truth,
    perturb_tree,
    random_poses,
    tree_tracker_samples,
    upper_body_urdf,
)
from jaxcal.tree_verification import load_tree_calibration
from jaxcal.trees import calibrate_tree, read_tree_samples, save_tree_calibration

ROOT = Path(__file__).resolve().parents[1]
PANDA_HAND = ROOT / "data" / "robots" / "trees" / "panda_arm_hand.urdf"
HANDS = ["left_hand", "right_hand"]


@pytest.fixture(scope="module")
def body(tmp_path_factory):
    path = tmp_path_factory.mktemp("body") / "upper_body.urdf"
    path.write_text(upper_body_urdf())
    return path


def _agrees_with_yourdfpy(path: Path, tree, seed: int) -> float:
    robot = yourdfpy.URDF.load(str(path), load_meshes=False)
    limits = actuated_limits(path, tree)
    worst = 0.0
    for q in random_poses(limits, 5, np.random.default_rng(seed)):
        robot.update_cfg(dict(zip(tree.actuated_names, q)))
        ours = np.asarray(tip_poses(tree, jnp.asarray(q)))
        for t, name in enumerate(tree.tip_names):
            worst = max(worst, float(np.abs(robot.get_transform(name, tree.link_names[0]) - ours[t]).max()))
    return worst


def test_tree_forward_kinematics_matches_yourdfpy_on_a_robot_file_written_by_others():
    """Franka's arm and hand: two fingers (two tips), the second a prismatic mimic of the first."""
    tree = load_urdf_tree(PANDA_HAND)
    assert tree.tip_names == ("panda_leftfinger", "panda_rightfinger")
    assert tree.actuated_names[-1] == "panda_finger_joint1" and tree.num_joints == tree.num_actuated + 1
    assert [tree.joint_names[j] for j in tree.coupled] == ["panda_finger_joint2"]
    assert _agrees_with_yourdfpy(PANDA_HAND, tree, seed=0) < 1e-12


def test_upper_body_forward_kinematics_and_its_branches(body):
    tree = load_urdf_tree(body)
    assert set(tree.tip_names) == {"camera", "left_hand", "right_hand"}
    assert [tree.joint_names[j] for j in tree.coupled] == ["torso_upper_pitch"]
    assert _agrees_with_yourdfpy(body, tree, seed=1) < 1e-12
    # The branch to a hand is a serial chain whose coupled joint follows the law.
    chain, C = branch(tree, "left_hand")
    assert chain.joint_names[:4] == ("torso_yaw", "torso_pitch", "torso_roll", "torso_upper_pitch")
    q = np.random.default_rng(2).uniform(-0.3, 0.3, tree.num_actuated)
    hand = np.asarray(tip_poses(tree, jnp.asarray(q)))[tree.tip_names.index("left_hand")]
    assert np.abs(np.asarray(forward_kinematics(chain, jnp.asarray(C @ q)))[-1] - hand).max() < 1e-12
    # Gravity: every link's mass is carried into the tree once.
    assert float(np.asarray(tree.masses).sum()) == pytest.approx(43.0)


def test_urdf_tree_round_trip_keeps_structure_and_mimic(body, tmp_path):
    nominal = load_urdf_tree(body)
    true = perturb_tree(nominal, np.random.default_rng(3))
    out = tmp_path / "written.urdf"
    before = body.read_bytes()
    save_urdf_tree(true, out, source=body)
    assert body.read_bytes() == before  # the source is never touched
    back = load_urdf_tree(out)
    # Zero offsets are turned into the origins (and a coupled joint's into its law's offset):
    # every URDF reader, yourdfpy here, then sees the calibrated robot.
    robot = yourdfpy.URDF.load(str(out), load_meshes=False)
    for q in random_poses(actuated_limits(body, nominal), 4, np.random.default_rng(4)):
        ours = np.asarray(tree_frames(true, jnp.asarray(q)))
        assert np.abs(np.asarray(tree_frames(back, jnp.asarray(q))) - ours).max() < 1e-12
        robot.update_cfg(dict(zip(true.actuated_names, q)))
        for t, name in enumerate(true.tip_names):
            assert (
                np.abs(
                    robot.get_transform(name, "pelvis") - np.asarray(tip_poses(true, jnp.asarray(q)))[t]
                ).max()
                < 1e-12
            )
    assert np.abs(np.asarray(back.zero_offset)).max() == 0.0
    assert (back.parent, back.joint_names, back.tip_names) == (true.parent, true.joint_names, true.tip_names)
    mimic = ET.parse(out).getroot().find("joint[@name='torso_upper_pitch']/mimic")
    assert mimic.get("joint") == "torso_pitch"
    assert float(mimic.get("multiplier")) == pytest.approx(float(true.coupling[3, 1]), abs=1e-15)
    # A source that is not this tree's robot file is refused, naming what differs.
    other = tmp_path / "other.urdf"
    other.write_text(upper_body_urdf().replace('mimic joint="torso_pitch"', 'mimic joint="torso_roll"'))
    with pytest.raises(ValueError, match="not this tree's robot file: its mimic joints follow other joints"):
        save_urdf_tree(true, tmp_path / "never.urdf", source=other)
    # The fixed shoulder mounts stay as they were: the arms' origins are written below them.
    mount = ET.parse(out).getroot().find("joint[@name='left_shoulder_mount_joint']/origin")
    assert mount.get("rpy") == ET.parse(body).getroot().find(
        "joint[@name='left_shoulder_mount_joint']/origin"
    ).get("rpy")


def test_tree_files_refuse_what_they_cannot_hold_by_name(body, tmp_path):
    with pytest.raises(ValueError, match=r"torso_upper_pitch.*mimics another joint.*load_urdf_tree"):
        load_urdf(body, tip_link="left_hand")
    bad = tmp_path / "bad.urdf"
    bad.write_text(upper_body_urdf().replace('mimic joint="torso_pitch"', 'mimic joint="torso_pich"'))
    with pytest.raises(ValueError, match=r"bad.urdf.*torso_upper_pitch.*mimics 'torso_pich'"):
        load_urdf_tree(bad)
    with pytest.raises(ValueError, match=r"tip link\(s\) \['left_foot'\]"):
        load_urdf_tree(body, tips=["left_hand", "left_foot"])


def _problem(body, seed, poses, noise_mm=0.1, test=0):
    nominal = load_urdf_tree(body, tips=HANDS)
    limits = actuated_limits(body, nominal)
    rng = np.random.default_rng(seed)
    true, elastic = perturb_tree(nominal, rng), elastic_truth(nominal, rng)
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = rotvec_to_matrix(np.array([0.0, 0.0, np.pi])), [2.0, 0.1, -0.4]
    points = np.array([[0.02, 0.0, -0.01]] * 2) + 2e-3 * rng.standard_normal((2, 3))
    q = random_poses(limits, poses + test, rng)
    samples = tree_tracker_samples(true, q, points, T, rng, noise_mm=noise_mm, elastic=elastic)
    return nominal, limits, elastic, samples.subset(slice(0, poses)), samples.subset(slice(poses, None))


#: The residuals' Jacobian by forward-mode autodiff through the whole body (compiled: run op by op
#: it costs more than its compilation).
AUTODIFF_JACOBIAN = eqx.filter_jit(jax.jacfwd(tf._residuals_autodiff))


def test_tree_jacobian_matches_autodiff(body):
    """Exact, for a rigid body and a sagging one: the gravity torques move with the geometry."""
    nominal, _, _, samples, _ = _problem(body, seed=4, poses=12)
    layout = tree_layout(nominal)
    problem = tf.problem_of(nominal, layout, samples, np.eye(4), np.zeros((2, 3)), 0.1)
    u = jnp.asarray(np.random.default_rng(5).standard_normal(layout.size))
    rigid = u.at[layout.slices["joint"]].set(0.0).at[layout.slices["lateral"]].set(0.0)
    args = (jnp.ones(layout.size), 1.0, problem)
    for point in (rigid, 0.3 * u):
        r, J = tf._residuals_terms(point, args)
        J_auto = AUTODIFF_JACOBIAN(point, args)
        assert np.abs(np.asarray(r - tf._residuals_autodiff(point, args))).max() < 1e-9
        scale = np.abs(np.asarray(J_auto)).max(axis=0) + 1e-9
        assert (np.abs(np.asarray(J - J_auto)).max(axis=0) / scale).max() < 1e-8


def test_upper_body_calibration_recovers_geometry_and_elasticity(body, tmp_path):
    """Both hands measured at 200 poses (0.1 mm): the torso seen through both arms, the
    compliances recovered within their standard deviations, the harmonic the truth lacks left out."""
    nominal, limits, elastic, fit, test = _problem(body, seed=6, poses=200, test=60)
    result = calibrate_tree(
        nominal, fit, noise_mm=0.1, points=[[0.02, 0.0, -0.01]] * 2, limits=limits, show_progress=False
    )
    assert set(result.fit.families) == {"joint", "lateral"}, result.fit.cv_mm
    assert result.status == "ok", result.notes
    held_out = 1e3 * np.linalg.norm(result.predict(test.q) - test.truth, axis=-1).mean()
    assert held_out < 0.07  # the noise is 0.16 mm per point; geometry alone leaves millimetres
    geometric = calibrate_tree(
        nominal, fit, noise_mm=0.1, points=[[0.02, 0.0, -0.01]] * 2, families=(), show_progress=False
    )
    assert 1e3 * np.linalg.norm(geometric.predict(test.q) - test.truth, axis=-1).mean() > 1.0
    assert geometric.status == "suspect"  # its residuals are far above the stated noise
    params = result.parameters()
    z = [v for k, v in compliance_z(result, elastic).items() if k.endswith(".compliance")]
    assert len(z) >= 12 and np.abs(z).max() < 4.0, np.round(z, 1)
    assert result.fit.noise_mm == pytest.approx(0.1, rel=0.15)
    # Both arms' and the torso's parameters are freed; what is held is named by branch.
    assert (
        "torso_roll.zero_offset" in params
        and "left_elbow.zero_offset" in params
        and "right_elbow.zero_offset" in params
    )
    assert "shared" in result.held and all(
        k in ("shared", "device", "unmeasured", *HANDS) for k in result.held
    )
    assert {n.split(".")[0] for n in result.held.get("unmeasured", [])} == {"neck_yaw", "neck_pitch"}
    save_tree_calibration(result, tmp_path / "out", source_urdf=body)
    doc = json.loads((tmp_path / "out" / "tree_result.json").read_text())
    assert doc["terms_kept"] == list(result.fit.families) and doc["status"] == "ok"
    assert doc["coupling"]["torso_upper_pitch"]["torso_pitch"] == pytest.approx(0.5, abs=0.05)
    # Each hand's branch as a modified-DH table whose forward kinematics is the tree's.
    table = json.loads((tmp_path / "out" / "left_hand_mdh.json").read_text())
    assert table["joint_names"][3] == "torso_upper_pitch" and list(table["coupled"]) == ["torso_upper_pitch"]
    # A measured hand's table is calibrated; a never-measured one's (its point held) says so: trial
    # 13 found such a table written like the others.
    assert "measured" not in table and trees.unmeasured_tips(result) == []
    names = ["left_elbow.origin.x", "left_hand.point.x"]
    unseen = dataclasses.replace(result, held={**result.held, "left_hand": names})
    doc = trees.branch_table(unseen, "left_hand")
    assert trees.unmeasured_tips(unseen) == ["left_hand"]
    assert doc["held"] == names and not doc["measured"] and "std 0 means held, not exact" in doc["note"]
    # ... with standard deviations from the fit's covariance: the arm's lengths to tens of microns.
    std_a = np.asarray(table["std"]["a"])
    assert np.isfinite(std_a).all() and 1e-7 < std_a[-3:].max() < 2e-4, std_a
    chain, C = branch(result.tree, "left_hand")
    mdh = dh_table(chain, "mdh", reference=dh_table(branch(nominal, "left_hand")[0], "mdh"))
    assert np.allclose(table["a"], np.asarray(mdh.a), atol=1e-15)
    q = jnp.asarray(C @ test.q[0])
    assert (
        np.abs(
            np.asarray(table_forward_kinematics(mdh, q)) - np.asarray(forward_kinematics(chain, q))[-1]
        ).max()
        < 1e-12
    )
    back = load_urdf_tree(tmp_path / "out" / "calibrated.urdf", tips=HANDS)
    q = jnp.asarray(test.q[0])
    assert np.abs(np.asarray(tip_poses(back, q)) - np.asarray(tip_poses(result.tree, q))).max() < 1e-12
    # The folder read back predicts what the calibration did, a once-per-turn harmonic's phase
    # (which the written origins' zero offsets shift) included.
    harmonic = result.layout.family("harmonic")
    fit = dataclasses.replace(
        result.fit, u=np.where(harmonic, 0.5, result.fit.u), free=result.fit.free | harmonic
    )
    wobbly = dataclasses.replace(result, fit=fit)
    save_tree_calibration(wobbly, tmp_path / "wobbly", source_urdf=body)
    read = load_tree_calibration(tmp_path / "wobbly")
    assert np.abs(read.predict(test.q) - wobbly.predict(test.q)).max() < 1e-9
    # ... and its predictions' covariance, from the saved parameters' covariance, to first order.
    claimed, reread = (np.trace(m.predict_covariance(test.q[:8]), axis1=-2, axis2=-1) for m in (wobbly, read))
    # The twists of the fit (about the nominal body) and of the body read back differ: their
    # right Jacobians relate them (without: up to 88 % off where gravity alone shows the base's tilt).
    assert np.abs(np.sqrt(reread / claimed) - 1.0).max() < 5e-3
    assert np.abs(wobbly.predict(test.q) - result.predict(test.q)).max() > 1e-5  # the harmonic counts
    with pytest.raises(Exception, match="exists|overwrite"):
        save_tree_calibration(result, tmp_path / "out", source_urdf=body)


def test_wrong_centres_of_mass_are_corrected_where_the_sag_sees_them(body):
    """The robot file's centres of mass 3 cm off (1 sigma per axis) and three of its heaviest
    links' masses 30 % low: the sag then follows other torques than the file's, and a fit of the
    compliances alone absorbs it only in part (and says `ok`); the `mass` family's corrections
    take the held-out error back to the noise."""
    nominal = load_urdf_tree(body, tips=HANDS)
    rng = np.random.default_rng(8)
    true, elastic = perturb_tree(nominal, rng), elastic_truth(nominal, rng)
    centres = np.asarray(true.centres) + 0.03 * rng.standard_normal(np.asarray(true.centres).shape)
    masses = np.asarray(true.masses).copy()
    masses[np.argsort(masses)[-6:][::2]] *= 1.3
    true = eqx.tree_at(lambda t: (t.centres, t.masses), true, (jnp.asarray(centres), jnp.asarray(masses)))
    T, points = np.eye(4), np.array([[0.02, 0.0, -0.01]] * 2)
    T[:3, 3] = [2.0, 0.1, -0.4]
    q = random_poses(actuated_limits(body, nominal), 260, rng)
    samples = tree_tracker_samples(true, q, points, T, rng, noise_mm=0.1, elastic=elastic)
    fit, test = samples.subset(slice(0, 200)), samples.subset(slice(200, None))
    error = {}
    for families in (("joint", "lateral"), ("joint", "lateral", "mass")):
        result = calibrate_tree(
            nominal, fit, noise_mm=0.1, points=points, families=families, show_progress=False
        )
        error[families[-1]] = 1e3 * np.linalg.norm(result.predict(test.q) - test.truth, axis=-1).mean()
    assert result.status == "ok" and result.fit.noise_mm < 0.12, result.notes
    assert (result.fit.free & result.layout.family("mass")).sum() >= 20
    assert error["mass"] < 0.09 and error["lateral"] > 3 * error["mass"], error


def test_tree_samples_from_csv_and_bad_input_named(body, tmp_path):
    nominal, limits, _, samples, _ = _problem(body, seed=7, poses=6)
    path = tmp_path / "poses.csv"
    header = list(nominal.actuated_names) + [f"{t}.{a}" for t in HANDS for a in "xyz"]
    rows = [list(q) + list(p.ravel()) for q, p in zip(samples.q, samples.points)]
    rows[2][-3:] = ["", "", ""]  # the right hand not seen in the third row
    path.write_text(",".join(header) + "\n" + "\n".join(",".join(map(str, r)) for r in rows) + "\n")
    read = read_tree_samples(path, nominal)
    assert np.allclose(read.q, samples.q) and read.measured.sum() == 11 and not read.measured[2, 1]
    text = path.read_text().splitlines()
    text[4] = text[4].replace(text[4].split(",")[3], "abc", 1)
    (tmp_path / "bad.csv").write_text("\n".join(text) + "\n")
    with pytest.raises(ValueError, match=r"bad.csv.*line 5, column 'neck_yaw'.*'abc'"):
        read_tree_samples(tmp_path / "bad.csv", nominal)
    # The coupled joint logged beside the others: read when it follows the robot file's law,
    # refused naming the column and the line when it breaks it (a driven joint, or a wrong law).
    j = nominal.joint_names.index("torso_upper_pitch")
    law = samples.q @ np.asarray(nominal.coupling)[j] + float(nominal.coupling_offset[j])
    for factor, ok in ((1.0, True), (1.8, False)):
        logged = [f"{line},{float(factor * v)!r}" for line, v in zip(path.read_text().splitlines()[1:], law)]
        (tmp_path / "coupled.csv").write_text(
            "\n".join([",".join(header) + ",torso_upper_pitch", *logged]) + "\n"
        )
        if ok:
            np.testing.assert_array_equal(read_tree_samples(tmp_path / "coupled.csv", nominal).q, read.q)
        else:
            with pytest.raises(
                ValueError, match=r"column 'torso_upper_pitch' logs a joint the robot file couples"
            ):
                read_tree_samples(tmp_path / "coupled.csv", nominal)
    degrees = samples.subset(slice(0, 6))
    degrees.q[1, 5] = 57.0
    with pytest.raises(
        ValueError, match=r"sample 1: joint 'left_shoulder_pitch' at 57.*outside its limits.*degrees"
    ):
        calibrate_tree(nominal, degrees, limits=limits, show_progress=False)


def test_tree_dataset_from_the_command_line(tmp_path, capsys):
    """`jaxcal simulate-tracker --robot upper_body` writes a tree dataset; `jaxcal calibrate` on it
    writes the tree's outputs and judges them against the simulator's held-out truth; `jaxcal verify`
    checks them on samples they were not fitted on."""
    ds, out = tmp_path / "body", tmp_path / "out"
    code = main(["simulate-tracker", "--robot", "upper_body", "--out", str(ds), "--noise-um", "100",
                 "--config", "random-poses=150", "--seed", "3", "--quiet"])  # fmt: skip
    assert code == 0 and (ds / "tree.json").is_file()
    doc = json.loads((ds / "tree.json").read_text())
    (ds / "tree.json").write_text(json.dumps(doc | {"terms": ["joint", "lateral"]}))
    before = {p.name: p.read_bytes() for p in ds.iterdir() if p.is_file()}
    assert main(["calibrate", str(ds), "--out", str(out), "--quiet"]) == 0
    printed = capsys.readouterr().out
    error = float(printed.split("against the simulator's truth: ")[1].split(" mm")[0])
    assert error < 0.08, printed  # geometry alone leaves millimetres (the test above)
    assert {p.name for p in out.iterdir()} >= {"calibrated.urdf", "tree_result.json", "left_hand_mdh.json"}
    assert {p.name: p.read_bytes() for p in ds.iterdir() if p.is_file()} == before
    # `jaxcal verify` on samples the calibration was not fitted on: the simulator's held-out poses
    # with the tracker's noise hold; with the right hand's reflector moved by 0.5 mm they do not.
    truth, loaded = json.loads((ds / "truth.json").read_text()), load_tree_dataset(ds)
    q, points = np.asarray(truth["test"]["q"]), np.asarray(truth["test"]["points_m"])
    noisy = points + 1e-4 * np.random.default_rng(0).standard_normal(points.shape)
    for name, moved in (("same", 0.0), ("moved", 5e-4), ("right_off", 2.5e-4)):
        write_tree_dataset(
            tmp_path / name, urdf_text=(ds / "robot.urdf").read_text(), tips=doc["tips"], tree=loaded.tree,
            samples=TreeSamples(q, noisy + [[0.0, 0.0, 0.0], [moved, 0.0, 0.0]], np.ones(points.shape[:2], bool)),
            noise_mm=0.1, points=loaded.points,
        )  # fmt: skip
    figures = tmp_path / "verify.json"
    assert main(["verify", str(out), str(tmp_path / "same"), "--json", str(figures)]) == 0
    v = json.loads(figures.read_text())
    assert v["holds"] and 0.8 < v["ratio"] < 1.3, v
    for tip in ("left_hand", "right_hand"):
        assert v["tips"][tip]["calibrated_mean_mm"] < 0.25 < 1.0 < v["tips"][tip]["nominal_mean_mm"]
    assert main(["verify", str(out), str(tmp_path / "moved")]) == 3
    assert "does NOT hold" in capsys.readouterr().out
    # Samples of the robot file's own body (another robot of the model, ideal): the calibration
    # predicts them worse than the robot file, and says what that means.
    model = load_tree_calibration(out)
    rigid = tf.Elastic(np.zeros_like(model.elastic.joint), np.zeros_like(model.elastic.lateral))
    ideal = np.asarray(
        tf.deflected_tips(loaded.tree, rigid, jnp.asarray(q), model.points, model.T_device_root)
    )
    write_tree_dataset(tmp_path / "ideal", urdf_text=(ds / "robot.urdf").read_text(), tips=doc["tips"],
                       tree=loaded.tree, samples=TreeSamples(q, ideal, np.ones(points.shape[:2], bool)),
                       noise_mm=0.1, points=loaded.points)  # fmt: skip
    assert main(["verify", str(out), str(tmp_path / "ideal")]) == 3
    said = " ".join(capsys.readouterr().out.split())
    assert "predicts these samples worse than the robot file does: they are of another robot" in said, said
    # The hands' columns swapped, or the left hand's points a row late: refused at load, naming it.
    late = noisy.copy()
    late[1:, 0] = noisy[:-1, 0]
    for name, wrong, said in (
        ("hands_swapped", noisy[:, ::-1], "the columns left_hand.x, .y, .z and right_hand's are swapped"),
        ("left_late", late, "tip 'left_hand''s points fit the robot file only with the rows shifted"),
    ):
        write_tree_dataset(tmp_path / name, urdf_text=(ds / "robot.urdf").read_text(), tips=doc["tips"],
                           tree=loaded.tree, samples=TreeSamples(q, wrong, np.ones(points.shape[:2], bool)),
                           noise_mm=0.1, points=loaded.points)  # fmt: skip
        with pytest.raises(ValueError, match=re.escape(said)):
            load_tree_dataset(tmp_path / name)
    # The right hand 0.25 mm off: the two hands pooled would hold, the right one alone does not.
    assert main(["verify", str(out), str(tmp_path / "right_off"), "--json", str(figures), "--overwrite"]) == 3
    off = json.loads(figures.read_text())
    assert (
        off["ratio"] <= 1.5 and off["tips"]["left_hand"]["holds"] and not off["tips"]["right_hand"]["holds"]
    )
    assert "tip(s) ['right_hand'] do not hold on their own" in " ".join(capsys.readouterr().out.split())
    # The result file's own path; the tips in another order (or only some of them); joints in
    # degrees refused with a hint; a folder without its tree_result.json refused naming it.
    assert main(["verify", str(out / "tree_result.json"), str(tmp_path / "same")]) == 0
    swapped = TreeSamples(q, noisy[:, ::-1], np.ones(points.shape[:2], bool))
    degrees = TreeSamples(np.rad2deg(q), noisy, np.ones(points.shape[:2], bool))
    for name, tips, samples in (("swapped", doc["tips"][::-1], swapped), ("degrees", doc["tips"], degrees)):
        write_tree_dataset(
            tmp_path / name, urdf_text=(ds / "robot.urdf").read_text(), tips=tips, tree=loaded.tree,
            samples=samples, noise_mm=0.1, points=loaded.points[::-1] if name == "swapped" else loaded.points,
        )  # fmt: skip
    assert main(["verify", str(out), str(tmp_path / "swapped"), "--json", str(figures), "--overwrite"]) == 0
    assert json.loads(figures.read_text())["tips"] == v["tips"]
    assert main(["verify", str(out), str(tmp_path / "degrees")]) == 2
    assert "degrees" in capsys.readouterr().err
    shutil.copytree(out, tmp_path / "no_result")
    (tmp_path / "no_result" / "tree_result.json").unlink()
    assert main(["verify", str(tmp_path / "no_result"), str(tmp_path / "same")]) == 2
    assert "tree_result.json" in capsys.readouterr().err
    # A damaged result file is refused naming the field (exit 2), never taken for a changed robot.
    result = json.loads((out / "tree_result.json").read_text())
    compliance = next(k for k in result["parameters"] if k.endswith(".compliance"))
    typo = dict(result["parameters"])
    typo[compliance.replace("compliance", "complianse")] = typo.pop(compliance)
    for damage, field in (
        ({"T_device": np.eye(3).tolist()}, "T_device"),
        ({"parameters": typo}, "complianse"),
        ({"parameters": result["parameters"] | {compliance: {"value": "soft"}}}, compliance),
    ):
        shutil.copytree(out, tmp_path / "damaged", dirs_exist_ok=True)
        (tmp_path / "damaged" / "tree_result.json").write_text(json.dumps(result | damage))
        assert main(["verify", str(tmp_path / "damaged"), str(tmp_path / "same")]) == 2
        assert field in capsys.readouterr().err
    # Malformed dataset files are refused naming the file and the field (exit 2, nothing written).
    (ds / "tree.json").write_text(json.dumps(doc | {"noise_mm": 0}))
    with pytest.raises(ValueError, match=r"tree.json.*'noise_mm' must be the device's positive noise"):
        load_tree_dataset(ds)
    (ds / "tree.json").write_text(json.dumps(doc | {"terms": ["compliance"]}))
    assert main(["calibrate", str(ds), "--out", str(tmp_path / "never"), "--quiet"]) == 2
    assert "field 'terms'" in capsys.readouterr().err and not (tmp_path / "never").exists()


def test_a_head_camera_seeing_both_hands(body):
    """The device rides on a tip (a head camera measuring both hands' points in its own frame):
    the Jacobian stays exact, the torso (which moves the camera and the hands alike) is held as
    unseen, and the neck and both arms are calibrated to the noise."""
    nominal = load_urdf_tree(body, tips=[*HANDS, "camera"])
    limits = actuated_limits(body, nominal)
    rng = np.random.default_rng(8)
    true, elastic = perturb_tree(nominal, rng), elastic_truth(nominal, rng)
    points = np.array([[0.02, 0.0, -0.01]] * 2 + [[0.0, 0.0, 0.0]])
    q = random_poses(limits, 260, rng)
    samples = tree_tracker_samples(
        true,
        q,
        points + np.array([[1e-3, -2e-3, 1e-3]] * 2 + [[0.0, 0.0, 0.0]]),
        np.eye(4),
        rng,
        noise_mm=0.2,
        elastic=elastic,
        device_tip=2,
    )
    layout = tree_layout(nominal)
    problem = tf.problem_of(
        nominal, layout, samples.subset(slice(0, 8)), np.eye(4), points, 0.2, device_tip=2
    )
    u = jnp.asarray(rng.standard_normal(layout.size))
    rigid = u.at[layout.slices["joint"]].set(0.0).at[layout.slices["lateral"]].set(0.0)
    args = (jnp.ones(layout.size), 1.0, problem)
    for point in (rigid, 0.3 * u):  # rigid, and sagging with the mass corrections
        J, J_auto = tf._residuals_terms(point, args)[1], AUTODIFF_JACOBIAN(point, args)
        assert np.abs(np.asarray(J - J_auto)).max() < 1e-10 * np.abs(np.asarray(J_auto)).max()
    fit, test = samples.subset(slice(0, 200)), samples.subset(slice(200, None))
    result = calibrate_tree(
        nominal, fit, noise_mm=0.2, points=points, device_on="camera", families=("joint", "lateral"),
        limits=limits, show_progress=False,
    )  # fmt: skip
    assert result.status == "ok", result.notes
    error = 1e3 * np.linalg.norm(result.predict(test.q)[:, :2] - test.truth[:, :2], axis=-1).mean()
    assert error < 0.15, error  # 0.2 mm per axis of noise; geometry alone leaves millimetres
    params = result.parameters()
    # (the last neck joint's zero offset turns the camera as its mount does: the mount takes it)
    assert "neck_yaw.zero_offset" in params and "left_elbow.zero_offset" in params
    # The torso moves the camera and both hands alike: only the sag shows it (its tilt against
    # gravity bends the arms), and what of it is freed, to within a typical size.
    size = dict(zip(result.layout.names, result.layout.scales))
    torso = {
        n: sd for n, (_, sd) in params.items() if n.startswith(("torso_yaw.", "torso_pitch.", "torso_roll."))
    }
    assert all(sd < size[n] for n, sd in torso.items()), torso
    assert len(torso) < 6 and any(n.startswith("torso_") for n in result.held["shared"])
    with pytest.raises(ValueError, match="rides on tip 'camera': no sample may measure"):
        bad = samples.subset(slice(0, 5))
        bad.measured[:, 2] = True
        calibrate_tree(nominal, bad, device_on="camera", show_progress=False)


def test_what_a_user_gets_wrong_is_named(body, tmp_path):
    """A new user's mistakes (trial 6): misnamed tip columns, a spreadsheet's byte-order mark, NaN
    cells, too few poses for what is freed, a continuous joint beyond a turn."""
    nominal, limits, _, samples, _ = _problem(body, seed=9, poses=6)
    header = list(nominal.actuated_names) + [f"{t}.{a}" for t in HANDS for a in "xyz"]
    rows = [",".join(map(str, list(q) + list(p.ravel()))) for q, p in zip(samples.q, samples.points)]

    def csv_of(header, rows, name, bom=False):
        path = tmp_path / name
        path.write_text(("\ufeff" if bom else "") + ",".join(header) + "\n" + "\n".join(rows) + "\n")
        return path

    assert read_tree_samples(csv_of(header, rows, "bom.csv", bom=True), nominal).measured.all()
    typo = [h.replace("right_hand", "rigth_hand") for h in header]
    with pytest.raises(ValueError, match=r"typo.csv.*columns for \['rigth_hand'\], which are not tips"):
        read_tree_samples(csv_of(typo, rows, "typo.csv"), nominal)
    with pytest.raises(ValueError, match=r"twice.csv.*\['torso_yaw'\] appear more than once"):
        read_tree_samples(csv_of(header + ["torso_yaw"], [r + ",0" for r in rows], "twice.csv"), nominal)
    nan = [rows[0], rows[1].replace(rows[1].split(",")[-1], "nan")] + rows[2:]
    with pytest.raises(
        ValueError, match=r"nan.csv.*line 3, column 'right_hand.z': 'nan' is not a finite number"
    ):
        read_tree_samples(csv_of(header, nan, "nan.csv"), nominal)
    # Six poses cannot check the 50-odd parameters they would free: suspect, and said why.
    few = calibrate_tree(nominal, samples, families=(), show_progress=False)
    assert few.status == "suspect" and any("too few to check the fit" in n for n in few.notes), few.notes
    # A continuous joint has no limits: four radians is a valid pose.
    loose = tmp_path / "loose.urdf"
    loose.write_text(
        upper_body_urdf().replace(
            'name="left_wrist_roll" type="revolute"', 'name="left_wrist_roll" type="continuous"'
        )
    )
    tree = load_urdf_tree(loose, tips=HANDS)
    lim = actuated_limits(loose, tree)
    assert np.isinf(lim[tree.actuated_names.index("left_wrist_roll")]).all()
    turned = tf.TreeSamples(samples.q.copy(), samples.points, samples.measured)
    turned.q[:, tree.actuated_names.index("left_wrist_roll")] = 4.0
    assert calibrate_tree(tree, turned, families=(), limits=lim, show_progress=False).fit.steps >= 0


def test_the_terms_are_chosen_again_without_the_bad_samples(body, monkeypatch):
    """A cross-validation over samples with gross misreads is swayed by them (each fold's held-out
    error is the misreads'): once they are left out, the terms are chosen again without them."""
    nominal, limits, _, fit, _ = _problem(body, seed=8, poses=80)
    fit = dataclasses.replace(fit, points=fit.points.copy())
    fit.points[[3, 10, 20], 0] += [0.0, 0.0, 0.1]
    seen = []

    def choose(problem, layout):  # the fit cross-validation would keep, and what it was shown
        seen.append(int(np.asarray(problem.weight).sum()))
        return tf.fit_tree(problem, layout, ("joint", "lateral"))

    monkeypatch.setattr(trees, "cross_validate_terms", choose)
    result = calibrate_tree(nominal, fit, noise_mm=0.1, limits=limits, show_progress=False)
    assert seen == [160, 157], seen
    assert result.status == "ok" and "3 of 160 measured points left out" in " ".join(result.notes)


def test_a_tree_is_imported_from_a_csv_in_its_own_units(body, tmp_path, capsys):
    """`jaxcal import-csv --link left_hand,right_hand`: degrees and millimetres, the user's column
    names, a column summed from two, a hand not seen in some rows; what a user gets wrong named."""
    nominal, _, _, samples, _ = _problem(body, seed=9, poses=30)
    names = [f"J{k}" for k in range(nominal.num_actuated)]
    hands = [f"{h}_{a}" for h in ("L", "R") for a in "xyz"]
    points = 1e3 * samples.points
    points[4, 1] = np.nan  # the right hand hidden in row 4
    lines = [",".join([*names, *hands, "R_z_offset"])]
    for q, p in zip(np.degrees(samples.q), points.reshape(len(points), 6)):
        cells = [repr(float(v)) for v in q] + ["" if np.isnan(v) else repr(float(v)) for v in p]
        z = ["", ""] if np.isnan(p[-1]) else [repr(float(p[-1] - 5.0)), "5.0"]  # the right z, summed
        lines.append(",".join([*cells[:-1], *z]))
    table = tmp_path / "poses.csv"
    table.write_text("\n".join(lines) + "\n")
    argv = ["import-csv", str(table), "--robot", str(body), "--link", "left_hand,right_hand", "--joint-unit", "deg",
            "--length-unit", "mm", "--sigma-mm", "0.1", "--joint-columns", ",".join(names)]  # fmt: skip
    xyz = ",".join(hands[:-1] + ["R_z+R_z_offset"])
    assert main([*argv, "--xyz", xyz, "--out", str(tmp_path / "ds")]) == 0
    assert "mm RMS from the robot file's link origins" in capsys.readouterr().out
    ds = load_tree_dataset(tmp_path / "ds")
    assert ds.noise_mm == 0.1 and list(ds.tree.tip_names) == list(HANDS)
    # The dataset's own file edited: one joint past its limit, then every point in millimetres.
    # Refused by line and column (the calibration named "sample 3", counting from 0).
    text = (tmp_path / "ds" / "samples.csv").read_text().splitlines()
    head = text[0].split(",")
    past = list(text)
    cells = past[4].split(",")
    cells[head.index("left_elbow")] = "1.6"
    past[4] = ",".join(cells)
    shutil.copytree(tmp_path / "ds", tmp_path / "past")
    (tmp_path / "past" / "samples.csv").write_text("\n".join(past) + "\n")
    with pytest.raises(
        ValueError, match=r"samples.csv'?: line 5, column 'left_elbow': 1.6 lies outside the robot"
    ):
        load_tree_dataset(tmp_path / "past")
    coords = [k for k, h in enumerate(head) if h.rsplit(".", 1)[-1] in ("x", "y", "z")]
    mm = [text[0]] + [
        ",".join(repr(1e3 * float(c)) if k in coords and c else c for k, c in enumerate(line.split(",")))
        for line in text[1:]
    ]
    shutil.copytree(tmp_path / "ds", tmp_path / "mm")
    (tmp_path / "mm" / "samples.csv").write_text("\n".join(mm) + "\n")
    with pytest.raises(ValueError, match=r"line 2, tip 'left_hand'.*give metres \(millimetres written\?\)"):
        load_tree_dataset(tmp_path / "mm")
    np.testing.assert_allclose(ds.samples.q, samples.q, atol=1e-12)
    seen = ds.samples.measured
    assert seen.sum() == 59 and not seen[4, 1]
    np.testing.assert_allclose(ds.samples.points[seen], samples.points[seen], atol=1e-12)
    wrong = {
        "--joint-unit rad": (["--joint-unit", "rad"], "line 2 column 'J0'.*outside the limits.*degrees"),
        "five --xyz": (["--xyz", ",".join(hands[:5])], "5 columns for 2 links"),
        "a column not there": (["--xyz", xyz.replace("L_y", "L_yy")], "no column \\['L_yy'\\]"),
        "a joint short": (["--joint-columns", ",".join(names[:-1])], "18 columns for the tree's 19 actuated"),
        "--time": (["--time", "J0"], "--time: not options of a tree's import"),
    }
    for what, (extra, message) in wrong.items():
        assert main([*argv, "--xyz", xyz, *extra, "--out", str(tmp_path / "bad")]) == 2, what
        assert re.search(message, capsys.readouterr().err), what
        assert not (tmp_path / "bad").exists()
