"""Figures of a solved trajectory and of its solve, for any task (matplotlib, no pyplot).

Every function builds on ``matplotlib.figure.Figure`` directly, so it works headless, in CI and
inline in Jupyter, and returns the Figure (pass ``fig=`` or ``ax=`` to draw into your own).
Times are in seconds from the first knot; flight phases (every contact corner off the ground,
``validation.flight_knots``) are shaded red as in the paper's Fig. 2b–4b.
"""

import pathlib

import numpy as np
from matplotlib.figure import Figure
from matplotlib.ticker import MaxNLocator

from jaxmm.analysis import animation, torques, validation
from jaxmm.rigid_body.centroidal import total_mass
from jaxmm.solver import interior_point as ip

FLIGHT_COLOUR = "tab:red"
CONTACT_HEIGHT = 0.01  # [m] a corner higher than this is off the ground (as ``validation.validate``)


def _time(trajectory):
    return np.asarray(trajectory.time)


def _runs(knots):
    """Runs of consecutive knots: a sequence of ints → a list of int arrays."""
    return np.split(np.asarray(knots, int), np.flatnonzero(np.diff(knots) > 1) + 1) if len(knots) else []


def flight_intervals(trajectory, contact_height=CONTACT_HEIGHT):
    """The flight phases as ((t_start, t_stop), ...) [s]: each run of consecutive flight knots
    k0..k1 (``validation.flight_knots``) spans [t_k0 − Δt/2, t_k1 + Δt/2] clipped to the horizon,
    so that a single flight knot still shows."""
    time = _time(trajectory)
    half = 0.5 * (time[1] - time[0])
    runs = _runs(validation.flight_knots(validation.airborne_corners(trajectory, contact_height)))
    return tuple(
        (float(max(time[run[0]] - half, time[0])), float(min(time[run[-1]] + half, time[-1]))) for run in runs
    )


def shade_flight(ax, intervals, label="flight phase"):
    """Shade the flight intervals ((t_start, t_stop) [s], from ``flight_intervals``) on ax;
    only the first carries the legend label."""
    for index, (start, stop) in enumerate(intervals):
        ax.axvspan(start, stop, color=FLIGHT_COLOUR, alpha=0.15, lw=0, label=label if index == 0 else None)


def _figure(fig, **kwargs):
    return Figure(**kwargs) if fig is None else fig


def plot_forces(task, trajectory, *, fig=None, contact_height=CONTACT_HEIGHT):
    """The paper's Fig. 2b/3b/4b: throttle u [%] and thrust T [N] of each jet (dotted: T_max),
    and the total vertical contact force Σ f_z [N] (dashed: the weight m g), against time,
    flight phases shaded. A robot without jets gets the contact-force panel only.
    Returns the Figure (its axes top to bottom)."""
    validation.check_trajectory(task, trajectory)
    fig = _figure(fig, figsize=(7, 7 if task.layout.n_jets else 3), layout="constrained")
    time, knots = _time(trajectory), trajectory.knots
    jets = task.robot.jet_frames
    axes = fig.subplots(3 if jets else 1, 1, sharex=True, squeeze=False)[:, 0]
    flight = flight_intervals(trajectory, contact_height)
    if jets:
        throttle, thrust = np.asarray(knots.throttle), np.asarray(knots.thrust)
        max_thrust = np.asarray(task.params.max_thrust)
        for j, name in enumerate(jets):
            axes[0].plot(time, throttle[:, j], marker=".", label=name)
            line, = axes[1].plot(time, thrust[:, j], marker=".", label=name)
            axes[1].axhline(max_thrust[j], color=line.get_color(), ls=":", lw=1)
        axes[0].set_ylabel("throttle u [%]")
        axes[1].set_ylabel("thrust T [N]")
        axes[0].legend(fontsize="small", ncols=2, loc="lower center", bbox_to_anchor=(0.5, 1.0))
    vertical = np.asarray(knots.contact_forces[..., 2]).sum(axis=1)
    weight = float(total_mass(task.robot.model)) * float(-task.params.gravity[2])
    axes[-1].plot(time, vertical, marker=".", color="k", label="Σ f_z")
    axes[-1].axhline(weight, color="0.5", ls="--", lw=1, label=f"weight m g = {weight:.0f} N")
    axes[-1].set_ylabel("vertical contact force [N]")
    axes[-1].set_xlabel("time [s]")
    for ax in axes:
        shade_flight(ax, flight)
        ax.grid(alpha=0.3)
    axes[-1].legend(fontsize="small")
    fig.suptitle(f"{task.name}: throttle, thrust and vertical contact force")
    return fig


def plot_com(task, trajectory, *, fig=None, contact_height=CONTACT_HEIGHT):
    """CoM x, y, z [m] against time and a side view z against x, with the task's targets
    (x_0 at t = 0, x_N at the end, the mid-horizon height bound) and the CoM re-simulated from
    the forces alone (``validation.resimulate_com``, dashed). Returns the Figure."""
    validation.check_trajectory(task, trajectory)
    fig = _figure(fig, figsize=(10, 6), layout="constrained")
    grid = fig.add_gridspec(3, 2, width_ratios=(3, 2))
    time, com = _time(trajectory), np.asarray(trajectory.knots.com)
    resimulated = validation.resimulate_com(task, trajectory)
    params = task.params
    initial, final = np.asarray(params.initial_com), np.asarray(params.final_com)
    mid_height, middle = float(params.mid_com_height), task.n_intervals // 2
    flight = flight_intervals(trajectory, contact_height)
    first = None
    for axis, name in enumerate("xyz"):
        ax = fig.add_subplot(grid[axis, 0], sharex=first)
        first = first or ax
        ax.plot(time, com[:, axis], marker=".", color="k", label="CoM")
        ax.plot(time, resimulated[:, axis], ls="--", color="tab:blue", label="re-simulated from the forces")
        ax.plot([time[0]], [initial[axis]], "o", mfc="none", color="tab:green", label="target $x_0$")
        ax.plot([time[-1]], [final[axis]], "*", ms=10, color="tab:orange", label="target $x_N$")
        # the CoM and its targets set the scale: the re-simulation of a guess may run far off
        shown = np.concatenate([com[:, axis], [initial[axis], final[axis]]])
        if name == "z" and np.isfinite(mid_height):
            ax.plot([time[middle]], [mid_height], "^", color="tab:purple", label=f"z ≥ {mid_height:.2f} m at N/2")
            shown = np.append(shown, mid_height)
        shade_flight(ax, flight)
        margin = max(0.1 * np.ptp(shown), 0.02)
        ax.set_ylim(shown.min() - margin, shown.max() + margin)
        ax.set_ylabel(f"CoM {name} [m]")
        ax.grid(alpha=0.3)
        if axis < 2:
            ax.tick_params(labelbottom=False)
    ax.set_xlabel("time [s]")
    first.legend(fontsize="small", ncols=3, loc="lower left", bbox_to_anchor=(0, 1.0))
    side = fig.add_subplot(grid[:, 1])
    side.plot(com[:, 0], com[:, 2], marker=".", color="k", label="CoM")
    side.plot(*initial[[0, 2]], "o", mfc="none", color="tab:green", ms=9, label="target $x_0$")
    side.plot(*final[[0, 2]], "*", ms=12, color="tab:orange", label="target $x_N$")
    if np.isfinite(mid_height):
        side.axhline(mid_height, color="tab:purple", ls=":", label="mid-horizon bound")
    side.set_aspect("equal", adjustable="datalim")
    side.xaxis.set_major_locator(MaxNLocator(5))
    side.set_xlabel("CoM x [m] (the robot faces −x)")
    side.set_ylabel("CoM z [m]")
    side.set_title("side view")
    side.grid(alpha=0.3)
    side.legend(fontsize="small")
    fig.suptitle(f"{task.name}: centre of mass")
    return fig


def plot_contact_schedule(task, trajectory, *, ax=None, contact_height=CONTACT_HEIGHT):
    """Gait diagram: one row per contact corner, grouped per foot; a bar where the corner is on
    the ground (c_z ≤ contact_height [m], ``validation.airborne_corners``), each knot covering
    ±Δt/2 around its time [s]; flight phases shaded. Returns the Figure."""
    validation.check_trajectory(task, trajectory)
    fig = Figure(figsize=(8, 0.35 * task.layout.n_contacts + 1.5), layout="constrained") if ax is None else ax.figure
    ax = fig.add_subplot() if ax is None else ax
    time = _time(trajectory)
    half = 0.5 * (time[1] - time[0])
    grounded = ~validation.airborne_corners(trajectory, contact_height)
    names = task.robot.contact_frames
    ticks, labels, row = [], [], 0
    for group, (label, members) in enumerate(validation.corner_groups(task.robot)):
        colour = f"C{group}"
        for corner in members:
            on = np.flatnonzero(grounded[:, corner])
            starts, stops = np.maximum(time[on] - half, time[0]), np.minimum(time[on] + half, time[-1])
            ax.broken_barh(list(zip(starts, stops - starts)), (row - 0.4, 0.8), color=colour,
                           label=label if corner == members[0] else None)
            ticks.append(row)
            labels.append(names[corner])
            row += 1
        row += 0.6  # a gap between feet
    shade_flight(ax, flight_intervals(trajectory, contact_height))
    ax.set_yticks(ticks, labels, fontsize="small")
    ax.invert_yaxis()
    ax.set_xlim(time[0], time[-1])
    ax.set_xlabel("time [s]")
    ax.set_title(f"{task.name}: contact schedule (on the ground: c_z ≤ {100 * contact_height:g} cm)")
    ax.legend(fontsize="small", loc="upper left", bbox_to_anchor=(1.0, 1.0))
    ax.grid(axis="x", alpha=0.3)
    return fig


def plot_schedules(summary, *, fig=None):
    """The distinct contact schedules of a batch (``batch.summarise``'s ``BatchSummary``), one
    panel each, best first: one row per contact corner, one column per knot, dark where the
    corner is on the ground; titled with the schedule's instances and best objective. Returns
    the Figure."""
    count, corners = len(summary.schedules), summary.corners
    if fig is None:
        fig = Figure(figsize=(8, (0.25 * len(corners) + 0.9) * count + 0.3), layout="constrained")
    objective = {r.index: r.objective for r in summary.ranking}
    for number, (schedule, ax) in enumerate(zip(summary.schedules, np.atleast_1d(fig.subplots(count, 1, sharex=True))),
                                            start=1):
        ax.imshow(~schedule.airborne.T, aspect="auto", cmap="Greys", vmin=0, vmax=1.6, interpolation="nearest")
        ax.set_yticks(range(len(corners)), corners, fontsize="x-small")
        members = schedule.members
        ax.set_title(f"schedule {number}: {len(members)} instance{'s' if len(members) != 1 else ''} "
                     f"(best {members[0]}, objective {objective[members[0]]:.6g})", fontsize="small")
        ax.xaxis.set_major_locator(MaxNLocator(integer=True))
    ax.set_xlabel("knot (dark: on the ground)")
    return fig


def plot_joints(task, trajectory, *, fig=None, columns=6, contact_height=CONTACT_HEIGHT):
    """One panel per optimised joint: s [deg] against time, its limits (the task's, grey
    bands beyond them) and the reference posture s̄ (dotted), flight phases shaded.
    Returns the Figure."""
    validation.check_trajectory(task, trajectory)
    names = task.robot.model.joint_names
    rows = -(-len(names) // columns)
    fig = _figure(fig, figsize=(2.3 * columns, 1.7 * rows + 0.6), layout="constrained")
    axes = fig.subplots(rows, columns, sharex=True, squeeze=False).ravel()
    time = _time(trajectory)
    joints = np.rad2deg(np.asarray(trajectory.knots.joint_positions))
    limits = np.rad2deg(np.asarray(task.params.joint_limits))
    reference = np.rad2deg(np.asarray(task.params.reference_configuration[7:]))
    flight = flight_intervals(trajectory, contact_height)
    for index, (ax, name) in enumerate(zip(axes, names)):
        lower, upper = limits[index]
        margin = 0.08 * (upper - lower)
        ax.axhspan(lower - margin, lower, color="0.8", lw=0)
        ax.axhspan(upper, upper + margin, color="0.8", lw=0)
        ax.axhline(reference[index], color="tab:green", ls=":", lw=1)
        ax.plot(time, joints[:, index], color="k", lw=1.2, marker=".", ms=3)
        shade_flight(ax, flight)
        ax.set_ylim(lower - margin, upper + margin)
        ax.set_title(name, fontsize="small")
        ax.tick_params(labelsize="x-small")
    for ax in axes[len(names):]:
        ax.set_axis_off()
    for ax in axes[(rows - 1) * columns : len(names)]:
        ax.set_xlabel("time [s]", fontsize="small")
    for ax in axes[::columns]:
        ax.set_ylabel("[deg]", fontsize="small")
    fig.suptitle(f"{task.name}: joint positions (grey: beyond the limits; dotted: reference posture)")
    return fig


def plot_torques(task, trajectory, *, fig=None, contact_height=CONTACT_HEIGHT):
    """The joint torques the plan needs (``torques.joint_torques``): |τ|/τ_max of every optimised
    joint against time (colour saturating at 1, where the motor's URDF effort limit is reached;
    black contours where it is exceeded), and the base residual, the unbalanced force [N] and
    torque about the CoM [N m] (zero for a plan consistent with the full dynamics), flight
    phases shaded. Returns the Figure."""
    validation.check_trajectory(task, trajectory)
    report = torques.joint_torques(task, trajectory)
    time = report.times
    fig = _figure(fig, figsize=(9, 0.22 * len(report.joint_names) + 3.6), layout="constrained")
    load_ax, base_ax = fig.subplots(2, 1, sharex=True, height_ratios=(len(report.joint_names), 8))
    half = 0.5 * (time[1] - time[0])
    image = load_ax.imshow(report.load.T, aspect="auto", origin="upper", cmap="viridis", vmin=0.0, vmax=1.0,
                           extent=(time[0] - half, time[-1] + half, len(report.joint_names) - 0.5, -0.5),
                           interpolation="nearest")
    if np.any(report.load > 1.0):
        load_ax.contour(time, np.arange(len(report.joint_names)), report.load.T, levels=[1.0], colors="k", linewidths=1)
    load_ax.set_yticks(np.arange(len(report.joint_names)), report.joint_names, fontsize="x-small")
    fig.colorbar(image, ax=load_ax, label="|τ| / τ_max", extend="max")
    name, knot, torque, limit = report.worst
    load_ax.set_title(f"{task.name}: joint torques against the effort limits — largest {np.max(report.load):.2g} "
                      f"({name}, {torque:.3g} N m at t = {time[knot]:.2f} s, limit {limit:.3g} N m)", fontsize="medium")
    base_ax.plot(time, np.linalg.norm(report.base_force, axis=1), color="tab:blue", label="|force| [N]")
    base_ax.plot(time, np.linalg.norm(report.base_torque, axis=1), color="tab:purple", label="|torque about CoM| [N m]")
    shade_flight(base_ax, flight_intervals(trajectory, contact_height))
    base_ax.set_ylabel("base residual")
    base_ax.set_xlabel("time [s]")
    base_ax.legend(fontsize="small", loc="upper right")
    base_ax.grid(alpha=0.3)
    return fig


_HISTORY_LABELS = dict(
    objective="objective", violation="constraint violation", stationarity="stationarity (scaled)",
    barrier="barrier parameter μ", step_length="step length α", regularisation="regularisation δ_w",
    linear_solves="block solves (refinement included)", factorisations="factorisations (inertia correction)",
)


def plot_convergence(result, *, fig=None, tolerance=ip.Options().tolerance):
    """The solve of a ``TaskSolution``: each column of ``solution.history``
    (``ip.HISTORY_COLUMNS``) against the iteration on a log axis (non-positive values are left out;
    rejected steps, α = 0, are marked ×; iterations of the restoration phase are marked on the
    violation panel rather than given one of their own), and the largest violation of each constraint family
    (NLP units) at the answer against tolerance (default: the solver's). Returns the Figure."""
    solution = result.solution
    history = np.asarray(solution.history)
    iterations = int(solution.iterations)
    if history.ndim != 2 or history.shape[1] != len(ip.HISTORY_COLUMNS):
        raise ValueError(f"the history must have shape (max_iterations, {len(ip.HISTORY_COLUMNS)}), got {history.shape}")
    history = history[:iterations]
    restoring = history[:, ip.HISTORY_COLUMNS.index("restoration")] == 1  # NaN (older files): no
    columns = [name for name in ip.HISTORY_COLUMNS if name != "restoration"]
    panels = len(columns)
    fig = _figure(fig, figsize=(12, 9), layout="constrained")
    grid = fig.add_gridspec((panels + 1) // 2, 3, width_ratios=(1, 1, 1.1))
    steps = np.arange(iterations)
    first = None
    for index, name in enumerate(columns):
        ax = fig.add_subplot(grid[index // 2, index % 2], sharex=first)
        first = first or ax
        values = history[:, ip.HISTORY_COLUMNS.index(name)]
        ax.semilogy(steps, np.where(values > 0, values, np.nan), color="k", lw=1)
        if name == "violation" and restoring.any():
            ax.plot(steps[restoring], np.where(values > 0, values, np.nan)[restoring], ".", color="tab:orange", ms=4,
                    label=f"restoration phase ({int(restoring.sum())})")
            ax.legend(fontsize="small")
        if name == "step_length":
            rejected = steps[values == 0]
            ax.plot(rejected, np.full(rejected.shape, np.nanmin(np.where(values > 0, values, np.nan), initial=1.0)),
                    "x", color="tab:red", ms=4, label=f"rejected ({rejected.size})")
            if rejected.size:
                ax.legend(fontsize="small")
        zeros = " (0 not shown)" if name != "step_length" and np.any(values == 0) else ""
        ax.set_title(_HISTORY_LABELS[name] + zeros, fontsize="medium")
        ax.grid(alpha=0.3, which="both")
        if index >= panels - 2:
            ax.set_xlabel("iteration")
    bars = fig.add_subplot(grid[:, 2])
    families = result.violation_per_family
    floor = 1e-16  # exactly satisfied families show at the floor of the log axis
    bars.barh(list(families), np.maximum([float(v) for v in families.values()], floor), color="tab:blue")
    bars.axvline(tolerance, color="tab:red", ls="--", label=f"tolerance {tolerance:g}")
    bars.legend(fontsize="small")
    bars.set_xscale("log")
    bars.invert_yaxis()
    bars.tick_params(axis="y", labelsize="small")
    bars.set_xlabel("largest violation (NLP units)")
    bars.set_title("violation per constraint family")
    bars.grid(axis="x", alpha=0.3)
    status = result.status.name
    fig.suptitle(f"solve: {status} after {iterations} iterations, objective {float(solution.objective):.6g}")
    return fig


def plot_validation(task, trajectory, *, ax=None):
    """The checks of ``validation.validate`` as bars of value / limit on a log axis (≤ 1 passes:
    green; red fails; orange: over the limit of a check that is reported, not enforced), each
    labelled with its value (the check's units). Returns the Figure."""
    validation.check_trajectory(task, trajectory)
    report = validation.validate(task, trajectory)
    fig = Figure(figsize=(8, 0.3 * len(report.checks) + 1.2), layout="constrained") if ax is None else ax.figure
    ax = fig.add_subplot() if ax is None else ax
    floor = 1e-12  # exactly satisfied checks show at the floor of the log axis
    ratios = np.maximum([check.value / check.limit for check in report.checks], floor)
    colours = ["tab:green" if check.passed else "tab:red" if check.enforced else "tab:orange" for check in report.checks]
    bars = ax.barh([check.name for check in report.checks], ratios, color=colours)
    ax.bar_label(bars, [f"{check.value:.2g}" for check in report.checks], padding=3, fontsize="x-small")
    ax.axvline(1.0, color="k", lw=1)
    ax.set_xscale("log")
    ax.set_xlim(floor / 3, max(1e2, 30 * np.nanmax(ratios)))
    ax.invert_yaxis()
    ax.tick_params(axis="y", labelsize="small")
    ax.set_xlabel("value / limit (≤ 1 passes)")
    verdict = "ok" if report.ok else f"{len(report.failed)} checks FAILED"
    flight = ", ".join(f"{run[0]}–{run[-1]}" if len(run) > 1 else f"{run[0]}" for run in _runs(report.flight_knots))
    ax.set_title(f"{task.name}: validate — {verdict}; flight knots: {flight or 'none'}", fontsize="medium")
    ax.grid(axis="x", alpha=0.3)
    return fig


def save_figures(task, result, directory, *, dpi=120, snapshots=True, style="mesh"):
    """Write every figure of a ``TaskSolution`` as PNG into directory (created if needed):
    forces, com, contact_schedule, joints, torques, convergence, validation and, with snapshots, the
    snapshot strip of ``animation.plot_snapshots`` (drawn in style). Returns {name: path}."""
    directory = pathlib.Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    trajectory = result.trajectory
    figures = dict(
        forces=lambda: plot_forces(task, trajectory),
        com=lambda: plot_com(task, trajectory),
        contact_schedule=lambda: plot_contact_schedule(task, trajectory),
        joints=lambda: plot_joints(task, trajectory),
        torques=lambda: plot_torques(task, trajectory),
        convergence=lambda: plot_convergence(result),
        validation=lambda: plot_validation(task, trajectory),
    )
    if snapshots:
        figures["snapshots"] = lambda: animation.plot_snapshots(task, trajectory, style=style)
    paths = {}
    for name, build in figures.items():
        paths[name] = directory / f"{task.name}_{name}.png"
        build().savefig(paths[name], dpi=dpi)
    return paths
