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
 * Friction at the hub, of Coulomb level Fc > 0 on the state i_speed (the hub's speed), breakaway Fs >= Fc and Stribeck
 * speed vs (0: none; the plant FMU's law), as the time-stepping methods of non-smooth mechanics take it: over each
 * sample the friction is one torque f held, which adds f bf to the state (bf: a unit torque's effect over a sample,
 * b = bf[i] > 0 on the speed). It is the torque that brings the speed to rest at the sample's end where that is
 * within +-Fs (the hub sticks: f = -v / b), else the sliding friction against the motion, Fc + (Fs - Fc)
 * exp(-(v / vs)^2) (Fc alone when vs = 0), for the speed v the step would reach without it. The filter knows v only as
 * N(v^, sv^2), so f is taken by its moments over that normal (an assumed-density filter, like the lattice's cells;
 * each region's, the exponential's with the normal a normal again, in closed form): the state moves by E[f] bf, the
 * covariance maps through J = I + beta bf e_i' (beta = Cov(f, v) / Var(v), f's regression on v; -P(stuck) / b for
 * Coulomb friction) and gains bf bf' times f's variance that J leaves out. Sure of its speed (sv = 0), the filter
 * takes the hard decision. The
 * likelihood is then smooth in Fc and the model's parameters, as a fit needs it. The hub sticks or slides within a
 * sample: with substeps > 1, A, B, Q and bf are a substep's, taken substeps times per sample (the command held), the
 * friction after each.
 *
 * A channel j with cubic[j] != 0 bends (a strain gauge's bridge): z = C_j x + cubic[j] (g_j x)^3 + v, g_j = bend's row j
 * (the part of the reading that bends: the gauge without its offset). Its update is the extended Kalman filter's: the
 * row linearised at the predicted state, C_j + 3 cubic[j] (g_j x)^2 g_j. cubic NULL: no channel bends.
 *
 * A gear's play of width play > 0 (Af NULL otherwise; the time-stepping of an impact / dead-zone hybrid): the state
 * i_gap is how far the motor side's teeth are ahead of the hub side's, within +-h, h = play / 2. A, B, Q are then
 * the teeth in contact's (the rig as one body: the gap held, the motor's speed the hub's), Af, Bf, Qf the two sides
 * apart, Pi (nx x nx) the plastic impact (momentum kept, the speeds made one, the gap's row zero). Over each step the
 * sides move apart, x <- Af x + Bf u; where that would take the gap g past +-h the teeth meet within the step, at
 * its fraction tau where g reaches the edge (g linear over the step), and the step is the impact at its start then
 * the rigid step, x <- A (Pi x +- h e_gap) + B u, and the step apart then the impact, x <- Pi (Af x + Bf u) +- h e_gap,
 * weighed (1 - tau) and tau: teeth pressed together (tau = 0) take the linear rig's step, a play that closes within
 * the step closes there to first order. With tau taken at each region's mean, the map is affine in x on each of the three regions of g, a linear function of x, so its moments under
 * N(x, P) are exact: the state given g's region (its regression on g, g's truncated normal moments) mapped
 * through the region's step, the three mixed by their probabilities and matched by one normal. Sure of g, the
 * filter takes the hard decision. Friction (Fc > 0) then acts on the rig as one body (bf: in contact).
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

/* The cell [a, b] (standardised; either end may be infinite) of a standard normal: its probability *p, and its
 * truncated mean *m and variance *v. Returns 0 when the probability underflows (the caller falls back to a Gaussian
 * reading, or leaves the cell out). */
static int cell(double a, double b, double *p, double *m, double *v) {
    double z;
    if (a > 0.0) z = upper_tail(a) - upper_tail(b);
    else if (b < 0.0) z = upper_tail(-b) - upper_tail(-a);
    else z = 1.0 - upper_tail(b) - upper_tail(-a);
    if (!(z > 1e-300)) return 0;
    double fa = density(a), fb = density(b);
    double d1 = (fa - fb) / z, d2 = ((isinf(a) ? 0.0 : a * fa) - (isinf(b) ? 0.0 : b * fb)) / z;
    *p = z;
    *m = d1;
    *v = 1.0 + d2 - d1 * d1;
    if (*v < 0.0) *v = 0.0;
    if (*v > 1.0) *v = 1.0;
    return 1;
}

/* The normal N(m, s^2) on [lo, hi] (either end infinite): the probability *p of the interval, and E[v 1] *e1 and
 * E[v^2 1] *e2 over it (0 where the probability underflows). s = 0: the point m. */
static void span(double m, double s, double lo, double hi, double *p, double *e1, double *e2) {
    double pr, mt, vt;
    *p = *e1 = *e2 = 0.0;
    if (!(s > 0.0)) {
        if (m >= lo && m <= hi) *p = 1.0, *e1 = m, *e2 = m * m;
        return;
    }
    if (!cell((lo - m) / s, (hi - m) / s, &pr, &mt, &vt)) return;
    const double mean = m + s * mt;
    *p = pr;
    *e1 = pr * mean;
    *e2 = pr * (s * s * vt + mean * mean);
}

/* The hub's friction over one step (the header's moments): x and P (nx, nx x nx) before it, changed in place; W is
 * nx x nx of scratch. Fc the Coulomb level, Fs >= Fc the breakaway, vs the Stribeck speed (0: none). */
static void friction(long nx, double *x, double *P, double *W, const double *bf, long i, double Fc, double Fs,
                     double vs) {
    const double b = bf[i], m = x[i], s = sqrt(P[i * nx + i] > 0.0 ? P[i * nx + i] : 0.0), a = b * Fs;
    const double D = vs > 0.0 ? Fs - Fc : 0.0;
    if (!(b > 0.0)) return;
    double ef = 0.0, efv = 0.0, ef2 = 0.0, p, e1, e2;
    /* stuck: f = -v / b */
    span(m, s, -a, a, &p, &e1, &e2);
    ef += -e1 / b, efv += -e2 / b, ef2 += e2 / (b * b);
    /* sliding forward (v > a), f = -(Fc + D g(v)), and back (v < -a), f = +(Fc + D g(v)), g = exp(-v^2 / vs^2) */
    for (int dir = 1; dir >= -1; dir -= 2) {
        const double lo = dir > 0 ? a : -INFINITY, hi = dir > 0 ? INFINITY : -a;
        span(m, s, lo, hi, &p, &e1, &e2);
        ef += -dir * Fc * p, efv += -dir * Fc * e1, ef2 += Fc * Fc * p;
        if (D > 0.0)
            for (int k = 1; k <= 2; k++) { /* g^k N(v; m, s^2) = c N(v; mk, sk^2) */
                const double t2 = vs * vs / (2.0 * k), den = s * s + t2;
                const double c = sqrt(t2 / den) * exp(-0.5 * m * m / den);
                const double mk = m * t2 / den, sk = s * sqrt(t2 / den);
                double q, g1, g2;
                span(mk, sk, lo, hi, &q, &g1, &g2);
                if (k == 1) ef += -dir * D * c * q, efv += -dir * D * c * g1, ef2 += 2.0 * Fc * D * c * q;
                else ef2 += D * D * c * q;
            }
    }
    /* in the state's units: the torque's effect bf; f's regression on v, beta, and what it leaves */
    const double cov = efv - ef * m, var = ef2 - ef * ef;
    const double beta = s > 0.0 ? cov / (s * s) : 0.0;
    double resid = var - beta * beta * s * s;
    if (resid < 0.0) resid = 0.0;
    for (long r = 0; r < nx; r++) x[r] += ef * bf[r];
    if (beta != 0.0) { /* P <- J P J', J = I + beta bf e_i': row r of J P is P[r] + beta bf[r] P[i] */
        for (long r = 0; r < nx; r++)
            for (long c = 0; c < nx; c++) W[r * nx + c] = P[r * nx + c] + beta * bf[r] * P[i * nx + c];
        for (long r = 0; r < nx; r++)
            for (long c = r; c < nx; c++) P[r * nx + c] = P[c * nx + r] = W[r * nx + c] + beta * W[r * nx + i] * bf[c];
    }
    for (long r = 0; r < nx; r++)
        for (long c = r; c < nx; c++) P[r * nx + c] = P[c * nx + r] = P[r * nx + c] + resid * bf[r] * bf[c];
}

/* W = M P M' (+ Q when not NULL), nx x nx; T is nx x nx of scratch. */
static void sandwich(long nx, const double *M, const double *P, const double *Q, double *T, double *W) {
    for (long a = 0; a < nx; a++)
        for (long b = 0; b < nx; b++) {
            double acc = 0.0;
            for (long c = 0; c < nx; c++) acc += M[a * nx + c] * P[c * nx + b];
            T[a * nx + b] = acc;
        }
    for (long a = 0; a < nx; a++)
        for (long b = a; b < nx; b++) {
            double acc = Q ? Q[a * nx + b] : 0.0;
            for (long c = 0; c < nx; c++) acc += T[a * nx + c] * M[b * nx + c];
            W[a * nx + b] = W[b * nx + a] = acc;
        }
}

#define PLAY_NEGLIGIBLE 1e-12 /* a region of the gap less likely than this is left out of the step's moments */

/* One step with a gear's play (the header): x and P (nx, nx x nx) changed in place. A, B, Q: in contact; Af, Bf, Qf:
 * apart; M = A Pi (Pi: the impact) and Ag = A's gap column; the gap's state ig, half the play h. */
static void play_step(long nx, long nu, double *x, double *P, const double *u, const double *B, const double *Q,
                      const double *Af, const double *Bf, const double *Qf, const double *M, const double *Ag,
                      const double *PAf, const double *PBf, const double *PQf, long ig, double h) {
    double k[KF_MAX_STATES], mean[3][KF_MAX_STATES], xr[KF_MAX_STATES], w[3] = {0.0, 0.0, 0.0}, shift[3], keep[3];
    double Pr[KF_MAX_STATES * KF_MAX_STATES], T[KF_MAX_STATES * KF_MAX_STATES], W[KF_MAX_STATES * KF_MAX_STATES];
    double acc[KF_MAX_STATES * KF_MAX_STATES], Fr[KF_MAX_STATES * KF_MAX_STATES], Qr[KF_MAX_STATES * KF_MAX_STATES];
    const double *af = Af + ig * nx;
    double mu = 0.0, var = 0.0;
    for (long c = 0; c < nu; c++) mu += Bf[ig * nu + c] * u[c];
    for (long a = 0; a < nx; a++) {
        double t = 0.0;
        for (long b = 0; b < nx; b++) t += P[a * nx + b] * af[b];
        k[a] = t;
        mu += af[a] * x[a];
    }
    for (long a = 0; a < nx; a++) var += af[a] * k[a];
    const double sd = sqrt(var > 0.0 ? var : 0.0);
    const double lo[3] = {-INFINITY, -h, h}, hi[3] = {-h, h, INFINITY};
    if (sd > 1e-12 * (h + fabs(mu))) { /* where the gap would go apart: below -h, within, above +h */
        for (int r = 0; r < 3; r++) {
            double p, m, v;
            if (cell((lo[r] - mu) / sd, (hi[r] - mu) / sd, &p, &m, &v) && p > PLAY_NEGLIGIBLE)
                w[r] = p, shift[r] = m / sd, keep[r] = 1.0 - v;
        }
    } else { /* sure of it */
        const int r = mu < -h ? 0 : mu > h ? 2 : 1;
        w[r] = 1.0, shift[r] = 0.0, keep[r] = 0.0;
    }
    const double total = w[0] + w[1] + w[2];
    memset(acc, 0, (size_t)(nx * nx) * sizeof(double));
    for (int r = 0; r < 3; r++) {
        if (!(w[r] > 0.0)) continue;
        w[r] /= total;
        /* the state given the gap's region: its regression on the gap, the gap's truncated moments */
        for (long a = 0; a < nx; a++) xr[a] = x[a] + k[a] * shift[r];
        for (long a = 0; a < nx; a++)
            for (long b = 0; b < nx; b++) Pr[a * nx + b] = P[a * nx + b] - k[a] * k[b] * keep[r] / (var > 0.0 ? var : 1.0);
        if (r == 1) { /* apart */
            for (long a = 0; a < nx; a++) {
                double t = 0.0;
                for (long b = 0; b < nx; b++) t += Af[a * nx + b] * xr[b];
                for (long c = 0; c < nu; c++) t += Bf[a * nu + c] * u[c];
                mean[r][a] = t;
            }
            sandwich(nx, Af, Pr, Qf, T, W);
        } else { /* in contact from the step's fraction tau on, where the gap's mean reaches the edge */
            const double edge = r == 0 ? -h : h;
            double gf = 0.0;
            for (long b = 0; b < nx; b++) gf += af[b] * xr[b];
            for (long c = 0; c < nu; c++) gf += Bf[ig * nu + c] * u[c];
            double tau = gf != xr[ig] ? (edge - xr[ig]) / (gf - xr[ig]) : 0.0;
            tau = tau > 0.0 ? (tau < 1.0 ? tau : 1.0) : 0.0;
            for (long a = 0; a < nx; a++) {
                double t = (1.0 - tau) * edge * Ag[a] + (a == ig ? tau * edge : 0.0);
                for (long b = 0; b < nx; b++) {
                    Fr[a * nx + b] = (1.0 - tau) * M[a * nx + b] + tau * PAf[a * nx + b];
                    Qr[a * nx + b] = (1.0 - tau) * Q[a * nx + b] + tau * PQf[a * nx + b];
                    t += Fr[a * nx + b] * xr[b];
                }
                for (long c = 0; c < nu; c++) t += ((1.0 - tau) * B[a * nu + c] + tau * PBf[a * nu + c]) * u[c];
                mean[r][a] = t;
            }
            sandwich(nx, Fr, Pr, Qr, T, W);
        }
        for (long a = 0; a < nx * nx; a++) acc[a] += w[r] * W[a];
    }
    for (long a = 0; a < nx; a++) x[a] = w[0] * mean[0][a] + w[1] * mean[1][a] + w[2] * mean[2][a];
    for (long a = 0; a < nx; a++)
        for (long b = a; b < nx; b++) {
            double t = acc[a * nx + b];
            for (int r = 0; r < 3; r++)
                if (w[r] > 0.0) t += w[r] * (mean[r][a] - x[a]) * (mean[r][b] - x[b]);
            P[a * nx + b] = P[b * nx + a] = t;
        }
}

EXPORT double kalman_filter(long nx, long ny, long nu, const double *A, const double *B, const double *Q,
                            const double *C, const double *r, const double *q, const double *x0, const double *P0,
                            long n,
                            const double *u, const double *y, const unsigned char *mask, const double *bf,
                            long i_speed, double Fc, double Fs, double vs, long substeps, const double *cubic, const double *bend,
                            double play, long i_gap, const double *Af, const double *Bf, const double *Qf,
                            const double *Pi, double *e, double *s, double *l, double *xp, double *Pp, double *xf,
                            double *Pf) {
    double x[KF_MAX_STATES], xn[KF_MAX_STATES], ph[KF_MAX_STATES], hl[KF_MAX_STATES];
    double P[KF_MAX_STATES * KF_MAX_STATES], AP[KF_MAX_STATES * KF_MAX_STATES];
    const double log2pi = log(2.0 * 3.14159265358979323846);
    double ll = 0.0;
    if (nx < 1 || nx > KF_MAX_STATES) return NAN;
    double M[KF_MAX_STATES * KF_MAX_STATES], Ag[KF_MAX_STATES], PAf[KF_MAX_STATES * KF_MAX_STATES];
    double PQf[KF_MAX_STATES * KF_MAX_STATES], PBf[KF_MAX_STATES * 4], T[KF_MAX_STATES * KF_MAX_STATES];
    if (play > 0.0 && nu > 4) return NAN;
    memcpy(x, x0, (size_t)nx * sizeof(double));
    memcpy(P, P0, (size_t)(nx * nx) * sizeof(double));
    if (play > 0.0) { /* in contact from the impact's state: M = A Pi, and the gap's column of A */
        for (long a = 0; a < nx; a++) {
            Ag[a] = A[a * nx + i_gap];
            for (long b = 0; b < nx; b++) {
                double acc = 0.0;
                for (long c = 0; c < nx; c++) acc += A[a * nx + c] * Pi[c * nx + b];
                M[a * nx + b] = acc;
                acc = 0.0;
                for (long c = 0; c < nx; c++) acc += Pi[a * nx + c] * Af[c * nx + b];
                PAf[a * nx + b] = acc;
            }
            for (long c = 0; c < nu; c++) {
                double acc = 0.0;
                for (long b = 0; b < nx; b++) acc += Pi[a * nx + b] * Bf[b * nu + c];
                PBf[a * nu + c] = acc;
            }
        }
        sandwich(nx, Pi, Qf, NULL, T, PQf);
    }
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
            if (play > 0.0) {
                play_step(nx, nu, x, P, u + k * nu, B, Q, Af, Bf, Qf, M, Ag, PAf, PBf, PQf, i_gap, 0.5 * play);
                if (Fc > 0.0 && bf) friction(nx, x, P, AP, bf, i_speed, Fc, Fs, vs);
                continue;
            }
            for (long a = 0; a < nx; a++) {
                double acc = 0.0;
                for (long b = 0; b < nx; b++) acc += A[a * nx + b] * x[b];
                for (long c = 0; c < nu; c++) acc += B[a * nu + c] * u[k * nu + c];
                xn[a] = acc;
            }
            memcpy(x, xn, (size_t)nx * sizeof(double));
            sandwich(nx, A, P, Q, AP, P); /* P <- A P A' + Q (sandwich reads P before it writes) */
            if (Fc > 0.0 && bf) friction(nx, x, P, AP, bf, i_speed, Fc, Fs, vs);
        }
    }
    return ll;
}
