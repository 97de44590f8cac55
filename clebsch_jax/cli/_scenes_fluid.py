r"""The scene `euler-sphere`: random vorticities on the quantised sphere, the Casimirs and the
angular momentum, and the orthographic plot."""

from __future__ import annotations


import jax.numpy as jnp
import numpy as np

from clebsch_jax.models import (
    euler_sphere,
    euler_sphere_angular_momentum,
    euler_sphere_casimirs,
    euler_sphere_orthographic,
    euler_sphere_quantise,
    euler_sphere_start,
    euler_sphere_vorticity,
)

from ._scene_types import Invariant, Scene, Setup, orthogonality

__all__ = ["EULER_SPHERE", "sphere_random_coefficients"]


# --------------------------------------------------------------------------------------------
# euler-sphere: incompressible Euler on the sphere, quantised (Euler–Zeitlin), reduced march.

SPHERE_N = 32
SPHERE_PEAK = 10
"""The scene's matrix size and the degree near which its initial energy spectrum peaks."""


def _sphere_system():
    return euler_sphere(SPHERE_N)


def sphere_random_coefficients(N: int, peak: float, rng: np.random.Generator) -> np.ndarray:
    r"""Spherical-harmonic coefficients c[l, m] of a random real vorticity whose energy spectrum
    $E_l \propto \sum_m |c_{lm}|^2 / (l(l+1))$ is $\propto l^3 e^{-2(l/l_p)^2}$-shaped, peaked near
    $l_p$ = `peak` (random phases; zero mean, $c_{00} = 0$), scaled to a root-mean-square
    vorticity of 1 ($\int\omega^2 dA = 4\pi$: a turnover time of order 1)."""
    l = np.arange(N, dtype=float)
    amplitude = np.sqrt(l * (l + 1) * l**3 * np.exp(-2 * (l / peak) ** 2) / np.maximum(2 * l + 1, 1))
    c = rng.normal(size=(N, N)) + 1j * rng.normal(size=(N, N))
    c = np.tril(c) * amplitude[:, None]
    c[:, 0] = c[:, 0].real * np.sqrt(2)
    c[0, 0] = 0.0
    enstrophy = np.sum(np.abs(c[:, 0]) ** 2) + 2 * np.sum(np.abs(c[:, 1:]) ** 2)  # ∫ω² dA
    return c * np.sqrt(4 * np.pi / enstrophy)


def _sphere_setup(batch, rng):
    starts = [
        euler_sphere_start(euler_sphere_quantise(sphere_random_coefficients(SPHERE_N, SPHERE_PEAK, rng)))
        for _ in range(batch)
    ]
    Q0 = np.stack([np.asarray(q) for q, _ in starts])
    xi0 = np.stack([np.asarray(x) for _, x in starts])
    return Setup(Q0=Q0, xi0=xi0, P0=None, members={"N": SPHERE_N, "peak_degree": SPHERE_PEAK})


def _sphere_casimir(k):
    def values(system, sol):
        return euler_sphere_casimirs(euler_sphere_vorticity(sol.momentum), powers=(k,))

    return values


def _sphere_casimir_scale(k):
    def scale(system, sol):  # Σ|λ|^k over W's eigenvalues: tr W³ of a random field is near 0
        H = 1j * euler_sphere_vorticity(sol.momentum[0])
        return jnp.sum(jnp.abs(jnp.linalg.eigvalsh(H)) ** k)

    return scale


def _sphere_angular_momentum(system, sol):
    return euler_sphere_angular_momentum(euler_sphere_vorticity(sol.momentum))


def _sphere_angular_scale(system, sol):  # |∫ω n| ≤ ∫|ω|: the size of ω at node 0 (Frobenius)
    W = euler_sphere_vorticity(sol.momentum[0])
    return jnp.sqrt(jnp.real(jnp.sum(jnp.conj(W) * W)) * 4 * np.pi / W.shape[-1])


def _sphere_trajectory(system, sol):
    return sol.momentum


def _sphere_plot(ax, ts, traj, setup, colors):
    """Member 0's vorticity at the last known node, orthographic view from above the equator."""
    known = np.flatnonzero(np.all(np.isfinite(traj[0].reshape(traj.shape[1], -1)), axis=-1))
    k = known[-1] if known.size else 0
    W = np.asarray(euler_sphere_vorticity(traj[0, k]))
    _orthographic(ax, W)
    ax.set_title(f"vorticity at t = {ts[k]:.3g} (orthographic, member 0)", fontsize=10)


def _orthographic(ax, W):
    """The field of W on the hemisphere seen from above the equator (`euler_sphere_orthographic`)."""
    values = euler_sphere_orthographic(W, colatitude=0.35, longitude=0.4)
    r = np.nanmax(np.abs(values))
    ax.imshow(values, origin="lower", extent=(-1, 1, -1, 1), cmap="RdBu_r", vmin=-r, vmax=r)
    ax.set_aspect("equal")
    ax.set_axis_off()


# --------------------------------------------------------------------------------------------
# The scenes.

EULER_SPHERE = Scene(
    name="euler-sphere",
    description="incompressible Euler on the sphere, quantised at N = 32 (Euler-Zeitlin)",
    details="The paper's fluid: vorticity as a skew-Hermitian 32 x 32 matrix, the reduced Cayley "
    "march (the isospectral midpoint method) solved by matrix-free sweeps. Member 0 and, "
    "with --batch B, the others are random vorticities with an energy spectrum peaked "
    "near degree 10. Reports the Casimirs tr W^2, tr W^3, tr W^4 (relative to sum "
    "|lambda|^k) and the total angular momentum (relative to |omega|).",
    model=f"euler_sphere(N={SPHERE_N})",
    system=_sphere_system,
    setup=_sphere_setup,
    dt=0.01,
    steps=2000,
    quick_steps=100,
    quick_batch=1,
    invariants=(
        Invariant("casimir_2", "Casimir tr W^2", _sphere_casimir(2), scale=_sphere_casimir_scale(2)),
        Invariant("casimir_3", "Casimir tr W^3", _sphere_casimir(3), scale=_sphere_casimir_scale(3)),
        Invariant("casimir_4", "Casimir tr W^4", _sphere_casimir(4), scale=_sphere_casimir_scale(4)),
        Invariant("angular_momentum", "angular momentum", _sphere_angular_momentum, scale=_sphere_angular_scale),
        Invariant("orthogonality", "|Q^T Q - I|", orthogonality, kind="error"),
    ),
    trajectory=_sphere_trajectory,
    plot=_sphere_plot,
)
