"""A head camera films marker plates on both hands of the synthetic upper body (issue 51's
rendered tree capture): the seed's method on a humanoid. MuJoCo renders the bent body, OpenCV
finds the plates and solves their PnP, and the tree fit weighs each plate's origin by the
covariance PnP gives it (a camera sees across far better than in depth)."""

import dataclasses
import json
import shutil

import numpy as np
import pytest

from jaxcal._treefit import TreeSamples
from jaxcal.cli import main
from jaxcal.io.tree_dataset import covariance_noise_mm, load_tree_dataset, write_tree_dataset
from jaxcal.io.urdf_tree import actuated_limits, load_urdf_tree
from jaxcal.sim.head_camera import CAMERA_TIP, film_upper_body, hand_plate, poses_in_view, tree_scene
from jaxcal.sim.humanoid import HANDS, compliance_z, random_poses, tree_tracker_samples, upper_body_urdf
from jaxcal.tree_verification import load_tree_calibration
from jaxcal.trees import calibrate_tree

#: Poses fitted and held out.
FIT, TEST = 150, 40


@pytest.fixture(scope="module")
def filmed():
    """The drawn body filmed at `FIT + TEST` poses, its plates 2 mm off their drawings."""
    return film_upper_body(FIT + TEST, seed=11, show_progress=False)


def test_the_head_camera_calibrates_both_arms_from_rendered_plates(filmed):
    nominal, elastic, capture = filmed.nominal, filmed.elastic, filmed.capture
    samples = capture.samples
    fit, test = samples.subset(slice(0, FIT)), samples.subset(slice(FIT, None))
    seen = fit.measured[:, :2].sum(axis=0)
    assert (seen > 0.7 * FIT).all(), capture.seen  # both plates found in most frames
    # PnP's covariances are honest: the plates' origins scatter about the truth as they say.
    m = samples.measured
    e = (samples.points - samples.truth)[m]
    z2 = np.einsum("na,nab,nb->n", e, np.linalg.inv(samples.covariance[m]), e)
    assert 0.6 < z2.mean() / 3.0 < 1.6, z2.mean() / 3.0
    # A plate misread by 5 cm in depth (a marker taken for another): left out, and named.
    row = int(np.flatnonzero(fit.measured[:, 0])[5])
    fit = dataclasses.replace(fit, points=fit.points.copy())
    fit.points[row, 0] += [0.0, 0.0, 0.05]
    # The body's own terms (cross-validation on 150 poses keeps the lateral compliance alone,
    # and the verdict then names the negative joint stiffnesses it implies: docs/trees.md).
    result = calibrate_tree(
        nominal, fit, points=filmed.points, device_on=CAMERA_TIP, families=("joint", "lateral"),
        limits=filmed.limits,
        show_progress=False,
    )  # fmt: skip
    assert result.status == "ok", result.notes
    assert f"sample {row} tip 'left_hand'" in result.notes[-1], result.notes
    stated = 1e3 * np.sqrt(np.trace(fit.covariance[fit.measured], axis1=1, axis2=2).mean() / 3.0)
    assert 0.7 < result.fit.noise_mm / stated < 1.4  # the residuals are as noisy as PnP said
    predicted, cov = result.predict(test.q), result.predict_covariance(test.q)
    for t, hand in enumerate(HANDS):
        rows = test.measured[:, t]
        e = predicted[rows, t] - test.truth[rows, t]
        error_mm = 1e3 * np.linalg.norm(e, axis=-1).mean()
        assert error_mm < 0.3, (hand, error_mm)  # PnP's depth noise is 0.7-1.3 mm per plate and frame
        # The hands' predicted points lie within the uncertainty the fit claims for them.
        z2 = np.einsum("na,nab,nb->n", e, np.linalg.inv(cov[rows, t]), e)
        assert 0.3 < z2.mean() / 3.0 < 2.0, (hand, z2.mean() / 3.0)
    params = result.parameters()
    z = [v for k, v in compliance_z(result, elastic).items() if k.endswith(".compliance")]
    assert len(z) >= 12 and np.abs(z).max() < 3.0, np.round(z, 1)
    # The torso moves the camera and both hands alike: held, and named as shared, but what the sag
    # shows of it (its tilt against gravity bends the arms), to within a typical size.
    size = dict(zip(result.layout.names, result.layout.scales))
    torso = {n: sd for n, (_, sd) in params.items() if n.startswith("torso_")}
    assert all(sd < size[n] for n, sd in torso.items()) and len(torso) < 6, torso
    assert any(n.startswith("torso_") for n in result.held["shared"]), result.held.keys()
    assert "left_elbow.zero_offset" in params and "right_elbow.zero_offset" in params


def test_covariances_are_checked_and_the_stated_noise_refused_beside_them(tmp_path):
    """Samples carrying their own covariance (a camera's PnP): one of the wrong shape, or not
    positive definite where a point is measured, is refused naming the sample and tip; a
    `noise_mm` given beside them is refused (they are the noise)."""
    path = tmp_path / "upper_body.urdf"
    path.write_text(upper_body_urdf())
    tree = load_urdf_tree(path, tips=[*HANDS, CAMERA_TIP])
    rng = np.random.default_rng(3)
    q = random_poses(actuated_limits(path, tree), 6, rng)
    samples = tree_tracker_samples(tree, q, np.zeros((3, 3)), np.eye(4), rng, device_tip=2)
    good = np.tile(1e-8 * np.eye(3), (6, 3, 1, 1))
    with_cov = lambda c: dataclasses.replace(samples, covariance=c)  # noqa: E731
    run = lambda s, **kw: calibrate_tree(tree, s, device_on=CAMERA_TIP, show_progress=False, **kw)  # noqa: E731
    with pytest.raises(ValueError, match=r"samples.covariance must be \(6, 3, 3, 3\)"):
        run(with_cov(good[:, :2]))
    flat = good.copy()
    flat[2, 1] = np.diag([1e-8, 1e-8, 0.0])
    with pytest.raises(
        ValueError, match="sample 2: the covariance of tip 'right_hand' is not finite and positive"
    ):
        run(with_cov(flat))
    with pytest.raises(ValueError, match="noise_mm is not used"):
        run(with_cov(good), noise_mm=0.1)
    ok = good.copy()  # an unmeasured tip's covariance (the camera's own) is not read
    ok[:, 2] = np.nan
    assert run(with_cov(ok), families=()).status in ("ok", "suspect")


def test_what_a_camera_user_gets_wrong_is_named(filmed):
    """Trial 8's mistakes: covariances in mm^2 for m^2 (overstated: suspect, not a confident
    wrong answer), a tenth of the plates misread (each left out and named, and too many to
    trust: suspect), two plates sharing marker ids, a plate on a link that is not a tip, poses
    of the wrong shape."""
    fit = filmed.capture.samples.subset(slice(0, FIT))
    kw = dict(points=filmed.points, device_on=CAMERA_TIP, families=("joint", "lateral"), show_progress=False)
    mm2 = calibrate_tree(filmed.nominal, dataclasses.replace(fit, covariance=fit.covariance * 1e6), **kw)
    assert mm2.status == "suspect" and "overstated" in mm2.notes[0], mm2.notes
    rng = np.random.default_rng(1)
    misread = dataclasses.replace(fit, points=fit.points.copy())
    rows = rng.choice(np.flatnonzero(misread.measured[:, 0]), FIT // 10, replace=False)
    misread.points[rows, 0, 2] += rng.uniform(0.04, 0.15, len(rows))
    result = calibrate_tree(filmed.nominal, misread, **kw)
    assert result.status == "suspect" and "too many to trust the rest" in result.notes[-1], result.notes
    assert all(f"sample {i} tip 'left_hand'" in result.notes[-1] for i in sorted(rows)[:3]), result.notes
    with pytest.raises(ValueError, match=r"share marker ids \[0, 1, 2, 3\]"):
        tree_scene(filmed.nominal, [hand_plate(HANDS[0], 0), hand_plate(HANDS[1], 0)])
    with pytest.raises(ValueError, match=r"'left_forearm', which is not a tip of the tree: tips are"):
        tree_scene(filmed.nominal, [hand_plate("left_forearm", 0)])
    with pytest.raises(ValueError, match=r"q must be \(poses, 19\)"):
        result.predict_covariance(fit.q[0])
    assert result.predict_covariance(fit.q[:0]).shape == (0, 3, 3, 3)


def test_a_head_camera_dataset_from_the_command_line(tmp_path, capsys):
    """`jaxcal simulate --robot upper_body` writes the head camera's capture as a tree dataset whose
    points carry their PnP covariances; `jaxcal calibrate` weighs them and `jaxcal verify` judges
    the result on held-out poses of the capture, in units of their own covariances."""
    ds = tmp_path / "filmed"
    assert main(["simulate", "--robot", "upper_body", "--out", str(ds), "--resolution", "320x240"]) == 2
    assert "--resolution: not options of the upper body's head-camera capture" in capsys.readouterr().err
    assert main(["simulate", "--robot", "upper_body", "--out", str(ds), "--seed", "5", "--quiet"]) == 0
    filmed = load_tree_dataset(ds)
    cov, measured = filmed.samples.covariance, filmed.samples.measured
    assert cov is not None and filmed.device_on == CAMERA_TIP and not measured[:, 2].any()
    # The stated noise is the covariances' RMS: about a millimetre in depth, a tenth across.
    assert (
        filmed.noise_mm == pytest.approx(covariance_noise_mm(filmed.samples)) and 0.2 < filmed.noise_mm < 1.5
    )
    depth, across = (1e3 * np.sqrt(cov[measured][:, k, k]) for k in (2, 0))
    assert np.median(depth) > 3 * np.median(across)
    # The capture's first 150 poses calibrate, the rest verify (the terms given: no cross-validation).
    urdf, split = (ds / "robot.urdf").read_text(), {"fit": slice(0, 150), "held": slice(150, None)}
    for name, rows in split.items():
        write_tree_dataset(
            tmp_path / name, urdf_text=urdf, tips=filmed.tree.tip_names, tree=filmed.tree,
            samples=filmed.samples.subset(rows), noise_mm=None, points=filmed.points, device_on=CAMERA_TIP,
            truth=filmed.truth,
        )  # fmt: skip
    doc = json.loads((tmp_path / "fit" / "tree.json").read_text())
    assert "noise_mm" not in doc and doc["device_on"] == CAMERA_TIP
    (tmp_path / "fit" / "tree.json").write_text(json.dumps(doc | {"terms": ["joint", "lateral"]}))
    out = tmp_path / "out"
    assert main(["calibrate", str(tmp_path / "fit"), "--out", str(out), "--quiet"]) == 0
    printed = capsys.readouterr().out
    assert "poses measuring left_hand, right_hand: " in printed and "the covariances RMS" in printed, printed
    error = float(printed.split("against the simulator's truth: ")[1].split(" mm")[0])
    assert error < 0.3, printed  # the robot file's geometry leaves 8-14 mm
    figures = tmp_path / "verify.json"
    assert main(["verify", str(out), str(tmp_path / "held"), "--json", str(figures)]) == 0
    v = json.loads(figures.read_text())
    assert v["holds"] and 0.5 < v["ratio"] < 1.6, v
    # A hand's plate moved 2 mm across the picture after the calibration: its points no longer hold.
    held = load_tree_dataset(tmp_path / "held")
    moved = dataclasses.replace(
        held.samples, points=held.samples.points + [[0, 0, 0], [2e-3, 0, 0], [0, 0, 0]]
    )
    write_tree_dataset(tmp_path / "moved", urdf_text=urdf, tips=held.tree.tip_names, tree=held.tree, samples=moved,
                       noise_mm=None, points=held.points, device_on=CAMERA_TIP)  # fmt: skip
    assert main(["verify", str(out), str(tmp_path / "moved")]) == 3
    # One plate misread by 5 cm among the held-out points is named and left out, not held against it.
    misread, row = held.samples.points.copy(), int(np.flatnonzero(held.samples.measured[:, 0])[3])
    misread[row, 0] += [0.0, 0.0, 0.05]
    write_tree_dataset(tmp_path / "misread", urdf_text=urdf, tips=held.tree.tip_names, tree=held.tree,
                       samples=dataclasses.replace(held.samples, points=misread), noise_mm=None,
                       points=held.points, device_on=CAMERA_TIP)  # fmt: skip
    assert main(["verify", str(out), str(tmp_path / "misread"), "--json", str(figures), "--overwrite"]) == 0
    v = json.loads(figures.read_text())
    assert [(x["sample"], x["tip"]) for x in v["left_out"]] == [(row, "left_hand")] and v["holds"], v
    # `jaxcal check`: the held-out poses find no drift; the camera moved 1 mm on its mount afterwards
    # (every point seen 1 mm back along its x) is found, and measured.
    assert main(["check", str(out), str(tmp_path / "held")]) == 0
    shifted = dataclasses.replace(held.samples, points=held.samples.points - [1e-3, 0.0, 0.0])
    write_tree_dataset(tmp_path / "shifted", urdf_text=urdf, tips=held.tree.tip_names, tree=held.tree,
                       samples=shifted, noise_mm=None, points=held.points, device_on=CAMERA_TIP)  # fmt: skip
    drift = tmp_path / "drift.json"
    assert main(["check", str(out), str(tmp_path / "shifted"), "--json", str(drift)]) == 3
    d = json.loads(drift.read_text())
    assert d["detected"] and abs(d["translation_mm"]["size"] - 1.0) < 3 * d["translation_mm"]["std"] + 0.05, d
    assert np.allclose(d["device_translation_m"], [1e-3, 0, 0], atol=3e-4) and d["moved"] == "camera"
    # `jaxcal certify` per hand at the simulator's held-out poses: the error it predicts there is the
    # error the calibration makes against the truth (within the spread of 44 poses' RMS).
    test = filmed.truth["test"]
    poses = tmp_path / "poses.csv"
    poses.write_text(
        ",".join(filmed.tree.actuated_names) + "\n" + "\n".join(",".join(map(repr, q)) for q in test["q"])
    )
    cert = tmp_path / "cert.json"
    assert main(["certify", str(out), "--poses", str(poses), "--json", str(cert)]) == 0
    tips = json.loads(cert.read_text())["tips"]
    assert set(tips) == set(HANDS)
    error = load_tree_calibration(out).predict(test["q"]) - np.asarray(test["points_m"])
    for k, hand in enumerate(HANDS):
        measured = 1e3 * np.sqrt(np.mean(np.sum(error[:, k] ** 2, axis=-1)))
        assert 0.5 < tips[hand]["summary"]["rms_mm"] / measured < 2.0, (hand, tips[hand]["summary"], measured)
        assert tips[hand]["extrapolation"]["share_of_poses_outside_joint_ranges"] < 0.5
    assert main(["certify", str(out), "--plot", str(tmp_path / "map.png")]) == 2
    degrees = tmp_path / "degrees.csv"
    degrees.write_text(
        ",".join(filmed.tree.actuated_names)
        + "\n"
        + "\n".join(",".join(repr(float(v)) for v in np.degrees(q)) for q in test["q"])
    )
    assert main(["certify", str(out), "--poses", str(degrees)]) == 2
    assert "degrees? give --config degrees=true" in capsys.readouterr().err
    # A covariance file that is not the result's (scaled, another calibration's) is refused by name.
    damaged = tmp_path / "damaged"
    shutil.copytree(out, damaged)
    doc = json.loads((damaged / "tree_covariance.json").read_text())
    (damaged / "tree_covariance.json").write_text(
        json.dumps(doc | {"matrix": (1e6 * np.asarray(doc["matrix"])).tolist()})
    )
    assert main(["certify", str(damaged)]) == 2
    assert "the two files are not one calibration's" in capsys.readouterr().err
    # `check` leaves the misread plate out by name, as `verify` does, and finds no drift.
    assert main(["check", str(out), str(tmp_path / "misread")]) == 0
    assert f"sample {row} tip 'left_hand'" in capsys.readouterr().out
    # Samples of another device (a tracker's, fixed) are refused by name, not judged; so are options
    # the upper body's tracker capture does not take.
    tracker = tmp_path / "tracker"
    argv = ["simulate-tracker", "--robot", "upper_body", "--out", str(tracker), "--config", "random-poses=20"]
    assert main([*argv, "--orientation"]) == 2 and not tracker.exists()
    assert "--orientation: not options of the upper body's tracker capture" in capsys.readouterr().err
    assert main([*argv, "--quiet"]) == 0
    assert main(["verify", str(out), str(tracker)]) == 2
    assert "by a device on no tip (fixed); the calibration" in capsys.readouterr().err


def test_covariance_columns_are_read_whole_or_refused_by_name(tmp_path):
    """Each point's covariance in six columns (m^2): all six for every tip or none; a dataset that
    also states `noise_mm` is refused naming the field."""
    nominal = load_urdf_tree(_urdf(tmp_path), tips=list(HANDS))
    q = np.zeros((2, nominal.num_actuated))
    cov = np.tile(np.diag([1e-8, 2e-8, 9e-8]), (2, 2, 1, 1))
    samples = TreeSamples(q, np.ones((2, 2, 3)), np.array([[True, True], [True, False]]), covariance=cov)
    ds = write_tree_dataset(tmp_path / "ds", urdf_text=upper_body_urdf(), tips=list(HANDS), tree=nominal,
                            samples=samples, noise_mm=None, points=np.zeros((2, 3)))  # fmt: skip
    read = load_tree_dataset(ds).samples
    np.testing.assert_array_equal(read.covariance[read.measured], cov[samples.measured])
    assert read.measured.tolist() == samples.measured.tolist()
    text = (ds / "samples.csv").read_text().splitlines()
    header = text[0].split(",")
    cut = header.index("right_hand.cov_zz")
    (ds / "samples.csv").write_text("\n".join(",".join(r.split(",")[:cut]) for r in text) + "\n")
    with pytest.raises(ValueError, match=r"samples.csv.*all six.*right_hand"):
        load_tree_dataset(ds)
    (ds / "samples.csv").write_text("\n".join(text) + "\n")
    doc = json.loads((ds / "tree.json").read_text())
    (ds / "tree.json").write_text(json.dumps(doc | {"noise_mm": 0.1}))
    with pytest.raises(ValueError, match=r"tree.json.*'noise_mm' is given, but the samples carry"):
        load_tree_dataset(ds)
    # A device riding on a tip measures the others: columns for its own tip are refused by name.
    on_hand = write_tree_dataset(tmp_path / "on_hand", urdf_text=upper_body_urdf(), tips=list(HANDS), tree=nominal,
                                 samples=samples, noise_mm=None, points=np.zeros((2, 3)))  # fmt: skip
    doc = json.loads((on_hand / "tree.json").read_text())
    (on_hand / "tree.json").write_text(json.dumps(doc | {"device_on": "right_hand"}))
    with pytest.raises(ValueError, match=r"columns \['right_hand.x'.*which the device rides on"):
        load_tree_dataset(on_hand)
    with pytest.raises(ValueError, match="not both"):
        write_tree_dataset(tmp_path / "both", urdf_text=upper_body_urdf(), tips=list(HANDS), tree=nominal,
                           samples=samples, noise_mm=0.1, points=np.zeros((2, 3)))  # fmt: skip


def _urdf(tmp_path):
    path = tmp_path / "upper_body.urdf"
    path.write_text(upper_body_urdf())
    return path


def test_candidate_poses_in_degrees_are_refused(filmed):
    candidates = np.degrees(random_poses(filmed.limits, 10, np.random.default_rng(0)))
    plates = [hand_plate(hand, 10 * k) for k, hand in enumerate(HANDS)]
    with pytest.raises(ValueError, match="at a revolute joint: degrees"):
        poses_in_view(filmed.nominal, candidates, plates, 1)
