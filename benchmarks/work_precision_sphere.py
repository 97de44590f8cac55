r"""Work-precision of point vortices on the sphere (issue 44): ours against diffrax on a 4-vortex scene.

Run from the repository root (`work_precision.py` hands the flag to this module):

    python benchmarks/work_precision.py --sphere-vortices           # T = 200
    python benchmarks/work_precision.py --sphere-vortices --quick   # smoke test, not a measurement

written as `work_precision_sphere.{json,png}` in `benchmarks/results/`.

**Scene**: four vortices on the unit sphere, circulations $\Gamma = (1, 0.8, -0.6, 0.7)$, at
colatitude/longitude $(0.5, 0)$, $(1.2, 2.0)$, $(2.2, 4.1)$ and $(1.6, 5.3)$ (no symmetry: four
vortices on the sphere are not integrable), over T = 200, about twenty turns of the fastest
vortex about the others. The equations
$\dot x_a = \frac1{4\pi}\sum_{b\ne a}\Gamma_b\,\frac{x_b\times x_a}{1 - x_a\cdot x_b}$ are written
here independently of `clebsch_jax` for the peers and the reference.

**Ours**: `cj.integrate` of `models.point_vortices_sphere` (the Hopf lift of each vortex to
$\mathbb C^2$, a degenerate Clebsch system) from `sphere_vortex_lift(x0)` and
`sphere_vortex_xi(Γ, x0)`: Gauss–Legendre of orders 6, 8 and 12 (`scheme="gauss"`) at several
Δt, every solve to round-off (the defaults). Concrete calls: the compiled chunks serve every Δt
and run length.

**Peers**: diffrax `Dopri8` and `Tsit5` (`PIDController(rtol, atol = rtol)`) under `jax.jit`,
`SaveAt` at `n_samples + 1` equal times; SciPy `DOP853` at rtol 1e-13 as the reference, checked
against diffrax Dopri8 at rtol 1e-13 (`reference.check`: global errors near it are not resolved).

**Measures**: `wall_s` (median of samples of a compiled call, `work_precision.time_point`; the
trajectory's diagnostics are computed outside the timed call for every method); `global_error`
$\max_a |x_a(T) - x_{a,\mathrm{ref}}(T)|$; `energy_error` $\max_t |H - H_0|/|H_0|$ (ours at every
node, the peers at the samples); `moment_error` $\max_t |M - M_0| / \sum_a|\Gamma_a|$ of the
vorticity moment $M = \sum_a\Gamma_a x_a$; `sphere_error` $\max_{t,a}||x_a| - 1|$.
"""

from __future__ import annotations

import numpy as np

import _timing as harness
import clebsch_jax as cj
import work_precision as wp
from clebsch_jax import models

GAMMA = (1.0, 0.8, -0.6, 0.7)
ANGLES = ((0.5, 0.0), (1.2, 2.0), (2.2, 4.1), (1.6, 5.3))  # (colatitude, longitude)
REF_RTOL = 1e-13

DEFAULT = {
    "T": 200.0,
    "n_samples": 200,
    "gauss": {6: (0.2, 0.1), 8: (0.4, 0.2, 0.1), 12: (0.5, 0.25)},
    "dopri8": (1e-8, 1e-10, 1e-12),
    "tsit5": (1e-8, 1e-10),
}
QUICK = {"T": 4.0, "n_samples": 4, "gauss": {8: (0.4,)}, "dopri8": (1e-8,), "tsit5": (1e-8,)}


def initial_positions() -> np.ndarray:
    th, ph = np.array(ANGLES).T
    return np.stack([np.sin(th) * np.cos(ph), np.sin(th) * np.sin(ph), np.cos(th)], -1)


class SphereVortices:
    """The scene as `work_precision`'s peers see it: state (N, 3) positions."""

    batched, members = False, 1

    def __init__(self, cfg):
        self.cfg, self.T = cfg, float(cfg["T"])
        self.gamma, self.y0 = np.array(GAMMA), initial_positions()
        self.scale = 1.0  # unit vectors: atol = rtol
        self.label = f"{len(GAMMA)} vortices on the sphere, T = {self.T:g}"

    def rhs_jax(self, t, y, args):
        import jax.numpy as jnp

        g = jnp.asarray(self.gamma)
        cross = jnp.cross(y[None, :, :], y[:, None, :])  # [a, b] = x_b × x_a
        denom = 1.0 - jnp.sum(y[:, None, :] * y[None, :, :], -1) + jnp.eye(len(g))
        w = (g[None, :] / denom * (1.0 - jnp.eye(len(g))))[..., None]
        return jnp.sum(w * cross, 1) / (4.0 * jnp.pi)

    def rhs_np(self, y):
        cross = np.cross(y[None, :, :], y[:, None, :])
        denom = 1.0 - np.einsum("ak,bk->ab", y, y) + np.eye(len(self.gamma))
        w = (self.gamma[None, :] / denom * (1.0 - np.eye(len(self.gamma))))[..., None]
        return np.sum(w * cross, 1) / (4.0 * np.pi)

    def energy(self, ys):
        """$H = -\\frac1{4\\pi}\\sum_{a<b}\\Gamma_a\\Gamma_b\\log(1 - x_a\\cdot x_b)$ of (..., N, 3), in NumPy."""
        ys = np.asarray(ys)
        n = len(self.gamma)
        a, b = np.triu_indices(n, 1)
        dots = np.sum(ys[..., a, :] * ys[..., b, :], -1)
        return -np.sum(self.gamma[a] * self.gamma[b] * np.log1p(-dots), -1) / (4.0 * np.pi)

    def diagnostics(self, ys) -> dict:
        ys = np.asarray(ys)
        H = self.energy(ys)
        M = np.einsum("a,...ak->...k", self.gamma, ys)
        return {
            "energy_error": float(np.max(np.abs(H - H[0])) / abs(H[0])),
            "moment_error": float(np.max(np.linalg.norm(M - M[0], axis=-1)) / np.sum(np.abs(self.gamma))),
            "sphere_error": float(np.max(np.abs(np.linalg.norm(ys, axis=-1) - 1.0))),
        }

    def global_error(self, y, ref) -> float:
        return float(np.max(np.linalg.norm(np.asarray(y) - ref, axis=-1)))


def ours_program(scene, order: int):
    """A blocking call (dt) -> positions at every node (n + 1, N, 3), sweeps per step, valid."""
    import jax.numpy as jnp

    G = jnp.asarray(scene.gamma)
    system = models.point_vortices_sphere(G)
    x0 = jnp.asarray(scene.y0)
    Z0, xi0 = models.sphere_vortex_lift(x0), models.sphere_vortex_xi(G, x0)

    def call(dt):
        n = wp._steps(scene.T, dt)
        sol = cj.integrate(system, Z0, xi0, dt=dt, n_steps=n, scheme="gauss", order=order, throw=False)
        xs = np.asarray(models.sphere_vortex_positions(sol.Q))
        its = np.asarray(sol.stats.iterations)
        return {"xs": xs, "sweeps_per_step": float(np.mean(its)), "valid": bool(np.all(np.asarray(sol.valid)))}

    return call


def _point(scene, family, method, param_name, param, timing, res, xs_all, ref_T) -> dict:
    return {
        "family": family,
        "method": method,
        param_name: param,
        **timing,
        "global_error": scene.global_error(xs_all[-1], ref_T),
        **scene.diagnostics(xs_all),
        **{k: v for k, v in res.items() if k not in ("xs", "ys")},
    }


def run_scene(run, cfg) -> dict:
    scene = SphereVortices(cfg)
    budget = 0.05 if run.quick else 20.0
    out = {"scene": "sphere_vortices_4", "label": scene.label, "T": scene.T, "gamma": list(GAMMA), "points": []}
    with run.case(f"reference: SciPy DOP853 rtol {REF_RTOL:g}"):
        ref = wp.scipy_dop853(scene, REF_RTOL)
        ref_T = ref["ys"][-1]
        out["reference"] = {
            "method": f"scipy DOP853 rtol {REF_RTOL:g}",
            "valid": ref["valid"],
            **scene.diagnostics(ref["ys"]),
        }
    programs = {name: wp.diffrax_program(scene, name, run.compiler_options) for name in ("dopri8", "tsit5")}
    with run.case(f"reference check: diffrax Dopri8 rtol {REF_RTOL:g}"):
        programs["dopri8"](1e-8)  # compile
        check = programs["dopri8"](REF_RTOL)
        out["reference"]["check"] = scene.global_error(check["ys"][-1], ref_T)
    for order, dts in cfg["gauss"].items():
        call = ours_program(scene, order)
        with run.case(f"ours Gauss {order} dt {list(dts)}"):
            call(dts[0])  # compiles the chunk programs (a new dt compiles nothing)
            for dt in dts:
                timing, res = wp.time_point(run, lambda d=dt: call(d), f"ours gauss{order} dt {dt:g}", budget)
                out["points"].append(_point(scene, "ours", f"gauss{order}", "dt", dt, timing, res, res["xs"], ref_T))
    for name, call in programs.items():
        with run.case(f"diffrax {name} rtol {list(cfg[name])}"):
            call(cfg[name][0])
            for rtol in cfg[name]:
                timing, res = wp.time_point(run, lambda r=rtol: call(r), f"diffrax {name} {rtol:g}", budget)
                out["points"].append(_point(scene, "diffrax", name, "rtol", rtol, timing, res, res["ys"], ref_T))
    out["dominance"] = dominance(out["points"], out["reference"]["check"])
    return out


def dominance(points, resolved) -> list:
    """For each diffrax point: the fastest point of ours with global error no larger (or both
    below the reference's own error `resolved`) and energy error no larger; its time ratio."""
    rows = []
    ours = [p for p in points if p["family"] == "ours" and p["valid"]]
    for peer in (p for p in points if p["family"] == "diffrax"):
        ok = [
            p
            for p in ours
            if p["global_error"] <= max(peer["global_error"], 10 * resolved)
            and p["energy_error"] <= peer["energy_error"]
        ]
        best = min(ok, key=lambda p: p["wall_s"]) if ok else None
        rows.append(
            {
                "peer": f"{peer['method']} rtol {peer['rtol']:g}",
                "ours": None if best is None else f"{best['method']} dt {best['dt']:g}",
                "time_ratio": None if best is None else best["wall_s"] / peer["wall_s"],
                "energy_ratio": None if best is None else peer["energy_error"] / max(best["energy_error"], 1e-300),
            }
        )
    return rows


def _e(x, w=9):
    return harness.fmt(x, ".1e", w)


def print_report(summary) -> None:
    for r in summary["results"]:
        ref = r["reference"]
        print(f"\n{r['label']}: reference {ref['method']}, its distance to Dopri8 at the same rtol {ref['check']:.1e}")
        head = f"{'method':>10} {'param':>7} {'wall s':>8} {'global':>9} {'energy':>9} {'moment':>9} {'sphere':>9} {'sweeps':>6}"
        lines = [
            f"{p['method']:>10} {p.get('dt', p.get('rtol')):>7g} {p['wall_s']:>8.3f} {_e(p['global_error'])} "
            f"{_e(p['energy_error'])} {_e(p['moment_error'])} {_e(p['sphere_error'])} "
            f"{harness.fmt(p.get('sweeps_per_step'), '.1f', 6)}"
            for p in r["points"]
        ]
        harness.print_table(head, lines)
        print("\nFastest point of ours no worse in global and energy error than each diffrax point:")
        for d in r["dominance"]:
            ratio = "-" if d["time_ratio"] is None else f"{d['time_ratio']:.2f}x its time"
            energy = "" if d["energy_ratio"] is None else f", energy error {d['energy_ratio']:.1e}x smaller"
            print(f"  {d['peer']:>18}: {d['ours'] or 'none'} ({ratio}{energy})")


def plot(summary, path) -> None:
    r = summary["results"][0]
    measures = ("global_error", "energy_error", "moment_error")
    fig, axes = harness.figure((1, 1, 1), size=(13, 4.4))
    style = {
        "gauss6": ("o", "C0"),
        "gauss8": ("s", "C1"),
        "gauss12": ("D", "C2"),
        "dopri8": ("^", "C3"),
        "tsit5": ("v", "C4"),
    }
    for ax, m in zip(axes, measures):
        for method in dict.fromkeys(p["method"] for p in r["points"]):
            pts = sorted((p for p in r["points"] if p["method"] == method), key=lambda p: p["wall_s"])
            marker, colour = style.get(method, ("x", "k"))
            label = f"ours {method}" if pts[0]["family"] == "ours" else f"diffrax {method}"
            ax.loglog(
                [p["wall_s"] for p in pts], [max(p[m], 1e-17) for p in pts], marker=marker, color=colour, label=label
            )
        if m == "global_error":
            ax.axhline(r["reference"]["check"], color="0.6", ls=":", label="reference's own error")
        ax.set_xlabel("wall time (s)")
        ax.set_ylabel(m.replace("_", " "))
        ax.grid(True, which="both", alpha=0.3)
    axes[0].legend(fontsize=8)
    fig.suptitle(harness.plot_title(summary, r["label"]), fontsize=9)
    fig.savefig(path, dpi=110)


def main(argv) -> dict:
    argv = [a for a in argv if a != "--sphere-vortices"]
    with harness.Run(
        "work_precision_sphere",
        argv,
        description="Work-precision of point vortices on the sphere: ours against diffrax Dopri8/Tsit5.",
    ) as run:
        cfg = QUICK if run.quick else DEFAULT
        results = [run_scene(run, cfg)]
        summary = run.summary(
            config={
                "mode": "quick" if run.quick else "default",
                **{k: ({str(o): list(d) for o, d in v.items()} if k == "gauss" else v) for k, v in cfg.items()},
                "gamma": list(GAMMA),
                "angles": [list(a) for a in ANGLES],
                "reference_rtol": REF_RTOL,
                "timing": "wall time of a compiled call, median of samples (work_precision.time_point)",
            },
            results=results,
        )
    return run.finish(summary, print_report, plot)
