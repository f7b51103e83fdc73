"""Ready robots: ``load_robot`` for any URDF, and the jet-powered iCub assembled from icub-models.

A ``Robot`` is a model plus what the multimodal problem needs to know about it: which frames
are jets, which frames are contact corners, and a standing configuration.
"""

import dataclasses
import importlib.resources
import tomllib

import jax
import jax.numpy as jnp
import numpy as np
import yourdfpy

from jaxmm.centroidal import com_position, total_mass
from jaxmm.configuration import check_configuration, make_configuration, neutral_configuration
from jaxmm.model import Model
from jaxmm.urdf import URDFError, model_from_urdf, read_urdf

ASSETS = importlib.resources.files("jaxmm.assets")


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
):
    """Load any URDF as a floating-base ``Robot``.

    urdf: path, XML string or ``yourdfpy.URDF``.
    joints: optimised joint names in the order of s (default: all moving joints).
    locked: {joint: value} for the other joints (default 0).
    jet_frames, contact_frames: frame names (checked against the model).
    standing_configuration: (7 + n,) configuration; default: the neutral configuration.
    check_inertia: reject link inertias that are not positive semi-definite.
    """
    model = model_from_urdf(urdf, joints=joints, locked=locked, name=name, check_inertia=check_inertia)
    model.frame_indices(jet_frames)
    model.frame_indices(contact_frames)
    if standing_configuration is None:
        standing = neutral_configuration(model)
    else:
        standing = check_configuration(model, jnp.asarray(standing_configuration, dtype=float))
    return Robot(model, standing, tuple(jet_frames), tuple(contact_frames), reference_mass)


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


def assemble_urdf(description):
    """A ``yourdfpy.URDF`` from an icub-models base and a description (a parsed TOML dict).

    The base's subtrees listed in ``base.remove_subtrees`` are removed, then each
    ``frames`` entry is added as a link on a fixed joint, with its inertia if it has a mass.
    """
    import icub_models

    base_name = description["base"]["icub_model"]
    base = read_urdf(icub_models.get_model_file(base_name)).robot
    removed = set(description["base"].get("remove_subtrees", ()))
    links_by_name = {link.name: link for link in base.links}
    for root in removed:
        if root not in links_by_name:
            raise URDFError(f"cannot remove unknown link {root!r} from {base_name}")
    changed = True
    while changed:  # close the removed set under "child of a removed link"
        changed = False
        for joint in base.joints:
            if joint.parent in removed and joint.child not in removed:
                removed.add(joint.child)
                changed = True
    links = [link for link in base.links if link.name not in removed]
    joints = [joint for joint in base.joints if joint.child not in removed]
    known = {link.name for link in links}
    for frame in description.get("frames", ()):
        if frame["parent"] not in known:
            raise URDFError(f"frame {frame['name']!r}: parent link {frame['parent']!r} is not in {base_name}")
        inertial = None
        if "mass" in frame:
            inertial = yourdfpy.Inertial(
                origin=_rpy_matrix(frame["com_xyz"], frame["com_rpy"]),
                mass=float(frame["mass"]),
                inertia=_inertia_matrix(*frame["inertia"]),
            )
        links.append(yourdfpy.Link(name=frame["name"], inertial=inertial))
        joints.append(
            yourdfpy.Joint(
                name=frame["joint"],
                type="fixed",
                parent=frame["parent"],
                child=frame["name"],
                origin=_rpy_matrix(frame["xyz"], frame["rpy"]),
            )
        )
        known.add(frame["name"])
    robot = yourdfpy.Robot(name=description["name"], links=links, joints=joints, materials=base.materials)
    return yourdfpy.URDF(robot=robot, build_scene_graph=False, load_meshes=False)


def ironcub_description():
    """The parsed ``assets/ironcub.toml`` description of the jet-powered iCub."""
    with (ASSETS / "ironcub.toml").open("rb") as stream:
        return tomllib.load(stream)


def load_ironcub(joints=None, locked=None):
    """The default robot: iRonCub assembled from icub-models' iCubGazeboV2_5 and ``assets/``.

    joints, locked: override the description's 23 optimised joints and locked neck; the
    standing configuration keeps the published values of the joints that remain optimised.
    """
    description = ironcub_description()
    joints = description["joints"]["optimised"] if joints is None else list(joints)
    locked = description["joints"].get("locked", {}) if locked is None else locked
    standing = description["standing"]
    published = dict(zip(description["joints"]["optimised"], standing["joint_positions"]))
    q = make_configuration(
        standing["base_position"],
        standing["base_quaternion"],
        [published.get(joint, 0.0) for joint in joints],
    )
    return load_robot(
        assemble_urdf(description),
        joints=joints,
        locked=locked,
        jet_frames=description["jets"]["frames"],
        contact_frames=description["contacts"]["frames"],
        standing_configuration=q,
        name=description["name"],
        reference_mass=description.get("reference_mass_kg"),
    )
