"""Any URDF loads the same way: a branching robot with every joint type, against Pinocchio."""

import functools

import jax
import numpy as np
import pytest

import jaxmm
from conftest import PinocchioTwin, assert_kinematics_derivatives_equal_autodiff, random_configurations


def _link(name, mass, com, rpy):
    if mass is None:
        return f'<link name="{name}"/>'
    return (
        f'<link name="{name}"><inertial><origin xyz="{com}" rpy="{rpy}"/><mass value="{mass}"/>'
        '<inertia ixx="0.03" ixy="0.004" ixz="-0.002" iyy="0.05" iyz="0.001" izz="0.04"/></inertial></link>'
    )


def _joint(name, kind, parent, child, xyz, rpy, axis="0.3 -0.5 0.8"):
    limit = '<limit lower="-1.2" upper="0.9" effort="1" velocity="3"/>' if kind in ("revolute", "prismatic") else ""
    return (
        f'<joint name="{name}" type="{kind}"><parent link="{parent}"/><child link="{child}"/>'
        f'<origin xyz="{xyz}" rpy="{rpy}"/><axis xyz="{axis}"/>{limit}</joint>'
    )


# A tree with two branches, a fixed link carrying mass, a massless frame, every joint type,
# a non-unit axis (normalised by both libraries) and one joint locked away from zero.
TREE = (
    '<robot name="tree">'
    + _link("trunk", 3.0, "0.01 0.02 -0.03", "0.1 0.2 0.3")
    + _link("arm", 1.0, "0.1 0 0", "0 0 0")
    + _link("forearm", 0.5, "0.05 0.01 0", "0.3 0 0.1")
    + _link("tool", 0.2, "0 0 0.02", "0 0 0")
    + _link("tip", None, "", "")
    + _link("slider", 0.7, "0 0.1 0", "0 0.4 0")
    + _link("wheel", 0.4, "0 0 0", "0 0 0")
    + _link("locked_link", 0.3, "0.02 0 0", "0 0 0")
    + _joint("shoulder", "revolute", "trunk", "arm", "0.1 0.2 0.3", "0.4 -0.2 1.0")
    + _joint("elbow", "revolute", "arm", "forearm", "0.3 0 0", "0 0.5 0", axis="0 1 0")
    + _joint("mount", "fixed", "forearm", "tool", "0.2 0.01 0", "1.0 0 0")
    + _joint("tip_joint", "fixed", "tool", "tip", "0 0 0.1", "0 0 0.7")
    + _joint("rail", "prismatic", "trunk", "slider", "-0.1 0 0.2", "0 0 -0.5", axis="1 2 0")
    + _joint("spin", "continuous", "slider", "wheel", "0 0.2 0", "0.3 0.2 0.1")
    + _joint("stiff", "revolute", "wheel", "locked_link", "0.1 0 0", "0 0 0")
    + "</robot>"
)


@pytest.fixture(scope="module")
def tree():
    robot = jaxmm.load_robot(TREE, joints=["spin", "elbow", "rail", "shoulder"], locked={"stiff": 0.37})
    return robot.model, PinocchioTwin(robot.model, TREE)


def test_structure(tree):
    model, _ = tree
    assert model.joint_names == ("spin", "elbow", "rail", "shoulder")
    assert model.locked_joint_names == ("stiff",)
    assert set(model.frame_names) == {"trunk", "arm", "forearm", "tool", "tip", "slider", "wheel", "locked_link"}
    assert np.isinf(np.asarray(model.position_limits[0])).all()  # continuous
    assert float(jaxmm.total_mass(model)) == pytest.approx(6.1, abs=1e-12)
    np.testing.assert_array_equal(np.asarray(model.effort_limits), [np.inf, 1.0, 1.0, 1.0])  # continuous: none


def test_an_effort_of_zero_means_no_limit():
    """URDFs write effort="0" where no motor limit is given: no limit, not a motor that can
    exert nothing (which would make every torque bound infeasible)."""
    xml = TREE.replace('effort="1"', 'effort="0"', 1)  # the first limited joint, the shoulder
    model = jaxmm.load_robot(xml, joints=["spin", "elbow", "rail", "shoulder"]).model
    np.testing.assert_array_equal(np.asarray(model.effort_limits), [np.inf, 1.0, 1.0, np.inf])


def test_against_pinocchio(tree):
    model, twin = tree
    pin = twin.pin
    Q = random_configurations(model, 50, seed=11)
    V = np.random.default_rng(12).normal(size=(len(Q), model.nv))
    positions, rotations = jax.vmap(functools.partial(jaxmm.frame_poses, model))(Q)
    com = jax.vmap(functools.partial(jaxmm.com_position, model))(Q)
    h = jax.vmap(functools.partial(jaxmm.centroidal_momentum, model))(Q, V)
    tip_jacobian = jax.vmap(lambda q: jaxmm.frame_jacobian(model, q, "tip"))(Q)
    for i, (q, nu) in enumerate(zip(Q, V)):
        q_pin, v_pin = twin.configuration(q), twin.velocity(q, nu)
        pin.framesForwardKinematics(twin.model, twin.data, q_pin)
        for k, name in enumerate(model.frame_names):
            placement = twin.data.oMf[twin.frame_id(name)]
            assert np.abs(placement.translation - positions[i, k]).max() <= 1e-10
            assert np.abs(placement.rotation - rotations[i, k]).max() <= 1e-10
        assert np.abs(pin.centerOfMass(twin.model, twin.data, q_pin) - com[i]).max() <= 1e-10
        assert np.abs(pin.computeCentroidalMap(twin.model, twin.data, q_pin) @ v_pin - h[i]).max() <= 1e-10
        J = pin.computeFrameJacobian(twin.model, twin.data, q_pin, twin.frame_id("tip"), pin.LOCAL_WORLD_ALIGNED)
        assert np.abs(J @ v_pin - tip_jacobian[i] @ nu).max() <= 1e-10


def test_kinematics_derivatives_by_the_tree_recursions_equal_autodiff(tree):
    """The tree recursions' Jacobian and curvature on a tree with two branches, a prismatic and a
    locked joint, a massless frame, and optimised joints listed out of the tree's order."""
    model, _ = tree
    configurations = random_configurations(model, 3, seed=13)
    assert_kinematics_derivatives_equal_autodiff(model, ("tip", "wheel", "locked_link", "slider", "trunk"),
                                                 configurations, seed=14)


# A small legged robot that is not an iCub: a trunk and two legs, with feet but no sole corners
# and no jets in its URDF.
WALKER = (
    '<robot name="walker">'
    + _link("pelvis", 8.0, "0 0 0.05", "0 0 0")
    + _link("left_leg", 2.0, "0 0 -0.2", "0 0 0")
    + _link("right_leg", 2.0, "0 0 -0.2", "0 0 0")
    + _link("left_foot", 0.5, "0.03 0 -0.02", "0 0 0")
    + _link("right_foot", 0.5, "0.03 0 -0.02", "0 0 0")
    + _link("camera", 0.3, "0 0 0", "0 0 0")
    + _joint("left_hip", "revolute", "pelvis", "left_leg", "0 0.1 0", "0 0 0", axis="0 1 0")
    + _joint("right_hip", "revolute", "pelvis", "right_leg", "0 -0.1 0", "0 0 0", axis="0 1 0")
    + _joint("left_knee", "revolute", "left_leg", "left_foot", "0 0 -0.4", "0 0 0", axis="0 1 0")
    + _joint("right_knee", "revolute", "right_leg", "right_foot", "0 0 -0.4", "0 0 0", axis="0 1 0")
    + _joint("neck", "revolute", "pelvis", "camera", "0 0 0.3", "0 0 0", axis="0 0 1")
    + "</robot>"
)
CORNERS = [(f"{side}_corner_{i}", f"{side}_foot", (x, y, -0.05), (0.0, 0.0, 0.0))
           for side in ("left", "right") for i, (x, y) in enumerate([(0.1, 0.04), (0.1, -0.04), (-0.05, 0.04),
                                                                    (-0.05, -0.04)])]
JET = jaxmm.Frame("back_jet", "pelvis", xyz=(-0.1, 0.0, 0.1), rpy=(0.0, 0.3, 0.0), mass=1.5,
                  com_xyz=(0.0, 0.0, -0.05), inertia=(0.01, 0.0, 0.0, 0.01, 0.0, 0.005))


def test_frames_and_removed_subtrees_without_editing_the_urdf():
    """``load_robot`` adds sole corners and a jet (with its mass) to a URDF that has neither and
    drops a subtree; each frame sits where its parent's pose and its origin put it."""
    plain = jaxmm.load_robot(WALKER)
    robot = jaxmm.load_robot(WALKER, frames=[*CORNERS, JET], remove_subtrees=["camera"],
                             jet_frames=["back_jet"], contact_frames=[c[0] for c in CORNERS])
    model = robot.model
    assert "camera" not in model.frame_names and "neck" not in model.joint_names
    assert model.joint_names == ("left_hip", "right_hip", "left_knee", "right_knee")
    assert float(jaxmm.total_mass(model)) == pytest.approx(float(jaxmm.total_mass(plain.model)) - 0.3 + 1.5, abs=1e-12)
    quaternion = np.array([0.05, 0.02, 0.1, 0.99])
    q = jaxmm.make_configuration([0.1, -0.2, 0.9], quaternion / np.linalg.norm(quaternion), [0.3, -0.2, 0.5, 0.1])
    positions, rotations = jaxmm.frame_poses(model, q)
    for name, parent, xyz, _ in CORNERS:
        p_parent, R_parent = (a[model.frame_index(parent)] for a in (positions, rotations))
        assert np.abs(positions[model.frame_index(name)] - (p_parent + R_parent @ np.asarray(xyz))).max() <= 1e-12
        assert np.abs(rotations[model.frame_index(name)] - R_parent).max() <= 1e-12
    p_jet, R_jet = jaxmm.frame_pose(model, q, "back_jet")
    R_y = np.array([[np.cos(0.3), 0.0, np.sin(0.3)], [0.0, 1.0, 0.0], [-np.sin(0.3), 0.0, np.cos(0.3)]])
    R_pelvis = rotations[model.frame_index("pelvis")]
    assert np.abs(R_jet - R_pelvis @ R_y).max() <= 1e-12
    assert "walker" == robot.name and robot.jet_frames == ("back_jet",)


def test_frames_that_do_not_fit_are_named():
    with pytest.raises(jaxmm.URDFError, match="parent link 'tail' is not in walker"):
        jaxmm.load_robot(WALKER, frames=[("tail_tip", "tail")])
    with pytest.raises(jaxmm.URDFError, match="already has a link or joint"):
        jaxmm.load_robot(WALKER, frames=[("left_foot", "pelvis")])
    with pytest.raises(jaxmm.URDFError, match="cannot remove unknown link 'arm'"):
        jaxmm.load_robot(WALKER, remove_subtrees=["arm"])
    with pytest.raises(TypeError, match="a frame is a Frame"):
        jaxmm.load_robot(WALKER, frames=["left_corner"])


def test_a_description_assembles_any_base_urdf(tmp_path):
    """The description format that assembles iRonCub takes any URDF file as its base."""
    path = tmp_path / "walker.urdf"
    path.write_text(WALKER)
    description = dict(name="jet_walker", base=dict(urdf=str(path), remove_subtrees=["camera"]),
                       frames=[dict(name=c[0], parent=c[1], xyz=c[2]) for c in CORNERS])
    urdf = jaxmm.assemble_urdf(description)
    model = jaxmm.load_robot(urdf).model
    assert model.name == "jet_walker" and "camera" not in model.frame_names
    assert {c[0] for c in CORNERS} <= set(model.frame_names)
