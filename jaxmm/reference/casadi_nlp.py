"""The NLP of docs/formulation.md (eq. 33 of L'Erario et al. 2022) in CasADi, solved by IPOPT.

An independent transcription: the residuals, the quaternion algebra (eq. 25b), the costs and
the bounds are written here again in CasADi; the rigid-body quantities (CoM, centroidal
momentum matrix in the mixed representation, frame forward kinematics) come from ADAM's CasADi
backend. Only bookkeeping is shared with the JAX side: ``Layout`` (sizes, slices, scaling) and
the ``Trajectory`` pytree.

The decision vector w has (N + 1) · nz + 1 entries [physical units]: knot 0, knot 1, …, knot N
(each in the order of ``Knot``'s fields), then T_total [s]. Every constraint family is one
CasADi Function of one knot (path families) or of two consecutive knots and T_total
(transition families), mapped over the horizon with ``Function.map``; nothing is unrolled.

Conventions: quaternions (x, y, z, w); ν = (ṗ, ω, ṡ) with ω in the world frame (ADAM's
MIXED_REPRESENTATION); arrays of shape (nc, 3) flatten corner-major.
"""

import dataclasses
import time
import xml.etree.ElementTree as ET

import casadi as cs
import jax.numpy as jnp
import numpy as np
from adam.casadi import KinDynComputations
from adam.core.constants import Representations

from jaxmm.transcription.variables import Knot, Trajectory

PATH_EQUALITIES = ("centroidal_dynamics", "com", "angular_momentum", "contact_points", "jet_dynamics")
TRANSITION_EQUALITIES = (
    "com_integration",
    "com_velocity_integration",
    "angular_momentum_integration",
    "base_position_integration",
    "base_quaternion_integration",
    "joint_integration",
    "force_integration",
    "thrust_integration",
    "thrust_rate_integration",
)
PATH_INEQUALITIES = ("friction_cone", "normal_complementarity", "corner_com", "jet_com")
TRANSITION_INEQUALITIES = ("planar_complementarity",)
JOINT_TORQUE = "joint_torque"  # a transition inequality where Task.joint_torque_limits asks for it
COST_TERMS = ("running", "final", "initial", "slack", "horizon")
HESSIANS = ("exact", "limited-memory")

# Below this squared angle the Taylor series of Exp and Log are exact to float64 rounding.
_SMALL_ANGLE_SQ = 1e-8
_IDENTITY = (0.0, 0.0, 0.0, 1.0)
# Per-knot Functions: forward derivatives through their symbolic (SX) Jacobian rather than
# many forward sweeps; with the derivative functions likewise, the exact Lagrangian Hessian is
# the symbolic Hessian of each knot. ~7x faster Jacobians, ~3x faster Hessians.
_FUNCTION_OPTIONS = dict(cse=True, enable_forward=False, der_options=dict(cse=True, enable_forward=False))


# --------------------------------------------------------------------------- quaternions


def _quaternion_multiply(a, b):
    """Hamilton product a ⊗ b, quaternions (x, y, z, w): (4,), (4,) → (4,)."""
    av, aw, bv, bw = a[:3], a[3], b[:3], b[3]
    return cs.vertcat(aw * bv + bw * av + cs.cross(av, bv), aw * bw - cs.dot(av, bv))


def _quaternion_conjugate(q):
    """(−x, −y, −z, w): (4,) → (4,)."""
    return cs.vertcat(-q[:3], q[3])


def _rotation(rho):
    """R(ρ): rotation matrix of ρ/‖ρ‖ (base → world), (4,) → (3, 3)."""
    q = rho / cs.norm_2(rho)
    x, y, z, w = q[0], q[1], q[2], q[3]
    return cs.vertcat(
        cs.horzcat(1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)),
        cs.horzcat(2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)),
        cs.horzcat(2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)),
    )


def _quaternion_exp(theta):
    """Exp(θ) as a unit quaternion (sin(|θ|/2) θ/|θ|, cos(|θ|/2)) (eq. 25b): (3,) → (4,).

    Taylor series below |θ|² = 1e-8, with a safe |θ| in the other branch, so that no NaN
    reaches a derivative at θ = 0.
    """
    angle_sq = cs.sumsqr(theta)
    small = angle_sq < _SMALL_ANGLE_SQ
    angle = cs.sqrt(cs.if_else(small, 1.0, angle_sq))
    half_sin_over = cs.if_else(small, 0.5 - angle_sq / 48 + angle_sq**2 / 3840, cs.sin(angle / 2) / angle)
    half_cos = cs.if_else(small, 1 - angle_sq / 8 + angle_sq**2 / 384, cs.cos(angle / 2))
    return cs.vertcat(half_sin_over * theta, half_cos)


def _quaternion_log(q):
    """Log of a unit quaternion (x, y, z, w): the rotation vector (3,), angle in [0, π].

    q and −q give the same rotation; the branch with w ≥ 0 is used. Taylor series of
    2 atan2(‖v‖, w)/‖v‖ for ‖v‖² < 1e-8.
    """
    q = cs.if_else(q[3] < 0, -q, q)
    v, w = q[:3], q[3]
    n_sq = cs.sumsqr(v)
    small = n_sq < _SMALL_ANGLE_SQ
    n = cs.sqrt(cs.if_else(small, 1.0, n_sq))
    w_safe = cs.if_else(small, w, 1.0)
    scale = cs.if_else(small, 2 / w_safe - 2 * n_sq / (3 * w_safe**3), 2 * cs.atan2(n, w) / n)
    return scale * v


def _base_transform(p, rho):
    """H (4, 4), base → world, from p (3,) and ρ (4,) (normalised inside R)."""
    return cs.vertcat(cs.horzcat(_rotation(rho), p), cs.horzcat(0, 0, 0, 1))


def _columns(vectors, rows):
    """Stack column vectors side by side: a (rows, len(vectors)) matrix, also when empty."""
    return cs.horzcat(*vectors) if vectors else cs.SX(rows, 0)


def _stack(vectors):
    """Stack column vectors on top of each other: (Σ rows, 1), also when empty."""
    return cs.vertcat(*vectors) if vectors else cs.SX(0, 1)


# --------------------------------------------------------------------------- kinematics (ADAM)


def _normalised_urdf(urdf_path):
    """The URDF as an XML string with every joint axis normalised.

    ADAM's revolute-joint rotation assumes a unit axis and does not normalise it; the public
    iRonCub URDF has shoulder axes with ‖a‖ − 1 ≈ 1.6e-7 (the URDF standard, Pinocchio and
    jaxmm normalise), which would shift the arm jets by ~1e-7 m.
    """
    root = ET.parse(urdf_path).getroot()
    for axis in root.iter("axis"):
        value = np.array(axis.get("xyz", "1 0 0").split(), dtype=float)
        norm = np.linalg.norm(value)
        if norm > 0:
            axis.set("xyz", " ".join(repr(float(x)) for x in value / norm))
    return root, ET.tostring(root, encoding="unicode")


def _kindyn(urdf_path, joint_names, frames, gravity):
    """ADAM KinDynComputations (mixed representation, gravity (3,) [m/s²]) after checking joint
    and frame names.

    Joints of the URDF that are not in joint_names are locked at 0 by ADAM.
    """
    root, xml = _normalised_urdf(urdf_path)
    moving = {j.get("name") for j in root.iter("joint") if j.get("type") not in ("fixed", "floating", "planar")}
    links = {link.get("name") for link in root.iter("link")}
    missing = [j for j in joint_names if j not in moving]
    if missing:
        raise ValueError(f"joints {missing} are not moving joints of {urdf_path}")
    missing = [f for f in frames if f not in links]
    if missing:
        raise ValueError(f"frames {missing} are not links of {urdf_path}")
    kindyn = KinDynComputations(xml, list(joint_names), gravity=np.concatenate([gravity, np.zeros(3)]))
    kindyn.set_frame_velocity_representation(Representations.MIXED_REPRESENTATION)
    return kindyn


def _kinematics_function(kindyn, n_joints, contact_frames, jet_frames):
    """Function (p (3,), ρ (4,), s (n,)) → CoM (3,), [0 I] J_CMM (3, 6 + n), contact
    corners (3, nc), jet positions (3, nj), jet z axes R_j e_z (3, nj), all in the world frame.
    """
    p, rho, s = cs.SX.sym("p", 3), cs.SX.sym("rho", 4), cs.SX.sym("s", n_joints)
    H = _base_transform(p, rho)
    com = kindyn.CoM_position_fun()(H, s)
    cmm = kindyn.centroidal_momentum_matrix_fun()(H, s)
    corners = [kindyn.forward_kinematics_fun(f)(H, s) for f in contact_frames]
    jets = [kindyn.forward_kinematics_fun(f)(H, s) for f in jet_frames]
    return cs.Function(
        "kinematics",
        [p, rho, s],
        [com, cmm[3:6, :], _columns([T[:3, 3] for T in corners], 3),
         _columns([T[:3, 3] for T in jets], 3), _columns([T[:3, 2] for T in jets], 3)],
        ["p", "rho", "s"],
        ["com", "cmm_angular", "corners", "jet_positions", "jet_axes"],
        dict(cse=True),
    )


def _joint_torque_function(kindyn, n_joints, contact_frames, jet_frames):
    """Function (p, ρ, s, ν (6 + n,), ν̇ (6 + n,), f (3, nc), T (nj,)) → the joint torques (n,)
    [N m] of τ = M(q) ν̇ + h(q, ν) − Σ_i J_i(q)ᵀ f_i − Σ_j J_j(q)ᵀ F_j with F_j = −T_j R_j e_z (eq. 5):
    ADAM's mass matrix, bias forces and frame Jacobians (mixed representation), not jaxmm's
    recursive Newton–Euler algorithm."""
    p, rho, s = cs.SX.sym("p", 3), cs.SX.sym("rho", 4), cs.SX.sym("s", n_joints)
    nu, nu_dot = cs.SX.sym("nu", 6 + n_joints), cs.SX.sym("nu_dot", 6 + n_joints)
    forces, thrust = cs.SX.sym("f", 3, len(contact_frames)), cs.SX.sym("T", len(jet_frames))
    H = _base_transform(p, rho)
    tau = cs.mtimes(kindyn.mass_matrix_fun()(H, s), nu_dot) + kindyn.bias_force_fun()(H, s, nu[:6], nu[6:])
    for i, frame in enumerate(contact_frames):
        tau -= cs.mtimes(kindyn.jacobian_fun(frame)(H, s)[:3, :].T, forces[:, i])
    for j, frame in enumerate(jet_frames):
        axis = kindyn.forward_kinematics_fun(frame)(H, s)[:3, 2]
        tau -= cs.mtimes(kindyn.jacobian_fun(frame)(H, s)[:3, :].T, -thrust[j] * axis)
    return cs.Function("joint_torque", [p, rho, s, nu, nu_dot, forces, thrust], [tau[6:]],
                       ["p", "rho", "s", "nu", "nu_dot", "f", "T"], ["tau"], dict(cse=True))


# --------------------------------------------------------------------------- the NLP


@dataclasses.dataclass(frozen=True)
class _Numbers:
    """The task's numbers as NumPy arrays (shapes as in ``TaskParams``) and float weights."""

    params: dict
    weights: dict

    @classmethod
    def of(cls, task):
        params = {f.name: np.asarray(getattr(task.params, f.name), dtype=float)
                  for f in dataclasses.fields(task.params)}
        weights = {name: float(value) for name, value in task.weights.to_dict().items()}
        return cls(params, weights)


class ReferenceNLP:
    """The NLP of docs/formulation.md for a jaxmm ``Task``, in CasADi with ADAM kinematics.

    task: a jaxmm ``Task`` (only its numbers, options and frame/joint names are used).
    urdf_path: the URDF of the task's robot; task.robot.model.joint_names are the optimised
    joints (ADAM locks the others at 0).

    Attributes: layout (jaxmm ``Layout``), n_intervals N, n_variables (N + 1) nz + 1,
    mass m [kg] (from ADAM).
    """

    def __init__(self, task, urdf_path):
        self.task = task
        # IPOPT's variables in the knot's reading order, whatever the JAX solver's flat layout:
        # IPOPT's path (its linear solver's pivoting) depends on the order of the variables.
        self.layout = dataclasses.replace(task.layout, fields=tuple(f.name for f in dataclasses.fields(Knot)))
        self.n_intervals = task.n_intervals
        self.n_variables = task.n_knots * self.layout.size + 1
        self._numbers = _Numbers.of(task)
        robot = task.robot
        kindyn = _kindyn(urdf_path, robot.model.joint_names, robot.contact_frames + robot.jet_frames,
                         self._numbers.params["gravity"])
        self.mass = float(kindyn.get_total_mass())
        self._kinematics = _kinematics_function(
            kindyn, self.layout.n_joints, robot.contact_frames, robot.jet_frames
        )
        self._effort_limits = np.asarray(robot.model.effort_limits, dtype=float)
        self._joint_torque = (_joint_torque_function(kindyn, self.layout.n_joints, robot.contact_frames,
                                                     robot.jet_frames) if task.joint_torque_limits else None)
        self._path = self._path_function()
        self._transition = self._transition_function()
        self._costs = {name: self._cost_function(name) for name in ("running", "final", "initial", "slack")}
        w = cs.MX.sym("w", self.n_variables)
        families, costs = self.symbolic(w)
        self._evaluate = cs.Function(
            "evaluate", [w], list(families.values()) + list(costs.values()),
            ["w"], list(families) + list(costs),
        )

    # ---- per-knot symbolic pieces

    def _knot(self, name):
        """A symbolic knot: (nz,) SX and {field: flat SX column}."""
        z = cs.SX.sym(name, self.layout.size)
        return z, {field: z[sl] for field, sl in self.layout.slices().items()}

    def _path_function(self):
        """Function z (nz,) → the path equalities then the path inequalities of one knot."""
        z, v = self._knot("z")
        nc, nj = self.layout.n_contacts, self.layout.n_jets
        com, cmm, corners, jet_positions, jet_axes = self._kinematics(
            v["base_position"], v["base_quaternion"], v["joint_positions"]
        )
        x = v["com"]
        forces, points = cs.reshape(v["contact_forces"], 3, nc), cs.reshape(v["contact_points"], 3, nc)
        mu = float(self._numbers.params["friction_coefficient"])
        nu = cs.vertcat(v["base_linear_velocity"], v["base_angular_velocity"], v["joint_velocities"])
        families = {
            "centroidal_dynamics": self._centroidal_dynamics(v, forces, points, jet_positions, jet_axes),
            "com": x - com,  # eq. (15)
            "angular_momentum": v["angular_momentum"] - cs.mtimes(cmm, nu),  # eq. (16)
            "contact_points": v["contact_points"] - cs.vec(corners),  # eq. (17)
            "jet_dynamics": v["thrust_acceleration"] - self._jet_model(v),  # eq. (8), (23)
            # eq. (12), (19): per corner f_x − μ f_z, −f_x − μ f_z, f_y − μ f_z, −f_y − μ f_z
            "friction_cone": _stack([
                cs.vertcat(f[0] - mu * f[2], -f[0] - mu * f[2], f[1] - mu * f[2], -f[1] - mu * f[2])
                for f in (forces[:, i] for i in range(nc))
            ]),
            "normal_complementarity": (forces[2, :] * points[2, :]).T - v["normal_slack"],  # eq. (20)
            "corner_com": _stack([points[:, i] - x for i in range(nc)]),  # eq. (29)
            "jet_com": _stack([jet_positions[:, j] - x for j in range(nj)]),
        }
        names = PATH_EQUALITIES + PATH_INEQUALITIES
        return cs.Function("path", [z], [families[n] for n in names], ["z"], list(names), _FUNCTION_OPTIONS)

    def _centroidal_dynamics(self, v, forces, points, jet_positions, jet_axes):
        """Eq. (14), 6 rows: m ẍ − Σ f_i − Σ F_j − m g and ḣ_ω − Σ (c_i − x) × f_i
        − Σ (p_j − x) × F_j, with F_j = −T_j R_j e_z (eq. 5). forces, points: (3, nc);
        jet_positions, jet_axes (R_j e_z): (3, nj)."""
        x = v["com"]
        jet_forces = [-v["thrust"][j] * jet_axes[:, j] for j in range(self.layout.n_jets)]
        moments = [cs.cross(points[:, i] - x, forces[:, i]) for i in range(self.layout.n_contacts)]
        moments += [cs.cross(jet_positions[:, j] - x, F) for j, F in enumerate(jet_forces)]
        gravity = cs.DM(self._numbers.params["gravity"])
        return cs.vertcat(
            self.mass * v["com_acceleration"] - cs.sum2(forces) - sum(jet_forces, cs.SX.zeros(3)) - self.mass * gravity,
            v["angular_momentum_rate"] - sum(moments, cs.SX.zeros(3)),
        )

    def _jet_model(self, v):
        """T̈ = f(T, Ṫ) + g(T, Ṫ, u) of eq. (8), per jet: (nj,) SX."""
        coefficients = self._numbers.params["jet_coefficients"]
        rows = []
        for j, (k_t, k_tt, k_d, k_dd, k_td, b_u, b_t, b_d, b_uu, c) in enumerate(coefficients):
            T, D, u = v["thrust"][j], v["thrust_rate"][j], v["throttle"][j]
            f = k_t * T + k_tt * T**2 + k_d * D + k_dd * D**2 + k_td * T * D + c
            g = (b_u + b_t * T + b_d * D) * (u + b_uu * u**2)
            rows.append(f + g)
        return _stack(rows)

    def _transition_function(self):
        """Function (z (nz,), z⁺ (nz,), T_total) → the transition equalities (eq. 24-27) then
        the planar complementarity (eq. 21) of one interval, and the joint torques at k+1 where
        the task bounds them."""
        z, a = self._knot("z")
        z_next, b = self._knot("z_next")
        total_time = cs.SX.sym("total_time")
        dt = total_time / self.n_intervals
        nc = self.layout.n_contacts
        if self.task.integration == "trapezoidal":
            com_rate = (a["com_velocity"] + b["com_velocity"]) / 2
            thrust_acceleration = (a["thrust_acceleration"] + b["thrust_acceleration"]) / 2
        else:
            com_rate, thrust_acceleration = b["com_velocity"], b["thrust_acceleration"]
        forces = cs.reshape(a["contact_forces"], 3, nc)
        sliding = cs.reshape(b["contact_points"], 3, nc)[:2, :] - cs.reshape(a["contact_points"], 3, nc)[:2, :]
        tangential = _stack([forces[2, i] * sliding[:, i] for i in range(nc)])
        slack = cs.vec(cs.repmat(a["tangential_slack"].T, 2, 1))  # each corner's ε_t for x and y
        families = {
            "com_integration": b["com"] - a["com"] - dt * com_rate,
            "com_velocity_integration": b["com_velocity"] - a["com_velocity"] - dt * b["com_acceleration"],
            "angular_momentum_integration":
                b["angular_momentum"] - a["angular_momentum"] - dt * b["angular_momentum_rate"],
            "base_position_integration":
                b["base_position"] - a["base_position"] - dt * b["base_linear_velocity"],
            "base_quaternion_integration": b["base_quaternion"] - _quaternion_multiply(
                _quaternion_exp(b["base_angular_velocity"] * dt), a["base_quaternion"]
            ),
            "joint_integration": b["joint_positions"] - a["joint_positions"] - dt * b["joint_velocities"],
            "force_integration": b["contact_forces"] - a["contact_forces"] - dt * b["contact_force_rates"],
            "thrust_integration": b["thrust"] - a["thrust"] - dt * b["thrust_rate"],
            "thrust_rate_integration": b["thrust_rate"] - a["thrust_rate"] - dt * thrust_acceleration,
            "planar_complementarity": cs.vertcat(tangential - slack, tangential + slack),
        }
        if self._joint_torque is not None:  # at knot k+1, with ν̇ by backward Euler (eq. 24)
            nu_now, nu_next = (cs.vertcat(c["base_linear_velocity"], c["base_angular_velocity"], c["joint_velocities"])
                               for c in (a, b))
            families[JOINT_TORQUE] = self._joint_torque(
                b["base_position"], b["base_quaternion"], b["joint_positions"], nu_next, (nu_next - nu_now) / dt,
                cs.reshape(b["contact_forces"], 3, nc), b["thrust"])
        names = TRANSITION_EQUALITIES + self._transition_inequalities()
        return cs.Function(
            "transition", [z, z_next, total_time], [families[n] for n in names],
            ["z", "z_next", "total_time"], list(names), _FUNCTION_OPTIONS,
        )

    def _cost_function(self, term):
        """Function z (nz,) → one knot's part of a cost term of eq. (32) (docs/formulation.md):
        "running" l[k] (without Δt), "final" l_N, "initial" l_0, "slack" (one knot's l_ε)."""
        z, v = self._knot("z")
        terms = dict(running=self._running, final=self._final, initial=self._initial, slack=self._slack)
        return cs.Function(term, [z], [terms[term](v)], ["z"], [term], _FUNCTION_OPTIONS)

    def _posture_error(self, v):
        """s − s̄, (n,) [rad]."""
        return v["joint_positions"] - cs.DM(self._numbers.params["reference_configuration"][7:])

    def _running(self, v):
        """l[k] of eq. (32), without the Δt factor."""
        W, sq = self._numbers.weights, cs.sumsqr
        upper = list(self.task.upper_body_joints)
        lower = [j for j in range(self.layout.n_joints) if j not in upper]
        sdot = v["joint_velocities"]
        return (
            W["com_acc"] * sq(v["com_acceleration"]) + W["com_vel"] * sq(v["com_velocity"])
            + W["com_vel_xy"] * sq(v["com_velocity"][:2]) + W["ang_mom_rate"] * sq(v["angular_momentum_rate"])
            + W["ang_mom"] * sq(v["angular_momentum"]) + W["joint_vel_upper"] * sq(sdot[upper])
            + W["joint_vel_lower"] * sq(sdot[lower]) + W["posture"] * sq(self._posture_error(v))
            + W["force"] * sq(v["contact_forces"]) + W["force_rate"] * sq(v["contact_force_rates"])
            + W["thrust"] * sq(v["thrust"]) + W["throttle"] * sq(v["throttle"])
            + W["base_orientation"] * sq(v["base_quaternion"] - cs.DM(_IDENTITY))
        )

    def _final(self, v):
        """l_N: final momentum, thrust, posture and force terms."""
        W, sq = self._numbers.weights, cs.sumsqr
        momentum = (sq(v["com_velocity"]) + sq(v["com_acceleration"]) + sq(v["angular_momentum"])
                    + sq(v["angular_momentum_rate"]))
        return (
            W["final_momentum"] * momentum + W["final_thrust"] * sq(v["thrust"])
            + W["final_posture"] * sq(self._posture_error(v)) + W["final_force"] * sq(v["contact_forces"])
        )

    def _initial(self, v):
        """l_0, with the orientation error Log(ρ̄* ⊗ ρ/‖ρ‖) on SO(3)."""
        W, sq = self._numbers.weights, cs.sumsqr
        rho = v["base_quaternion"] / cs.norm_2(v["base_quaternion"])
        rho_bar = cs.DM(self._numbers.params["reference_configuration"][3:7])
        error = _quaternion_log(_quaternion_multiply(_quaternion_conjugate(rho_bar), rho))
        return (
            W["initial_posture"] * sq(self._posture_error(v)) + W["initial_base_orientation"] * sq(error)
            + W["initial_force"] * sq(v["contact_forces"])
        )

    def _slack(self, v):
        """w_ε Σ_i (ε_n,i + ε_t,i) (published) + w_ε² Σ_i (ε_n,i² + ε_t,i²) (the text)."""
        slacks = cs.vertcat(v["normal_slack"], v["tangential_slack"])
        W = self._numbers.weights
        return W["complementarity_slack"] * cs.sum1(slacks) + W["complementarity_slack_squared"] * cs.sumsqr(slacks)

    # ---- the whole horizon

    def symbolic(self, w):
        """The NLP as CasADi expressions of a decision vector w (MX, (N + 1) nz + 1, physical).

        Returns ({family: (rows, K) MX}, {cost term: scalar MX, and "total"}) with K = N + 1
        knots for path families and N intervals for transition families.
        """
        N, nz = self.n_intervals, self.layout.size
        knots = cs.reshape(w[:-1], nz, N + 1)  # column k = knot k
        total_time = w[-1]
        path = self._path.map(N + 1)(knots)
        transition = self._transition.map(N)(knots[:, :N], knots[:, 1:], cs.repmat(total_time, 1, N))
        by_name = dict(zip(PATH_EQUALITIES + PATH_INEQUALITIES, path))
        by_name.update(zip(TRANSITION_EQUALITIES + self._transition_inequalities(), transition))
        families = {name: by_name[name] for name in self.family_names()}
        costs = {
            "running": total_time / N * cs.sum2(self._costs["running"].map(N)(knots[:, :N])),
            "final": self._costs["final"](knots[:, N]),
            "initial": self._costs["initial"](knots[:, 0]),
            "slack": cs.sum2(self._costs["slack"].map(N + 1)(knots)),
            "horizon": self._numbers.weights["horizon"] * total_time,
        }
        costs["total"] = sum(costs[name] for name in COST_TERMS)
        return families, costs

    def _transition_inequalities(self):
        return TRANSITION_INEQUALITIES + ((JOINT_TORQUE,) if self.task.joint_torque_limits else ())

    def family_names(self):
        """Every constraint family: equalities (path, transition), then inequalities."""
        return PATH_EQUALITIES + TRANSITION_EQUALITIES + PATH_INEQUALITIES + self._transition_inequalities()

    def n_stages(self, family):
        """N + 1 for a path family, N for a transition family."""
        path = family in PATH_EQUALITIES + PATH_INEQUALITIES
        return self.n_intervals + 1 if path else self.n_intervals

    # ---- numbers

    def flatten(self, trajectory):
        """jaxmm ``Trajectory`` → w, a (N + 1) nz + 1 NumPy vector (physical units)."""
        knots = np.asarray(self.layout.flatten(trajectory.knots), dtype=float)
        if knots.shape != (self.task.n_knots, self.layout.size):
            raise ValueError(
                f"the trajectory has knots of shape {knots.shape}; this NLP has "
                f"{self.task.n_knots} knots of {self.layout.size} variables"
            )
        return np.concatenate([knots.ravel(), [float(trajectory.total_time)]])

    def unflatten(self, w):
        """w ((N + 1) nz + 1,) → jaxmm ``Trajectory``."""
        w = np.asarray(w, dtype=float).ravel()
        knots = self.layout.unflatten(jnp.asarray(w[:-1].reshape(self.task.n_knots, self.layout.size)))
        return Trajectory(knots=knots, total_time=jnp.asarray(w[-1]))

    def _numeric(self, trajectory):
        outputs = self._evaluate(w=self.flatten(trajectory))
        return {name: np.asarray(value.full()) for name, value in outputs.items()}

    def evaluate(self, trajectory):
        """Every constraint family at a trajectory: {family: (K, rows) NumPy array}, K = N + 1
        for path families and N for transition families (rows in docs/formulation.md order)."""
        values = self._numeric(trajectory)
        return {name: values[name].reshape(-1, self.n_stages(name)).T for name in self.family_names()}

    def cost_terms(self, trajectory):
        """The cost terms of eq. (32) at a trajectory: {"running", "final", "initial", "slack",
        "horizon", "total"} → float ("running" includes Δt and the sum over k = 0..N−1)."""
        values = self._numeric(trajectory)
        return {name: float(values[name].item()) for name in COST_TERMS + ("total",)}

    def inequality_bounds(self):
        """{family: (lower (rows,), upper (rows,))} of every inequality family (knot-independent)."""
        nc, nj = self.layout.n_contacts, self.layout.n_jets
        P = self._numbers.params
        corner, jet = np.tile(P["corner_com_bound"], nc), np.full(3 * nj, float(P["jet_com_bound"]))
        sigma = np.full(nc, float(P["complementarity_tolerance"]))  # eq. (20) relaxed by σ_n
        sigma_t = np.full(2 * nc, float(P["planar_tolerance"]))  # eq. (21) relaxed by σ_t
        return {
            "friction_cone": (np.full(4 * nc, -np.inf), np.zeros(4 * nc)),
            "normal_complementarity": (np.full(nc, -np.inf), sigma),
            "corner_com": (-corner, corner),
            "jet_com": (-jet, jet),
            "planar_complementarity": (
                np.concatenate([np.full(2 * nc, -np.inf), -sigma_t]),
                np.concatenate([sigma_t, np.full(2 * nc, np.inf)]),
            ),
            JOINT_TORQUE: (-self._effort_limits, self._effort_limits),
        }

    def constraint_bounds(self):
        """(lower, upper) of the stacked constraint vector g of ``solve`` (every family in
        ``family_names`` order, each flattened knot-major)."""
        inequalities = self.inequality_bounds()
        lower, upper = [], []
        for name in self.family_names():
            rows = self._evaluate.size1_out(name)
            lo, up = inequalities.get(name, (np.zeros(rows), np.zeros(rows)))
            lower.append(np.tile(lo, self.n_stages(name)))
            upper.append(np.tile(up, self.n_stages(name)))
        return np.concatenate(lower), np.concatenate(upper)

    def variable_bounds(self):
        """(lower, upper): the boxes of docs/formulation.md as two ((N + 1) nz + 1,) vectors.

        Every-knot boxes intersected with the knot-dependent ones of k = 0, ⌊N/2⌋ and N
        (the boundary conditions, eq. 30, 31).
        """
        N, P = self.n_intervals, self._numbers.params
        lower, upper = _knot_boxes(self.layout, self.task.n_knots, P)
        slices = self.layout.slices()

        def box(k, field, lo, up, index=slice(None)):
            sl = np.arange(self.layout.size)[slices[field]][index]
            lower[k, sl] = np.maximum(lower[k, sl], lo)
            upper[k, sl] = np.minimum(upper[k, sl], up)

        tol = float(P["boundary_tolerance"])
        box(0, "com", P["initial_com"], P["initial_com"])
        box(N, "com", P["final_com"], P["final_com"])
        box(N // 2, "com", float(P["mid_com_height"]), np.inf, 2)
        for field in ("com_velocity", "com_acceleration", "angular_momentum", "angular_momentum_rate"):
            box(0, field, -tol, tol)
        rho_bar = P["reference_configuration"][3:7]
        box(0, "base_quaternion", rho_bar - tol, rho_bar + tol)
        final_tol = float(P["final_orientation_tolerance"])
        box(N, "base_quaternion", np.array(_IDENTITY) - final_tol, np.array(_IDENTITY) + final_tol)
        box(0, "contact_points", 0.0, 0.0, slice(2, None, 3))
        box(0, "contact_force_rates", 0.0, 0.0)
        if self.task.zero_initial_thrust:
            box(0, "thrust", 0.0, tol)
            box(0, "thrust_rate", -tol, tol)
        time_bounds = self.n_intervals * np.array([P["min_dt"], P["max_dt"]])
        return (np.concatenate([lower.ravel(), time_bounds[:1]]),
                np.concatenate([upper.ravel(), time_bounds[1:]]))

    def scale(self):
        """((N + 1) nz + 1,) the published variable scaling d (z = d · z̃), T_total unscaled."""
        return np.concatenate([np.tile(np.asarray(self.layout.scale()), self.task.n_knots), [1.0]])

    def violations(self, trajectory):
        """{family: max violation} of every constraint family, and "variable_bounds"
        (physical units; 0 when satisfied)."""
        values = self.evaluate(trajectory)
        inequalities = self.inequality_bounds()
        out = {}
        for name, value in values.items():
            lo, up = inequalities.get(name, (0.0, 0.0))
            excess = np.maximum(np.maximum(lo - value, value - up), 0.0)
            out[name] = float(excess.max(initial=0.0))
        w = self.flatten(trajectory)
        lower, upper = self.variable_bounds()
        out["variable_bounds"] = float(np.maximum(np.maximum(lower - w, w - upper), 0.0).max())
        return out

    # ---- IPOPT

    def _ipopt_solver(self, d, ipopt_options):
        """IPOPT on the scaled variables z̃ = w / d, with g every family stacked as in
        ``constraint_bounds``."""
        w_scaled = cs.MX.sym("w_scaled", self.n_variables)
        families, costs = self.symbolic(cs.DM(d) * w_scaled)
        g = cs.vertcat(*[cs.vec(families[name]) for name in self.family_names()])
        return cs.nlpsol(
            "reference", "ipopt", {"x": w_scaled, "f": costs["total"], "g": g},
            dict(ipopt=ipopt_options, print_time=False),
        )

    def solve(self, guess, *, tol=1e-4, max_iter=3000, print_level=0, scaled=True, hessian="exact", options=None):
        """Solve with IPOPT + MUMPS from a guess (a jaxmm ``Trajectory``).

        tol: IPOPT's ``tol`` and ``constr_viol_tol`` (constraint violation in physical units).
        scaled: IPOPT sees z̃ = z / d (``scale``). hessian: "exact" (default) or
        "limited-memory" (the paper's runs, with MA97; with MUMPS it did not converge on
        take-off N = 10 within 3000 iterations, the exact Hessian does in ~200).
        options: extra IPOPT options {name: value}.
        Returns (``Trajectory``, info) with info: status, success, objective, iterations,
        wall_time [s] (IPOPT only), setup_time [s] (solver construction), max_violation,
        hessian, scaled.
        """
        if hessian not in HESSIANS:
            raise ValueError(f"hessian must be one of {HESSIANS}, got {hessian!r}")
        start = time.perf_counter()
        d = self.scale() if scaled else np.ones(self.n_variables)
        ipopt = dict(
            linear_solver="mumps", tol=tol, constr_viol_tol=tol, max_iter=max_iter,
            print_level=print_level, hessian_approximation=hessian, sb="yes",
        )
        solver = self._ipopt_solver(d, dict(ipopt, **(options or {})))
        lower, upper = self.variable_bounds()
        lower_g, upper_g = self.constraint_bounds()
        setup_time = time.perf_counter() - start
        start = time.perf_counter()
        solution = solver(x0=self.flatten(guess) / d, lbx=lower / d, ubx=upper / d, lbg=lower_g, ubg=upper_g)
        wall_time = time.perf_counter() - start
        stats = solver.stats()
        trajectory = self.unflatten(d * np.asarray(solution["x"].full()).ravel())
        info = dict(
            status=stats["return_status"],
            success=bool(stats["success"]),
            objective=float(solution["f"]),
            iterations=int(stats["iter_count"]),
            wall_time=wall_time,
            setup_time=setup_time,
            max_violation=max(self.violations(trajectory).values()),
            hessian=hessian,
            scaled=scaled,
        )
        return trajectory, info


def _knot_boxes(layout, n_knots, P):
    """Every-knot boxes of docs/formulation.md in ``layout``: (lower, upper), each (N + 1, nz)."""
    fields = {name: (np.full(shape, -np.inf), np.full(shape, np.inf)) for name, shape in layout.shapes().items()}
    xy = float(P["com_xy_limit"])
    fields["com"] = (np.array([-xy, -xy, 0.0]), np.array([xy, xy, np.inf]))
    fields["base_quaternion"] = (-np.ones(4), np.ones(4))
    fields["joint_positions"] = (P["joint_limits"][:, 0], P["joint_limits"][:, 1])
    for name, limit in (("base_linear_velocity", "base_linear_velocity_limit"),
                        ("base_angular_velocity", "base_angular_velocity_limit"),
                        ("joint_velocities", "joint_velocity_limit")):
        value = float(P[limit])
        fields[name] = (np.full(layout.shapes()[name], -value), np.full(layout.shapes()[name], value))
    nc = layout.n_contacts
    nonnegative_z = np.tile([-np.inf, -np.inf, 0.0], nc).reshape(nc, 3)
    fields["contact_forces"] = (nonnegative_z, np.full((nc, 3), np.inf))
    fields["contact_points"] = (nonnegative_z, np.full((nc, 3), np.inf))
    fields["thrust"] = (np.zeros(layout.n_jets), P["max_thrust"])
    low, high = P["throttle_range"]
    fields["throttle"] = (np.full(layout.n_jets, low), np.full(layout.n_jets, high))
    for name in ("normal_slack", "tangential_slack"):
        fields[name] = (np.zeros(nc), np.full(nc, float(P["slack_limit"])))
    lower = np.concatenate([np.ravel(fields[name][0]) for name in layout.fields])
    upper = np.concatenate([np.ravel(fields[name][1]) for name in layout.fields])
    return np.tile(lower, (n_knots, 1)), np.tile(upper, (n_knots, 1))


def solve_ipopt(task, urdf_path, guess=None, *, tol=1e-4, max_iter=3000, print_level=0, scaled=True,
                hessian="exact", options=None):
    """Build the ``ReferenceNLP`` of a task and solve it with IPOPT + MUMPS.

    guess: a jaxmm ``Trajectory`` (default: ``jaxmm.tasks.initial_guess(task)``, the published
    guess). Other arguments as ``ReferenceNLP.solve``. Returns (``Trajectory``, info); info
    also has build_time [s] (the CasADi NLP build).
    """
    from jaxmm.tasks import initial_guess

    start = time.perf_counter()
    nlp = ReferenceNLP(task, urdf_path)
    build_time = time.perf_counter() - start
    guess = initial_guess(task) if guess is None else guess
    trajectory, info = nlp.solve(
        guess, tol=tol, max_iter=max_iter, print_level=print_level, scaled=scaled, hessian=hessian, options=options
    )
    return trajectory, dict(info, build_time=build_time)
