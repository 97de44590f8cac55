"""Small pieces of user systems shared by test files: module-level functions, so that systems
built from them in different files are equal as jit static data and share compiled programs."""

import jax.numpy as jnp
import numpy as np


def kinetic(xi):
    """l(ξ) = |ξ|²/2."""
    return 0.5 * jnp.sum(xi**2)


def translation(xi, Q):
    """L_ξ Q = ξ: translations of a vector space."""
    return xi


def unit_vector(Q):
    """A check_Q for the unit sphere: None, or what is wrong."""
    n = float(np.linalg.norm(Q))
    return None if abs(n - 1.0) <= 1e-12 else f"not a unit vector (|Q| = {n:.6g})."


def kepler(xi, q):
    """l(ξ, q) = |ξ|²/2 + 1/|q|: Kepler's problem (GM = 1), singular at q = 0."""
    return 0.5 * jnp.sum(xi**2) + 1.0 / jnp.sqrt(jnp.sum(q**2))
