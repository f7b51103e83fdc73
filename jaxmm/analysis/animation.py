"""The robot in 3D: a snapshot strip at chosen knots (the paper's Fig. 2a) and an animation.

The robot is drawn from its link meshes (``jaxmm.robots.meshes``) or as a stick figure (links as
segments between joint origins, feet as the rectangles of their contact corners); jets as
cylinders; the forces on the robot as arrows force_scale [m/N] long: the thrust −T R e_z of
each jet (orange), drawn from the jet's top along its axis (its line of action, so the arrow
stays outside the jet), and the contact force f at each corner (green). Built on
``matplotlib.figure.Figure`` only (no pyplot), so it works headless.
"""

import functools
import math
import pathlib
import warnings

import jax
import numpy as np
from matplotlib import animation as mpl_animation
from matplotlib.colors import to_rgb
from matplotlib.figure import Figure
from mpl_toolkits.mplot3d.art3d import Line3DCollection, Poly3DCollection

from jaxmm.analysis import validation
from jaxmm.robots import meshes
from jaxmm.rigid_body.kinematics import body_poses, frame_poses

STYLES = ("mesh", "stick")
FORCE_SCALE = 1.0 / 500.0  # [m/N]: a contact corner holding 1/8 of iRonCub's weight is 9 cm long
VIEW = (12.0, -150.0)  # (elevation, azimuth) [deg]: from the robot's front left (it faces −x)
JET_LENGTH, JET_RADIUS = 0.30, 0.05  # [m] a jet body, from its nozzle (the frame origin) along −z
LIGHT = np.array([-0.5, -0.3, 1.0]) / np.linalg.norm([-0.5, -0.3, 1.0])
THRUST_COLOUR, CONTACT_COLOUR, JET_COLOUR, FOOT_COLOUR = "tab:orange", "tab:green", "0.3", "tab:blue"
GROUND_SPACING = 0.25  # [m] between the lines of the ground grid


@functools.partial(jax.jit, static_argnames=("jets", "corners"))
def _poses(model, configurations, jets, corners):
    def one(q):
        R, p = body_poses(model, q)
        jet_p, jet_R = frame_poses(model, q, jets)
        corner_p, _ = frame_poses(model, q, corners)
        return R, p, jet_p, jet_R, corner_p

    return jax.vmap(one)(configurations)


def _robot_poses(robot, configurations):
    """What a drawing needs, for configurations (K, 7 + n): {body_R (K, nb, 3, 3), body_p
    (K, nb, 3) [m], jet_p (K, nj, 3) [m], jet_R (K, nj, 3, 3), corner_p (K, nc, 3) [m]}."""
    values = _poses(robot.model, np.asarray(configurations, float), tuple(robot.jet_frames), tuple(robot.contact_frames))
    return dict(zip(("body_R", "body_p", "jet_p", "jet_R", "corner_p"), (np.asarray(v) for v in values)))


def _pose(poses, index):
    return {name: value[index] for name, value in poses.items()}


def _robot_mesh(robot, style, urdf, resolution):
    """The RobotMesh for style "mesh"; None (a stick figure) for "stick" or, with a warning,
    when the meshes cannot be loaded."""
    if style not in STYLES:
        raise ValueError(f"style must be one of {STYLES}, got {style!r}")
    if style == "stick":
        return None
    try:
        return meshes.load_robot_mesh(robot, urdf, resolution)
    except (meshes.MeshNotFoundError, ValueError) as error:
        warnings.warn(f"drawing a stick figure: {error}", stacklevel=3)
        return None


def _cylinder(bottom, axis, length, radius, sides=10):
    """Side of a cylinder from bottom [m] along the unit axis, as triangles (2 · sides, 3, 3)
    (triangles only: a collection of polygons of one size is not padded, masked, by mplot3d)."""
    helper = np.array([1.0, 0, 0]) if abs(axis[0]) < 0.9 else np.array([0, 1.0, 0])
    u = np.cross(axis, helper)
    u /= np.linalg.norm(u)
    v = np.cross(axis, u)
    angles = np.linspace(0, 2 * np.pi, sides + 1)
    ring = bottom + radius * (np.cos(angles)[:, None] * u + np.sin(angles)[:, None] * v)
    top = ring + length * axis
    return np.concatenate([np.stack([ring[:-1], ring[1:], top[1:]], axis=1), np.stack([ring[:-1], top[1:], top[:-1]], axis=1)])


def _jets(pose):
    """(nj · 2 sides, 3, 3) triangles of the jet cylinders, each from the nozzle up its −z axis."""
    faces = [_cylinder(p, -R[:, 2], JET_LENGTH, JET_RADIUS) for p, R in zip(pose["jet_p"], pose["jet_R"])]
    return np.concatenate(faces) if faces else np.zeros((0, 3, 3))


def _shade(polygons, colours):
    """Two-sided Lambert shading of polygons (F, k, 3) of RGB colours (F, 3)."""
    normals = np.cross(polygons[:, 1] - polygons[:, 0], polygons[:, 2] - polygons[:, 0])
    normals /= np.maximum(np.linalg.norm(normals, axis=1, keepdims=True), 1e-12)
    return np.clip(colours * (0.45 + 0.55 * np.abs(normals @ LIGHT))[:, None], 0, 1)


def _feet(robot, corners):
    """[(body index, sole polygon (k, 3) [m])]: each foot's corners ordered around their centre."""
    model = robot.model
    feet = []
    for _, members in validation.corner_groups(robot):
        points = corners[list(members)]
        centre = points.mean(axis=0)
        order = np.argsort(np.arctan2(points[:, 1] - centre[1], points[:, 0] - centre[0]))
        body = model.topology.frame_body[model.frame_index(robot.contact_frames[members[0]])]
        feet.append((body, points[order]))
    return feet


def _outline(robot, pose, mesh):
    """(k, 3) [m] points that bound the drawn robot."""
    if mesh is not None:
        R, p = pose["body_R"][mesh.vertex_body], pose["body_p"][mesh.vertex_body]
        body = np.einsum("vij,vj->vi", R, mesh.vertices) + p
    else:
        body = np.concatenate([pose["body_p"], pose["corner_p"]])
    return np.concatenate([body, _jets(pose).reshape(-1, 3)])


def _draw(ax, robot, pose, mesh, thrust, forces, force_scale):
    """Draw one robot (pose: one entry of ``_robot_poses``) into a 3D axes; returns its artists."""
    jets = _jets(pose)
    if mesh is not None:
        triangles = np.concatenate([mesh.triangles(pose["body_R"], pose["body_p"]), jets])
        colours = _shade(triangles, np.concatenate([mesh.face_colours, np.tile(to_rgb(JET_COLOUR), (len(jets), 1))]))
        # edges in the face colour hide the seams between the simplified triangles
        artists = [ax.add_collection3d(Poly3DCollection(triangles, facecolors=colours, edgecolors=colours, linewidths=0.3))]
    else:
        model, p = robot.model, pose["body_p"]
        parent = model.topology.body_parent
        links = [(p[parent[b]], p[b]) for b in range(1, len(parent))]
        feet = _feet(robot, pose["corner_p"])
        links += [(p[body], sole.mean(axis=0)) for body, sole in feet]  # ankle to the sole's centre
        jet_bodies = [model.topology.frame_body[i] for i in model.frame_indices(robot.jet_frames)]
        middles = pose["jet_p"] - 0.5 * JET_LENGTH * pose["jet_R"][:, :, 2]
        links += [(p[b], middle) for b, middle in zip(jet_bodies, middles)]
        soles = [sole for _, sole in feet]
        artists = [
            ax.add_collection3d(Poly3DCollection(soles, facecolors=FOOT_COLOUR, edgecolors="k", linewidths=0.5)),
            ax.add_collection3d(Poly3DCollection(jets, facecolors=JET_COLOUR, edgecolors=JET_COLOUR, linewidths=0.3,
                                                 alpha=0.5)),
            ax.add_collection3d(Line3DCollection(links, colors="k", linewidths=2.0)),
            ax.scatter(*p.T, s=8, color="k", depthshade=False),
        ]
    up = -pose["jet_R"][:, :, 2]  # along each jet, nozzle to top: the direction of its thrust
    thrust_forces = up * np.asarray(thrust, float)[:, None]
    artists += _arrows(ax, pose["jet_p"] + JET_LENGTH * up, thrust_forces, force_scale, THRUST_COLOUR)
    artists += _arrows(ax, pose["corner_p"], np.asarray(forces, float), force_scale, CONTACT_COLOUR)
    return artists


def _arrows(ax, points, forces, scale, colour, threshold=1.0):
    """Arrows of forces (k, 3) [N] at points (k, 3) [m]; those below threshold [N] left out."""
    shown = np.linalg.norm(forces, axis=1) > threshold
    if not shown.any():
        return []
    return [ax.quiver(*points[shown].T, *(scale * forces[shown]).T, color=colour, linewidths=1.5,
                      arrow_length_ratio=0.2, zorder=10)]


def _window(ax, centre, half_width, top, view, zoom=1.0):
    """Axis limits: a box of half_width [m] around centre (x, y) from the ground up to top [m],
    equal scales, zoomed by zoom, the ground grid and the camera at view (elevation, azimuth)
    [deg]."""
    (x0, x1), (y0, y1) = ((c - half_width, c + half_width) for c in centre)
    ax.set(xlim=(x0, x1), ylim=(y0, y1), zlim=(0.0, top))
    ax.set_box_aspect((x1 - x0, y1 - y0, top), zoom=zoom)
    ax.view_init(*view)
    ax.set_axis_off()
    lines = [((x, y0, 0), (x, y1, 0)) for x in np.arange(math.ceil(x0 / GROUND_SPACING), x1 / GROUND_SPACING) * GROUND_SPACING]
    lines += [((x0, y, 0), (x1, y, 0)) for y in np.arange(math.ceil(y0 / GROUND_SPACING), y1 / GROUND_SPACING) * GROUND_SPACING]
    ax.add_collection3d(Line3DCollection(lines, colors="0.75", linewidths=0.6, zorder=0))
    ground = [[(x0, y0, 0), (x1, y0, 0), (x1, y1, 0), (x0, y1, 0)]]
    ax.add_collection3d(Poly3DCollection(ground, facecolors="0.93", edgecolors="0.6", zorder=-1))


def draw_robot(ax, task, configuration, *, thrust=None, contact_forces=None, style="mesh", urdf=None,
               force_scale=FORCE_SCALE, resolution=meshes.RESOLUTION):
    """Draw task.robot at configuration (7 + n,) into the 3D axes ax, with thrust (nj,) [N] and
    contact_forces (nc, 3) [N] as arrows (None: none). style "mesh" (falls back to "stick"
    with a warning when the meshes cannot be loaded) or "stick"; urdf: the URDF path for the
    meshes of a robot other than the default iRonCub. Returns the list of artists."""
    robot = task.robot
    mesh = _robot_mesh(robot, style, urdf, resolution)
    pose = _pose(_robot_poses(robot, np.asarray(configuration, float)[None]), 0)
    thrust = np.zeros(len(robot.jet_frames)) if thrust is None else thrust
    contact_forces = np.zeros((len(robot.contact_frames), 3)) if contact_forces is None else contact_forces
    return _draw(ax, robot, pose, mesh, thrust, contact_forces, force_scale)


def default_knots(task, trajectory, count=6):
    """count knots evenly spread from 0 to N (both included) and the first knot of each flight
    phase (``validation.flight_knots``), as a sorted tuple of ints."""
    even = np.round(np.linspace(0, task.n_intervals, min(count, task.n_knots)))
    flight = validation.flight_knots(validation.airborne_corners(trajectory))
    take_offs = [k for k in flight if k - 1 not in flight]
    return tuple(int(k) for k in np.unique(np.concatenate([even, take_offs])))


def plot_snapshots(task, trajectory, knots=None, *, style="mesh", urdf=None, fig=None, force_scale=FORCE_SCALE,
                   view=VIEW, resolution=meshes.RESOLUTION):
    """The robot at several knots side by side (the paper's Fig. 2a): one 3D panel per knot,
    all at the same scale and height (ground at z = 0, a grid every 25 cm), each centred on its
    robot, titled with its time [s]; thrust and contact-force arrows force_scale [m/N] long.

    knots: knot indices in 0..N (default: ``default_knots``). style, urdf, resolution: as
    ``draw_robot``. view: (elevation, azimuth) [deg]. Returns the Figure.
    """
    validation.check_trajectory(task, trajectory)
    knots = default_knots(task, trajectory) if knots is None else tuple(knots)
    bad = [k for k in knots if not isinstance(k, (int, np.integer)) or not 0 <= k <= task.n_intervals]
    if not knots or bad:
        raise ValueError(f"knots must be a non-empty sequence of integers in 0..{task.n_intervals}, got {knots!r}")
    robot = task.robot
    mesh = _robot_mesh(robot, style, urdf, resolution)
    index = np.asarray(knots, int)
    poses = _robot_poses(robot, np.asarray(trajectory.knots.configuration)[index])
    thrust = np.asarray(trajectory.knots.thrust)[index]
    forces = np.asarray(trajectory.knots.contact_forces)[index]
    outlines = [_outline(robot, _pose(poses, i), mesh) for i in range(len(knots))]
    half_width = max(0.5 * np.ptp(o[:, :2], axis=0).max() for o in outlines) + 0.1
    top = max(o[:, 2].max() for o in outlines) + 0.1
    if fig is None:
        fig = Figure(figsize=(2.2 * len(knots), 4.0))
        fig.subplots_adjust(left=0, right=1, bottom=0.02, top=0.86, wspace=0)
    time = np.asarray(trajectory.time)
    for i, knot in enumerate(knots):
        ax = fig.add_subplot(1, len(knots), i + 1, projection="3d", computed_zorder=False)
        # mplot3d keeps its axes square: a tall panel holds a square axes, zoomed to the
        # panel's height, whose artists may then draw outside it
        panel = ax.get_position(original=True)
        width, height = panel.width * fig.get_figwidth(), panel.height * fig.get_figheight()
        centre = 0.5 * (outlines[i][:, :2].min(axis=0) + outlines[i][:, :2].max(axis=0))
        _window(ax, centre, half_width, top, view, zoom=max(height / width, 1.0))
        _draw(ax, robot, _pose(poses, i), mesh, thrust[i], forces[i], force_scale)
        for artist in ax.collections:
            artist.set_clip_on(False)
        fig.text(0.5 * (panel.x0 + panel.x1), panel.y1, f"t = {time[knot]:.2f} s (knot {knot})", ha="center", va="bottom")
    arrows = ("thrust orange, " if robot.jet_frames else "") + f"contact forces green, {force_scale * 1000:g} mm/N"
    fig.suptitle(f"{task.name}: snapshots (arrows: {arrows})")
    return fig


def interpolate(trajectory, times):
    """The motion at times (F,) [s], linear between knots: configurations (F, 7 + n) with the
    quaternion normalised (and its sign kept continuous), thrust (F, nj) [N] and contact forces
    (F, nc, 3) [N]."""
    knots = trajectory.knots
    knot_times = np.asarray(trajectory.time)
    q = np.array(knots.configuration, float)
    flips = np.cumprod(np.where(np.sum(q[1:, 3:7] * q[:-1, 3:7], axis=1) < 0, -1.0, 1.0))
    q[1:, 3:7] *= flips[:, None]

    def along(values):
        values = np.asarray(values, float)
        flat = values.reshape(len(knot_times), -1)
        out = np.empty((len(times), flat.shape[1]))
        for column in range(flat.shape[1]):
            out[:, column] = np.interp(times, knot_times, flat[:, column])
        return out.reshape((len(times),) + values.shape[1:])

    configurations = along(q)
    configurations[:, 3:7] /= np.linalg.norm(configurations[:, 3:7], axis=1, keepdims=True)
    return configurations, along(knots.thrust), along(knots.contact_forces)


def frame_times(total_time, fps):
    """The times [s] of the frames of an animation at fps: every 1/fps s from 0, the last one
    at total_time [s] (ceil(total_time · fps) + 1 frames)."""
    count = math.ceil(float(total_time) * fps - 1e-9) + 1
    return np.minimum(np.arange(count) / fps, float(total_time))


def animate(task, trajectory, path, fps=10, *, style="mesh", urdf=None, force_scale=FORCE_SCALE, view=VIEW,
            resolution=meshes.RESOLUTION, size=(5.0, 5.0), dpi=80):
    """Write the motion to path: a GIF (Pillow), or an MP4 when the path ends in .mp4 and
    ffmpeg is available. Frames every 1/fps s of the trajectory's time (``frame_times``), the
    motion interpolated linearly between knots (``interpolate``), a fixed camera that frames the
    whole motion, a time label. size [in] and dpi set the frame size. style, urdf, resolution,
    force_scale, view: as ``plot_snapshots``. Returns the path (a ``pathlib.Path``)."""
    validation.check_trajectory(task, trajectory)
    path = pathlib.Path(path)
    if path.suffix.lower() not in (".gif", ".mp4"):
        raise ValueError(f"the animation path must end in .gif or .mp4, got {str(path)!r}")
    if not fps > 0:
        raise ValueError(f"fps must be positive, got {fps!r}")
    if path.suffix.lower() == ".mp4":
        if not mpl_animation.FFMpegWriter.isAvailable():
            raise ValueError(f"writing {path.name} needs ffmpeg, which is not available: write a .gif instead")
        writer = mpl_animation.FFMpegWriter(fps=fps)
    else:
        writer = mpl_animation.PillowWriter(fps=fps)
    robot = task.robot
    mesh = _robot_mesh(robot, style, urdf, resolution)
    times = frame_times(trajectory.total_time, fps)
    configurations, thrust, forces = interpolate(trajectory, times)
    poses = _robot_poses(robot, configurations)
    outline = np.concatenate([_outline(robot, _pose(poses, i), mesh) for i in range(len(times))])
    fig = Figure(figsize=size)
    ax = fig.add_axes((0, 0, 1, 1), projection="3d", computed_zorder=False)
    centre = 0.5 * (outline[:, :2].min(axis=0) + outline[:, :2].max(axis=0))
    _window(ax, centre, 0.5 * np.ptp(outline[:, :2], axis=0).max() + 0.1, outline[:, 2].max() + 0.1, view)
    label = fig.text(0.04, 0.95, "", fontsize="large", family="monospace")
    fig.text(0.04, 0.91, task.name, fontsize="medium")
    artists = []
    with writer.saving(fig, str(path), dpi):
        for i, t in enumerate(times):
            for artist in artists:
                artist.remove()
            artists = _draw(ax, robot, _pose(poses, i), mesh, thrust[i], forces[i], force_scale)
            label.set_text(f"t = {t:5.2f} s")
            writer.grab_frame()
    return path
