"""Centroidal dynamics under contact and thrust forces (eq. 13, 14)."""

import jax.numpy as jnp


def momentum_rate(mass, com, contact_forces, contact_points, jet_forces, jet_positions, gravity):
    """Rate of the centroidal momentum ḣ = (m ẍ, ḣ_ω) of eq. (13).

    mass m [kg]; com x (3,) [m]; contact_forces, contact_points (nc, 3); jet_forces,
    jet_positions (nj, 3) (pure forces at points, eq. 5); gravity (3,) [m/s²].
    Returns (6,): [Σ f + m g; Σ (p − x) × f] about the CoM, world-aligned.
    """
    forces = jnp.concatenate([contact_forces, jet_forces])
    points = jnp.concatenate([contact_points, jet_positions])
    linear = jnp.sum(forces, axis=0) + mass * gravity
    angular = jnp.sum(jnp.cross(points - com, forces), axis=0)
    return jnp.concatenate([linear, angular])
