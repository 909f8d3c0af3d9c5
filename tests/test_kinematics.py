"""Forward kinematics, model conversions, perturbation and URDF input/output."""

import math
import os

import equinox as eqx
import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import pytest
import yourdfpy

from jaxcal import PerturbationScales, forward_kinematics, make_model, perturb_model, to_poe
from jaxcal._kinematics import poe_forward_kinematics
from jaxcal.io import load_urdf, save_urdf
from jaxcal.robots import dh_model, load_robot, robot_path

ROBOTS = ("ur5e", "panda")
# Jitted once per module (op-by-op dispatch of these small-array functions is slow), and
# shared by the tests with the same robot, scales and batch size so that they compile once.
perturb = eqx.filter_jit(perturb_model)
perturb_many = eqx.filter_jit(jax.vmap(perturb_model, in_axes=(None, 0, None)))
poe_fk = jax.jit(jax.vmap(poe_forward_kinematics, in_axes=(None, 0)))
fk_configs = jax.jit(jax.vmap(forward_kinematics, in_axes=(None, 0)))
fk_models = jax.jit(jax.vmap(forward_kinematics, in_axes=(0, None)))
SCALES = PerturbationScales(
    origin_mm=1.5, origin_deg=0.3, axis_tilt_deg=0.4, zero_offset_deg=1.0, ratio_percent=2.0, tool_mm=3.0
)
NUM_Q = 20


def random_configs(urdf: yourdfpy.URDF, names, n: int, seed: int) -> np.ndarray:
    """`n` configurations drawn uniformly within the URDF joint limits."""
    joints = {j.name: j for j in urdf.robot.joints}
    lower = np.array([joints[name].limit.lower for name in names])
    upper = np.array([joints[name].limit.upper for name in names])
    return np.random.default_rng(seed).uniform(lower, upper, size=(n, len(names)))


def fk_batch(model, qs):
    return np.asarray(fk_configs(model, jnp.asarray(qs)))


# --------------------------------------------------------------------------- oracles


@pytest.mark.parametrize("robot", ROBOTS)
def test_fk_matches_yourdfpy_and_mujoco(robot):
    path = robot_path(robot)
    model = load_urdf(path)
    urdf = yourdfpy.URDF.load(str(path), build_scene_graph=True, load_meshes=False)
    assert tuple(urdf.actuated_joint_names) == model.joint_names
    mj = mujoco.MjModel.from_xml_path(str(path))
    data = mujoco.MjData(mj)
    qpos_adr = [int(mj.joint(name).qposadr[0]) for name in model.joint_names]

    qs = random_configs(urdf, model.joint_names, NUM_Q, seed=0)
    ours = fk_batch(model, qs)
    assert ours.shape == (NUM_Q, model.num_joints + 2, 4, 4)
    for q, frames in zip(qs, ours):
        urdf.update_cfg(q)
        data.qpos[:] = 0.0
        data.qpos[qpos_adr] = q
        mujoco.mj_kinematics(mj, data)
        for link, T in zip(model.link_names, frames):
            T_urdf = urdf.get_transform(frame_to=link, frame_from=model.link_names[0])
            np.testing.assert_allclose(T, T_urdf, rtol=0, atol=1e-9, err_msg=f"{robot} {link} vs yourdfpy")
            body = mj.body(link).id
            np.testing.assert_allclose(T[:3, 3], data.xpos[body], rtol=0, atol=1e-9, err_msg=link)
            np.testing.assert_allclose(
                T[:3, :3],
                data.xmat[body].reshape(3, 3),
                rtol=0,
                atol=1e-9,
                err_msg=f"{robot} {link} vs MuJoCo",
            )


@pytest.mark.parametrize(
    ("robot", "table"), [("ur5e", "ur5e_dh"), ("ur5e", "ur5e_mdh"), ("panda", "panda_mdh")]
)
def test_dh_tables_match_urdf(robot, table):
    urdf_model = load_robot(robot)
    table_model = dh_model(table)
    assert table_model.joint_names == urdf_model.joint_names
    assert (table_model.link_names[0], table_model.link_names[-1]) == (
        urdf_model.link_names[0],
        urdf_model.link_names[-1],
    )
    qs = np.random.default_rng(1).uniform(-math.pi, math.pi, size=(NUM_Q, urdf_model.num_joints))
    np.testing.assert_allclose(
        fk_batch(table_model, qs)[:, -1], fk_batch(urdf_model, qs)[:, -1], rtol=0, atol=1e-12
    )


def test_published_flange_positions_at_zero():
    # data/robots/README.md: UR5e flange at (-0.8172, -0.2329, 0.0628), Panda at (0.088, 0, 0.926).
    for robot, expected in [("ur5e", [-0.8172, -0.2329, 0.0628]), ("panda", [0.088, 0.0, 0.926])]:
        model = load_robot(robot)
        flange = forward_kinematics(model, jnp.zeros(model.num_joints))[-1]
        np.testing.assert_allclose(flange[:3, 3], expected, rtol=0, atol=1e-12, err_msg=robot)


def test_unknown_names():
    with pytest.raises(ValueError, match=r"unknown robot 'kuka'.*\['panda', 'scara', 'ur3', 'ur5e'\]"):
        load_robot("kuka")
    with pytest.raises(ValueError, match=r"unknown DH table 'ur5e'.*'ur5e_dh'"):
        dh_model("ur5e")


def test_poe_matches_fk_for_perturbed_model(key):
    model = perturb(load_robot("ur5e"), key, SCALES)
    assert np.all(np.abs(model.zero_offset) > 1e-4)
    poe = to_poe(model)
    qs = np.random.default_rng(2).uniform(-math.pi, math.pi, size=(NUM_Q, 6))
    np.testing.assert_allclose(poe_fk(poe, jnp.asarray(qs)), fk_batch(model, qs)[:, -1], rtol=0, atol=1e-10)


def test_poe_prismatic_joint():
    # R-P-R chain with tilted axes and a nonzero offset on the prismatic joint.
    rng = np.random.default_rng(3)
    T = np.tile(np.eye(4), (3, 1, 1))
    T[:, :3, 3] = rng.normal(size=(3, 3)) * 0.2
    model = make_model(
        T,
        rng.normal(size=(3, 3)),
        joint_names=["j1", "j2", "j3"],
        joint_types=["revolute", "prismatic", "revolute"],
        zero_offset=[0.1, 0.05, -0.2],
        T_last_flange=T[0],
    )
    qs = rng.uniform(-1, 1, size=(NUM_Q, 3))
    np.testing.assert_allclose(
        poe_fk(to_poe(model), jnp.asarray(qs)), fk_batch(model, qs)[:, -1], rtol=0, atol=1e-12
    )


# --------------------------------------------------------------------------- batching


@pytest.fixture(scope="module")
def ur5e_batch():
    """The UR5e and 2000 perturbations of it (one compile, shared by the tests below)."""
    model = load_robot("ur5e")
    keys = jax.random.split(jax.random.key(0), 2000)
    return model, keys, perturb_many(model, keys, SCALES)


def test_vmap_equals_loop(ur5e_batch):
    model, keys, models = ur5e_batch
    qs = jnp.asarray(np.random.default_rng(4).uniform(-2, 2, size=(NUM_Q, 6)))
    batched = fk_batch(model, qs)
    for q, frames in zip(qs, batched):
        np.testing.assert_allclose(frames, forward_kinematics(model, q), rtol=0, atol=1e-12)

    assert models.T_parent_joint.shape == (2000, 6, 4, 4)
    by_model = fk_models(models, qs[0])
    for i in (0, 1, 1999):
        one = perturb(model, keys[i], SCALES)
        sliced = jax.tree.map(lambda x, i=i: x[i], models)
        for a, b in zip(jax.tree.leaves(sliced), jax.tree.leaves(one)):
            np.testing.assert_allclose(a, b, rtol=0, atol=1e-12)
        np.testing.assert_allclose(by_model[i], forward_kinematics(one, qs[0]), rtol=0, atol=1e-12)


# --------------------------------------------------------------------------- perturbation


def test_perturb_model_statistics(ur5e_batch):
    model, keys, models = ur5e_batch
    deg = math.pi / 180.0

    d_offset = np.asarray(models.zero_offset - model.zero_offset)
    assert abs(d_offset.std() / (SCALES.zero_offset_deg * deg) - 1.0) < 0.1
    assert abs(d_offset.mean()) < 4 * SCALES.zero_offset_deg * deg / math.sqrt(d_offset.size)

    d_ratio = np.asarray(models.reduction_ratio / model.reduction_ratio - 1.0)
    assert abs(d_ratio.std() / (0.01 * SCALES.ratio_percent) - 1.0) < 0.1

    d_xyz = np.asarray(models.T_parent_joint[..., :3, 3] - model.T_parent_joint[..., :3, 3])
    assert abs(d_xyz.std() / (SCALES.origin_mm * 1e-3) - 1.0) < 0.1

    # Rotation of each origin in its joint frame; vee of the skew part is the rotation vector
    # to O(theta^3), far below the 10 % tolerance at these angles.
    R = np.asarray(models.T_parent_joint[..., :3, :3])
    R_rel = np.einsum("jba,kjbc->kjac", np.asarray(model.T_parent_joint[:, :3, :3]), R)
    w = 0.5 * np.stack(
        [
            R_rel[..., 2, 1] - R_rel[..., 1, 2],
            R_rel[..., 0, 2] - R_rel[..., 2, 0],
            R_rel[..., 1, 0] - R_rel[..., 0, 1],
        ]
    )
    assert abs(w.std() / (SCALES.origin_deg * deg) - 1.0) < 0.1
    np.testing.assert_allclose(
        np.einsum("kjba,kjbc->kjac", R, R), np.broadcast_to(np.eye(3), R.shape), rtol=0, atol=1e-12
    )

    axes = np.asarray(models.axis)
    np.testing.assert_allclose(np.linalg.norm(axes, axis=-1), 1.0, rtol=0, atol=1e-12)
    # The tilt is a 2D Gaussian perpendicular to the axis: RMS angle = sqrt(2) sigma.
    nominal = np.asarray(model.axis)
    tilt = np.arctan2(np.linalg.norm(np.cross(axes, nominal), axis=-1), np.sum(axes * nominal, axis=-1))
    assert abs(np.sqrt(np.mean(tilt**2)) / (math.sqrt(2) * SCALES.axis_tilt_deg * deg) - 1.0) < 0.1

    d_tool = np.asarray(models.T_flange_tool[:, :3, 3])
    assert abs(d_tool.std() / (SCALES.tool_mm * 1e-3) - 1.0) < 0.1
    # tool_deg = 0: the tool does not rotate.
    np.testing.assert_array_equal(models.T_flange_tool[:, :3, :3], np.broadcast_to(np.eye(3), (2000, 3, 3)))

    # Deterministic in the key; different keys give different arms.
    again = perturb(model, keys[7], SCALES)
    np.testing.assert_allclose(again.T_parent_joint, models.T_parent_joint[7], rtol=0, atol=1e-15)
    assert not np.allclose(models.zero_offset[0], models.zero_offset[1])


# --------------------------------------------------------------------------- URDF input


def write(tmp_path, name, text) -> str:
    path = tmp_path / name
    path.write_text(text)
    return str(path)


def joint_xml(name, kind, parent, child, xyz="0 0 0", rpy="0 0 0", axis="0 0 1"):
    axis_el = (
        ""
        if kind == "fixed"
        else f'<axis xyz="{axis}"/><limit lower="-3" upper="3" effort="1" velocity="1"/>'
    )
    return (
        f'<joint name="{name}" type="{kind}"><parent link="{parent}"/><child link="{child}"/>'
        f'<origin xyz="{xyz}" rpy="{rpy}"/>{axis_el}</joint>'
    )


def urdf_xml(links, joints, extra=""):
    body = "".join(f'<link name="{name}"/>' for name in links) + "".join(joints) + extra
    return f'<?xml version="1.0"?><robot name="test">{body}</robot>'


# base -fixed-> mount -revolute-> l1 -fixed-> l1b -prismatic-> l2 -continuous-> l3 -fixed-> tip0 -fixed-> tip
FOLDED_LINKS = ["base", "mount", "l1", "l1b", "l2", "l3", "tip0", "tip"]
FOLDED_JOINTS = [
    joint_xml("mount_joint", "fixed", "base", "mount", "0.1 0 0.2", "0 0.3 0"),
    joint_xml("j1", "revolute", "mount", "l1", "0 0 0.1", "0.1 0 0", "0 0 2"),
    joint_xml("l1b_joint", "fixed", "l1", "l1b", "0.3 0 0", "0 0 0.5"),
    # Unit prismatic axis: yourdfpy (the oracle) does not normalise prismatic axes.
    joint_xml("j2", "prismatic", "l1b", "l2", "0 0.05 0", "0 0 0", "0.6 0.8 0"),
    joint_xml("j3", "continuous", "l2", "l3", "0 0 0.2", "1.5707963267948966 0 0", "0 1 0"),
    joint_xml("tip0_joint", "fixed", "l3", "tip0", "0 0 0.1", "0 0 0"),
    joint_xml("tip_joint", "fixed", "tip0", "tip", "0.01 0 0", "0 0.2 0"),
]
TRANSMISSION = (
    '<transmission name="t2"><type>transmission_interface/SimpleTransmission</type>'
    '<joint name="j2"><hardwareInterface>x</hardwareInterface></joint>'
    '<actuator name="m2"><mechanicalReduction>50.5</mechanicalReduction></actuator></transmission>'
)


def test_load_urdf_folds_fixed_joints(tmp_path):
    path = write(tmp_path, "folded.urdf", urdf_xml(FOLDED_LINKS, FOLDED_JOINTS, TRANSMISSION))
    model = load_urdf(path)
    assert model.joint_names == ("j1", "j2", "j3")
    assert model.joint_types == ("revolute", "prismatic", "revolute")
    assert model.link_names == ("base", "l1", "l2", "l3", "tip")
    np.testing.assert_allclose(
        model.axis, [[0.0, 0.0, 1.0], [0.6, 0.8, 0.0], [0.0, 1.0, 0.0]], rtol=0, atol=1e-15
    )
    np.testing.assert_array_equal(model.reduction_ratio, [1.0, 50.5, 1.0])
    np.testing.assert_array_equal(model.zero_offset, [0.0, 0.0, 0.0])
    urdf = yourdfpy.URDF.load(path, build_scene_graph=True, load_meshes=False)
    for q in np.random.default_rng(5).uniform(-1, 1, size=(5, 3)):
        urdf.update_cfg(q)
        frames = forward_kinematics(model, q)
        for link, T in zip(model.link_names, frames):
            np.testing.assert_allclose(T, urdf.get_transform(link, "base"), rtol=0, atol=1e-12, err_msg=link)

    # A sub-chain between named links.
    sub = load_urdf(path, base_link="l1", tip_link="l3")
    assert sub.joint_names == ("j2", "j3")
    assert sub.link_names == ("l1", "l2", "l3", "l3")


def test_load_urdf_errors(tmp_path):
    with pytest.raises(ValueError, match=r"'.*nowhere\.urdf' does not exist"):
        load_urdf(tmp_path / "nowhere.urdf")

    bad = write(tmp_path, "bad.urdf", '<robot name="r"><link name="a"></robot>')
    with pytest.raises(ValueError, match=r"bad\.urdf' is not well-formed XML"):
        load_urdf(bad)

    good = write(tmp_path, "good.urdf", urdf_xml(FOLDED_LINKS, FOLDED_JOINTS))
    with pytest.raises(ValueError, match=r"good\.urdf.*unknown tip link 'hand'"):
        load_urdf(good, tip_link="hand")
    with pytest.raises(ValueError, match=r"good\.urdf.*unknown base link 'world'"):
        load_urdf(good, base_link="world")
    with pytest.raises(ValueError, match=r"no chain of joints from base link 'l2' to tip link 'l1'"):
        load_urdf(good, base_link="l2", tip_link="l1")
    with pytest.raises(ValueError, match=r"no movable joint between base link 'l3' and tip link 'tip'"):
        load_urdf(good, base_link="l3", tip_link="tip")

    floating = write(
        tmp_path,
        "floating.urdf",
        urdf_xml(
            ["a", "b", "c"], [joint_xml("free", "floating", "a", "b"), joint_xml("j", "revolute", "b", "c")]
        ),
    )
    with pytest.raises(ValueError, match=r"floating\.urdf.*joint 'free' is floating"):
        load_urdf(floating)

    zero_axis = write(
        tmp_path, "zero.urdf", urdf_xml(["a", "b"], [joint_xml("j", "revolute", "a", "b", axis="0 0 0")])
    )
    with pytest.raises(ValueError, match=r"zero\.urdf.*joint 'j' has a zero or invalid axis"):
        load_urdf(zero_axis)

    branched = write(
        tmp_path,
        "branched.urdf",
        urdf_xml(FOLDED_LINKS + ["cam"], FOLDED_JOINTS + [joint_xml("cam_joint", "revolute", "l1", "cam")]),
    )
    with pytest.raises(
        ValueError,
        match=r"branched\.urdf.*name the flange link, one of the leaves \['cam', 'tip'\].*flange-link=NAME",
    ):
        load_urdf(branched)
    assert load_urdf(branched, tip_link="cam").joint_names == ("j1", "cam_joint")


# --------------------------------------------------------------------------- URDF output


def test_save_urdf_round_trip(tmp_path, key):
    nominal = load_robot("ur5e")
    model = perturb(nominal, key, SCALES)
    model = eqx.tree_at(lambda m: m.T_last_flange, model, model.T_last_flange.at[:3, 3].add(0.001))
    qs = np.random.default_rng(6).uniform(-math.pi, math.pi, size=(NUM_Q, 6))
    expected = fk_batch(model, qs)

    out = tmp_path / "calibrated.urdf"
    out.write_text("stale")  # replaced atomically
    save_urdf(model, out, source=robot_path("ur5e"))
    minimal = tmp_path / "minimal.urdf"
    save_urdf(model, minimal)
    assert sorted(os.listdir(tmp_path)) == ["calibrated.urdf", "minimal.urdf"]  # no temporary files left

    for path in (out, minimal):
        back = load_urdf(path)
        assert (back.joint_names, back.link_names, back.joint_types) == (
            model.joint_names,
            model.link_names,
            model.joint_types,
        )
        np.testing.assert_allclose(fk_batch(back, qs), expected, rtol=0, atol=1e-12)
        np.testing.assert_allclose(back.T_parent_joint, model.T_parent_joint, rtol=0, atol=1e-12)
        np.testing.assert_allclose(back.axis, model.axis, rtol=0, atol=1e-15)
        np.testing.assert_allclose(back.T_last_flange, model.T_last_flange, rtol=0, atol=1e-12)
        np.testing.assert_array_equal(back.zero_offset, model.zero_offset)
        np.testing.assert_array_equal(back.reduction_ratio, model.reduction_ratio)

    # The copy keeps the rest of the source: geometry and the MuJoCo compiler options still load.
    mj = mujoco.MjModel.from_xml_path(str(out))
    assert mj.nbody == len(model.link_names) + 1


def test_save_urdf_gimbal_lock_origin(tmp_path):
    # A joint origin at pitch exactly pi/2, built with exact zeros: roll and yaw are only
    # determined through their difference, which the writer must keep.
    Ry = np.array([[0.0, 0.0, 1.0], [0.0, 1.0, 0.0], [-1.0, 0.0, 0.0]])
    c, s = math.cos(0.2), math.sin(0.2)
    Rz = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    T = np.tile(np.eye(4), (2, 1, 1))
    T[0, :3, :3] = Rz @ Ry
    T[1, :3, :3] = Ry.T @ Rz
    model = make_model(T, [[0.0, 0.0, 1.0], [1.0, 0.0, 0.0]], joint_names=["a", "b"])
    save_urdf(model, tmp_path / "gimbal.urdf")
    back = load_urdf(tmp_path / "gimbal.urdf")
    np.testing.assert_allclose(back.T_parent_joint, T, rtol=0, atol=1e-12)


def test_save_urdf_errors(tmp_path, monkeypatch):
    source = write(tmp_path, "folded.urdf", urdf_xml(FOLDED_LINKS, FOLDED_JOINTS, TRANSMISSION))
    model = load_urdf(source)
    with pytest.raises(
        ValueError, match=r"fixed joint 'mount_joint' .* folded into the origin of joint 'j1'"
    ):
        save_urdf(model, tmp_path / "out.urdf", source=source)

    batch = jax.tree.map(lambda x: jnp.stack([x, x]), model)
    with pytest.raises(ValueError, match=r"model.T_parent_joint has shape \(2, 3, 4, 4\)"):
        save_urdf(batch, tmp_path / "out.urdf")

    # A failing rename leaves the previous file intact and no temporary file behind.
    target = tmp_path / "kept.urdf"
    target.write_text("previous")

    def fail(*args):
        raise OSError("disk full")

    monkeypatch.setattr(os, "replace", fail)
    with pytest.raises(OSError, match="disk full"):
        save_urdf(load_robot("ur5e"), target)
    assert target.read_text() == "previous"
    assert sorted(os.listdir(tmp_path)) == ["folded.urdf", "kept.urdf"]
