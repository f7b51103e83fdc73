"""Any URDF loads the same way: a branching robot with every joint type, against Pinocchio."""

import functools

import jax
import numpy as np
import pytest

import jaxmm
from conftest import PinocchioTwin, random_configurations

pytest.importorskip("pinocchio", reason="Pinocchio (pin) is the reference: pip install -e '.[test]'")


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
