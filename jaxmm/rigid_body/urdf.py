"""URDF → ``Model``, parsed with yourdfpy: joint selection, locking and validation.

Fixed joints are folded into their parent body (their links stay addressable as frames and
their inertias become inertial elements of that body). Each moving joint starts a body; the
joints not chosen for optimisation are locked at given values.
"""

import collections
import io
import os

import jax.numpy as jnp
import numpy as np
import yourdfpy

from jaxmm.rigid_body.model import Model, Topology, lookup

_MOVING = ("revolute", "continuous", "prismatic")


class URDFError(ValueError):
    """A URDF that cannot describe a floating-base tree robot, with the reason."""


def read_urdf(source):
    """Parse a URDF from a path (str or PathLike), an XML string, or a ``yourdfpy.URDF``.

    Meshes are not loaded. Raises FileNotFoundError for a missing file and URDFError for
    malformed XML or a document yourdfpy cannot read.
    """
    if isinstance(source, yourdfpy.URDF):
        return source
    if isinstance(source, str) and source.lstrip().startswith("<"):
        stream, where = io.StringIO(source), "URDF string"
    elif isinstance(source, (str, os.PathLike)):
        path = os.fspath(source)
        if not os.path.isfile(path):
            raise FileNotFoundError(f"URDF file not found: {path}")
        stream, where = path, f"URDF file {path}"
    else:
        raise TypeError(f"expected a URDF path, XML string or yourdfpy.URDF, got {type(source).__name__}")
    try:
        return yourdfpy.URDF.load(
            stream,
            load_meshes=False,
            build_scene_graph=False,
            load_collision_meshes=False,
            build_collision_scene_graph=False,
        )
    except Exception as error:  # lxml and yourdfpy raise many kinds; name the source
        raise URDFError(f"could not parse {where}: {error}") from error


def _transform(origin):
    return np.eye(4) if origin is None else np.asarray(origin, dtype=float)


def _validate_structure(robot, check_inertia):
    links = [link.name for link in robot.links]
    joints = [joint.name for joint in robot.joints]
    for kind, names in (("link", links), ("joint", joints)):
        repeated = sorted(n for n, c in collections.Counter(names).items() if c > 1)
        if repeated:
            raise URDFError(f"duplicated {kind} names: {', '.join(repeated)}")
    if not links:
        raise URDFError("the URDF has no links")
    known = set(links)
    parent_of = {}
    for joint in robot.joints:
        for end in (joint.parent, joint.child):
            if end not in known:
                raise URDFError(f"joint {joint.name!r} refers to unknown link {end!r}")
        if joint.child in parent_of:
            raise URDFError(
                f"link {joint.child!r} is the child of two joints "
                f"({parent_of[joint.child]!r} and {joint.name!r}): kinematic loops are not supported"
            )
        parent_of[joint.child] = joint.name
        if joint.type not in _MOVING + ("fixed",):
            raise URDFError(f"joint {joint.name!r} has unsupported type {joint.type!r}")
        if joint.mimic is not None:
            raise URDFError(f"joint {joint.name!r} is a mimic joint: mimic joints are not supported")
    roots = [name for name in links if name not in parent_of]
    if len(roots) != 1:
        detail = ", ".join(roots) if roots else "none (every link has a parent: a loop)"
        raise URDFError(f"a URDF must have exactly one root link; found {detail}")
    for link in robot.links:
        inertial = link.inertial
        if inertial is None or inertial.mass is None:
            continue
        if not np.isfinite(inertial.mass) or inertial.mass < 0:
            raise URDFError(f"link {link.name!r} has invalid mass {inertial.mass}")
        inertia = np.asarray(inertial.inertia if inertial.inertia is not None else np.zeros((3, 3)))
        if not np.all(np.isfinite(inertia)):
            raise URDFError(f"link {link.name!r} has a non-finite inertia")
        if check_inertia and np.any(inertia):
            eig = np.linalg.eigvalsh(0.5 * (inertia + inertia.T))
            if eig.min() < -1e-12 * max(1.0, eig.max()):
                raise URDFError(
                    f"link {link.name!r} has an inertia that is not positive semi-definite "
                    f"(eigenvalues {eig}); pass check_inertia=False to load it anyway"
                )
    masses = [link.inertial.mass for link in robot.links if link.inertial is not None and link.inertial.mass]
    if not sum(masses) > 0:
        raise URDFError("the robot's links have no mass (total mass 0): its centre of mass is undefined")
    return roots[0]


def _chosen_joints(robot, joints, locked):
    """The optimised joints' names (default: every moving joint not in ``locked``, in URDF
    order), checked: each listed once, moving, known, and not also locked."""
    moving_names = [j.name for j in robot.joints if j.type in _MOVING]
    joint_types = {j.name: j.type for j in robot.joints}
    if joints is None:
        joints = [j for j in moving_names if j not in locked]
    joints = list(joints)
    if len(set(joints)) != len(joints):
        raise ValueError(f"joints are listed more than once: {sorted({j for j in joints if joints.count(j) > 1})}")
    for j in joints:
        if j in joint_types and joint_types[j] == "fixed":
            raise ValueError(f"joint {j!r} is fixed and cannot be optimised")
        lookup(moving_names, j, "joint")
    for j in locked:
        lookup(moving_names, j, "joint")
        if j in joints:
            raise ValueError(f"joint {j!r} is both optimised and locked")
    return joints


def _walk_bodies(robot, root):
    """Breadth-first walk over bodies (each body's fixed-joint links first), so bodies are
    numbered by depth and each depth level is a contiguous range of indices. Returns a dict of
    lists: bodies (names, parents, depths), moving joints (names, prismatic, 4×4 placements in
    the parent body, unit axes, (lower, upper, velocity) limits), frames (one per link: name,
    body, 4×4 placement in it) and link_body {link: (body, 4×4 placement)}."""
    children = collections.defaultdict(list)
    for joint in robot.joints:
        children[joint.parent].append(joint)
    tree = dict(body_names=[root], body_parent=[-1], body_depth=[0], joint_names=[], joint_prismatic=[], joint_T=[],
                joint_axis=[], joint_limits=[], frame_names=[], frame_body=[], frame_T=[], link_body={})
    bodies = collections.deque([0])
    while bodies:
        body = bodies.popleft()
        links = [(tree["body_names"][body], np.eye(4))]
        while links:
            link, T_link = links.pop()
            tree["link_body"][link] = (body, T_link)
            tree["frame_names"].append(link)
            tree["frame_body"].append(body)
            tree["frame_T"].append(T_link)
            for joint in children[link]:
                T_joint = T_link @ _transform(joint.origin)
                if joint.type == "fixed":
                    links.append((joint.child, T_joint))
                    continue
                bodies.append(len(tree["body_names"]))
                _add_joint(tree, joint, body, T_joint)
    return tree


def _add_joint(tree, joint, parent, T_joint):
    """Append a moving URDF ``joint`` and its child body (on ``parent``) to ``tree``."""
    axis = np.asarray(joint.axis if joint.axis is not None else [1.0, 0.0, 0.0], float)
    if not np.linalg.norm(axis) > 0:
        raise URDFError(f"joint {joint.name!r} has a zero axis")
    tree["body_names"].append(joint.child)
    tree["body_parent"].append(parent)
    tree["body_depth"].append(tree["body_depth"][parent] + 1)
    tree["joint_names"].append(joint.name)
    tree["joint_prismatic"].append(joint.type == "prismatic")
    tree["joint_T"].append(T_joint)
    tree["joint_axis"].append(axis / np.linalg.norm(axis))
    limit = joint.limit
    lower = -np.inf if joint.type == "continuous" or limit is None or limit.lower is None else limit.lower
    upper = np.inf if joint.type == "continuous" or limit is None or limit.upper is None else limit.upper
    velocity = np.inf if limit is None or limit.velocity is None else limit.velocity
    # URDFs write effort="0" for "not given" (passive or unlisted motors): no limit, not τ = 0.
    effort = np.inf if limit is None or limit.effort is None or not limit.effort > 0 else limit.effort
    tree["joint_limits"].append((lower, upper, velocity, effort))


def _inertials(robot, link_body):
    """The links' inertials in their bodies: (names, bodies, masses [kg], CoMs (3,) [m],
    rotational inertias (3, 3) about the CoM [kg m²]); links without mass are left out (a
    massless link with a rotational inertia keeps it, as in Pinocchio)."""
    names, bodies, masses, coms, inertias = [], [], [], [], []
    for link in robot.links:
        inertial = link.inertial
        if inertial is None or inertial.mass is None:
            continue
        if inertial.mass == 0 and (inertial.inertia is None or not np.any(inertial.inertia)):
            continue
        body, T_link = link_body[link.name]
        T = T_link @ _transform(inertial.origin)
        R = T[:3, :3]
        inertia = np.asarray(inertial.inertia if inertial.inertia is not None else np.zeros((3, 3)), float)
        names.append(link.name)
        bodies.append(body)
        masses.append(float(inertial.mass))
        coms.append(T[:3, 3])
        inertias.append(R @ (0.5 * (inertia + inertia.T)) @ R.T)
    return names, bodies, masses, coms, inertias


def model_from_urdf(source, joints=None, locked=None, name=None, check_inertia=True):
    """Build a floating-base ``Model`` from a URDF.

    source: path, XML string or ``yourdfpy.URDF``.
    joints: names of the optimised joints, in the order they take in s; default: every moving
        joint, in URDF order.
    locked: {joint name: value} for joints not optimised; unspecified ones are locked at 0.
    name: model name (default: the URDF robot name).
    check_inertia: reject inertias that are not positive semi-definite. The public iRonCub
        Mk1.1 URDF has such inertias on both elbows: load it with check_inertia=False.
    """
    urdf = read_urdf(source)
    robot = urdf.robot
    root = _validate_structure(robot, check_inertia)
    locked = dict(locked or {})
    joints = _chosen_joints(robot, joints, locked)
    tree = _walk_bodies(robot, root)
    body_names, body_parent, body_depth = tree["body_names"], tree["body_parent"], tree["body_depth"]
    joint_names, joint_prismatic, joint_T = tree["joint_names"], tree["joint_prismatic"], tree["joint_T"]
    joint_axis, joint_limits = tree["joint_axis"], tree["joint_limits"]
    frame_names, frame_body, frame_T = tree["frame_names"], tree["frame_body"], tree["frame_T"]
    inertial_names, inertial_body, masses, coms, inertias = _inertials(robot, tree["link_body"])

    optimised = tuple(joint_names.index(j) for j in joints)
    locked_idx = tuple(i for i, j in enumerate(joint_names) if i not in optimised)
    levels = tuple(
        (body_depth.index(d), len(body_depth) - body_depth[::-1].index(d))
        for d in range(1, max(body_depth) + 1)
    )
    topology = Topology(
        name=name or robot.name or "robot",
        body_names=tuple(body_names),
        body_parent=tuple(body_parent),
        body_levels=levels,
        joint_names=tuple(joint_names),
        joint_is_prismatic=tuple(joint_prismatic),
        optimised_joints=optimised,
        locked_joints=locked_idx,
        frame_names=tuple(frame_names),
        frame_body=tuple(frame_body),
        inertial_body=tuple(inertial_body),
        inertial_names=tuple(inertial_names),
    )
    limits = np.asarray(joint_limits, float).reshape(-1, 4)
    array = lambda x, shape: jnp.asarray(np.asarray(x, float).reshape(shape))  # noqa: E731
    nj = len(joint_names)
    return Model(
        joint_rotation=array([T[:3, :3] for T in joint_T], (nj, 3, 3)),
        joint_translation=array([T[:3, 3] for T in joint_T], (nj, 3)),
        joint_axis=array(joint_axis, (nj, 3)),
        frame_rotation=array([T[:3, :3] for T in frame_T], (-1, 3, 3)),
        frame_translation=array([T[:3, 3] for T in frame_T], (-1, 3)),
        inertial_mass=array(masses, (-1,)),
        inertial_com=array(coms, (-1, 3)),
        inertial_inertia=array(inertias, (-1, 3, 3)),
        position_limits=array(limits[list(optimised), :2], (-1, 2)),
        velocity_limits=array(limits[list(optimised), 2], (-1,)),
        effort_limits=array(limits[list(optimised), 3], (-1,)),
        locked_positions=array([locked.get(joint_names[i], 0.0) for i in locked_idx], (-1,)),
        topology=topology,
    )
