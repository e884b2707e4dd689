/* flexjoint: SRV02 servo + flexible link plant (FMI 2.0 co-simulation). All SI, angles in rad. */
#ifndef FLEXJOINT_CONFIG_H
#define FLEXJOINT_CONFIG_H

#define MODEL_NAME "flexjoint"
/* must equal the guid attribute of modelDescription.xml (harness/build.py checks it) */
#define MODEL_GUID "{6c1f4a52-3f0e-4b8e-9a57-1d2b7c9e0f11}"

#define MAX_MODES 3
#define MAX_DOF (MAX_MODES + 1)         /* hub angle + modal tip-angle coordinates a_i */
#define MAX_X (2 * MAX_DOF + 2)         /* positions, velocities, motor-side angle and speed */

/* value references: must equal modelDescription.xml */
typedef enum {
    vr_Rm = 0,
    vr_kt = 1,
    vr_km = 2,
    vr_Kg = 3,
    vr_eta_g = 4,
    vr_eta_m = 5,
    vr_Jeq = 6,
    vr_Beq = 7,
    vr_m_link = 8,
    vr_L_link = 9,
    vr_Ks = 10,
    vr_zeta_link = 11,
    vr_n_modes = 12, /* Integer */
    vr_coulomb_torque = 13,
    vr_stiction_ratio = 14,
    vr_backlash = 15,
    vr_Jm_share = 16,
    vr_amp_limit = 17,
    vr_internal_step = 18,
    vr_theta_start = 19,
    vr_hub_locked = 20, /* Integer */
    vr_u = 30,
    vr_tau_tip = 31,
    vr_theta = 40,
    vr_alpha = 41,
    vr_y = 42,
    vr_theta_dot = 43,
    vr_alpha_dot = 44,
    vr_alpha_gauge = 45,
    vr_theta_motor = 46
} ValueReference;

typedef struct {
    /* parameters */
    double Rm, kt, km, Kg, eta_g, eta_m, Jeq, Beq, m_link, L_link, Ks, zeta_link;
    int n_modes;
    double coulomb_torque, stiction_ratio, backlash, Jm_share, amp_limit, internal_step, theta_start;
    int hub_locked;
    /* inputs */
    double u, tau_tip;
    /* outputs */
    double theta, alpha, y, theta_dot, alpha_dot, alpha_gauge, theta_motor;

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
    double h_max;                   /* largest internal step [s]: internal_step, limited for RK4 stability */
    double Fs;                      /* static friction torque [N.m] */

    /* state */
    double X[MAX_X]; /* [theta, a_1..a_n, theta_dot, a_dot_1..n, theta_m, omega_m] */
    int stuck;       /* hub held by static friction */
    int side;        /* backlash: 0 = in the play, +1/-1 = teeth in contact (motor ahead / behind) */
    int slip;        /* sign of the hub velocity while sliding with friction (0: no friction force) */
    double v_amp;    /* amplifier output held over the current step [V] */

    /* linear fast path (no friction, no backlash, hub free): one RK4 step is X <- Phi X + h P3 f */
    int linear;                               /* 1 when the fast path applies */
    double lin_h;                             /* internal step Phi and P3 were computed for [s] */
    double Phi[2 * MAX_DOF][2 * MAX_DOF];     /* I + hA + (hA)^2/2 + (hA)^3/6 + (hA)^4/24 */
    double P3h[2 * MAX_DOF][2 * MAX_DOF];     /* h (I + hA/2 + (hA)^2/6 + (hA)^3/24) */
} ModelData;

#endif
