"""The joint torques a plan needs: inverse dynamics along a trajectory, against the motors' limits.

The paper's NLP (eq. 33) plans with the centroidal momentum and the kinematics and never asks
for the joint torques. Here they are computed after the fact by the recursive Newton–Euler
algorithm (``rigid_body.dynamics``) at every knot, with the contact forces and the jets' thrust
forces (eq. 5) as external forces, and the accelerations from the transcription's own rule.
"""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np

from jaxmm.transcription.whole_body import generalised_forces


@dataclasses.dataclass(frozen=True)
class TorqueReport:
    """Joint torques along a plan, N + 1 knots and n optimised joints.

    times: (N + 1,) [s]; joint_names: (n,); torques: (N + 1, n) τ [N m]; effort_limits: (n,) the
    URDF's |τ| limits [N m] (inf where it gives none); base_force: (N + 1, 3) [N] and
    base_torque: (N + 1, 3) [N m] about the CoM, world-aligned: the wrench on the floating base
    that the forces, thrusts and gravity leave unbalanced. The full dynamics need it to be zero;
    the centroidal transcription (eq. 13) does not force it to, so its size says how far the plan
    is from full-dynamics consistency (the difference of the CMM's finite difference and J_CMM ν̇).
    """

    times: np.ndarray
    joint_names: tuple
    torques: np.ndarray
    effort_limits: np.ndarray
    base_force: np.ndarray
    base_torque: np.ndarray

    @property
    def load(self):
        """(N + 1, n) |τ| / τ_max: above 1 where a motor would saturate (0 where unlimited)."""
        return np.abs(self.torques) / self.effort_limits

    @property
    def worst(self):
        """(joint name, knot, τ [N m], limit [N m]) of the largest |τ| / τ_max."""
        knot, joint = np.unravel_index(np.argmax(self.load), self.load.shape)
        return self.joint_names[joint], int(knot), float(self.torques[knot, joint]), float(self.effort_limits[joint])

    @property
    def saturated(self):
        """{joint name: (knots where |τ| > τ_max, largest |τ| / τ_max)} of the joints over their limit."""
        over = self.load > 1.0
        return {name: (tuple(int(k) for k in np.flatnonzero(over[:, j])), float(self.load[:, j].max()))
                for j, name in enumerate(self.joint_names) if over[:, j].any()}

    def __str__(self):
        name, knot, torque, limit = self.worst
        lines = [f"largest |τ|/τ_max {np.max(self.load):.3g}: {name} at knot {knot} ({torque:.3g} N m, limit {limit:.3g} N m)"]
        for joint, (knots, load) in self.saturated.items():
            lines.append(f"  over its limit: {joint} at {len(knots)} knot(s), up to {load:.3g}× τ_max")
        lines.append(f"base residual: force ≤ {np.linalg.norm(self.base_force, axis=1).max():.3g} N, "
                     f"torque about the CoM ≤ {np.linalg.norm(self.base_torque, axis=1).max():.3g} N m")
        return "\n".join(lines)


def knot_accelerations(task, trajectory):
    """ν̇ at every knot (N + 1, 6 + n) by the transcription's rule for velocities (backward Euler,
    eq. 24): ν̇[k] = (ν[k] − ν[k−1]) / Δt for k ≥ 1; knot 0, which no rule reaches, takes knot 1's."""
    velocity = jnp.asarray(trajectory.knots.velocity)
    dt = trajectory.total_time / task.n_intervals
    rates = (velocity[1:] - velocity[:-1]) / dt
    return jnp.concatenate([rates[:1], rates])


@jax.jit
def _plan_torques(task, trajectory):
    knots = trajectory.knots
    return jax.vmap(generalised_forces, in_axes=(None, 0, 0, 0, 0, 0, None))(
        task.robot, knots.configuration, knots.velocity, knot_accelerations(task, trajectory), knots.contact_forces,
        knots.thrust, task.params.gravity)


def joint_torques(task, trajectory):
    """The joint torques and the base residual of a plan (``TorqueReport``).

    At every knot, inverse dynamics at (q, ν, ν̇) with ν̇ from ``knot_accelerations``, the contact
    forces at the contact corners and the jets' thrust forces (eq. 5) at the jet frames as external
    forces, and the task's gravity."""
    tau = np.asarray(_plan_torques(task, trajectory))
    model = task.robot.model
    return TorqueReport(
        times=np.linspace(0.0, float(trajectory.total_time), task.n_knots),
        joint_names=model.joint_names,
        torques=tau[:, 6:],
        effort_limits=np.asarray(model.effort_limits),
        base_force=tau[:, :3],
        base_torque=tau[:, 3:6],
    )
