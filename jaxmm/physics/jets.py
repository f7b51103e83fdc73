"""Jet engines: thrust force (eq. 5) and the identified second-order thrust dynamics (eq. 8)."""

import jax.numpy as jnp


def thrust_forces(thrust, jet_rotations):
    """Force of each jet, along its frame's −z axis (eq. 5): f_j = R_j (0, 0, −T_j).

    thrust: (nj,) [N]; jet_rotations: (nj, 3, 3) jet frame → world. Returns (nj, 3) [N].
    """
    return -thrust[:, None] * jet_rotations[:, :, 2]


def thrust_acceleration(thrust, thrust_rate, throttle, coefficients):
    """T̈ = f(T, Ṫ) + g(T, Ṫ, u) of eq. (8), per jet.

    thrust T [N], thrust_rate Ṫ [N/s], throttle u [%]: (nj,) each; coefficients: (nj, 10) in
    the order K_T, K_TT, K_D, K_DD, K_TD, B_U, B_T, B_D, B_UU, c. Returns (nj,) [N/s²].
    """
    k_t, k_tt, k_d, k_dd, k_td, b_u, b_t, b_d, b_uu, c = jnp.moveaxis(coefficients, -1, 0)
    T, D, u = thrust, thrust_rate, throttle
    f = k_t * T + k_tt * T**2 + k_d * D + k_dd * D**2 + k_td * T * D + c
    g = (b_u + b_t * T + b_d * D) * (u + b_uu * u**2)
    return f + g
