"""The multimodal trajectory-optimisation problem (eq. 33): weights, parameters and the task.

A ``Task`` is a pytree: its numbers (targets, bounds, weights, jet coefficients, the robot
model) are array leaves that can be differentiated and vmapped; its structure (knot count,
options, frame names) is static.
"""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np

from jaxmm.robots import Robot
from jaxmm.transcription.variables import Layout

INTEGRATION_RULES = ("trapezoidal", "backward_euler")


def _weight():
    return dataclasses.field(default=0.0)


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class Weights:
    """Cost weights of eq. (32) (docs/formulation.md, "Cost"); every weight defaults to 0.

    Running terms (× Δt, knots 0..N−1), final terms (knot N), initial terms (knot 0), the
    complementarity slacks (every knot) and the total time. The slacks ε_n, ε_t of eq. (20, 21)
    are paid for by ``complementarity_slack`` × Σ ε (the published runs) plus
    ``complementarity_slack_squared`` × Σ ε² (the paper's text); both are data, so that one
    compiled solve serves either penalty (``tasks.with_slack_penalty``).
    """

    com_acc: float = _weight()
    com_vel: float = _weight()
    com_vel_xy: float = _weight()
    ang_mom_rate: float = _weight()
    ang_mom: float = _weight()
    joint_vel_upper: float = _weight()
    joint_vel_lower: float = _weight()
    posture: float = _weight()
    force: float = _weight()
    force_rate: float = _weight()
    thrust: float = _weight()
    throttle: float = _weight()
    base_orientation: float = _weight()
    final_momentum: float = _weight()
    final_thrust: float = _weight()
    final_posture: float = _weight()
    final_force: float = _weight()
    initial_posture: float = _weight()
    initial_base_orientation: float = _weight()
    initial_force: float = _weight()
    complementarity_slack: float = _weight()
    complementarity_slack_squared: float = _weight()
    horizon: float = 1.0

    @classmethod
    def from_dict(cls, weights):
        """Weights from {name: value}, every weight a float array (the unnamed ones at their
        default), so that tasks which differ in any weight share one compiled solve; unknown
        names and non-scalar values raise ValueError."""
        names = {f.name for f in dataclasses.fields(cls)}
        unknown = sorted(set(weights) - names)
        if unknown:
            raise ValueError(f"unknown cost weights {unknown}; known weights: {sorted(names)}")
        checked = {f.name: jnp.asarray(f.default, dtype=float) for f in dataclasses.fields(cls)}
        for name, value in weights.items():
            array = jnp.asarray(value, dtype=float)
            if array.shape != ():
                raise ValueError(f"weight {name!r} must be a scalar, got shape {array.shape}")
            if not (np.isfinite(float(array)) and float(array) >= 0):
                raise ValueError(f"weight {name!r} must be finite and non-negative, got {float(array)}")
            checked[name] = array
        return cls(**checked)

    def to_dict(self):
        return {f.name: getattr(self, f.name) for f in dataclasses.fields(self)}


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class TaskParams:
    """The numbers of a task (physical units). nj jets, n optimised joints.

    initial_com, final_com: (3,) x_0, x_N [m]; mid_com_height: () h_min at knot N/2 [m]
    (−inf: none); reference_configuration: (7 + n,) standing pose (posture s̄, initial ρ̄);
    friction_coefficient μ; corner_com_bound: (3,) [m]; jet_com_bound: () [m];
    max_thrust: (nj,) [N]; throttle_range: (2,) [%]; jet_coefficients: (nj, 10) (eq. 8);
    joint_limits: (n, 2) [rad]; joint_velocity_limit [rad/s]; base_linear_velocity_limit [m/s];
    base_angular_velocity_limit [rad/s]; com_xy_limit [m]; boundary_tolerance: initial
    equilibrium/orientation tolerance; final_orientation_tolerance; min_dt, max_dt [s];
    gravity: (3,) [m/s²]; complementarity_tolerance: () σ_n ≥ 0 [N m], planar_tolerance: ()
    σ_t ≥ 0 [N m] and slack_limit: () ε_max ≥ 0 of the complementarity rows f_z c_z − ε_n ≤ σ_n,
    |f_z Δc − ε_t| ≤ σ_t with 0 ≤ ε ≤ ε_max (eq. 20, 21): the published relaxation is σ = 0,
    ε_max = ∞ (slacks paid for in the cost); σ > 0, ε_max = 0 is Scholtes' relaxation without
    slacks (``tasks.exact_complementarity``). σ_n bounds the force of a corner above the ground
    (σ_n / c_z [N]), σ_t its slip per interval under load (σ_t / f_z [m]). planar_relaxation: ()
    κ_t ≥ 0: where the solver's relaxation homotopy (``Options.relaxation``) widens the normal
    rows by σ(μ), it widens the planar rows by κ_t σ(μ) (1: alike; < 1: a loaded foot slides
    less while σ is large).
    """

    initial_com: jax.Array
    final_com: jax.Array
    mid_com_height: jax.Array
    reference_configuration: jax.Array
    friction_coefficient: jax.Array
    corner_com_bound: jax.Array
    jet_com_bound: jax.Array
    max_thrust: jax.Array
    throttle_range: jax.Array
    jet_coefficients: jax.Array
    joint_limits: jax.Array
    joint_velocity_limit: jax.Array
    base_linear_velocity_limit: jax.Array
    base_angular_velocity_limit: jax.Array
    com_xy_limit: jax.Array
    boundary_tolerance: jax.Array
    final_orientation_tolerance: jax.Array
    min_dt: jax.Array
    max_dt: jax.Array
    gravity: jax.Array
    complementarity_tolerance: jax.Array
    planar_tolerance: jax.Array
    slack_limit: jax.Array
    planar_relaxation: jax.Array


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class Task:
    """A complete problem instance: robot, parameters, weights and static options.

    n_intervals: N (the trajectory has N + 1 knots); zero_initial_thrust: T[0], Ṫ[0] ≈ 0;
    integration: "trapezoidal" (published runs) or "backward_euler" (the paper's text);
    upper_body_joints: indices in s of the joints weighted by ``joint_vel_upper``;
    joint_torque_limits: add the ``joint_torque`` family |τ_j| ≤ τ_max,j (the URDF's effort
    limits, ``Model.effort_limits``) at knots 1..N, beyond the paper's NLP.
    """

    robot: Robot
    params: TaskParams
    weights: Weights
    name: str = dataclasses.field(metadata=dict(static=True))
    n_intervals: int = dataclasses.field(metadata=dict(static=True))
    zero_initial_thrust: bool = dataclasses.field(default=True, metadata=dict(static=True))
    integration: str = dataclasses.field(default="trapezoidal", metadata=dict(static=True))
    upper_body_joints: tuple = dataclasses.field(default=(), metadata=dict(static=True))
    joint_torque_limits: bool = dataclasses.field(default=False, metadata=dict(static=True))

    @property
    def layout(self):
        return Layout(self.robot.model.n_joints, len(self.robot.contact_frames), len(self.robot.jet_frames))

    @property
    def n_knots(self):
        """N + 1."""
        return self.n_intervals + 1
