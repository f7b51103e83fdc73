"""Figures and animations of a trajectory (jaxmm.analysis.plots, jaxmm.analysis.animation, jaxmm.robots.meshes).

No solve: the reduced take-off's published guess, and a synthetic trajectory made from it with
known flight knots, contact forces and thrusts. Everything renders with Agg through ``Figure``.
"""

import dataclasses
import io
import math
import types

import jax.numpy as jnp
import numpy as np
import pytest
from matplotlib.animation import FFMpegWriter
from matplotlib.collections import PolyCollection
from matplotlib.figure import Figure
from mpl_toolkits.mplot3d.art3d import Line3DCollection, Poly3DCollection
from PIL import Image

from jaxmm.analysis import animation, plots
from jaxmm import assemble_urdf, solve, tasks
from jaxmm.robots import meshes
from jaxmm.robots import ironcub_description
from jaxmm.solver import interior_point as ip

from conftest import REDUCED_TAKE_OFF

FLIGHT = (3, 9, 10, 11, 12, 13, 14)  # knots of the synthetic trajectory with every corner up


@pytest.fixture(scope="module")
def task():
    return tasks.scenario("take_off", **REDUCED_TAKE_OFF)


@pytest.fixture(scope="module")
def guess(task):
    return tasks.initial_guess(task)


@pytest.fixture(scope="module")
def trajectory(task, guess):
    """The guess with every corner 5 cm up at the FLIGHT knots, 40 N up on each grounded
    corner, thrust ramping 0 → 100 N and throttle 0 → 50 %."""
    knots = guess.knots
    airborne = np.isin(np.arange(task.n_knots), FLIGHT)
    points = np.asarray(knots.contact_points).copy()
    points[airborne, :, 2] = 0.05
    forces = np.zeros(knots.contact_forces.shape)
    forces[~airborne, :, 2] = 40.0
    ramp = np.linspace(0.0, 1.0, task.n_knots)[:, None] * np.ones(task.layout.n_jets)
    knots = dataclasses.replace(
        knots, contact_points=jnp.asarray(points), contact_forces=jnp.asarray(forces),
        thrust=jnp.asarray(100.0 * ramp), throttle=jnp.asarray(50.0 * ramp),
    )
    return dataclasses.replace(guess, knots=knots)


@pytest.fixture(scope="module")
def result(trajectory):
    """A TaskSolution-like record of a solve of 40 iterations (no solve run)."""
    iterations = 40
    history = np.full((100, len(ip.HISTORY_COLUMNS)), np.nan)
    steps = np.arange(iterations)
    history[:iterations] = np.stack(
        [1e6 / (1 + steps), 10.0 ** -(steps / 6), 10.0 ** -(steps / 10), 0.1 * 0.2 ** (steps // 10),
         np.where(steps % 7 == 3, 0.0, 1.0), np.where(steps < 5, 1e-4, 0.0), np.where(steps < 20, 6.0, 3.0),
         np.where((steps >= 12) & (steps < 15), 1.0, 0.0), np.where(steps < 5, 2.5, 1.0)], axis=1)
    solution = types.SimpleNamespace(history=history, iterations=iterations, objective=5.1e6,
                                     status=int(ip.Status.CONVERGED))
    families = {"centroidal_dynamics": 2e-9, "com": 0.0, "friction_cone": 3e-7}
    return solve.TaskSolution(trajectory, solution, families)


def _spans(ax):
    """(start, stop) [s] of the flight shading of ax."""
    return sorted((p.get_x(), p.get_x() + p.get_width()) for p in ax.patches)


def test_flight_intervals_follow_flight_knots(trajectory):
    dt = float(trajectory.total_time) / 14
    expected = ((2.5 * dt, 3.5 * dt), (8.5 * dt, 14 * dt))
    assert np.allclose(plots.flight_intervals(trajectory), expected)


def test_forces_figure_is_fig_2b(task, trajectory):
    fig = plots.plot_forces(task, trajectory)
    assert isinstance(fig, Figure)
    throttle, thrust, contact = fig.axes
    jets = task.robot.jet_frames
    assert [line.get_label() for line in throttle.lines] == list(jets)
    assert len(thrust.lines) == 2 * len(jets)  # thrust and T_max of each jet
    assert {line.get_ydata()[0] for line in thrust.lines[1::2]} == {160.0, 220.0}
    assert np.allclose(contact.lines[0].get_ydata(), np.where(np.isin(np.arange(15), FLIGHT), 0.0, 8 * 40.0))
    for ax in fig.axes:
        assert np.allclose(_spans(ax), plots.flight_intervals(trajectory))
    assert "[%]" in throttle.get_ylabel() and "[N]" in thrust.get_ylabel() and "[N]" in contact.get_ylabel()


def test_forces_figure_without_jets():
    task = tasks.scenario("jumping", knots=6)
    fig = plots.plot_forces(task, tasks.initial_guess(task))
    assert len(fig.axes) == 1 and fig.axes[0].get_xlabel() == "time [s]"


def test_com_figure_marks_targets(task, trajectory):
    fig = plots.plot_com(task, trajectory)
    assert len(fig.axes) == 4
    x, y, z, side = fig.axes
    final = np.asarray(task.params.final_com)
    for axis, ax in enumerate((x, y, z)):
        (target,) = [line for line in ax.lines if line.get_label() == "target $x_N$"]
        assert target.get_ydata()[0] == pytest.approx(final[axis])
        assert np.allclose(ax.lines[0].get_ydata(), trajectory.knots.com[:, axis])
        assert np.allclose(_spans(ax), plots.flight_intervals(trajectory))
    (target,) = [line for line in side.lines if line.get_label() == "target $x_N$"]
    assert (target.get_xdata()[0], target.get_ydata()[0]) == pytest.approx((final[0], final[2]))


def test_contact_schedule_bars(task, trajectory):
    fig = plots.plot_contact_schedule(task, trajectory)
    (ax,) = fig.axes
    bars = [c for c in ax.collections if isinstance(c, PolyCollection)]
    assert len(bars) == task.layout.n_contacts
    grounded = task.n_knots - len(FLIGHT)
    assert all(len(bar.get_paths()) == grounded for bar in bars)
    assert [t.get_text() for t in ax.get_yticklabels()] == list(task.robot.contact_frames)
    assert [t.get_text() for t in ax.get_legend().get_texts()][:2] == ["l_sole", "r_sole"]
    assert np.allclose(_spans(ax), plots.flight_intervals(trajectory))


def test_contact_schedule_into_given_axes(task, trajectory):
    fig = Figure()
    ax = fig.add_subplot()
    assert plots.plot_contact_schedule(task, trajectory, ax=ax) is fig


def test_joints_figure_shows_limits(task, trajectory):
    fig = plots.plot_joints(task, trajectory)
    names = task.robot.model.joint_names
    panels = [ax for ax in fig.axes if ax.axison]
    assert [ax.get_title() for ax in panels] == list(names)
    limits = np.rad2deg(np.asarray(task.params.joint_limits))
    for ax, (lower, upper) in zip(panels, limits):
        bottom, top = ax.get_ylim()
        assert bottom < lower < upper < top


def test_convergence_figure(result):
    fig = plots.plot_convergence(result)
    panels = len(ip.HISTORY_COLUMNS) - 1  # the restoration column marks the violation panel
    history_axes, bars = fig.axes[:panels], fig.axes[panels]
    assert [ax.get_yscale() for ax in history_axes] == ["log"] * panels
    assert [ax.get_title() for ax in history_axes][-2:] == ["block solves (refinement included)",
                                                            "factorisations (inertia correction)"]
    assert len(history_axes[0].lines[0].get_xdata()) == 40
    rejected = [line for line in history_axes[4].lines if line.get_label().startswith("rejected")]
    assert len(rejected[0].get_xdata()) == 6  # steps 3, 10, 17, 24, 31, 38
    restoration = [line for line in history_axes[1].lines if line.get_label().startswith("restoration")]
    assert list(restoration[0].get_xdata()) == [12, 13, 14]
    assert [t.get_text() for t in bars.get_yticklabels()] == list(result.violation_per_family)
    assert "CONVERGED after 40 iterations" in fig.get_suptitle()


def test_convergence_rejects_a_bad_history(result):
    bad = dataclasses.replace(result, solution=types.SimpleNamespace(**{**vars(result.solution), "history": np.zeros(5)}))
    with pytest.raises(ValueError, match="history must have shape"):
        plots.plot_convergence(bad)


def test_validation_figure(task, trajectory):
    fig = plots.plot_validation(task, trajectory)
    (ax,) = fig.axes
    labels = [t.get_text() for t in ax.get_yticklabels()]
    assert "re-simulated CoM" in labels and "FAILED" in ax.get_title()  # a guess is no solution


def test_torques_figure(task, trajectory):
    """A heat map of |τ|/τ_max (joints × knots) with a contour where a limit is crossed, and the
    base residual over time. With every limit at the joint's median |τ|, each joint crosses it."""
    from jaxmm.analysis import torques

    report = torques.joint_torques(task, trajectory)
    fig = plots.plot_torques(task, trajectory)
    load_ax, base_ax, _ = fig.axes  # the colour bar comes last
    assert load_ax.images[0].get_array().shape == (len(report.joint_names), task.n_knots)
    assert [t.get_text() for t in load_ax.get_yticklabels()] == list(report.joint_names)
    assert report.worst[0] in load_ax.get_title()
    assert bool(load_ax.collections) == bool(np.any(report.load > 1.0))  # a contour only where a limit is crossed
    assert [len(line.get_xdata()) for line in base_ax.get_lines()] == [task.n_knots] * 2
    model = task.robot.model
    median = jnp.asarray(np.median(np.abs(report.torques), axis=0))
    tight = dataclasses.replace(task, robot=dataclasses.replace(task.robot, model=dataclasses.replace(
        model, effort_limits=median)))
    assert plots.plot_torques(tight, trajectory).axes[0].collections  # the contour of |τ| = τ_max


def test_bad_trajectory_is_a_value_error(task, guess):
    short = tasks.initial_guess(tasks.scenario("take_off", knots=5))
    with pytest.raises(ValueError, match="15 knots"):
        plots.plot_forces(task, short)
    with pytest.raises(ValueError, match="15 knots"):
        animation.plot_snapshots(task, short)


def test_save_figures_writes_pngs(task, result, tmp_path):
    paths = plots.save_figures(task, result, tmp_path / "figures", dpi=40, style="stick")
    assert set(paths) == {"forces", "com", "contact_schedule", "joints", "torques", "convergence", "validation",
                          "snapshots"}
    for path in paths.values():
        assert path.stat().st_size > 1000
        with Image.open(path) as image:
            assert image.format == "PNG" and min(image.size) > 50


def _drawn(fig):
    """fig, drawn: 3D collections get their projected paths when drawn."""
    fig.savefig(io.BytesIO(), format="png", dpi=30)
    return fig


def _polygons(fig):
    return [c for ax in _drawn(fig).axes for c in ax.collections if isinstance(c, Poly3DCollection)]


def test_snapshots_with_meshes(task, trajectory):
    knots = (0, 7, 14)
    fig = _drawn(animation.plot_snapshots(task, trajectory, knots=knots))
    assert len(fig.axes) == 3
    time = np.asarray(trajectory.time)
    assert [text.get_text() for text in fig.texts][:3] == [f"t = {time[k]:.2f} s (knot {k})" for k in knots]
    for ax in fig.axes:
        robot = max((c for c in ax.collections if isinstance(c, Poly3DCollection)), key=lambda c: len(c.get_paths()))
        assert len(robot.get_paths()) > 1000  # the link meshes
    # arrows: thrust at every knot but the first (0 N), contact forces on the grounded knot 0
    assert all(any(isinstance(c, Line3DCollection) and c.get_zorder() == 10 for c in ax.collections) for ax in fig.axes)


def test_snapshots_stick_figure(task, trajectory):
    fig = _drawn(animation.plot_snapshots(task, trajectory, knots=(0, 14), style="stick"))
    for ax in fig.axes:
        links = [c for c in ax.collections if isinstance(c, Line3DCollection) and c.get_linewidth()[0] == 2.0]
        assert len(links) == 1
        assert max(len(c.get_paths()) for c in ax.collections if isinstance(c, Poly3DCollection)) < 100


def test_missing_mesh_falls_back_to_stick(task, trajectory, tmp_path):
    xml = assemble_urdf(ironcub_description()).write_xml_string().decode().replace("package://iCub/", "package://nowhere/")
    urdf = tmp_path / "robot.urdf"
    urdf.write_text(xml)
    with pytest.warns(UserWarning, match="stick figure: mesh 'package://nowhere/"):
        fig = animation.plot_snapshots(task, trajectory, knots=(0,), urdf=urdf)
    assert max(len(c.get_paths()) for c in _polygons(fig)) < 100


def test_snapshots_without_jets():
    task = tasks.scenario("jumping", knots=4)
    fig = animation.plot_snapshots(task, tasks.initial_guess(task), knots=(0, 4), style="stick")
    assert len(fig.axes) == 2 and "thrust" not in fig.get_suptitle()


def test_default_snapshots_include_the_take_off(task, trajectory):
    assert animation.default_knots(task, trajectory) == (0, 3, 6, 8, 9, 11, 14)


@pytest.mark.parametrize("knots", [(0, 15), (-1,), (), (1.5,)])
def test_snapshot_knots_out_of_range(task, trajectory, knots):
    with pytest.raises(ValueError, match=r"integers in 0\.\.14"):
        animation.plot_snapshots(task, trajectory, knots=knots, style="stick")


def test_unknown_style(task, trajectory):
    with pytest.raises(ValueError, match="style must be one of"):
        animation.plot_snapshots(task, trajectory, style="wireframe")


def test_draw_robot_into_own_axes(task, trajectory):
    fig = Figure()
    ax = fig.add_subplot(projection="3d")
    artists = animation.draw_robot(ax, task, trajectory.knots.configuration[0], thrust=np.full(4, 100.0),
                                   contact_forces=trajectory.knots.contact_forces[0])
    assert len(artists) == 3  # the robot, the thrust arrows, the contact-force arrows


def test_interpolate_hits_knots_and_keeps_unit_quaternions(trajectory):
    knots = trajectory.knots
    flipped = np.asarray(knots.base_quaternion).copy()
    flipped[1::2] *= -1  # the same rotations, with alternating signs
    trajectory = dataclasses.replace(trajectory, knots=dataclasses.replace(knots, base_quaternion=jnp.asarray(flipped)))
    times = np.asarray(trajectory.time)
    q, thrust, forces = animation.interpolate(trajectory, times)
    assert np.allclose(np.abs(np.sum(q[:, 3:7] * flipped, axis=1)), 1.0)
    assert np.allclose(q[:, 7:], knots.joint_positions) and np.allclose(thrust, knots.thrust)
    middle = animation.interpolate(trajectory, 0.5 * (times[:-1] + times[1:]))[0]
    assert np.allclose(np.linalg.norm(middle[:, 3:7], axis=1), 1.0)
    assert np.allclose(forces, knots.contact_forces)


def test_animate_writes_a_gif(task, trajectory, tmp_path):
    fps = 2
    path = animation.animate(task, trajectory, tmp_path / "take_off.gif", fps=fps, style="stick", size=(3, 3), dpi=40)
    with Image.open(path) as gif:
        assert gif.n_frames == math.ceil(float(trajectory.total_time) * fps) + 1
        assert gif.size == (120, 120)


def test_animate_bad_input(task, trajectory, tmp_path):
    with pytest.raises(ValueError, match=r"\.gif or \.mp4"):
        animation.animate(task, trajectory, tmp_path / "motion.avi")
    with pytest.raises(ValueError, match="fps must be positive"):
        animation.animate(task, trajectory, tmp_path / "motion.gif", fps=0)
    with pytest.raises(ValueError, match="knots"):
        animation.animate(task, tasks.initial_guess(tasks.scenario("take_off", knots=5)), tmp_path / "motion.gif")


def test_mp4_without_ffmpeg_says_so(task, trajectory, tmp_path, monkeypatch):
    monkeypatch.setattr(FFMpegWriter, "isAvailable", classmethod(lambda cls: False))  # a machine without ffmpeg
    with pytest.raises(ValueError, match="needs ffmpeg"):
        animation.animate(task, trajectory, tmp_path / "motion.mp4")


def test_frame_times_end_at_the_last_knot():
    assert np.allclose(animation.frame_times(1.05, 10), np.append(np.arange(11) / 10, 1.05))
    assert np.allclose(animation.frame_times(1.0, 4), np.arange(5) / 4)


def test_mesh_simplification_keeps_the_shape():
    import trimesh

    sphere = trimesh.creation.icosphere(subdivisions=4, radius=0.1)
    vertices, faces = meshes.cluster_vertices(np.asarray(sphere.vertices), np.asarray(sphere.faces), 0.02)
    assert len(faces) < len(sphere.faces) / 5
    assert np.all(np.linalg.norm(vertices, axis=1) < 0.1 + 1e-9)
    assert np.all(np.linalg.norm(vertices, axis=1) > 0.08)


def test_missing_mesh_file_names_where_it_looked(tmp_path):
    with pytest.raises(meshes.MeshNotFoundError, match="nowhere/part.stl"):
        meshes.resolve_mesh("package://nowhere/part.stl", tmp_path)


def test_meshes_of_another_robot_need_its_urdf(task):
    robot = dataclasses.replace(task.robot, model=dataclasses.replace(
        task.robot.model, topology=dataclasses.replace(task.robot.model.topology, name="other")))
    with pytest.raises(ValueError, match="pass urdf="):
        meshes.load_robot_mesh(robot)
