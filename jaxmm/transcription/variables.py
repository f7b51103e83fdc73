"""Decision variables: one knot as a named pytree, the trajectory, flat layout and scaling.

The flat layout of a knot is the order of ``FIELDS`` (docs/formulation.md, "Variables").
"""

import dataclasses
import numbers

import jax
import jax.numpy as jnp
import numpy as np


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class Knot:
    """The decision variables of one knot (physical units; shapes for one knot).

    n joints, nc contact corners, nj jets. With a leading axis (N + 1,) on every leaf the same
    class holds a whole trajectory's knots.
    """

    com: jax.Array  # (3,) x [m], world
    com_velocity: jax.Array  # (3,) ẋ [m/s]
    com_acceleration: jax.Array  # (3,) ẍ [m/s²]
    angular_momentum: jax.Array  # (3,) h_ω [kg m²/s], about the CoM
    angular_momentum_rate: jax.Array  # (3,) ḣ_ω [N m]
    base_position: jax.Array  # (3,) p [m]
    base_quaternion: jax.Array  # (4,) ρ (x, y, z, w)
    joint_positions: jax.Array  # (n,) s [rad]
    base_linear_velocity: jax.Array  # (3,) ṗ [m/s], world
    base_angular_velocity: jax.Array  # (3,) ω [rad/s], world
    joint_velocities: jax.Array  # (n,) ṡ [rad/s]
    contact_forces: jax.Array  # (nc, 3) f [N], world
    contact_force_rates: jax.Array  # (nc, 3) ḟ [N/s]
    contact_points: jax.Array  # (nc, 3) c [m], world
    thrust: jax.Array  # (nj,) T [N]
    thrust_rate: jax.Array  # (nj,) Ṫ [N/s]
    thrust_acceleration: jax.Array  # (nj,) T̈ [N/s²]
    throttle: jax.Array  # (nj,) u [%]
    normal_slack: jax.Array  # (nc,) ε_n
    tangential_slack: jax.Array  # (nc,) ε_t

    @property
    def configuration(self):
        """q = (p, ρ, s): (7 + n,) (or (N + 1, 7 + n) for a trajectory)."""
        return jnp.concatenate([self.base_position, self.base_quaternion, self.joint_positions], axis=-1)

    @property
    def velocity(self):
        """ν = (ṗ, ω, ṡ): (6 + n,) (or (N + 1, 6 + n))."""
        return jnp.concatenate(
            [self.base_linear_velocity, self.base_angular_velocity, self.joint_velocities], axis=-1
        )


# The flat layout of a knot: the fields that no transition row couples to the next knot first,
# those it couples (the integrated states, the contact points and forces, the thrust chain, ε_t)
# last. The block factorisation eliminates each knot's variables with the coupled ones last
# (``solver.linalg.coupled_order``), so in this order it reorders nothing.
FIELDS = (
    "com_acceleration", "angular_momentum_rate", "base_linear_velocity", "base_angular_velocity",
    "joint_velocities", "contact_force_rates", "throttle", "normal_slack",
    "com", "com_velocity", "angular_momentum", "base_position", "base_quaternion", "joint_positions",
    "contact_forces", "contact_points", "thrust", "thrust_rate", "thrust_acceleration", "tangential_slack",
)


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class Trajectory:
    """A whole trajectory: knots (every leaf with a leading (N + 1,) axis) and the total time [s]."""

    knots: Knot
    total_time: jax.Array  # () T_total [s]

    @property
    def n_knots(self):
        """N + 1."""
        return self.knots.com.shape[0]

    @property
    def time(self):
        """(N + 1,) time of each knot [s]."""
        return jnp.linspace(0.0, 1.0, self.n_knots) * self.total_time


def resample(trajectory, n_knots):
    """The trajectory on ``n_knots`` evenly spaced knots over the same total time: every knot
    field interpolated linearly in time, the base quaternion normalised after interpolation
    (its sign made continuous first). For refining a coarse solution into the guess of the same
    task at a larger N (or coarsening one). Returns a ``Trajectory``; ``n_knots`` ≥ 2."""
    if not isinstance(trajectory, Trajectory):
        raise TypeError(f"trajectory must be a Trajectory, got {type(trajectory).__name__}")
    if isinstance(n_knots, bool) or not isinstance(n_knots, numbers.Integral) or n_knots < 2:
        raise ValueError(f"n_knots must be an integer ≥ 2, got {n_knots!r}")
    source = jnp.linspace(0.0, 1.0, trajectory.n_knots)
    target = jnp.linspace(0.0, 1.0, int(n_knots))
    quaternions = trajectory.knots.base_quaternion
    # q and −q are one rotation: flip each knot's sign to the side of its predecessor's
    signs = jnp.cumprod(jnp.where(jnp.sum(quaternions[1:] * quaternions[:-1], axis=-1) < 0, -1.0, 1.0))
    quaternions = quaternions.at[1:].multiply(signs[:, None])

    def along(values):
        flat = values.reshape(values.shape[0], -1)
        out = jax.vmap(lambda column: jnp.interp(target, source, column), in_axes=1, out_axes=1)(flat)
        return out.reshape((target.shape[0],) + values.shape[1:])

    knots = jax.tree.map(along, dataclasses.replace(trajectory.knots, base_quaternion=quaternions))
    unit = knots.base_quaternion / jnp.linalg.norm(knots.base_quaternion, axis=-1, keepdims=True)
    return Trajectory(knots=dataclasses.replace(knots, base_quaternion=unit), total_time=trajectory.total_time)


@dataclasses.dataclass(frozen=True)
class Layout:
    """Static sizes of a knot and the map between ``Knot`` and flat vectors.

    n_joints n, n_contacts nc, n_jets nj (all Python ints, hashable); fields: the order of the
    fields in the flat vector (default ``FIELDS``).
    """

    n_joints: int
    n_contacts: int
    n_jets: int
    fields: tuple = FIELDS

    def shapes(self):
        n, nc, nj = self.n_joints, self.n_contacts, self.n_jets
        sizes = dict(
            com=(3,), com_velocity=(3,), com_acceleration=(3,), angular_momentum=(3,),
            angular_momentum_rate=(3,), base_position=(3,), base_quaternion=(4,),
            joint_positions=(n,), base_linear_velocity=(3,), base_angular_velocity=(3,),
            joint_velocities=(n,), contact_forces=(nc, 3), contact_force_rates=(nc, 3),
            contact_points=(nc, 3), thrust=(nj,), thrust_rate=(nj,), thrust_acceleration=(nj,),
            throttle=(nj,), normal_slack=(nc,), tangential_slack=(nc,),
        )
        return {name: sizes[name] for name in self.fields}

    @property
    def size(self):
        """nz, the number of variables of one knot."""
        return sum(int(np.prod(s)) for s in self.shapes().values())

    def slices(self):
        """{field: slice of the flat knot vector}."""
        out, start = {}, 0
        for name, shape in self.shapes().items():
            size = int(np.prod(shape))
            out[name] = slice(start, start + size)
            start += size
        return out

    def flatten(self, knot):
        """Knot → (nz,) (or (..., nz) for batched knots)."""
        shapes = self.shapes()
        leaves = []
        for name in self.fields:
            leaf = jnp.asarray(getattr(knot, name))
            batch = leaf.shape[: leaf.ndim - len(shapes[name])]
            leaves.append(leaf.reshape(batch + (-1,)))
        return jnp.concatenate(leaves, axis=-1)

    def unflatten(self, z):
        """(nz,) (or (..., nz)) → Knot."""
        if z.shape[-1] != self.size:
            raise ValueError(f"a flat knot has {self.size} entries, got shape {z.shape}")
        batch = z.shape[:-1]
        # lax.slice_in_dim, not z[..., sl]: NumPy-style indexing costs far more Python per call
        # when the solver's derivatives are traced (dozens of knots unflattened per iteration).
        return Knot(**{
            name: jax.lax.slice_in_dim(z, sl.start, sl.stop, axis=-1).reshape(batch + shape)
            for (name, shape), sl in zip(self.shapes().items(), self.slices().values())
        })

    def scale(self):
        """(nz,) variable scaling d of the published runs: z = d · z̃ (T 100; f, ḟ 50; s 2; ṡ 7)."""
        d, slices = np.ones(self.size), self.slices()  # NumPy: a constant, not traced operations
        for name, factor in (("thrust", 100.0), ("contact_forces", 50.0), ("contact_force_rates", 50.0),
                             ("joint_positions", 2.0), ("joint_velocities", 7.0)):
            d[slices[name]] = factor
        return d
