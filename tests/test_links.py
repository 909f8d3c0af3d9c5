"""Markers on every link with arbitrary motion, through `jaxcal.calibrate`:
every joint moves at once (random waypoints, 640x480, 160 frames, the
camera clock 40 ms off and not given), a ChArUco plate rides on every link; the seed's sequential initialisation (each
joint's axis from its child link's plate, the earlier joints undone with
their encoders), then the refinement over every plate's corners."""

import json

import numpy as np
import pytest

from jaxcal.io.dataset import load_dataset
from jaxcal.pipeline import CalibrationError, calibrate
from jaxcal.robots import load_robot
from jaxcal.sim.motion import random_motion
from jaxcal.sim.simulate import SimConfig, simulate

pytestmark = pytest.mark.slow

NAMES = load_robot("ur5e").joint_names
CONFIG = SimConfig(
    robot="ur5e",
    seed=0,
    resolution=(640, 480),
    markers_on_links=True,
    clock_offset_ms=40.0,
    clock_known=False,
)


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    motion = random_motion(NAMES, seconds=160 / CONFIG.fps, amplitude_deg=25.0, seed=0)
    return simulate(CONFIG, tmp_path_factory.mktemp("links") / "ur5e", trajectory=motion, progress=False)


@pytest.fixture(scope="module")
def result(dataset):
    return calibrate(dataset, progress=False, workers=1)


def test_every_joint_moves_and_every_link_carries_a_plate(dataset):
    ds = load_dataset(dataset)
    assert [s[0] for s in ds.segments] == [None]
    assert {t.link for t in ds.targets} == set(load_robot("ur5e").link_names[1:-2]) | {"flange"}
    truth = json.loads((dataset / "truth.json").read_text())
    q = np.array([f["q"] for f in truth["frames"]])
    assert np.all(np.ptp(q, axis=0) > np.radians(15.0))  # every joint moves...
    assert np.mean(np.sum(np.abs(np.diff(q, axis=0)) > 1e-4, axis=1) >= 4) > 0.8  # ...mostly together


def test_sequential_initialisation_then_refinement(result):
    v = result.validation
    print({k: v[k] for k in v if k.startswith("ee_")}, v["T_cam_base_error"], result.refinement["sigma_px"])
    assert result.ok
    assert len(result.targets) == 6 and result.targets[0] == "plate0"  # the flange plate first
    assert any("sequential" in w for w in result.warnings)
    assert all(a["solver"]["result"] == "successful" for a in result.arcs)
    assert min(result.frames["used_per_joint"].values()) > 100
    # Every plate's corners join the refinement; each mount is estimated on its own link.
    assert result.refinement["views"] > 4 * 160
    assert np.asarray(result.T_flange_target).shape == (6, 4, 4)
    assert v["ee_rms_mm_before"] > 4.0
    assert v["ee_rms_mm_after"] < 0.25 * v["ee_rms_mm_before"]
    assert v["T_cam_base_error"]["trans_mm"] < 1.0
    # The unknown 40 ms clock offset, from the first joint's plate before anything is undone.
    assert result.clock["estimated"] and abs(v["clock_offset_error_ms"]) < 0.5
    ratio = [e["ratio_percent"] for e in v["parameter_errors"].values()]
    assert max(abs(r) for r in ratio) < 0.2  # 1 % perturbations, recovered from the encoders


def test_arbitrary_motion_needs_a_plate_on_every_link(dataset, tmp_path):
    import shutil

    ds = tmp_path / "copy"
    shutil.copytree(dataset, ds)
    meta = json.loads((ds / "metadata.json").read_text())
    meta["targets"] = [t for t in meta["targets"] if t["link"] != "forearm_link"]
    (ds / "metadata.json").write_text(json.dumps(meta))
    (ds / "truth.json").unlink()  # it names the removed plate: the loader would refuse it first
    with pytest.raises(CalibrationError, match="joint 'elbow_joint': no target on link 'forearm_link'"):
        calibrate(ds, progress=False, workers=1)


def test_undo_joint_inverts_a_turn_about_the_axis():
    from jaxcal._links import undo_joint
    from jaxcal._npgeom import axis_rotation as _rotation

    rng = np.random.default_rng(2)
    V = rng.normal(size=3)
    V /= np.linalg.norm(V)
    Q = rng.normal(size=3)
    angle = rng.uniform(-1.0, 1.0, 5)
    P = rng.normal(size=(5, 3))
    O = np.stack([_rotation(rng.normal(size=3) / np.sqrt(3.0), rng.uniform(0, 3, 1))[0] for _ in range(5)])
    A = rng.normal(size=(5, 6, 6))
    C = A @ np.swapaxes(A, 1, 2)
    R = _rotation(V, angle)  # the joint turns the poses by +angle about (V, Q)
    B = np.zeros((5, 6, 6))
    B[:, :3, :3] = B[:, 3:, 3:] = R
    P2, O2, C2 = undo_joint(
        Q + np.einsum("fab,fb->fa", R, P - Q), R @ O, B @ C @ np.swapaxes(B, 1, 2), V, Q, angle
    )
    np.testing.assert_allclose(P2, P, atol=1e-12)
    np.testing.assert_allclose(O2, O, atol=1e-12)
    np.testing.assert_allclose(C2, C, atol=1e-10)


def test_a_target_no_image_shows_names_the_fields_to_check():
    """A plate whose `first_id` is one off (a new user's) is found in no image: the message says which
    of its fields decide what the detector looks for, not only that it is never seen."""
    from types import SimpleNamespace

    from jaxcal._links import link_poses

    targets = [SimpleNamespace(name="plate0"), SimpleNamespace(name="plate2")]
    with pytest.raises(
        ValueError, match=r"target 'plate2' is never seen: .* dictionary, first_id and squares"
    ):
        link_poses([{"plate0": None}, {}], targets, [1])
