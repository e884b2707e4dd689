/* flexjoint: SRV02 servo + flexible link plant (FMI 2.0 co-simulation). All SI, angles in rad. */
#ifndef FLEXJOINT_CONFIG_H
#define FLEXJOINT_CONFIG_H

#include <stdint.h>

#define MODEL_NAME "flexjoint"
/* must equal the guid attribute of modelDescription.xml (harness/fmu/build.py checks it) */
#define MODEL_GUID "{6c1f4a52-3f0e-4b8e-9a57-1d2b7c9e0f12}"

#define MAX_MODES 3
#define MAX_DOF (MAX_MODES + 1)         /* hub angle + modal tip-angle coordinates a_i */
enum { RIGID = 0, PLAY = 1, STUCK = 2, CONFIGS = 4 }; /* the configurations of ModelData.maps */
#define MAX_X (2 * MAX_DOF + 2)         /* positions, velocities, motor-side angle and speed */

/* The variables, one line each, in modelDescription.xml order: X(name, value reference, start value) for the
   parameters, X(name, value reference) for inputs and outputs.  These lists are the C side's only copy of the
   variable table: they declare the ModelData fields and the value references, and drive the start values, the
   finiteness check and get/set in model.c.  tests/test_fmu_config.py checks them against modelDescription.xml. */
#define REAL_PARAMETERS(X)       \
    X(Rm, 0, 2.6)                \
    X(kt, 1, 7.68e-3)            \
    X(km, 2, 7.68e-3)            \
    X(Kg, 3, 70.0)               \
    X(eta_g, 4, 0.9)             \
    X(eta_m, 5, 0.69)            \
    X(Jeq, 6, 2.08e-3)           \
    X(Beq, 7, 0.004)             \
    X(m_link, 8, 0.065)          \
    X(L_link, 9, 0.419)          \
    X(Ks, 10, 1.3)               \
    X(zeta_link, 11, 0.01)       \
    X(coulomb_torque, 13, 0.0)   \
    X(stiction_ratio, 14, 1.0)   \
    X(backlash, 15, 0.0)         \
    X(Jm_share, 16, 0.5)         \
    X(amp_limit, 17, 0.0)        \
    X(internal_step, 18, 1e-3)   \
    X(theta_start, 19, 0.0)      \
    X(m_tip, 21, 0.0)            \
    X(alpha_start, 22, 0.0)      \
    X(theta_dot_start, 23, 0.0)  \
    X(alpha_dot_start, 24, 0.0)  \
    X(stribeck_speed, 25, 0.0)   \
    X(u_offset, 26, 0.0)         \
    X(hub_torque_noise, 27, 0.0) \
    X(tip_torque_noise, 28, 0.0)
#define INTEGER_PARAMETERS(X)    \
    X(n_modes, 12, 1)            \
    X(hub_locked, 20, 0)         \
    X(noise_seed, 29, 0)
#define INPUTS(X)                \
    X(u, 30)                     \
    X(tau_tip, 31)
#define OUTPUTS(X)               \
    X(theta, 40)                 \
    X(alpha, 41)                 \
    X(y, 42)                     \
    X(theta_dot, 43)             \
    X(alpha_dot, 44)             \
    X(alpha_gauge, 45)           \
    X(theta_motor, 46)

#include "variables.h"

typedef enum {
    REAL_PARAMETERS(VALUE_REFERENCE) INTEGER_PARAMETERS(VALUE_REFERENCE) INPUTS(VALUE_REFERENCE_IO)
    OUTPUTS(VALUE_REFERENCE_IO)
} ValueReference;

typedef struct {
    REAL_PARAMETERS(DECLARE_REAL)
    INTEGER_PARAMETERS(DECLARE_INTEGER)
    INPUTS(DECLARE_VARIABLE)
    OUTPUTS(DECLARE_VARIABLE)

    /* derived constants (initialize) */
    int N;                          /* degrees of freedom on the hub side: 1 + n_modes */
    double G;                       /* motor torque per volt at the load shaft [N.m/V] */
    double Bemf;                    /* back-EMF damping at the load shaft [N.m.s/rad] */
    double Jm, Jh, Bm, Bh;          /* motor / hub side inertia and viscous split (backlash) */
    double Jmode;                   /* modal inertia J_i = m L^2 / 4 [kg.m2] */
    double k[MAX_DOF], c[MAX_DOF];  /* modal stiffness [N.m/rad] and damping [N.m.s/rad], index 1..n */
    double b[MAX_DOF];              /* hub-mode inertia coupling [kg.m2], index 1..n */
    double g[MAX_DOF];              /* gauge weights (root curvature per unit a_i, mode 1 = 1) */
    double c_g;                     /* static gauge calibration factor */
    double Minv_r[MAX_DOF][MAX_DOF]; /* inverse mass matrix, rigid gear (Jeq on the hub) */
    double Minv_f[MAX_DOF][MAX_DOF]; /* inverse mass matrix, hub side only (gear in the play) */
    double Mc_inv[MAX_DOF][MAX_DOF]; /* inverse modal mass of the clamped link (hub at rest), index 1..n */
    double M0[MAX_DOF];             /* hub row of the mass matrix: hub-mode coupling [kg.m2], index 1..n */
    double h_max;                   /* largest internal step [s]: internal_step, limited for RK4 stability */
    double Fs;                      /* static friction torque [N.m] */
    double r2_flat;                 /* (v / stribeck_speed)^2 beyond which the Stribeck term is below Fc's last bit */

    /* state */
    double X[MAX_X]; /* [theta, a_1..a_n, theta_dot, a_dot_1..n, theta_m, omega_m] */
    int stuck;       /* hub held by static friction */
    int side;        /* backlash: 0 = in the play, +1/-1 = teeth in contact (motor ahead / behind) */
    int slip;        /* sign of the hub velocity while sliding with friction (0: no friction force) */
    double v_amp;    /* amplifier output held over the current step [V] */
    double v_noise;  /* the hub's process-noise torque over the current communication step, as volts [V] */
    uint64_t noise_key[2]; /* the process noise's streams: hub, tip */

    /* communication steps finer than the internal step: X stays on the grid of whole internal steps (Xg, its
       flags, lag the time integrated past it as a preview, lag_u and lag_tau the inputs over that part) */
    double lag, lag_u, lag_tau;
    double Xg[MAX_X];
    int stuck_g, side_g, slip_g;

    /* linear fast path (no friction, no backlash, hub free): one RK4 step is X <- Phi X + h P3 f */
    int linear; /* 1 when the fast path applies */
    /* one RK4 step as its polynomial, per configuration (the gear in contact or in the play, the hub sliding or
       stuck), for internal steps of h [s] */
    struct {
        double h;
        double Phi[MAX_X][MAX_X]; /* I + hA + (hA)^2/2 + (hA)^3/6 + (hA)^4/24 */
        double P3h[MAX_X][MAX_X]; /* h (I + hA/2 + (hA)^2/6 + (hA)^3/24) */
        double Minv[MAX_DOF][MAX_DOF]; /* the configuration's inverse mass matrix (set with the maps) */
        /* its forcing f [rad/s^2] for the amplifier output f_v [V], tip torque f_tau [N.m] and sliding direction
           f_slip it was taken with (f_set 0: none yet) */
        double f[MAX_X], f_v, f_tau;
        int f_slip, f_set;
    } maps[CONFIGS];
} ModelData;

#endif
