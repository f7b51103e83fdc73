"""The robot model: an immutable pytree of static topology and differentiable array leaves.

Conventions (the one place they are written down; the README repeats them):

* **Configuration** q = (p, ρ, s), shape (7 + n,): base position p (3,) in the world frame
  [m]; base orientation ρ (4,), a unit quaternion **(x, y, z, w)** rotating base-frame vectors
  into the world frame; positions s (n,) of the *optimised* joints [rad or m], in the order
  given when the model was loaded. Locked joints are held at ``Model.locked_positions``.
* **Velocity** ν = (ṗ, ω, ṡ), shape (6 + n,): ṗ the base origin's velocity and ω the base
  angular velocity, both expressed in the world frame (the paper's "mixed" velocity, eq. 1),
  then the joint velocities ṡ. Hence Ṙ = S(ω) R and q̇ = (ṗ, ½ (ω, 0) ⊗ ρ, ṡ).
* Units are SI; every array is float64.

Structure (names, parent indices, joint types) lives in ``Topology``, a hashable static
field, so it never becomes a tracer; all numbers are ``jax.Array`` leaves, so they can be
differentiated and vmapped. Names are resolved to indices in Python, once, outside traced code.
"""

import dataclasses
import difflib

import jax
import numpy as np


class UnknownNameError(KeyError, ValueError):
    """A joint or frame name that the model does not have."""

    def __str__(self):
        return str(self.args[0])


@dataclasses.dataclass(frozen=True)
class Topology:
    """Static structure of a model (hashable, never traced).

    Bodies are the rigid groups of links separated by moving joints; body 0 is the floating
    base. Every moving joint of the URDF (optimised or locked) starts one body.

    body_names: (nb,) name of the URDF link each body starts with.
    body_parent: (nb,) parent body index (−1 for the base).
    body_levels: (start, stop) index range of the bodies at each depth 1, 2, … (bodies are
        numbered by depth, so each level is contiguous; used for batched kinematics).
    joint_names: (nb − 1,) name of the joint moving body i + 1.
    joint_is_prismatic: (nb − 1,) True for prismatic, False for revolute/continuous joints.
    optimised_joints: (n,) index into joint_names of each entry of s.
    locked_joints: index into joint_names of each locked joint.
    frame_names: (nf,) every URDF link, then every extra frame, each addressable by name.
    frame_body: (nf,) body each frame is rigidly attached to.
    inertial_body: body of each link that has mass (links with mass are "inertial elements").
    inertial_names: name of the link of each inertial element.
    """

    name: str
    body_names: tuple
    body_parent: tuple
    body_levels: tuple
    joint_names: tuple
    joint_is_prismatic: tuple
    optimised_joints: tuple
    locked_joints: tuple
    frame_names: tuple
    frame_body: tuple
    inertial_body: tuple
    inertial_names: tuple

    @property
    def n_joints(self):
        """Number of optimised joints n."""
        return len(self.optimised_joints)

    @property
    def joint_support(self):
        """(nb − 1, nb) bool: entry [j, b] is True when joint j moves body b."""
        nb = len(self.body_names)
        support = np.zeros((nb - 1, nb), dtype=bool)
        for body in range(1, nb):
            ancestor = body
            while ancestor > 0:
                support[ancestor - 1, body] = True
                ancestor = self.body_parent[ancestor]
        return support


def lookup(names, name, what):
    if not isinstance(name, str):
        raise TypeError(f"{what} name must be a string, got {type(name).__name__}")
    try:
        return names.index(name)
    except ValueError:
        close = difflib.get_close_matches(name, names, n=3, cutoff=0.5)
        if close:
            hint = f"; did you mean {', '.join(map(repr, close))}?"
        else:
            shown = ", ".join(map(repr, names[:10])) + (", …" if len(names) > 10 else "")
            hint = f"; the model has {len(names)}: {shown}"
        raise UnknownNameError(f"unknown {what} {name!r}{hint}") from None


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class Model:
    """A floating-base robot model (a pytree; see the module docstring for conventions).

    Shapes: nb bodies, nb − 1 moving joints, n optimised joints, nf frames, ne inertial elements.

    joint_rotation, joint_translation: (nb − 1, 3, 3), (nb − 1, 3): placement of each joint
        frame in its parent body's frame (the URDF joint origin, fixed joints folded in).
    joint_axis: (nb − 1, 3) unit axis in the joint frame.
    frame_rotation, frame_translation: (nf, 3, 3), (nf, 3): each frame in its body's frame.
    inertial_mass: (ne,) [kg]; inertial_com: (ne, 3) [m] and inertial_inertia: (ne, 3, 3)
        [kg m²] about the element's CoM, both in its body's frame.
    position_limits: (n, 2) lower and upper limit of each optimised joint (URDF limits).
    velocity_limits: (n,) URDF velocity limits [rad/s or m/s].
    effort_limits: (n,) URDF effort limits: the largest |torque| [N m] (force [N] for prismatic
        joints) each optimised joint's motor can exert; inf where the URDF gives none (or 0).
    locked_positions: (n_locked,) values of the locked joints.
    topology: static structure (``Topology``).
    """

    joint_rotation: jax.Array
    joint_translation: jax.Array
    joint_axis: jax.Array
    frame_rotation: jax.Array
    frame_translation: jax.Array
    inertial_mass: jax.Array
    inertial_com: jax.Array
    inertial_inertia: jax.Array
    position_limits: jax.Array
    velocity_limits: jax.Array
    effort_limits: jax.Array
    locked_positions: jax.Array
    topology: Topology = dataclasses.field(metadata=dict(static=True))

    @property
    def name(self):
        return self.topology.name

    @property
    def n_joints(self):
        """Number of optimised joints n."""
        return self.topology.n_joints

    @property
    def nq(self):
        """Size of a configuration q: 7 + n."""
        return 7 + self.n_joints

    @property
    def nv(self):
        """Size of a velocity ν: 6 + n."""
        return 6 + self.n_joints

    @property
    def joint_names(self):
        """Names of the optimised joints, in the order of s."""
        return tuple(self.topology.joint_names[j] for j in self.topology.optimised_joints)

    @property
    def locked_joint_names(self):
        return tuple(self.topology.joint_names[j] for j in self.topology.locked_joints)

    @property
    def frame_names(self):
        return self.topology.frame_names

    def frame_index(self, frame):
        """Index of a frame given by name (or already an index); raises on unknown names."""
        if isinstance(frame, (int, np.integer)):
            if not 0 <= frame < len(self.frame_names):
                raise IndexError(f"frame index {frame} out of range [0, {len(self.frame_names)})")
            return int(frame)
        return lookup(self.frame_names, frame, "frame")

    def frame_indices(self, frames):
        """Indices of several frames (names or indices), as a tuple of ints."""
        if isinstance(frames, (str, int, np.integer)):
            raise TypeError("frame_indices expects a sequence of frames, got a single frame")
        return tuple(self.frame_index(f) for f in frames)

    def joint_index(self, joint):
        """Position in s of an optimised joint given by name."""
        return lookup(self.joint_names, joint, "optimised joint")
