"""Independent references for the tests: nothing here calls the code under test's march."""

from __future__ import annotations

import contextlib
import traceback

import jax
import numpy as np
from scipy.integrate import solve_ivp
from scipy.special import sph_legendre_p_all


def hat(w):
    w = np.asarray(w, float)
    return np.array([[0.0, -w[2], w[1]], [w[2], 0.0, -w[0]], [-w[1], w[0], 0.0]])


def rigid_body_reference(inertia, Q0, omega0, ts, rtol=1e-13, atol=1e-13):
    """Euler's equations I dω/dt = (Iω)×ω with dQ/dt = Q hat(ω), solved by SciPy's DOP853."""
    inertia = np.asarray(inertia, float)

    def rhs(t, y):
        Q = y[:9].reshape(3, 3)
        w = y[9:]
        dQ = Q @ hat(w)
        dw = np.cross(inertia * w, w) / inertia
        return np.concatenate([dQ.ravel(), dw])

    y0 = np.concatenate([np.asarray(Q0, float).ravel(), np.asarray(omega0, float)])
    sol = solve_ivp(rhs, (ts[0], ts[-1]), y0, method="DOP853", t_eval=ts, rtol=rtol, atol=atol)
    assert sol.success
    Y = sol.y.T
    return Y[:, :9].reshape(-1, 3, 3), Y[:, 9:]


def cay_recursion(inertia, omega_first, dt, n):
    """Example 30's reduced CAY recursion in vector form, solved by NumPy Newton.

    The compact form (I - hX⁻/2) M⁻ (I + hX⁻/2) = (I + hX/2) M (I - hX/2), with X = hat(ω),
    M = hat(Iω), is hat of  m ∓ (h/2) ω×m + (h²/4)(ω·m) ω  (using hat(a)hat(b)hat(a) =
    -(a·b)hat(a)). Given ω⁻ this solves for ω.
    """
    inertia = np.asarray(inertia, float)
    h = dt
    out = [np.asarray(omega_first, float)]
    for _ in range(n - 1):
        wp = out[-1]
        mp = inertia * wp
        rhs = mp - 0.5 * h * np.cross(wp, mp) + 0.25 * h * h * np.dot(wp, mp) * wp
        out.append(cay_velocity(inertia, h, rhs, wp))
    return np.array(out)


def cay_velocity(inertia, h, rhs, w):
    """Newton's method (NumPy) for the CAY step velocity w: (Iw) + h/2 w×(Iw) + h²/4 (w·Iw) w = rhs,
    from the guess w."""
    w = np.array(w, dtype=float)
    for _ in range(50):
        m = inertia * w
        F = m + 0.5 * h * np.cross(w, m) + 0.25 * h * h * np.dot(w, m) * w - rhs
        # d/dw of w×(Iw) = -hat(Iw) + hat(w) I ; d/dw of (w·Iw) w = w (2Iw)^T + (w·Iw) Id
        J = (
            np.diag(inertia)
            + 0.5 * h * (-hat(m) + hat(w) @ np.diag(inertia))
            + 0.25 * h * h * (np.outer(w, 2 * m) + np.dot(w, m) * np.eye(3))
        )
        dw = np.linalg.solve(J, F)
        w = w - dw
        if np.max(np.abs(dw)) < 1e-16 * max(1.0, np.max(np.abs(w))):
            break
    return w


def cay_compact_residual(inertia, Xs, dt):
    """Max over n of |(I - hX⁻/2) M⁻ (I + hX⁻/2) - (I + hX/2) M (I - hX/2)| in matrix form."""
    I3 = np.eye(3)
    worst = 0.0
    for wp, w in zip(Xs[:-1], Xs[1:]):
        Xp, X = hat(wp), hat(w)
        Mp, M = hat(inertia * wp), hat(inertia * w)
        lhs = (I3 - 0.5 * dt * Xp) @ Mp @ (I3 + 0.5 * dt * Xp)
        rhs = (I3 + 0.5 * dt * X) @ M @ (I3 - 0.5 * dt * X)
        worst = max(worst, np.max(np.abs(lhs - rhs)))
    return worst


def vortex_rhs(gamma, Q):
    """Biot–Savart velocities of planar point vortices, written directly (not from a Hamiltonian):
    dQ_a/dt = Σ_{b≠a} Γ_b/(2π) · (−(y_a − y_b), x_a − x_b) / |Q_a − Q_b|²."""
    gamma = np.asarray(gamma, float)
    d = Q[:, None, :] - Q[None, :, :]
    r2 = np.sum(d * d, axis=-1)
    np.fill_diagonal(r2, np.inf)
    w = gamma[None, :] / (2.0 * np.pi * r2)
    return np.stack([-np.sum(w * d[..., 1], axis=1), np.sum(w * d[..., 0], axis=1)], axis=-1)


def vortex_reference(gamma, Q0, ts, rtol=1e-13, atol=1e-13):
    """Point vortices solved by SciPy's DOP853 at tight tolerance; positions at `ts`."""
    Q0 = np.asarray(Q0, float)
    rhs = lambda t, y: vortex_rhs(gamma, y.reshape(Q0.shape)).ravel()
    sol = solve_ivp(rhs, (ts[0], ts[-1]), Q0.ravel(), method="DOP853", t_eval=ts, rtol=rtol, atol=atol)
    assert sol.success
    return sol.y.T.reshape((len(ts),) + Q0.shape)


def implicit_midpoint_vortices(gamma, Q0, dt, n_steps):
    """The implicit midpoint rule Q¹ = Q⁰ + Δt f((Q⁰ + Q¹)/2), each step solved by fixed-point
    iteration to round-off: an independent implementation of what the midpoint principle
    should reduce to for point vortices."""
    Q = np.asarray(Q0, float)
    out = [Q]
    for _ in range(n_steps):
        Q1 = Q + dt * vortex_rhs(gamma, Q)
        for _ in range(200):
            Q1_new = Q + dt * vortex_rhs(gamma, 0.5 * (Q + Q1))
            done = np.max(np.abs(Q1_new - Q1)) <= 4e-16 * max(1.0, np.max(np.abs(Q1)))
            Q1 = Q1_new
            if done:
                break
        Q = Q1
        out.append(Q)
    return np.stack(out)


@contextlib.contextmanager
def compiles_recorded(where: str | tuple | None = None):
    """The XLA compilations made inside the `with` block, as a list of program names filled in
    as they happen; with `where`, only those whose innermost `clebsch_jax` frame is in a file
    whose path ends with `where` (or with one of a tuple of them). (JAX's listeners cannot be
    removed: this one stops recording when the block ends.)"""
    names, on = [], [True]

    def listen(event, secs, fun_name=None, **kw):
        if not (on[0] and "backend_compile" in event):
            return
        if where is not None:
            frames = [f.filename for f in traceback.extract_stack() if "clebsch_jax" in f.filename]
            if not (frames and frames[-1].endswith(where)):
                return
        names.append(fun_name)

    jax.monitoring.register_event_duration_secs_listener(listen)
    try:
        yield names
    finally:
        on[0] = False


def _sphere_legendre(L, x):
    """Y_lm(θ, 0) (SciPy's `sph_legendre_p_all`, Condon–Shortley phase) at cos θ = x and
    sin θ ∂θ of it, shapes (L+1, L+1, len(x)) for 0 ≤ m ≤ l."""
    theta = np.arccos(x)
    values = sph_legendre_p_all(L, L, theta, diff_n=1)[:, :, : L + 1]
    return values[0], np.sin(theta) * values[1]


def sphere_euler_spectral(c0, T, L, rtol=1e-12):
    r"""Euler's equations on the unit sphere, $\omega_t = \{\psi, \omega\}$, $\Delta\psi = \omega$,
    $\{f, g\} = (f_\theta g_\phi - f_\phi g_\theta)/\sin\theta$, by a pseudo-spectral Galerkin
    method truncated at degree L (products on a Gauss–Legendre × uniform grid of 3L/2 + 2 by
    3L + 3 points: no aliasing of the quadratic term), integrated by SciPy's DOP853 at `rtol`.
    `c0[l, m]` (0 ≤ m ≤ l) are the complex coefficients of the real field
    $\sum_l c_{l0}Y_{l0} + 2\,\mathrm{Re}\sum_{m>0} c_{lm}Y_{lm}$. **Returns:** c at time T,
    (L+1, L+1). Independent of the Zeitlin model and of the engine."""
    x, w = np.polynomial.legendre.leggauss(3 * L // 2 + 2)
    n_phi = 3 * L + 3
    P, D = _sphere_legendre(L, x)
    sin = np.sqrt(1 - x * x)[:, None]
    l = np.arange(L + 1)
    inverse_laplacian = np.where(l > 0, -1.0 / np.maximum(l * (l + 1), 1), 0.0)[:, None]
    im = 1j * np.arange(L + 1)[:, None]
    lower = np.nonzero(np.tril(np.ones((L + 1, L + 1), bool)))

    def synthesis(c, basis, factor=1.0):
        per_m = np.einsum("lm,lmt->mt", c, basis) * factor
        F = np.zeros((len(x), n_phi), complex)
        F[:, : L + 1] = per_m.T
        F[:, 1 : L + 1] *= 2.0
        return (np.fft.ifft(F, axis=1) * n_phi).real

    def analysis(f):
        F = np.fft.fft(f, axis=1)[:, : L + 1] * (2 * np.pi / n_phi)  # ∫ f e^{-imφ} dφ
        return np.tril(np.einsum("t,lmt,tm->lm", w, P, F))

    def rhs(t, y):
        c = np.zeros((L + 1, L + 1), complex)
        c[lower] = y[: len(lower[0])] + 1j * y[len(lower[0]) :]
        psi = c * inverse_laplacian
        bracket = (synthesis(psi, D) / sin * synthesis(c, P, im) - synthesis(psi, P, im) * synthesis(c, D) / sin) / sin
        d = analysis(bracket)[lower]
        return np.concatenate([d.real, d.imag])

    c = np.zeros((L + 1, L + 1), complex)
    k = min(L + 1, c0.shape[0])
    c[:k, :k] = np.tril(np.asarray(c0)[:k, :k])
    y0 = np.concatenate([c[lower].real, c[lower].imag])
    y = solve_ivp(rhs, (0.0, T), y0, method="DOP853", rtol=rtol, atol=rtol).y[:, -1]
    c = np.zeros((L + 1, L + 1), complex)
    c[lower] = y[: len(lower[0])] + 1j * y[len(lower[0]) :]
    return c


def solution_leaves(sol):
    """(path, NumPy array) of every leaf of a pytree (a `Solution`), in order."""
    return [(jax.tree_util.keystr(path), np.asarray(x)) for path, x in jax.tree_util.tree_flatten_with_path(sol)[0]]


def assert_same_solution(native, xla):
    """Every leaf of two Solutions: integers (statuses, failed steps, iterations, valid nodes)
    exactly, NaNs at the same places, floats to 1e-12 of the leaf's largest entry (Newton's
    residual norms, round-off, to 1e-12 absolutely)."""
    for (name, a), (_, b) in zip(solution_leaves(native), solution_leaves(xla)):
        assert a.shape == b.shape and a.dtype == b.dtype, name
        if a.dtype.kind != "f":
            np.testing.assert_array_equal(a, b, err_msg=name)
            continue
        np.testing.assert_array_equal(np.isnan(a), np.isnan(b), err_msg=name)
        if np.all(np.isnan(b)):
            continue
        atol = 1e-12 if "residual_norm" in name else 1e-12 * np.nanmax(np.abs(b))
        np.testing.assert_allclose(a, b, rtol=0, atol=atol, equal_nan=True, err_msg=name)
