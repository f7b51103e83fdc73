"""``load_robot`` for any URDF: a ``Robot`` is a model plus what the multimodal problem needs to
know about it: which frames are jets, which frames are contact corners, and a standing
configuration.

Frames the URDF lacks (sole corners, jet nozzles) are added at load time as links on fixed
joints (``Frame``), and subtrees the robot does not have (say, forearms replaced by jets) are
removed, so that no URDF needs editing by hand.
"""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import yourdfpy

from jaxmm.rigid_body.centroidal import com_position, total_mass
from jaxmm.rigid_body.configuration import check_configuration, neutral_configuration
from jaxmm.rigid_body.model import Model
from jaxmm.rigid_body.urdf import URDFError, model_from_urdf, read_urdf

@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class Robot:
    """A model with its jet frames, contact-corner frames and a standing configuration.

    model: the rigid-body ``Model``.
    standing_configuration: (7 + n,) a configuration standing on the ground.
    jet_frames: names of the jet frames (thrust along each frame's −z axis, eq. 5).
    contact_frames: names of the contact corner frames (4 per rectangular sole).
    reference_mass: mass of the real robot this one stands for [kg], or None.
    """

    model: Model
    standing_configuration: jax.Array
    jet_frames: tuple = dataclasses.field(default=(), metadata=dict(static=True))
    contact_frames: tuple = dataclasses.field(default=(), metadata=dict(static=True))
    reference_mass: float | None = dataclasses.field(default=None, metadata=dict(static=True))

    @property
    def name(self):
        return self.model.name

    def summary(self):
        """A short human-readable description: mass, joints, frames, CoM when standing."""
        model = self.model
        mass = float(total_mass(model))
        com = np.asarray(com_position(model, self.standing_configuration))
        mass_line = f"mass            {mass:.3f} kg"
        if self.reference_mass is not None:
            mass_line += f"  (real robot {self.reference_mass:.3f} kg, {mass - self.reference_mass:+.3f} kg)"
        lines = [
            f"robot           {model.name}",
            mass_line,
            f"joints          {model.n_joints} optimised, {len(model.locked_joint_names)} locked"
            + (f" ({', '.join(model.locked_joint_names)})" if model.locked_joint_names else ""),
            f"bodies          {len(model.topology.body_names)}, frames {len(model.frame_names)}, "
            f"links with mass {len(model.topology.inertial_names)}",
            f"jets            {len(self.jet_frames)}: {', '.join(self.jet_frames) or '-'}",
            f"contact corners {len(self.contact_frames)}: {', '.join(self.contact_frames) or '-'}",
            f"CoM standing    [{com[0]: .4f}, {com[1]: .4f}, {com[2]: .4f}] m (world frame)",
            "optimised joints " + ", ".join(model.joint_names),
        ]
        return "\n".join(lines)


@dataclasses.dataclass(frozen=True)
class Frame:
    """A frame to add to a URDF: a link named ``name`` on a fixed joint to link ``parent``.

    xyz [m], rpy [rad]: the joint's URDF origin in the parent link's frame (R = Rz(yaw) Ry(pitch)
    Rx(roll)). mass [kg]: optional; with it, com_xyz [m], com_rpy [rad] place the centre of mass
    and inertia = (ixx, ixy, ixz, iyy, iyz, izz) [kg m²] is about it, in the com_rpy frame.
    joint: the fixed joint's name (default ``name + "_fixed_joint"``).
    """

    name: str
    parent: str
    xyz: tuple = (0.0, 0.0, 0.0)
    rpy: tuple = (0.0, 0.0, 0.0)
    mass: float | None = None
    com_xyz: tuple = (0.0, 0.0, 0.0)
    com_rpy: tuple = (0.0, 0.0, 0.0)
    inertia: tuple = (0.0, 0.0, 0.0, 0.0, 0.0, 0.0)
    joint: str | None = None

    @classmethod
    def of(cls, value):
        """A ``Frame`` from a ``Frame``, a tuple (name, parent[, xyz[, rpy]]) or a mapping of its fields."""
        if isinstance(value, cls):
            return value
        if isinstance(value, dict):
            unknown = set(value) - {field.name for field in dataclasses.fields(cls)}
            if unknown:
                raise ValueError(f"frame {value.get('name')!r}: unknown keys {sorted(unknown)}")
            return cls(**value)
        if isinstance(value, (tuple, list)) and 2 <= len(value) <= 4:
            return cls(*value)
        raise TypeError(f"a frame is a Frame, a (name, parent, xyz, rpy) tuple or a dict, got {value!r}")


def _rpy_matrix(xyz, rpy):
    """URDF origin (xyz, rpy: R = Rz(yaw) Ry(pitch) Rx(roll)) → 4×4 transform."""
    r, p, y = rpy
    cr, sr, cp, sp, cy, sy = np.cos(r), np.sin(r), np.cos(p), np.sin(p), np.cos(y), np.sin(y)
    T = np.eye(4)
    T[:3, :3] = [
        [cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr],
        [sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr],
        [-sp, cp * sr, cp * cr],
    ]
    T[:3, 3] = xyz
    return T


def _inertia_matrix(ixx, ixy, ixz, iyy, iyz, izz):
    return np.array([[ixx, ixy, ixz], [ixy, iyy, iyz], [ixz, iyz, izz]])


def _removed_links(robot, roots):
    """The links of ``robot`` (a ``yourdfpy.Robot``) in the subtrees rooted at ``roots``."""
    names = {link.name for link in robot.links}
    for root in roots:
        if root not in names:
            raise URDFError(f"cannot remove unknown link {root!r} from {robot.name}")
    removed = set(roots)
    changed = True
    while changed:  # close the removed set under "child of a removed link"
        changed = False
        for joint in robot.joints:
            if joint.parent in removed and joint.child not in removed:
                removed.add(joint.child)
                changed = True
    return removed


def edit_urdf(urdf, frames=(), remove_subtrees=(), name=None):
    """A copy of ``urdf`` (path, XML string or ``yourdfpy.URDF``) without the subtrees rooted at
    the links ``remove_subtrees`` and with ``frames`` (``Frame``s, or what ``Frame.of`` takes)
    added, each a link on a fixed joint, carrying its inertia if it has a mass. Raises
    URDFError naming an unknown link, a frame whose parent is missing or a duplicate name."""
    base = read_urdf(urdf).robot
    removed = _removed_links(base, remove_subtrees)
    links = [link for link in base.links if link.name not in removed]
    joints = [joint for joint in base.joints if joint.child not in removed]
    known = {link.name for link in links}
    joint_names = {joint.name for joint in joints}
    for frame in map(Frame.of, frames):
        if frame.parent not in known:
            raise URDFError(f"frame {frame.name!r}: parent link {frame.parent!r} is not in {base.name}")
        joint_name = frame.joint or f"{frame.name}_fixed_joint"
        if frame.name in known or joint_name in joint_names:
            raise URDFError(f"frame {frame.name!r}: {base.name} already has a link or joint of that name")
        inertial = None
        if frame.mass is not None:
            inertial = yourdfpy.Inertial(origin=_rpy_matrix(frame.com_xyz, frame.com_rpy), mass=float(frame.mass),
                                         inertia=_inertia_matrix(*frame.inertia))
        links.append(yourdfpy.Link(name=frame.name, inertial=inertial))
        joints.append(yourdfpy.Joint(name=joint_name, type="fixed", parent=frame.parent, child=frame.name,
                                     origin=_rpy_matrix(frame.xyz, frame.rpy)))
        known.add(frame.name)
        joint_names.add(joint_name)
    robot = yourdfpy.Robot(name=name or base.name, links=links, joints=joints, materials=base.materials)
    return yourdfpy.URDF(robot=robot, build_scene_graph=False, load_meshes=False)


def load_robot(
    urdf,
    joints=None,
    locked=None,
    jet_frames=(),
    contact_frames=(),
    standing_configuration=None,
    name=None,
    reference_mass=None,
    check_inertia=True,
    frames=(),
    remove_subtrees=(),
):
    """Load any URDF as a floating-base ``Robot``.

    urdf: path, XML string or ``yourdfpy.URDF``; it is not modified.
    frames: ``Frame``s (or (name, parent, xyz, rpy) tuples) added on fixed joints, e.g. the sole
    corners and jet frames that a URDF lacks; remove_subtrees: links whose subtrees are dropped
    (see ``edit_urdf``).
    joints: optimised joint names in the order of s (default: all moving joints).
    locked: {joint: value} for the other joints (default 0).
    jet_frames, contact_frames: frame names (checked against the model).
    standing_configuration: (7 + n,) configuration; default: the neutral configuration.
    check_inertia: reject link inertias that are not positive semi-definite.
    """
    if frames or remove_subtrees:
        urdf = edit_urdf(urdf, frames, remove_subtrees)
    model = model_from_urdf(urdf, joints=joints, locked=locked, name=name, check_inertia=check_inertia)
    model.frame_indices(jet_frames)
    model.frame_indices(contact_frames)
    if standing_configuration is None:
        standing = neutral_configuration(model)
    else:
        standing = check_configuration(model, jnp.asarray(standing_configuration, dtype=float))
    return Robot(model, standing, tuple(jet_frames), tuple(contact_frames), reference_mass)


