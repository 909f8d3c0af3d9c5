"""Malformed URDF joints are refused, and a robot bolted to its table can be planned.

URDF: a revolute or prismatic joint without `<limit>` or with lower >= upper,
a non-finite origin, axis or limit, a zero axis and a joint naming a missing
link each raise a `ValueError` naming the file and the joint, from both
`load_urdf` and `urdf_outline`; a continuous joint without limits still loads.

Floor: the capsule ends that no joint can move up or down (the base, a
shoulder turning about the vertical) are not checked against the floor, so the
UR5e's tool-down pose passes with the floor at the base (z = 0), while a pose
that puts the wrist through it is still rejected, with a reason naming the body.
"""

import equinox as eqx
import jax.numpy as jnp
import numpy as np
import pytest

from jaxcal._kinematics import forward_kinematics
from jaxcal.io.urdf import load_urdf, urdf_outline
from jaxcal.planning import FeasibilityLimits, Robot, default_layout, scene_of
from jaxcal.planning._optimise import correct_toward
from jaxcal.robots import load_robot, robot_path, shipped

# --------------------------------------------------------------------------- URDF


def _joint(name, kind, parent, child, origin='xyz="0 0 0.1" rpy="0 0 0"', axis="0 0 1", limit="default"):
    if limit == "default":
        limit = '<limit lower="-2" upper="2" effort="1" velocity="1"/>'
    body = f"<origin {origin}/>"
    if kind != "fixed":
        body += f'<axis xyz="{axis}"/>{limit or ""}'
    return (
        f'<joint name="{name}" type="{kind}"><parent link="{parent}"/><child link="{child}"/>{body}</joint>'
    )


def _urdf(tmp_path, j2: str, j2_child="l2") -> str:
    """A three-link arm whose middle joint `j2` (l1 -> l2) is given; written to tmp_path."""
    text = (
        '<?xml version="1.0"?><robot name="arm">'
        + "".join(f'<link name="{n}"/>' for n in ("base", "l1", "l2", "flange"))
        + _joint("j1", "revolute", "base", "l1")
        + j2
        + _joint("flange_joint", "fixed", j2_child, "flange")
        + "</robot>"
    )
    path = tmp_path / "arm.urdf"
    path.write_text(text)
    return str(path)


def _refused(path: str, *needles: str) -> None:
    for read in (load_urdf, lambda p: urdf_outline(p, ("j1", "j2"))):
        with pytest.raises(ValueError) as e:
            read(path)
        msg = str(e.value)
        assert "arm.urdf" in msg and "'j2'" in msg, msg
        for needle in needles:
            assert needle in msg, msg


@pytest.mark.parametrize(
    "j2, needles",
    [
        (
            _joint("j2", "revolute", "l1", "l2", limit='<limit lower="2.0" upper="-2.0" effort="1" velocity="1"/>'),
            ["lower='2.0' upper='-2.0'", "empty"],
        ),
        (_joint("j2", "revolute", "l1", "l2", limit=None), ["revolute but has no <limit>", "continuous"]),
        (_joint("j2", "prismatic", "l1", "l2", limit=None), ["prismatic but has no <limit>"]),
        (
            _joint("j2", "revolute", "l1", "l2", limit='<limit lower="1" upper="1" effort="1" velocity="1"/>'),
            ["[1, 1] is empty"],
        ),
        (_joint("j2", "revolute", "l1", "l2", origin='xyz="0 0 nan" rpy="0 0 0"'), ["xyz='0 0 nan'", "not finite"]),
        (_joint("j2", "revolute", "l1", "l2", origin='xyz="0 0 0" rpy="0 inf 0"'), ["rpy='0 inf 0'", "not finite"]),
        (_joint("j2", "revolute", "l1", "l2", axis="0 nan 1"), ["<axis xyz='0 nan 1'>", "not finite"]),
        (_joint("j2", "revolute", "l1", "l2", axis="0 0 0"), ["zero or invalid axis"]),
        (
            _joint("j2", "revolute", "l1", "l2", limit='<limit lower="-1" upper="inf" effort="1" velocity="1"/>'),
            ["upper='inf'"],
        ),
    ],
    ids=["lower>upper", "no-limit", "prismatic-no-limit", "empty-range", "nan-xyz", "inf-rpy", "nan-axis",
         "zero-axis", "inf-limit"],
)  # fmt: skip
def test_a_malformed_joint_is_refused_naming_the_file_and_the_joint(tmp_path, j2, needles):
    _refused(_urdf(tmp_path, j2), *needles)


def test_a_joint_naming_a_missing_link_is_refused_naming_both(tmp_path):
    path = _urdf(tmp_path, _joint("j2", "revolute", "l1", "l9"), j2_child="l2")
    _refused(path, "child link 'l9'", "not a <link>")


def test_a_continuous_joint_needs_no_limits(tmp_path):
    path = _urdf(tmp_path, _joint("j2", "continuous", "l1", "l2", limit=None))
    assert load_urdf(path).joint_names == ("j1", "j2")
    limits = urdf_outline(path, ("j1", "j2")).limits
    assert (limits["j1"].lower, limits["j1"].upper) == (-2.0, 2.0)
    assert (limits["j2"].lower, limits["j2"].upper) == (None, None)


def test_a_limit_without_lower_and_upper_states_no_range(tmp_path):
    """`<limit effort velocity/>` alone: the specification's (0, 0) would lock the joint; files that
    write it mean no range, and it reads as unlimited (as before), not as an error."""
    path = _urdf(tmp_path, _joint("j2", "revolute", "l1", "l2", limit='<limit effort="1" velocity="1"/>'))
    assert load_urdf(path).joint_names == ("j1", "j2")
    limits = urdf_outline(path, ("j1", "j2")).limits
    assert (limits["j2"].lower, limits["j2"].upper) == (None, None)


def test_the_shipped_robots_still_load():
    for name in shipped():
        model = load_urdf(robot_path(name))
        limits = urdf_outline(robot_path(name), model.joint_names).limits
        assert all(v.lower < v.upper for v in limits.values()), name


# --------------------------------------------------------------------------- floor

#: The UR5e tool-down, flange at z = 0.49 m (commanded, rad).
TOOL_DOWN = np.array([0.0, -1.571, 1.571, -1.571, -1.571, 0.0])


@pytest.fixture(scope="module")
def bolted():
    """The UR5e's planning scene at the tool-down pose with the floor at its base (z = 0)."""
    robot = Robot.load("ur5e")
    camera, target = default_layout(robot.model, TOOL_DOWN)
    return robot, scene_of(robot, camera, target, 0.0)


def test_a_robot_bolted_to_its_table_passes_the_floor_check(bolted):
    robot, scene = bolted
    lim = FeasibilityLimits()
    _, frac, why = correct_toward(scene, lim, TOOL_DOWN, TOOL_DOWN[None])
    assert frac[0] == 1.0 and why == [None]  # before the fix: 'scene_collision' (the shoulder's drum)
    from jaxcal.planning._scene import explain

    assert explain(scene, lim, TOOL_DOWN) is None

    down = TOOL_DOWN + np.array([0.0, 0.8, 0.8, 0.0, 0.0, 0.0])  # the wrist through the table
    F = np.asarray(forward_kinematics(robot.model, jnp.asarray(down)))
    assert F[robot.model.link_names.index("wrist_3_link"), 2, 3] < -0.02  # its origin: 3 cm below
    _, frac, why = correct_toward(scene, lim, TOOL_DOWN, down[None])
    assert why == ["scene_collision"] and frac[0] < 1.0
    reason = explain(scene, lim, down)
    assert reason.startswith("scene_collision: ") and "m below the floor at z = 0 m" in reason, reason


def test_only_ends_that_the_joints_can_lower_are_checked():
    from jaxcal.planning._scene import arm_capsules, floor_checked, floor_fixed_links

    ur5e = load_robot("ur5e")
    caps, _ = arm_capsules(ur5e)
    checked = floor_checked(ur5e, caps, np.eye(4))
    body = np.asarray(caps.body)
    assert not checked[body <= 1].any()  # the base and the shoulder turn about the vertical only
    assert checked[body >= 3].all()  # everything beyond the shoulder lift moves up and down
    assert floor_fixed_links(ur5e) == ("base_link", "shoulder_link")
    # The SCARA's two vertical joints keep heights; its vertical slide does not.
    assert floor_fixed_links(load_robot("scara")) == ("base_link", "link1", "link2")
    # Mounted on a wall (first axis horizontal) the drum of the shoulder lift (capsule 3) moves up
    # and down too; the shoulder's own capsules lie along the first axis and still do not.
    tilted = ur5e.T_parent_joint.at[0].set(
        jnp.asarray([[1.0, 0, 0, 0], [0, 0, -1, 0], [0, 1, 0, 0], [0, 0, 0, 1]]) @ ur5e.T_parent_joint[0]
    )
    wall = eqx.tree_at(lambda m: m.T_parent_joint, ur5e, tilted)
    assert floor_fixed_links(wall) == ("base_link",)
    on_wall = floor_checked(wall, arm_capsules(wall)[0], np.eye(4))
    assert body[3] == 2 and on_wall[3].all() and not checked[3].any()
    assert not on_wall[body <= 1].any()
