"""Bad input raises an error that names the problem."""

import jax.numpy as jnp
import numpy as np
import pytest

import jaxmm

LINK = '<link name="{name}"><inertial><mass value="{mass}"/><inertia ixx="{i}" iyy="{i}" izz="{i}" ixy="0" ixz="0" iyz="0"/></inertial></link>'
JOINT = '<joint name="{name}" type="{type}"><parent link="{parent}"/><child link="{child}"/><axis xyz="0 0 1"/><limit lower="-1" upper="1" effort="1" velocity="1"/></joint>'


def urdf(links, joints):
    return f'<robot name="r">{"".join(links)}{"".join(joints)}</robot>'


def link(name, mass=1.0, i=0.1):
    return LINK.format(name=name, mass=mass, i=i)


def joint(name, parent, child, type="revolute"):
    return JOINT.format(name=name, parent=parent, child=child, type=type)


GOOD = urdf([link("base"), link("a"), link("b")], [joint("j1", "base", "a"), joint("j2", "a", "b")])


@pytest.mark.parametrize(
    "source, error, message",
    [
        ("/no/such/robot.urdf", FileNotFoundError, "/no/such/robot.urdf"),
        ("<robot name='r'><link name='a'></robot>", jaxmm.URDFError, "could not parse"),
        (urdf([link("base"), link("a"), link("b")], [joint("j1", "base", "a")]), jaxmm.URDFError, "exactly one root"),
        (urdf([link("a"), link("b")], [joint("j1", "a", "b"), joint("j2", "b", "a")]), jaxmm.URDFError, "a loop"),
        (urdf([link("base"), link("a"), link("b")], [joint("j1", "base", "a"), joint("j2", "base", "b"), joint("j3", "b", "a")]), jaxmm.URDFError, "child of two joints"),
        (urdf([link("base"), link("a", mass=-1)], [joint("j1", "base", "a")]), jaxmm.URDFError, "invalid mass"),
        (urdf([link("base"), link("a", i=-0.1)], [joint("j1", "base", "a")]), jaxmm.URDFError, "not positive semi-definite"),
        (urdf([link("base"), link("a"), link("a")], [joint("j1", "base", "a")]), jaxmm.URDFError, "duplicated link names: a"),
        (urdf([link("base"), link("a")], [joint("j1", "base", "ghost")]), jaxmm.URDFError, "unknown link 'ghost'"),
        (urdf([link("base"), link("a")], [joint("j1", "base", "a", type="planar")]), jaxmm.URDFError, "unsupported type"),
        (42, TypeError, "expected a URDF path"),
    ],
)
def test_bad_urdf(source, error, message):
    with pytest.raises(error, match=message.replace("(", r"\(")):
        jaxmm.load_robot(source)


def test_good_urdf_loads():
    robot = jaxmm.load_robot(GOOD)
    assert robot.model.joint_names == ("j1", "j2")
    assert float(jaxmm.total_mass(robot.model)) == 3.0


@pytest.mark.parametrize(
    "kwargs, error, message",
    [
        (dict(joints=["j1", "j3"]), jaxmm.UnknownNameError, "unknown joint 'j3'; did you mean 'j2', 'j1'"),
        (dict(joints=["j1"], locked={"j9": 0.0}), jaxmm.UnknownNameError, "unknown joint 'j9'"),
        (dict(joints=["j1"], locked={"j1": 0.0}), ValueError, "both optimised and locked"),
        (dict(joints=["j1", "j1"]), ValueError, "more than once"),
        (dict(jet_frames=["nozzle"]), jaxmm.UnknownNameError, "unknown frame 'nozzle'"),
        (dict(standing_configuration=np.zeros(5)), ValueError, r"shape \(9,\)"),
    ],
)
def test_bad_selection(kwargs, error, message):
    with pytest.raises(error, match=message):
        jaxmm.load_robot(GOOD, **kwargs)


def test_fixed_joint_cannot_be_optimised():
    fixed = urdf([link("base"), link("a"), link("b")], [joint("j1", "base", "a"), joint("f", "a", "b", type="fixed")])
    with pytest.raises(ValueError, match="joint 'f' is fixed"):
        jaxmm.load_robot(fixed, joints=["f"])


def test_unknown_frame_and_wrong_shapes(ironcub):
    model, q = ironcub.model, ironcub.standing_configuration
    with pytest.raises(jaxmm.UnknownNameError, match="unknown frame 'l_sole_9'; did you mean 'l_sole_"):
        jaxmm.frame_pose(model, q, "l_sole_9")
    with pytest.raises(IndexError, match="frame index 10000 out of range"):
        jaxmm.frame_pose(model, q, 10000)
    with pytest.raises(ValueError, match=r"configuration q must have shape \(30,\).*got \(29,\)"):
        jaxmm.com_position(model, q[:-1])
    with pytest.raises(ValueError, match=r"configuration q must have shape \(30,\).*got \(2, 30\)"):
        jaxmm.centroidal_momentum_matrix(model, jnp.stack([q, q]))
    with pytest.raises(ValueError, match=r"velocity ν must have shape \(29,\)"):
        jaxmm.centroidal_momentum(model, q, jnp.zeros(30))
    with pytest.raises(jaxmm.UnknownNameError, match="unknown optimised joint 'neck_pitch'"):
        model.joint_index("neck_pitch")
