/* The reduced CAY rigid-body step of benchmarks/throughput.py's `hand_rows_march`, in C: the
 * hardware reference of the sweep benchmark (issue 20), not a library path.
 *
 * Same discrete equations and arithmetic: the linear predictor 2 xi^{n-1} - xi^{n-2}, the
 * Jacobian of D(h xi, I xi) in closed form at the prediction, inverted by cofactors with one
 * division, UPDATES chord updates with no test, mu^{n+1} = D(-h xi, I xi), and the largest
 * |E - E^0| over the nodes, E = 1/2 sum mu_i^2 / I_i (D(y, M) = M + y x M / 2 + y (y . M) / 4).
 * Bodies are marched LANES at a time, each state component a LANES-long array and the step
 * straight-line scalar code, so that the compiler puts the bodies in SIMD lanes (one thread).
 * throughput.py builds it with the system's C compiler when one is present. */

#include <math.h>

#define LANES 16
#ifndef UPDATES
#define UPDATES 3 /* throughput.py's ROWS_UPDATES, passed as -DUPDATES */
#endif

/* out = D(s * h * x, I x) */
#define D_OF(s, o0, o1, o2)                                                             \
    do {                                                                                \
        double y0 = (s) * h * x0, y1 = (s) * h * x1, y2 = (s) * h * x2;                 \
        double m0 = I0 * x0, m1 = I1 * x1, m2 = I2 * x2;                                \
        double ym = y0 * m0 + y1 * m1 + y2 * m2;                                        \
        o0 = m0 + 0.5 * (y1 * m2 - y2 * m1) + 0.25 * y0 * ym;                           \
        o1 = m1 + 0.5 * (y2 * m0 - y0 * m2) + 0.25 * y1 * ym;                           \
        o2 = m2 + 0.5 * (y0 * m1 - y1 * m0) + 0.25 * y2 * ym;                           \
    } while (0)

void rigid_body_cay_march(long B, long n_steps, double h, const double *I, const double *xi0, double *mu_out,
                          double *err_out) {
    const double I0 = I[0], I1 = I[1], I2 = I[2], a = 0.5 * h, q = 0.25 * h * h;
    for (long b0 = 0; b0 < B; b0 += LANES) {
        double mu0[LANES], mu1[LANES], mu2[LANES], p0[LANES], p1[LANES], p2[LANES];
        double r0[LANES], r1[LANES], r2[LANES], E0[LANES], err[LANES];
        for (int l = 0; l < LANES; l++) { /* lanes past B repeat the last body */
            long b = b0 + l < B ? b0 + l : B - 1;
            p0[l] = r0[l] = xi0[3 * b]; p1[l] = r1[l] = xi0[3 * b + 1]; p2[l] = r2[l] = xi0[3 * b + 2];
            mu0[l] = I0 * p0[l]; mu1[l] = I1 * p1[l]; mu2[l] = I2 * p2[l];
            E0[l] = 0.5 * (mu0[l] * mu0[l] / I0 + mu1[l] * mu1[l] / I1 + mu2[l] * mu2[l] / I2);
            err[l] = 0.0;
        }
        for (long n = 0; n < n_steps; n++) {
            for (int l = 0; l < LANES; l++) {
                /* p: xi^{n-1}, r: xi^{n-2} */
                double x0 = 2.0 * p0[l] - r0[l], x1 = 2.0 * p1[l] - r1[l], x2 = 2.0 * p2[l] - r2[l];
                double M0 = I0 * x0, M1 = I1 * x1, M2 = I2 * x2, xM = x0 * M0 + x1 * M1 + x2 * M2;
                /* J[i][j] = d_ij I_i + (h/2)(x x (I e_j) - M x e_j)_i + (h^2/4)(d_ij x.M + 2 x_i M_j) */
                double J00 = I0 + q * (xM + 2.0 * x0 * M0), J01 = a * (M2 - I1 * x2) + q * 2.0 * x0 * M1,
                       J02 = a * (I2 * x1 - M1) + q * 2.0 * x0 * M2;
                double J10 = a * (I0 * x2 - M2) + q * 2.0 * x1 * M0, J11 = I1 + q * (xM + 2.0 * x1 * M1),
                       J12 = a * (M0 - I2 * x0) + q * 2.0 * x1 * M2;
                double J20 = a * (M1 - I0 * x1) + q * 2.0 * x2 * M0, J21 = a * (I1 * x0 - M0) + q * 2.0 * x2 * M1,
                       J22 = I2 + q * (xM + 2.0 * x2 * M2);
                /* cofactors, one division */
                double C00 = J11 * J22 - J12 * J21, C01 = J12 * J20 - J10 * J22, C02 = J10 * J21 - J11 * J20;
                double C10 = J21 * J02 - J22 * J01, C11 = J22 * J00 - J20 * J02, C12 = J20 * J01 - J21 * J00;
                double C20 = J01 * J12 - J02 * J11, C21 = J02 * J10 - J00 * J12, C22 = J00 * J11 - J01 * J10;
                double s = 1.0 / (J00 * C00 + J01 * C01 + J02 * C02);
                double H00 = C00 * s, H01 = C10 * s, H02 = C20 * s, H10 = C01 * s, H11 = C11 * s, H12 = C21 * s,
                       H20 = C02 * s, H21 = C12 * s, H22 = C22 * s;
#pragma GCC unroll 8
                for (int u = 0; u < UPDATES; u++) {
                    double d0, d1, d2;
                    D_OF(1.0, d0, d1, d2);
                    double e0 = d0 - mu0[l], e1 = d1 - mu1[l], e2 = d2 - mu2[l];
                    x0 -= H00 * e0 + H01 * e1 + H02 * e2;
                    x1 -= H10 * e0 + H11 * e1 + H12 * e2;
                    x2 -= H20 * e0 + H21 * e1 + H22 * e2;
                }
                double n0, n1, n2;
                D_OF(-1.0, n0, n1, n2);
                mu0[l] = n0; mu1[l] = n1; mu2[l] = n2;
                r0[l] = p0[l]; r1[l] = p1[l]; r2[l] = p2[l];
                p0[l] = x0; p1[l] = x1; p2[l] = x2;
                double E = 0.5 * (n0 * n0 / I0 + n1 * n1 / I1 + n2 * n2 / I2);
                double dE = fabs(E - E0[l]);
                err[l] = dE > err[l] ? dE : err[l];
            }
        }
        for (int l = 0; l < LANES && b0 + l < B; l++) {
            mu_out[3 * (b0 + l)] = mu0[l]; mu_out[3 * (b0 + l) + 1] = mu1[l]; mu_out[3 * (b0 + l) + 2] = mu2[l];
            err_out[b0 + l] = err[l];
        }
    }
}
