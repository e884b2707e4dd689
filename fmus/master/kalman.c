/* The likelihood engine's Kalman filter (harness/likelihood/kalman.py): the per-sample loop only, the model's
 * matrices come from Python. A time-invariant linear Gaussian state-space model
 *
 *     x[k+1] = A x[k] + B u[k] + w[k],   w[k] ~ N(0, Q)
 *     z[k]   = C x[k] + v[k],            v[k] ~ N(0, diag(r))
 *
 * is run over n samples from x[0] ~ N(x0, P0). The channels of a sample are taken one at a time (the measurement
 * noise is independent between channels), so a masked channel (mask 0: a sample that says nothing) is simply
 * skipped and no matrix is inverted. Row-major arrays throughout: A nx x nx, B nx x nu, Q nx x nx, C ny x nx,
 * u n x nu, y and mask n x ny.
 *
 * A channel with a lattice step q[j] > 0 was written on a lattice (an ADC, an encoder): its reading y says only that
 * z lay in the cell [y - q/2, y + q/2]. Its term of the likelihood is that cell's probability under the predicted
 * N(mu, s), s = h P h' + r, and the update conditions on the cell: the state moves by the truncated normal's mean
 * and its covariance keeps the truncated normal's variance (moment matching). Far in a tail, where the cell's
 * probability is below what a double holds, the cell is taken as a reading at its centre with r + q^2 / 12.
 * A channel with q[j] = 0 is a plain Gaussian reading.
 *
 * Coulomb friction of level Fc > 0 on the state i_speed (the hub's speed), as the time-stepping methods of
 * non-smooth mechanics take it: over each sample the friction is one torque f held, which adds f bf to the state (bf:
 * a unit torque's effect over a sample). It is the torque that brings the speed to rest at the sample's end where
 * that is within +-Fc (the hub sticks), else +-Fc against the motion (it slides): f = clip(-v / bf[i], -Fc, Fc) for
 * the speed v the step would reach without it. The filter knows v only as N(v^, sv^2), so f is taken by its moments
 * over that normal (an assumed-density filter, like the lattice's cells): the state moves by E[f] bf, the covariance
 * maps through J = I - p bf e_i' / bf[i] (p: the probability that the hub sticks, which is E[df/dv] bf[i]) and gains
 * bf bf' times f's variance that J leaves out. Sure of its speed (sv = 0), the filter takes the hard decision. The
 * likelihood is then smooth in Fc and the model's parameters, as a fit needs it. The hub sticks or slides within a
 * sample: with substeps > 1, A, B, Q and bf are a substep's, taken substeps times per sample (the command held), the
 * friction after each.
 *
 * A channel j with cubic[j] != 0 bends (a strain gauge's bridge): z = C_j x + cubic[j] (g_j x)^3 + v, g_j = bend's row j
 * (the part of the reading that bends: the gauge without its offset). Its update is the extended Kalman filter's: the
 * row linearised at the predicted state, C_j + 3 cubic[j] (g_j x)^2 g_j. cubic NULL: no channel bends.
 *
 * Returns the log-likelihood: the sum over measured channels of -(log(2 pi s) + e^2 / s) / 2, or log P(cell) on a
 * lattice; NaN when a variance is not positive and finite. e, s and l (n x ny) receive each channel's innovation
 * y - mu, its predicted variance s (without the lattice) and its term of the log-likelihood (0 where masked); xp, Pp (predicted: before
 * sample k's measurements) and xf, Pf (filtered: after them), n x nx and n x nx x nx, are written when not NULL (the
 * smoother's input).
 */
#include <math.h>
#include <stddef.h>
#include <string.h>

#if defined(_WIN32)
#define EXPORT __declspec(dllexport)
#else
#define EXPORT
#endif

#define KF_MAX_STATES 32

EXPORT int kalman_max_states(void) { return KF_MAX_STATES; }

static double upper_tail(double x) { return 0.5 * erfc(x / sqrt(2.0)); } /* P(Z > x), Z standard normal */
static double density(double x) { return exp(-0.5 * x * x) / sqrt(2.0 * 3.14159265358979323846); }

/* The cell [a, b] (standardised) of a standard normal: its probability *p, and its truncated mean *m and variance
 * *v. Returns 0 when the probability underflows (the caller falls back to a Gaussian reading). */
static int cell(double a, double b, double *p, double *m, double *v) {
    double z;
    if (a > 0.0) z = upper_tail(a) - upper_tail(b);
    else if (b < 0.0) z = upper_tail(-b) - upper_tail(-a);
    else z = 1.0 - upper_tail(b) - upper_tail(-a);
    if (!(z > 1e-300)) return 0;
    double fa = density(a), fb = density(b);
    double d1 = (fa - fb) / z, d2 = (a * fa - b * fb) / z;
    *p = z;
    *m = d1;
    *v = 1.0 + d2 - d1 * d1;
    if (*v < 0.0) *v = 0.0;
    if (*v > 1.0) *v = 1.0;
    return 1;
}

/* Coulomb friction over one sample (the header's moments): x and P (nx, nx x nx) before it, changed in place; W is
 * nx x nx of scratch. */
static void friction(long nx, double *x, double *P, double *W, const double *bf, long i, double Fc) {
    const double b = bf[i], m = -x[i] / b, sd = sqrt(P[i * nx + i] > 0.0 ? P[i * nx + i] : 0.0) / fabs(b);
    double mean, p, resid = 0.0;
    if (sd > 1e-12 * (Fc + fabs(m))) {
        const double al = (-Fc - m) / sd, be = (Fc - m) / sd, fa = density(al), fb = density(be);
        const double lo = upper_tail(-al), hi = upper_tail(be); /* P(f = -Fc), P(f = +Fc) */
        p = al > 0.0 ? upper_tail(al) - upper_tail(be) : be < 0.0 ? upper_tail(-be) - upper_tail(-al) : 1.0 - lo - hi;
        mean = Fc * (hi - lo) + m * p + sd * (fa - fb);
        const double second =
            Fc * Fc * (hi + lo) + m * m * p + 2.0 * m * sd * (fa - fb) + sd * sd * (p + al * fa - be * fb);
        resid = second - mean * mean - p * p * sd * sd;
        if (resid < 0.0) resid = 0.0;
    } else {
        mean = m > Fc ? Fc : m < -Fc ? -Fc : m;
        p = fabs(m) < Fc ? 1.0 : 0.0;
    }
    for (long a = 0; a < nx; a++) x[a] += mean * bf[a];
    if (p > 0.0) { /* P <- J P J', J = I - p g e_i', g = bf / b: row a of J P is P[a] - p g[a] P[i] */
        for (long a = 0; a < nx; a++)
            for (long c = 0; c < nx; c++) W[a * nx + c] = P[a * nx + c] - p * bf[a] / b * P[i * nx + c];
        for (long a = 0; a < nx; a++)
            for (long c = a; c < nx; c++) P[a * nx + c] = P[c * nx + a] = W[a * nx + c] - p * W[a * nx + i] * bf[c] / b;
    }
    for (long a = 0; a < nx; a++)
        for (long c = a; c < nx; c++) P[a * nx + c] = P[c * nx + a] = P[a * nx + c] + resid * bf[a] * bf[c];
}

EXPORT double kalman_filter(long nx, long ny, long nu, const double *A, const double *B, const double *Q,
                            const double *C, const double *r, const double *q, const double *x0, const double *P0,
                            long n,
                            const double *u, const double *y, const unsigned char *mask, const double *bf,
                            long i_speed, double Fc, long substeps, const double *cubic, const double *bend, double *e, double *s, double *l, double *xp, double *Pp, double *xf,
                            double *Pf) {
    double x[KF_MAX_STATES], xn[KF_MAX_STATES], ph[KF_MAX_STATES], hl[KF_MAX_STATES];
    double P[KF_MAX_STATES * KF_MAX_STATES], AP[KF_MAX_STATES * KF_MAX_STATES];
    const double log2pi = log(2.0 * 3.14159265358979323846);
    double ll = 0.0;
    if (nx < 1 || nx > KF_MAX_STATES) return NAN;
    memcpy(x, x0, (size_t)nx * sizeof(double));
    memcpy(P, P0, (size_t)(nx * nx) * sizeof(double));
    for (long k = 0; k < n; k++) {
        if (xp) memcpy(xp + k * nx, x, (size_t)nx * sizeof(double));
        if (Pp) memcpy(Pp + k * nx * nx, P, (size_t)(nx * nx) * sizeof(double));
        /* measurement update, one channel at a time */
        for (long j = 0; j < ny; j++) {
            const double *h = C + j * nx;
            long kj = k * ny + j;
            if (!mask[kj]) {
                e[kj] = 0.0;
                s[kj] = 0.0;
                l[kj] = 0.0;
                continue;
            }
            double pred = 0.0, sj = r[j];
            for (long a = 0; a < nx; a++) pred += h[a] * x[a];
            if (cubic && cubic[j] != 0.0) { /* the bent reading, and its row linearised at x */
                const double *g = bend + j * nx;
                double L = 0.0;
                for (long a = 0; a < nx; a++) L += g[a] * x[a];
                pred += cubic[j] * L * L * L;
                for (long a = 0; a < nx; a++) hl[a] = h[a] + 3.0 * cubic[j] * L * L * g[a];
                h = hl;
            }
            for (long a = 0; a < nx; a++) {
                double acc = 0.0;
                for (long b = 0; b < nx; b++) acc += P[a * nx + b] * h[b];
                ph[a] = acc;
            }
            for (long a = 0; a < nx; a++) sj += h[a] * ph[a];
            double ej = y[kj] - pred;
            if (!(sj > 0.0) || !isfinite(sj) || !isfinite(ej)) return NAN;
            e[kj] = ej;
            s[kj] = sj;
            /* x += ph move / s, P -= ph ph' shrink: move is how far the reading moves the channel's mean */
            double move = ej, shrink = 1.0 / sj, sd = sqrt(sj), p, m, v;
            if (q[j] > 0.0 && cell((ej - 0.5 * q[j]) / sd, (ej + 0.5 * q[j]) / sd, &p, &m, &v)) {
                l[kj] = log(p);
                move = m * sd; /* to the truncated normal's mean */
                shrink = (1.0 - v) / sj;
            } else {
                double sq = sj + (q[j] > 0.0 ? q[j] * q[j] / 12.0 : 0.0);
                l[kj] = -0.5 * (log2pi + log(sq) + ej * ej / sq);
                move = ej * sj / sq;
                shrink = 1.0 / sq;
            }
            ll += l[kj];
            for (long a = 0; a < nx; a++) x[a] += ph[a] * move / sj;
            for (long a = 0; a < nx; a++)
                for (long b = a; b < nx; b++) {
                    double w = 0.5 * (P[a * nx + b] + P[b * nx + a]) - ph[a] * ph[b] * shrink;
                    P[a * nx + b] = P[b * nx + a] = w;
                }
        }
        if (xf) memcpy(xf + k * nx, x, (size_t)nx * sizeof(double));
        if (Pf) memcpy(Pf + k * nx * nx, P, (size_t)(nx * nx) * sizeof(double));
        /* time update: x <- A x + B u[k], P <- A P A' + Q, over each of the sample's substeps */
        for (long sub = 0; sub < substeps; sub++) {
            for (long a = 0; a < nx; a++) {
                double acc = 0.0;
                for (long b = 0; b < nx; b++) acc += A[a * nx + b] * x[b];
                for (long c = 0; c < nu; c++) acc += B[a * nu + c] * u[k * nu + c];
                xn[a] = acc;
            }
            memcpy(x, xn, (size_t)nx * sizeof(double));
            for (long a = 0; a < nx; a++)
                for (long b = 0; b < nx; b++) {
                    double acc = 0.0;
                    for (long c = 0; c < nx; c++) acc += A[a * nx + c] * P[c * nx + b];
                    AP[a * nx + b] = acc;
                }
            for (long a = 0; a < nx; a++)
                for (long b = a; b < nx; b++) {
                    double acc = Q[a * nx + b];
                    for (long c = 0; c < nx; c++) acc += AP[a * nx + c] * A[b * nx + c];
                    P[a * nx + b] = P[b * nx + a] = acc;
                }
            if (Fc > 0.0 && bf) friction(nx, x, P, AP, bf, i_speed, Fc);
        }
    }
    return ll;
}
