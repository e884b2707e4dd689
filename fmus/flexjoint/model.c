/*
 * flexjoint: Quanser SRV02 servo driving a flexible link (assumed modes), FMI 2.0 co-simulation.
 * All SI units, angles in rad.
 *
 * Coordinates: hub (load shaft) angle theta and a_i, the tip-angle contribution of clamped-free
 * beam mode i (alpha = sum a_i).  Mode shapes phi_i are normalised to phi_i(L) = +2, int phi_i^2 = L,
 * which gives, in closed form (int_0^L x phi_i dx = 2 (-1)^(i+1) L^2 / (beta_i L)^2):
 *   Jl = m L^2 / 3,  J_i = m L^2 / 4,  b_i = (-1)^(i+1) m L^2 / (beta_i L)^2,
 *   k_i = J_i w_i^2,  w_i = w_1 (beta_i / beta_1)^2,  w_1 = sqrt(Ks / Jl),  c_i = 2 zeta J_i w_i.
 *   M = [[Jeq + Jl, b^T], [b, diag(J_i)]],  K = diag(0, k_i).
 * A tip mass m_tip at x = L moves with L (theta_dot + sum a_i'): it adds m_tip L^2 to every entry of M (and
 * nothing to K); then the modes couple through it and M is inverted in full (m_tip = 0 keeps the arrow form).
 * The tip torque tau_tip enters theta and every a_i with unit generalised force.
 * Strain gauge: root curvature phi_i''(0) = 2 (-1)^(i+1) beta_i^2, so per unit a_i mode i reads
 * g_i = (-1)^(i+1) (beta_i / beta_1)^2 times mode 1 (mode 2: -6.27); c_g scales the reading so that a
 * static tip load (a_i = tau / k_i) reads the static tip deflection.
 *
 * Motor at the load shaft: tau_m = G v - Bemf omega_m, G = eta_g Kg eta_m kt / Rm, Bemf = G Kg km,
 * v = clamp(u + u_offset, +-amp_limit) (no clamp when amp_limit = 0): u_offset is the amplifier's input offset.
 *
 * Integration: classical RK4 with a fixed internal step h = comm_step / ceil(comm_step / h_max),
 * h_max = min(internal_step, 2 / rho), rho an upper estimate of the spectral radius of the linear
 * dynamics (so that an over-large internal_step cannot make RK4 unstable).
 *
 * With every non-smooth effect off (coulomb_torque = 0, backlash = 0, hub free) the dynamics are linear,
 * X' = A X + f, and the same RK4 step is applied as its polynomial X <- Phi(hA) X + h P3(hA) f (matrices
 * computed once per internal step size): identical to the stage-by-stage RK4 up to rounding, ~10x faster.
 * With friction or a play the dynamics are affine over every step in which the configuration (gear in contact or
 * in the play, hub sliding or stuck) and the friction torque are fixed: such a step is the polynomial of its
 * configuration's A (affineStepN); a step in the Stribeck drop, where friction varies with speed, or after an
 * event is taken stage by stage.
 *
 * Non-smooth effects are handled as a hybrid system: the mode (stuck/sliding, in contact/in the play)
 * is fixed during an RK4 step; an event found at the end of a step (velocity reversal, gap closure)
 * is located by regula falsi on the RK4 step length, the state is taken at the event, the event is
 * applied, and the rest of the step is integrated in the new mode.
 *  - Coulomb friction at the hub (Karnopp): the hub is stuck while the friction torque needed to keep
 *    it at rest is within Fs = stiction_ratio * coulomb_torque (the link still vibrates clamped);
 *    otherwise it slides with -tau_f(theta_dot) * sign, the sliding friction
 *      tau_f(v) = Fc + (Fs - Fc) exp(-(v / stribeck_speed)^2),  Fc = coulomb_torque
 *    (Stribeck: from the breakaway level Fs at rest down to Fc; stribeck_speed = 0: Fc at any speed).
 *    The sign is the sliding direction, fixed over a step as the mode is.  A sliding hub whose velocity
 *    reaches zero is set exactly to rest and re-checked: no chattering, no creep.
 *  - Backlash: impact / dead-zone hybrid.  The gear splits Jeq into a motor side (Jm_share Jeq, with the
 *    motor torque and back-EMF) and a hub side (the rest + link).  In contact the two sides move as one
 *    rigid body (exactly the backlash = 0 equations); contact opens when the transmitted gear torque
 *    would change sign; in the play both sides move freely; when the play closes, a perfectly plastic
 *    impact (momentum-conserving impulse through the gear) brings them to a common speed.
 *    No contact stiffness, so nothing stiff for the fixed step.  backlash = 0 uses the rigid model only.
 */
#include <math.h>
#include <stdio.h>
#include <string.h>

#include "fmi2common.h"
#include "noise.h"

/* roots of cos(x) cosh(x) + 1 = 0: beta_i L of the clamped-free beam */
static const double BETA_L[MAX_MODES] = {1.8751040687119611, 4.694091132974175, 7.854757438237613};

#define MAX_EVENTS_PER_STEP 8

void setStartValues(ModelInstance *comp) {
    ModelData *d = &comp->data;
    memset(d, 0, sizeof(*d)); /* inputs start at 0 */
    REAL_PARAMETERS(SET_START)
    INTEGER_PARAMETERS(SET_START)
}

/* ------------------------------------------------------------ validation */

bool validate(ModelInstance *comp, char *msg, size_t len) {
    const ModelData *d = &comp->data;
    const struct {
        const char *name;
        double value;
    } reals[] = {REAL_PARAMETERS(NAME_VALUE)};
    size_t i;
    for (i = 0; i < sizeof(reals) / sizeof(reals[0]); i++)
        CHECK(isfinite(reals[i].value), "invalid parameter %s = %g: must be finite", reals[i].name,
              reals[i].value);
    CHECK(d->Rm > 0, "invalid parameter Rm = %g: armature resistance must be > 0", d->Rm);
    CHECK(d->kt > 0, "invalid parameter kt = %g: torque constant must be > 0", d->kt);
    CHECK(d->km >= 0, "invalid parameter km = %g: back-EMF constant must be >= 0", d->km);
    CHECK(d->Kg > 0, "invalid parameter Kg = %g: gear ratio must be > 0", d->Kg);
    CHECK(d->eta_g > 0 && d->eta_g <= 1, "invalid parameter eta_g = %g: efficiency must be in (0, 1]", d->eta_g);
    CHECK(d->eta_m > 0 && d->eta_m <= 1, "invalid parameter eta_m = %g: efficiency must be in (0, 1]", d->eta_m);
    CHECK(d->Jeq > 0, "invalid parameter Jeq = %g: inertia must be > 0", d->Jeq);
    CHECK(d->Beq >= 0, "invalid parameter Beq = %g: damping must be >= 0", d->Beq);
    CHECK(d->m_link > 0, "invalid parameter m_link = %g: link mass must be > 0", d->m_link);
    CHECK(d->L_link > 0, "invalid parameter L_link = %g: link length must be > 0", d->L_link);
    CHECK(d->Ks > 0, "invalid parameter Ks = %g: link stiffness must be > 0", d->Ks);
    CHECK(d->zeta_link >= 0, "invalid parameter zeta_link = %g: damping ratio must be >= 0", d->zeta_link);
    CHECK(d->n_modes >= 1 && d->n_modes <= MAX_MODES, "invalid parameter n_modes = %d: must be in 1..%d",
          d->n_modes, MAX_MODES);
    CHECK(d->coulomb_torque >= 0, "invalid parameter coulomb_torque = %g: must be >= 0", d->coulomb_torque);
    CHECK(d->stiction_ratio >= 1, "invalid parameter stiction_ratio = %g: static/Coulomb ratio must be >= 1",
          d->stiction_ratio);
    CHECK(d->stribeck_speed >= 0, "invalid parameter stribeck_speed = %g: must be >= 0 (0 = no Stribeck drop)",
          d->stribeck_speed);
    CHECK(d->backlash >= 0, "invalid parameter backlash = %g: must be >= 0", d->backlash);
    CHECK(d->hub_torque_noise >= 0, "invalid parameter hub_torque_noise = %g: must be >= 0", d->hub_torque_noise);
    CHECK(d->tip_torque_noise >= 0, "invalid parameter tip_torque_noise = %g: must be >= 0", d->tip_torque_noise);
    CHECK(d->Jm_share >= 0.05 && d->Jm_share <= 0.95, "invalid parameter Jm_share = %g: must be in [0.05, 0.95]",
          d->Jm_share);
    CHECK(d->amp_limit >= 0, "invalid parameter amp_limit = %g: must be >= 0 (0 = no saturation)", d->amp_limit);
    CHECK(d->internal_step > 0, "invalid parameter internal_step = %g: must be > 0", d->internal_step);
    CHECK(d->hub_locked == 0 || d->hub_locked == 1, "invalid parameter hub_locked = %d: must be 0 or 1",
          d->hub_locked);
    CHECK(d->m_tip >= 0, "invalid parameter m_tip = %g: tip mass must be >= 0", d->m_tip);
    CHECK(!d->hub_locked || d->theta_dot_start == 0.0,
          "invalid parameter theta_dot_start = %g: must be 0 with hub_locked = 1 (the hub is clamped)",
          d->theta_dot_start);
    return true;
}

/* -------------------------------------------------------- initialisation */

/* inverse of the arrow matrix [[a, b^T], [b, J I]] (N x N, b in b[1..N-1]) via its Schur complement */
static void arrowInverse(double a, const double *b, double J, int N, double Minv[MAX_DOF][MAX_DOF]) {
    double s = a;
    int i, j;
    for (i = 1; i < N; i++) s -= b[i] * b[i] / J;
    Minv[0][0] = 1.0 / s;
    for (i = 1; i < N; i++) {
        Minv[0][i] = Minv[i][0] = -b[i] / (J * s);
        for (j = 1; j < N; j++) Minv[i][j] = (i == j ? 1.0 / J : 0.0) + b[i] * b[j] / (J * J * s);
    }
}

/* inverse of the symmetric positive definite n x n matrix A (rows/columns off..off+n-1 of MAX_DOF arrays) by
   Gauss-Jordan elimination; n <= MAX_DOF */
static void fullInverse(double A[MAX_DOF][MAX_DOF], int off, int n, double Minv[MAX_DOF][MAX_DOF]) {
    double T[MAX_DOF][2 * MAX_DOF];
    int i, j, r;
    for (i = 0; i < n; i++)
        for (j = 0; j < n; j++) {
            T[i][j] = A[off + i][off + j];
            T[i][n + j] = (i == j) ? 1.0 : 0.0;
        }
    for (r = 0; r < n; r++) { /* no pivoting needed: A is positive definite */
        const double p = T[r][r];
        for (j = 0; j < 2 * n; j++) T[r][j] /= p;
        for (i = 0; i < n; i++) {
            const double f = T[i][r];
            if (i == r || f == 0.0) continue;
            for (j = 0; j < 2 * n; j++) T[i][j] -= f * T[r][j];
        }
    }
    for (i = 0; i < n; i++)
        for (j = 0; j < n; j++) Minv[off + i][off + j] = T[i][n + j];
}

/* the mass matrix [[a, b^T + mt], [b + mt, J I + mt]] with mt = m_tip L^2 on every entry, inverted into Minv */
static void massInverse(const ModelData *d, double a, double Minv[MAX_DOF][MAX_DOF]) {
    double M[MAX_DOF][MAX_DOF];
    const double mt = d->m_tip * d->L_link * d->L_link;
    int i, j;
    if (mt == 0.0) {
        arrowInverse(a, d->b, d->Jmode, d->N, Minv);
        return;
    }
    for (i = 0; i < d->N; i++)
        for (j = 0; j < d->N; j++) {
            const double arrow = i == 0 ? (j == 0 ? a : d->b[j]) : (j == 0 ? d->b[i] : (i == j ? d->Jmode : 0.0));
            M[i][j] = mt + arrow;
        }
    fullInverse(M, 0, d->N, Minv);
}

static double infNorm(const double *A, int n) {
    double m = 0.0;
    int i, j;
    for (i = 0; i < n; i++) {
        double r = 0.0;
        for (j = 0; j < n; j++) r += fabs(A[i * n + j]);
        if (r > m) m = r;
    }
    return m;
}

/* upper estimate of the spectral radius: ||A^64||^(1/64) by repeated squaring (Gelfand) */
static double spectralRadius(const double *A, int n) {
    double B[(2 * MAX_DOF) * (2 * MAX_DOF)], T[(2 * MAX_DOF) * (2 * MAX_DOF)];
    double nrm = infNorm(A, n), logScale;
    int i, j, l, k;
    if (!(nrm > 0)) return 0.0;
    for (i = 0; i < n * n; i++) B[i] = A[i] / nrm;
    logScale = log(nrm);
    for (k = 0; k < 6; k++) {
        for (i = 0; i < n; i++)
            for (j = 0; j < n; j++) {
                double s = 0.0;
                for (l = 0; l < n; l++) s += B[i * n + l] * B[l * n + j];
                T[i * n + j] = s;
            }
        nrm = infNorm(T, n);
        if (!(nrm > 0)) return 0.0;
        for (i = 0; i < n * n; i++) B[i] = T[i] / nrm;
        logScale = 2.0 * logScale + log(nrm);
    }
    return exp(logScale / 64.0);
}

/* spectral radius of the linear hub-side dynamics with inverse mass Minv and hub damping D0 */
static double hubRadius(const ModelData *d, double Minv[MAX_DOF][MAX_DOF], double D0) {
    const int N = d->N, n = 2 * N;
    double A[(2 * MAX_DOF) * (2 * MAX_DOF)];
    int i, j;
    memset(A, 0, sizeof(A));
    for (i = 0; i < N; i++) {
        A[i * n + N + i] = 1.0;
        for (j = 0; j < N; j++) {
            A[(N + i) * n + j] = -Minv[i][j] * (j == 0 ? 0.0 : d->k[j]);
            A[(N + i) * n + N + j] = -Minv[i][j] * (j == 0 ? D0 : d->c[j]);
        }
    }
    return spectralRadius(A, n);
}

fmi2Status initialize(ModelInstance *comp) {
    ModelData *d = &comp->data;
    const double m = d->m_link, L = d->L_link;
    const double Jl = m * L * L / 3.0;
    const double w1 = sqrt(d->Ks / Jl);
    double sumDefl = 0.0, sumGauge = 0.0, rho, r;
    int i;

    d->N = d->n_modes + 1;
    d->Jmode = m * L * L / 4.0;
    d->k[0] = d->c[0] = d->b[0] = d->g[0] = 0.0;
    for (i = 1; i < d->N; i++) {
        const double bl = BETA_L[i - 1];
        const double ratio = (bl / BETA_L[0]) * (bl / BETA_L[0]);
        const double sgn = (i % 2) ? 1.0 : -1.0;
        const double w = w1 * ratio;
        d->k[i] = d->Jmode * w * w;
        d->c[i] = 2.0 * d->zeta_link * d->Jmode * w;
        d->b[i] = sgn * m * L * L / (bl * bl);
        d->g[i] = sgn * ratio;
        sumDefl += 1.0 / d->k[i];
        sumGauge += d->g[i] / d->k[i];
    }
    d->c_g = sumDefl / sumGauge;

    d->G = d->eta_g * d->Kg * d->eta_m * d->kt / d->Rm;
    d->Bemf = d->G * d->Kg * d->km;
    d->Jm = d->Jm_share * d->Jeq;
    d->Jh = d->Jeq - d->Jm;
    d->Bm = d->Jm_share * d->Beq;
    d->Bh = d->Beq - d->Bm;
    d->Fs = d->stiction_ratio * d->coulomb_torque;
    d->v_noise = 0.0;
    d->noise_key[0] = mix64((uint64_t)(int64_t)d->noise_seed ^ 0x687562ULL); /* "hub" */
    d->noise_key[1] = mix64((uint64_t)(int64_t)d->noise_seed ^ 0x746970ULL); /* "tip" */
    /* (Fs - Fc) exp(-r^2) < Fc 2^-55 leaves Fc + it = Fc to the last bit: the exponential need not be taken */
    d->r2_flat = 0.0;
    if (d->Fs > d->coulomb_torque) d->r2_flat = log((d->Fs - d->coulomb_torque) / d->coulomb_torque) + 55.0 * log(2.0);
    massInverse(d, d->Jeq + Jl, d->Minv_r);
    massInverse(d, d->Jh + Jl, d->Minv_f);
    {   /* the clamped link (hub at rest): modal mass J I + mt and the hub row b + mt */
        const double mt = d->m_tip * L * L;
        double Mc[MAX_DOF][MAX_DOF];
        int j;
        for (i = 1; i < d->N; i++) {
            d->M0[i] = d->b[i] + mt;
            for (j = 1; j < d->N; j++) Mc[i][j] = mt + (i == j ? d->Jmode : 0.0);
        }
        fullInverse(Mc, 1, d->N - 1, d->Mc_inv);
    }

    /* RK4 stability: |lambda h| <= 2 for every configuration that can occur */
    rho = hubRadius(d, d->Minv_r, d->Beq + d->Bemf);
    for (i = 1; i < d->N; i++) rho = fmax(rho, w1 * (BETA_L[i - 1] / BETA_L[0]) * (BETA_L[i - 1] / BETA_L[0]));
    if (d->backlash > 0) {
        rho = fmax(rho, hubRadius(d, d->Minv_f, d->Bh));
        rho = fmax(rho, (d->Bm + d->Bemf) / d->Jm);
    }
    r = rho > 0 ? 2.0 / rho : d->internal_step;
    d->h_max = fmin(d->internal_step, r);
    if (d->h_max < d->internal_step)
        logInfo(comp, "internal step limited to %g s for RK4 stability (internal_step = %g s)", d->h_max,
                d->internal_step);

    memset(d->X, 0, sizeof(d->X));
    d->lag = 0.0; /* on the grid of internal steps */
    d->X[0] = d->theta_start;
    d->X[1] = d->alpha_start; /* an initial deflection and deflection rate in mode 1 */
    d->X[d->N] = d->theta_dot_start;
    d->X[d->N + 1] = d->alpha_dot_start;
    d->X[2 * d->N] = d->theta_start; /* the motor side with the hub: teeth at the middle of the play */
    d->X[2 * d->N + 1] = d->theta_dot_start;
    d->stuck = (d->coulomb_torque > 0 && d->theta_dot_start == 0.0) ? 1 : 0;
    d->side = 0;
    d->slip = (d->coulomb_torque > 0 && d->theta_dot_start != 0.0) ? (d->theta_dot_start > 0 ? 1 : -1) : 0;
    d->linear = d->coulomb_torque == 0.0 && d->backlash == 0.0 && !d->hub_locked;
    for (i = 0; i < CONFIGS; i++) d->maps[i].h = 0.0, d->maps[i].f_set = 0;
    return fmi2OK;
}

void releaseModel(ModelInstance *comp) { (void)comp; }

/* -------------------------------------------------------------- dynamics */

static inline int isCoupled(const ModelData *d) { return d->backlash == 0.0 || d->side != 0 || d->hub_locked; }

static inline double motorTorque(const ModelData *d, double w) { return d->G * d->v_amp - d->Bemf * w; }

/* friction torque on the hub sliding in the direction slip at speed v [N.m] (0 when not sliding):
   slip (Fc + (Fs - Fc) exp(-(v / stribeck_speed)^2)), the Coulomb level Fc alone when stribeck_speed = 0 */
static inline double slidingFriction(const ModelData *d, double v) {
    if (d->stribeck_speed > 0) {
        const double r = v / d->stribeck_speed;
        if (r * r > d->r2_flat) return d->coulomb_torque * d->slip;
        return d->slip * (d->coulomb_torque + (d->Fs - d->coulomb_torque) * exp(-r * r));
    }
    return d->coulomb_torque * d->slip;
}

/* the step's inner functions written once for any N (the hub and its modes) and compiled for each N a rig can have
   (WITH_N): loop counts the compiler knows and unrolls, the same operations in the same order, so the same numbers
   to the bit, 1.3-1.9x faster */
#if defined(_MSC_VER)
#define FOR_EACH_N static __forceinline
#else
#define FOR_EACH_N static inline __attribute__((always_inline))
#endif
/* stmt with N = n (n_modes + 1, 2..MAX_DOF) a constant, one copy per value */
#define WITH_N(n, stmt)                                                                                                \
    switch (n) {                                                                                                       \
    case 2: { enum { N = 2 }; stmt; } break;                                                                           \
    case 3: { enum { N = 3 }; stmt; } break;                                                                           \
    default: { enum { N = MAX_DOF }; stmt; } break;                                                                    \
    }

/* modal generalised forces Q_i, i = 1..n */
FOR_EACH_N void modalForcesN(const ModelData *d, const double *X, double *Q, const int N) {
    int i;
    for (i = 1; i < N; i++) Q[i] = d->tau_tip - d->k[i] * X[i] - d->c[i] * X[N + i];
}

FOR_EACH_N void derivN(const ModelData *d, const double *X, double *dX, const int N) {
    const int coupled = isCoupled(d);
    double Q[MAX_DOF];
    int i, j;
    for (i = 0; i < N; i++) dX[i] = X[N + i];
    modalForcesN(d, X, Q, N);
    if (d->hub_locked || d->stuck) {
        dX[N] = 0.0;
        if (d->m_tip == 0.0)
            for (i = 1; i < N; i++) dX[N + i] = Q[i] / d->Jmode;
        else
            for (i = 1; i < N; i++) {
                double s = 0.0;
                for (j = 1; j < N; j++) s += d->Mc_inv[i][j] * Q[j];
                dX[N + i] = s;
            }
    } else {
        const double v0 = X[N];
        const double (*Minv)[MAX_DOF] = coupled ? d->Minv_r : d->Minv_f;
        if (coupled) /* rigid gear or teeth in contact: motor and hub as one body, Jeq on the hub */
            Q[0] = motorTorque(d, v0) - d->Beq * v0 + d->tau_tip - slidingFriction(d, v0);
        else /* in the play: hub side alone */
            Q[0] = -d->Bh * v0 + d->tau_tip - slidingFriction(d, v0);
        for (i = 0; i < N; i++) {
            double s = 0.0;
            for (j = 0; j < N; j++) s += Minv[i][j] * Q[j];
            dX[N + i] = s;
        }
    }
    if (coupled) {
        dX[2 * N] = X[N];
        dX[2 * N + 1] = dX[N];
    } else {
        const double wm = X[2 * N + 1];
        dX[2 * N] = wm;
        dX[2 * N + 1] = (motorTorque(d, wm) - d->Bm * wm) / d->Jm;
    }
}

FOR_EACH_N void rk4N(const ModelData *d, const double *X0, double *X1, double h, const int N) {
    const int nx = 2 * N + 2;
    double k1[MAX_X], k2[MAX_X], k3[MAX_X], k4[MAX_X], T[MAX_X];
    int i;
    derivN(d, X0, k1, N);
    for (i = 0; i < nx; i++) T[i] = X0[i] + 0.5 * h * k1[i];
    derivN(d, T, k2, N);
    for (i = 0; i < nx; i++) T[i] = X0[i] + 0.5 * h * k2[i];
    derivN(d, T, k3, N);
    for (i = 0; i < nx; i++) T[i] = X0[i] + h * k3[i];
    derivN(d, T, k4, N);
    for (i = 0; i < nx; i++) X1[i] = X0[i] + h / 6.0 * (k1[i] + 2.0 * (k2[i] + k3[i]) + k4[i]);
}

static void rk4(const ModelData *d, const double *X0, double *X1, double h) { WITH_N(d->N, rk4N(d, X0, X1, h, N)) }

/* friction torque on the hub needed to keep it (and the motor side, if coupled) at rest [N.m] */
FOR_EACH_N double frictionRequiredN(const ModelData *d, const int N) {
    double Q[MAX_DOF], s = 0.0;
    int i;
    modalForcesN(d, d->X, Q, N);
    if (d->m_tip == 0.0)
        for (i = 1; i < N; i++) s += d->b[i] * Q[i] / d->Jmode;
    else
        for (i = 1; i < N; i++) {
            double acc = 0.0; /* modal acceleration of the clamped link */
            int j;
            for (j = 1; j < N; j++) acc += d->Mc_inv[i][j] * Q[j];
            s += d->M0[i] * acc;
        }
    return s - d->tau_tip - (isCoupled(d) ? motorTorque(d, 0.0) : 0.0);
}

static double frictionRequired(const ModelData *d) { return frictionRequiredN(d, d->N); }

/* torque transmitted by the gear teeth in contact, motor to hub [N.m] */
FOR_EACH_N double gearTorqueN(const ModelData *d, const int N) {
    double Q[MAX_DOF], acc0 = 0.0, v0 = d->X[N];
    int j;
    if (d->stuck) return motorTorque(d, 0.0);
    modalForcesN(d, d->X, Q, N);
    Q[0] = motorTorque(d, v0) - d->Beq * v0 + d->tau_tip - slidingFriction(d, v0);
    for (j = 0; j < N; j++) acc0 += d->Minv_r[0][j] * Q[j];
    return motorTorque(d, v0) - d->Bm * v0 - d->Jm * acc0;
}

/* hub at rest: stick if static friction can hold it, else slide in the direction of the net torque */
static void settle(ModelData *d) {
    const double tr = frictionRequired(d);
    if (fabs(tr) <= d->Fs) {
        d->stuck = 1;
        d->slip = 0;
    } else {
        d->stuck = 0;
        d->slip = tr > 0 ? -1 : 1;
    }
}

FOR_EACH_N void updateModesN(ModelData *d, const int N) {
    if (d->hub_locked) return;
    if (d->backlash > 0 && d->side != 0 && d->side * gearTorqueN(d, N) < 0) d->side = 0; /* contact opens */
    if (d->coulomb_torque > 0 && d->stuck) {
        const double tr = frictionRequiredN(d, N);
        if (fabs(tr) > d->Fs) { /* break away */
            d->stuck = 0;
            d->slip = tr > 0 ? -1 : 1;
        }
    }
}

/* plastic impact when the play closes on side s (+1: motor ahead of the hub) */
static void impact(ModelData *d, int s) {
    const int N = d->N;
    double *X = d->X;
    double P;
    int i;
    X[2 * N] = X[0] + s * 0.5 * d->backlash;
    P = (X[2 * N + 1] - X[N]) / (1.0 / d->Jm + d->Minv_f[0][0]);
    for (i = 0; i < N; i++) X[N + i] += d->Minv_f[i][0] * P;
    X[2 * N + 1] = X[N];
    d->side = s;
    if (d->coulomb_torque > 0) {
        if (X[N] != 0.0) {
            d->stuck = 0;
            d->slip = X[N] > 0 ? 1 : -1;
        } else {
            settle(d);
        }
    }
}

/* sliding hub velocity reached zero */
static void velocityZero(ModelData *d) {
    const int N = d->N;
    d->X[N] = 0.0;
    if (isCoupled(d)) d->X[2 * N + 1] = 0.0;
    settle(d);
}

/* event function, positive before and <= 0 after the event: ev = +-1 gap closes on side ev, 2 reversal */
static double eventValue(const ModelData *d, const double *X, int ev) {
    const int N = d->N;
    if (ev == 2) return d->slip * X[N];
    return 0.5 * d->backlash - ev * (X[2 * N] - X[0]);
}

/* fraction f of the step [0, h] where the event ev occurs (Illinois regula falsi); leaves the state at f in Xf */
static double locateEvent(const ModelData *d, const double *X0, double h, int ev, double e0, double e1, double *Xf) {
    double fa = 0.0, fb = 1.0, ea = e0, eb = e1, f = 0.0;
    int it, side = 0;
    if (!(e0 > 0.0)) {
        memcpy(Xf, X0, sizeof(double) * MAX_X);
        return 0.0;
    }
    for (it = 0; it < 6; it++) {
        double e;
        f = fa - ea * (fb - fa) / (eb - ea);
        f = fmin(fmax(f, fa), fb);
        rk4(d, X0, Xf, f * h);
        e = eventValue(d, Xf, ev);
        if (fabs(e) <= 1e-13 * (fabs(e0) + fabs(e1))) break;
        if (e > 0.0) {
            fa = f;
            ea = e;
            if (side == 1) eb *= 0.5;
            side = 1;
        } else {
            fb = f;
            eb = e;
            if (side == -1) ea *= 0.5;
            side = -1;
        }
    }
    return f;
}

FOR_EACH_N int affineStepN(ModelData *d, const double *X0, double *X1, double h, const int N);

FOR_EACH_N void substepN(ModelData *d, double h, const int N) {
    const double half = 0.5 * d->backlash;
    double X0[MAX_X], X1[MAX_X];
    double rem = h;
    int events = 0;
    while (rem > 0.0) {
        double f = 2.0, e0 = 0.0, e1 = 0.0;
        int ev = 0;
        updateModesN(d, N);
        memcpy(X0, d->X, sizeof(X0));
        if (rem != h || !affineStepN(d, X0, X1, rem, N)) rk4N(d, X0, X1, rem, N);
        if (events < MAX_EVENTS_PER_STEP && !d->hub_locked) {
            if (d->backlash > 0 && d->side == 0 && fabs(X1[2 * N] - X1[0]) > half) {
                ev = (X1[2 * N] - X1[0]) > 0 ? 1 : -1; /* the play closes on side ev */
                e0 = eventValue(d, X0, ev);
                e1 = eventValue(d, X1, ev);
                f = e0 > 0.0 ? e0 / (e0 - e1) : 0.0;
            }
            if (d->coulomb_torque > 0 && !d->stuck && d->slip != 0 && X1[N] * d->slip <= 0.0) {
                const double v0 = eventValue(d, X0, 2), v1 = eventValue(d, X1, 2);
                const double fv = v0 > 0.0 ? v0 / (v0 - v1) : 0.0;
                if (fv < f) { /* the hub velocity reverses first */
                    ev = 2;
                    e0 = v0;
                    e1 = v1;
                }
            }
        }
        if (ev == 0) {
            memcpy(d->X, X1, sizeof(X1));
            break;
        }
        events++;
        f = locateEvent(d, X0, rem, ev, e0, e1, d->X);
        if (ev == 2)
            velocityZero(d);
        else
            impact(d, ev);
        rem -= f * rem;
    }
}

/* Phi = I + B + B^2/2 + B^3/6 + B^4/24 and P3h = h (I + B/2 + B^2/6 + B^3/24) of B = h A, A of size n: one RK4
   step of X' = A X + f is X <- Phi X + P3h f */
static void rk4Maps(int n, double Bm[MAX_X][MAX_X], double h, double Phi[MAX_X][MAX_X], double P3h[MAX_X][MAX_X]) {
    double Pw[MAX_X][MAX_X], T[MAX_X][MAX_X];
    double fact = 1.0;
    int i, j, l, p;
    for (i = 0; i < n; i++)
        for (j = 0; j < n; j++) {
            Pw[i][j] = (i == j) ? 1.0 : 0.0; /* B^0 */
            Phi[i][j] = Pw[i][j];
            P3h[i][j] = h * Pw[i][j];
        }
    for (p = 1; p <= 4; p++) { /* Pw = B^p */
        for (i = 0; i < n; i++)
            for (j = 0; j < n; j++) {
                double s = 0.0;
                for (l = 0; l < n; l++) s += Pw[i][l] * Bm[l][j];
                T[i][j] = s;
            }
        memcpy(Pw, T, sizeof(T));
        fact *= p;
        for (i = 0; i < n; i++)
            for (j = 0; j < n; j++) {
                Phi[i][j] += Pw[i][j] / fact;
                if (p < 4) P3h[i][j] += h * Pw[i][j] / (fact * (p + 1));
            }
    }
}

/* the configuration the rig's dynamics are affine in over a step: gear in contact (or no play) or in the play, hub
   sliding (or free) or stuck */
static int configuration(const ModelData *d) { return (isCoupled(d) ? RIGID : PLAY) + (d->stuck ? STUCK : 0); }

/* states a configuration's maps act on: the rigid drive's hub and modes (the motor side follows the hub), else all */
static int mapSize(const ModelData *d, int cfg) { return cfg == RIGID ? 2 * d->N : 2 * d->N + 2; }

/* entry (i, j) of configuration cfg's inverse mass matrix: the rigid drive's or the hub side's (Minv_r, Minv_f) with
   the hub free; with the hub stuck, the clamped link's modal one (i, j >= 1) */
static double inverseMass(const ModelData *d, int cfg, int i, int j) {
    if (!(cfg & STUCK)) return ((cfg & ~STUCK) == RIGID ? d->Minv_r : d->Minv_f)[i][j];
    return d->m_tip == 0.0 ? (i == j ? 1.0 / d->Jmode : 0.0) : d->Mc_inv[i][j];
}

/* the maps of configuration cfg for steps of h: B = h A of the derivatives derivN takes in it, friction aside; and
   the configuration's inverse mass matrix beside them */
static void affineMaps(ModelData *d, int cfg, double h) {
    const int N = d->N, n = 2 * N, first = cfg & STUCK ? 1 : 0, drive = cfg & ~STUCK;
    const double Bhub = drive == RIGID ? d->Beq + d->Bemf : d->Bh;
    double Bm[MAX_X][MAX_X];
    int i, j;
    for (i = 0; i < N; i++)
        for (j = 0; j < N; j++) d->maps[cfg].Minv[i][j] = inverseMass(d, cfg, i, j);
    memset(Bm, 0, sizeof(Bm));
    for (i = first; i < N; i++) { /* a stuck hub (row 0) stays where it is */
        Bm[i][N + i] = h;
        for (j = first; j < N; j++) {
            const double m = d->maps[cfg].Minv[i][j];
            Bm[N + i][j] = -h * m * (j == 0 ? 0.0 : d->k[j]);
            Bm[N + i][N + j] = -h * m * (j == 0 ? Bhub : d->c[j]);
        }
    }
    if (drive == PLAY) { /* the motor side on its own */
        Bm[n][n + 1] = h;
        Bm[n + 1][n + 1] = -h * (d->Bemf + d->Bm) / d->Jm;
    }
    rk4Maps(mapSize(d, cfg), Bm, h, d->maps[cfg].Phi, d->maps[cfg].P3h);
    d->maps[cfg].h = h;
}

/* The forcing f of configuration cfg's affine dynamics X' = A X + f [rad/s^2] over a step: the drive's and the tip's
   torques, less Coulomb's level where the hub slides (coulomb_torque slip), through the configuration's inverse mass
   (its maps made first: affineMaps); in the play, the motor side's drive of its own. Zero on the positions and on a
   stuck hub's rate. */
FOR_EACH_N void affineForcingN(const ModelData *d, int cfg, double *f, const int N) {
    const int n = 2 * N, first = cfg & STUCK ? 1 : 0, drive = cfg & ~STUCK;
    double Q[MAX_DOF];
    int i, j;
    Q[0] = (drive == RIGID ? d->G * d->v_amp : 0.0) + d->tau_tip -
           (d->coulomb_torque > 0 ? d->coulomb_torque * d->slip : 0.0);
    for (i = 1; i < N; i++) Q[i] = d->tau_tip;
    for (i = 0; i < N; i++) {
        double s = 0.0;
        for (j = first; j < N; j++) s += d->maps[cfg].Minv[i][j] * Q[j];
        f[i] = 0.0;
        f[N + i] = i < first ? 0.0 : s;
    }
    f[n] = 0.0;
    f[n + 1] = drive == PLAY ? d->G * d->v_amp / d->Jm : 0.0;
}

/* configuration cfg's forcing (affineForcingN) for the current v_amp, tau_tip and slip: the one kept in its maps,
   taken again when one of them changed */
FOR_EACH_N const double *keptForcingN(ModelData *d, int cfg, const int N) {
    if (!d->maps[cfg].f_set || d->maps[cfg].f_v != d->v_amp || d->maps[cfg].f_tau != d->tau_tip ||
        d->maps[cfg].f_slip != d->slip) {
        affineForcingN(d, cfg, d->maps[cfg].f, N);
        d->maps[cfg].f_v = d->v_amp, d->maps[cfg].f_tau = d->tau_tip, d->maps[cfg].f_slip = d->slip;
        d->maps[cfg].f_set = 1;
    }
    return d->maps[cfg].f;
}

/* One RK4 step from X0 to X1 as its polynomial (X1 = Phi X0 + P3h f) where the dynamics are affine over the step,
   the friction torque fixed: the hub stuck, or sliding with Coulomb's level at both ends (stribeck_speed = 0, or a
   speed where the Stribeck term is below rounding), in the configuration's maps. Returns 0 where it does not apply
   (the hub locked, the Stribeck drop): the caller takes RK4 stage by stage. */
FOR_EACH_N int affineStepN(ModelData *d, const double *X0, double *X1, double h, const int N) {
    const int n = 2 * N, cfg = configuration(d), m = mapSize(d, cfg);
    const int stribeck = !d->stuck && d->stribeck_speed > 0 && d->coulomb_torque > 0;
    const double *f;
    int i, j;
    if (d->hub_locked) return 0;
    if (stribeck) {
        const double r = X0[N] / d->stribeck_speed;
        if (!(r * r > d->r2_flat)) return 0;
    }
    if (d->maps[cfg].h != h) affineMaps(d, cfg, h);
    f = keptForcingN(d, cfg, N);
    for (i = 0; i < m; i++) {
        double s = 0.0;
        for (j = 0; j < m; j++) s += d->maps[cfg].Phi[i][j] * X0[j];
        for (j = N; j < m; j++) s += d->maps[cfg].P3h[i][j] * f[j]; /* f is 0 on the positions */
        X1[i] = s;
    }
    if (stribeck) {
        const double r = X1[N] / d->stribeck_speed;
        if (!(r * r > d->r2_flat) || X1[N] * d->slip <= 0.0) return 0; /* it left the flat level: RK4 by stages */
    }
    if (cfg == RIGID) { /* the motor side moves with the hub */
        X1[n] = X0[n] + (X1[0] - X0[0]);
        X1[n + 1] = X1[N];
    }
    return 1;
}

/* nsub RK4 steps of size hs of the linear rig with constant inputs */
FOR_EACH_N void linearStepsN(ModelData *d, double hs, long nsub, const int N) {
    const int n = 2 * N;
    double f[MAX_X], g[2 * MAX_DOF], Y[2 * MAX_DOF];
    long k;
    int i, j;
    if (d->maps[RIGID].h != hs) affineMaps(d, RIGID, hs);
    affineForcingN(d, RIGID, f, N); /* no friction on the linear rig */
    for (i = 0; i < n; i++) {
        double s = 0.0;
        for (j = 0; j < n; j++) s += d->maps[RIGID].P3h[i][j] * f[j];
        g[i] = s;
    }
    for (k = 0; k < nsub; k++) {
        for (i = 0; i < n; i++) {
            double s = g[i];
            for (j = 0; j < n; j++) s += d->maps[RIGID].Phi[i][j] * d->X[j];
            Y[i] = s;
        }
        memcpy(d->X, Y, (size_t)n * sizeof(double));
    }
    d->X[n] = d->X[0]; /* motor side = hub without backlash */
    d->X[n + 1] = d->X[N];
}

/* h [s] of integration with the inputs u, tau_tip: internal steps of equal size at most h_max */
static fmi2Status integrate(ModelInstance *comp, double h, double u, double tau) {
    ModelData *d = &comp->data;
    const double tau_now = d->tau_tip;
    double nsub_d;
    long nsub, k;
    d->v_amp = u + d->u_offset;
    if (d->amp_limit > 0) d->v_amp = fmin(fmax(d->v_amp, -d->amp_limit), d->amp_limit);
    d->v_amp += d->v_noise; /* the hub's process noise, as the drive's torque */
    nsub_d = ceil(h / d->h_max - 1e-9);
    if (nsub_d < 1) nsub_d = 1;
    if (nsub_d > 1e9) {
        logError(comp, "communication step %g s needs more than 1e9 internal steps of %g s", h, d->h_max);
        return fmi2Error;
    }
    nsub = (long)nsub_d;
    d->tau_tip = tau;
    if (d->linear) {
        WITH_N(d->N, linearStepsN(d, h / (double)nsub, nsub, N))
    } else {
        WITH_N(d->N, for (k = 0; k < nsub; k++) substepN(d, h / (double)nsub, N))
    }
    d->tau_tip = tau_now;
    return fmi2OK;
}

static void saveGrid(ModelData *d) {
    memcpy(d->Xg, d->X, sizeof(d->X));
    d->stuck_g = d->stuck, d->side_g = d->side, d->slip_g = d->slip;
}

static void restoreGrid(ModelData *d) {
    memcpy(d->X, d->Xg, sizeof(d->X));
    d->stuck = d->stuck_g, d->side = d->side_g, d->slip = d->slip_g;
}

/* A step of at least the internal step integrates it in equal internal steps.  A finer step (a master that steps
 * every FMU at a fraction of the sample period) keeps the state on the grid of whole internal steps, as a step of
 * the sample period would integrate it, and previews the part of an internal step past it: the same numbers at the
 * grid points whatever the master's step, while the inputs change only there. */
static fmi2Status stepInputs(ModelInstance *comp, double t, double h);

/* The process noise (hub_torque_noise, tip_torque_noise): over the communication step k = t / h, white torques held,
 * of rms intensity / sqrt(h), deviate k of each stream (noise.h) - the hub's added to the drive's output (as volts:
 * on the motor's side of a play), the tip's to tau_tip. */
fmi2Status doStep(ModelInstance *comp, double t, double h) {
    ModelData *d = &comp->data;
    if (d->hub_torque_noise == 0.0 && d->tip_torque_noise == 0.0) return stepInputs(comp, t, h);
    const int64_t k = (int64_t)floor(t / h + 0.5);
    const double tau_in = d->tau_tip, scale = 1.0 / sqrt(h);
    d->v_noise = d->hub_torque_noise * scale * gauss(d->noise_key[0], k) / d->G;
    d->tau_tip = tau_in + d->tip_torque_noise * scale * gauss(d->noise_key[1], k);
    const fmi2Status s = stepInputs(comp, t, h);
    d->tau_tip = tau_in;
    return s;
}

static fmi2Status stepInputs(ModelInstance *comp, double t, double h) {
    ModelData *d = &comp->data;
    const int nx = 2 * d->N + 2;
    const double eps = 1e-9 * d->h_max;
    fmi2Status s = fmi2OK;
    int i;
    if (!isfinite(d->u) || !isfinite(d->tau_tip)) {
        logError(comp, "input u or tau_tip is not finite at t = %g s", t);
        return fmi2Error;
    }
    if (d->lag == 0 && h >= d->h_max - eps) {
        s = integrate(comp, h, d->u, d->tau_tip);
    } else {
        if (d->lag > 0) {
            restoreGrid(d); /* undo the preview */
            if (d->u != d->lag_u || d->tau_tip != d->lag_tau) { /* inputs changed within an internal step */
                s = integrate(comp, d->lag, d->lag_u, d->lag_tau);
                d->lag = 0;
            }
        }
        d->lag_u = d->u, d->lag_tau = d->tau_tip;
        d->lag += h;
        while (s == fmi2OK && d->lag >= d->h_max - eps) {
            s = integrate(comp, d->h_max, d->u, d->tau_tip);
            d->lag = d->lag - d->h_max < eps ? 0.0 : d->lag - d->h_max;
        }
        saveGrid(d);
        if (s == fmi2OK && d->lag > 0) s = integrate(comp, d->lag, d->u, d->tau_tip);
    }
    if (s != fmi2OK) return s;
    for (i = 0; i < nx; i++) {
        if (!isfinite(d->X[i])) {
            logError(comp, "state became non-finite at t = %g s (check parameters and internal_step)", t + h);
            return fmi2Error;
        }
    }
    return fmi2OK;
}

void calculateValues(ModelInstance *comp) {
    ModelData *d = &comp->data;
    const int N = d->N;
    double a = 0.0, ad = 0.0, gsum = 0.0;
    int i;
    if (N < 2) return; /* not initialised yet */
    for (i = 1; i < N; i++) {
        a += d->X[i];
        ad += d->X[N + i];
        gsum += d->g[i] * d->X[i];
    }
    d->theta = d->X[0];
    d->alpha = a;
    d->y = d->theta + a;
    d->theta_dot = d->X[N];
    d->alpha_dot = ad;
    d->alpha_gauge = d->c_g * gsum;
    d->theta_motor = d->backlash > 0 ? d->X[2 * N] : d->X[0];
}

/* ------------------------------------------------------- get / set */

static double *realParameter(ModelData *d, fmi2ValueReference vr, const char **pname) {
    switch (vr) {
        REAL_PARAMETERS(PARAMETER_CASE)
    default: return NULL;
    }
}

static int *intParameter(ModelData *d, fmi2ValueReference vr, const char **pname) {
    switch (vr) {
        INTEGER_PARAMETERS(PARAMETER_CASE)
    default: return NULL;
    }
}

fmi2Status getFloat64(ModelInstance *comp, fmi2ValueReference vr, double *value) {
    ModelData *d = &comp->data;
    const char *name;
    const double *p;
    switch (vr) { /* the inputs and outputs first: the master reads them every sample */
        INPUTS(GET_CASE)
        OUTPUTS(GET_CASE)
    default: break;
    }
    p = realParameter(d, vr, &name);
    if (!p) return unknownReference(comp, "Real", vr);
    *value = *p;
    return fmi2OK;
}

fmi2Status setFloat64(ModelInstance *comp, fmi2ValueReference vr, double value) {
    ModelData *d = &comp->data;
    const char *name;
    double *p;
    switch (vr) { /* the inputs first: the master sets them every sample */
    case vr_u: d->u = value; return fmi2OK;
    case vr_tau_tip: d->tau_tip = value; return fmi2OK;
    default: break;
    }
    p = realParameter(d, vr, &name);
    if (p) {
        if (!parametersSettable(comp)) return fixedAfterInit(comp, name);
        *p = value;
        return fmi2OK;
    }
    if (vr >= vr_theta && vr <= vr_theta_motor) {
        logError(comp, "output value reference %u cannot be set", (unsigned)vr);
        return fmi2Error;
    }
    return unknownReference(comp, "Real", vr);
}

fmi2Status getInt32(ModelInstance *comp, fmi2ValueReference vr, int *value) {
    const char *name;
    const int *p = intParameter(&comp->data, vr, &name);
    if (!p) return unknownReference(comp, "Integer", vr);
    *value = *p;
    return fmi2OK;
}

fmi2Status setInt32(ModelInstance *comp, fmi2ValueReference vr, int value) {
    const char *name;
    int *p = intParameter(&comp->data, vr, &name);
    if (!p) return unknownReference(comp, "Integer", vr);
    if (!parametersSettable(comp)) return fixedAfterInit(comp, name);
    *p = value;
    return fmi2OK;
}
