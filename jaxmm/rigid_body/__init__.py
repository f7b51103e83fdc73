"""The rigid-body library: a floating-base ``Model`` (static topology, array leaves) read from a
URDF, SO(3) maps, configurations, forward kinematics and frame Jacobians, and the centroidal
quantities (CoM, centroidal momentum and its matrix), and inverse dynamics (the recursive
Newton–Euler algorithm, the mass matrix, the bias forces). Pure JAX, jit- and vmap-ready; exact
against Pinocchio. Conventions (q = (p, ρ xyzw, s), ν = (ṗ, ω world, ṡ)) are in ``model``."""
