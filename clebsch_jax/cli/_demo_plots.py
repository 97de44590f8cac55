r"""The figures of the main demo (Figure 1 of Cotter & Holm): the orbits on the momentum sphere
with the separatrix, and the invariants' errors over time. matplotlib's object-oriented API:
no pyplot, no global backend, no display.
"""

from __future__ import annotations

import math

import numpy as np

__all__ = ["block_max", "orbit_colors", "separatrix_curve", "plot_orbits", "plot_invariants"]


def block_max(t: np.ndarray, y: np.ndarray, max_points: int = 2000):
    """Downsample (t, y) along the last axis keeping the maximum of each block (error envelopes)."""
    n = y.shape[-1]
    if n <= max_points:
        return t, y
    size = -(-n // max_points)
    pad = (-n) % size
    yp = np.concatenate([y, np.repeat(y[..., -1:], pad, axis=-1)], axis=-1)
    tp = np.concatenate([t, np.repeat(t[-1:], pad)])
    return tp[size - 1 :: size], yp.reshape(y.shape[:-1] + (-1, size)).max(axis=-1)


def orbit_colors(energy2: np.ndarray, inertia):
    """Reds for orbits about the minor axis, blues about the major axis; darker = nearer the axis."""
    from matplotlib import colormaps

    sep, hi, lo = 1.0 / inertia[1], 1.0 / inertia[0], 1.0 / inertia[2]
    colors = []
    for e in energy2:
        if e > sep:
            colors.append(colormaps["Reds"](0.4 + 0.55 * (e - sep) / (hi - sep)))
        else:
            colors.append(colormaps["Blues"](0.4 + 0.55 * (sep - e) / (sep - lo)))
    return colors


def separatrix_curve(inertia, n: int = 181) -> list:
    """The two great circles through ±e2 on which 2E = |m|^2 / I2 (the separatrix), on |m| = 1."""
    i1, i2, i3 = inertia
    s = math.sqrt((1 / i2 - 1 / i3) / (1 / i1 - 1 / i2))  # |m1| = s |m3| on the separatrix
    u = np.linspace(0.0, 2.0 * np.pi, n)
    circles = []
    for sign in (1.0, -1.0):
        d1 = np.array([sign * s, 0.0, 1.0]) / math.hypot(s, 1.0)
        circles.append(np.cos(u)[:, None] * d1 + np.sin(u)[:, None] * np.array([0.0, 1.0, 0.0]))
    return circles


def plot_orbits(path, m: np.ndarray, colors, title: str, inertia) -> None:
    from matplotlib import colormaps
    from matplotlib.figure import Figure
    from matplotlib.lines import Line2D

    fig = Figure(figsize=(12, 8.4), dpi=100)
    fig.suptitle(title, fontsize=11)
    ax = fig.add_axes((0.0, 0.0, 0.66, 0.93), projection="3d")

    # matplotlib's 3-D axes do no hidden-line removal: draw the far side of the sphere faintly.
    elev, azim = 20.0, 30.0
    ce, se = math.cos(math.radians(elev)), math.sin(math.radians(elev))
    view = np.array([ce * math.cos(math.radians(azim)), ce * math.sin(math.radians(azim)), se])

    def plot3(xyz, **kw):
        front = xyz @ view >= 0.0
        for mask, alpha in ((front, 1.0), (~front, 0.15)):
            pts = np.where(mask[:, None], xyz, np.nan)
            ax.plot(pts[:, 0], pts[:, 1], pts[:, 2], alpha=alpha, **kw)

    u = np.linspace(0.0, 2.0 * np.pi, 73)
    for lat in np.deg2rad(np.arange(-60, 61, 30)):
        plot3(
            np.stack([math.cos(lat) * np.cos(u), math.cos(lat) * np.sin(u), np.full_like(u, math.sin(lat))], axis=-1),
            color="0.8",
            lw=0.4,
        )
    for lon in np.deg2rad(np.arange(0, 180, 30)):
        plot3(np.stack([math.cos(lon) * np.cos(u), math.sin(lon) * np.cos(u), np.sin(u)], axis=-1), color="0.8", lw=0.4)
    separatrix = separatrix_curve(inertia)
    for curve in separatrix:
        plot3(curve, color="k", lw=0.8, ls="--")
    for mk, col in zip(m, colors):
        plot3(mk, color=col, lw=0.8)
    for k, name in enumerate(("$m_1$", "$m_2$", "$m_3$")):
        for sign in (1.0, -1.0):
            e = np.zeros(3)
            e[k] = sign
            ax.plot(*np.stack([e, 1.3 * e]).T, color="0.3", lw=0.8, alpha=1.0 if e @ view >= 0 else 0.3)
        e = np.zeros(3)
        e[k] = 1.38
        ax.text(*e, name, ha="center", va="center")
    ax.view_init(elev=elev, azim=azim)
    ax.set_box_aspect((1, 1, 1), zoom=1.25)
    ax.set_axis_off()
    for setlim in (ax.set_xlim, ax.set_ylim, ax.set_zlim):
        setlim(-1.05, 1.05)
    i1, i2, i3 = inertia
    ax.legend(
        handles=[
            Line2D([], [], color=colormaps["Reds"](0.8), lw=1.5),
            Line2D([], [], color=colormaps["Blues"](0.8), lw=1.5),
            Line2D([], [], color="k", lw=0.8, ls="--"),
        ],
        labels=[
            f"about the minor axis $m_1$ ($I_1 = {i1:g}$)",
            f"about the major axis $m_3$ ($I_3 = {i3:g}$)",
            f"separatrix (through the middle axis $m_2$, $I_2 = {i2:g}$)",
        ],
        loc="lower left",
        fontsize=9,
        frameon=False,
    )

    names = ("$m_1$", "$m_2$", "$m_3$")
    circle = np.linspace(0.0, 2.0 * np.pi, 200)
    for row, (i, j) in enumerate(((0, 1), (0, 2), (1, 2))):
        ax2 = fig.add_axes((0.70, 0.675 - 0.315 * row, 0.27, 0.245))
        ax2.plot(np.cos(circle), np.sin(circle), color="0.8", lw=0.6)
        for curve in separatrix:
            ax2.plot(curve[:, i], curve[:, j], color="k", lw=0.6, ls="--")
        for mk, col in zip(m, colors):
            ax2.plot(mk[:, i], mk[:, j], color=col, lw=0.7)
        ax2.set_aspect("equal")
        ax2.set_xlim(-1.08, 1.08)
        ax2.set_ylim(-1.08, 1.08)
        ax2.set_xlabel(names[i], labelpad=1)
        ax2.set_ylabel(names[j], labelpad=1)
        ax2.tick_params(labelsize=8)
        ax2.set_title(f"seen along {names[3 - i - j]}", fontsize=9, pad=3)
    fig.savefig(path)


def plot_invariants(path, t: np.ndarray, errors: dict, colors, title: str) -> None:
    from matplotlib.figure import Figure

    fig = Figure(figsize=(11, 8), dpi=100)
    fig.suptitle(title, fontsize=11)
    fig.subplots_adjust(left=0.08, right=0.96, bottom=0.07, top=0.87, hspace=0.42, wspace=0.22)
    eps = float(np.finfo(float).eps)
    floor = 1e-17
    panels = (
        ("energy", "relative energy error $|E - E_0|\\,/\\,E_0$", False),
        ("casimir", "Casimir error $||m|^2 - |m_0|^2|\\,/\\,|m_0|^2$", True),
        ("spatial", r"spatial angular momentum drift $\|\pi - \pi_0\|_\infty / \|\pi_0\|_\infty$", True),
        ("orthogonality", "orthogonality error $\\max\\,|Q^TQ - I|$", True),
    )
    axes = fig.subplots(2, 2, sharex=True)
    for ax, (key, label, roundoff) in zip(axes.ravel(), panels):
        err = np.asarray(errors[key])
        tt, yy = block_max(t, np.maximum(err, floor) if roundoff else err)
        for y, col in zip(yy, colors):
            ax.plot(tt, y, color=col, lw=0.7)
        if roundoff:
            ax.set_yscale("log")
            ax.axhline(eps, color="k", lw=0.6, ls=":")
            ax.text(tt[-1], eps / 1.5, "machine epsilon", va="top", ha="right", fontsize=8)
            ax.set_ylim(floor, max(1e-10, 10.0 * float(np.max(err))))
        else:
            ax.set_ylim(bottom=0.0)
            ax.ticklabel_format(axis="y", style="sci", scilimits=(-2, 2))
        ax.set_title(f"{label}\nmax {np.max(err):.2e}", fontsize=10)
        ax.grid(True, lw=0.3, alpha=0.5)
    for ax in axes[-1]:
        ax.set_xlabel("t")
    fig.savefig(path)
