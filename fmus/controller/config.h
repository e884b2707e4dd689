/* controller: the lab's digital controller, state feedback, PID or LQG on the sampled angles (FMI 2.0 co-simulation). */
#ifndef CONTROLLER_CONFIG_H
#define CONTROLLER_CONFIG_H

#include <stdint.h>

#define MODEL_NAME "controller"
/* must equal the guid attribute of modelDescription.xml (harness/fmu/build.py checks it) */
#define MODEL_GUID "{5e2b8c41-7d93-4f0a-b6e1-9c4d2a7f3b58}"

#define KIND_STATE_FEEDBACK 1
#define KIND_PID 2
#define KIND_LQG 3

/* the LQG's largest number of estimator states; harness/rig/controller.py has the same number (NX_MAX) */
#define NX_MAX 10

/* The variables, one line each, in modelDescription.xml order: X(name, value reference, start value) for the
   parameters, X(name, value reference) for inputs and outputs.  These lists are the C side's only copy of the
   variable table: they declare the ModelData fields and the value references, and drive the start values, the
   finiteness check and get/set in model.c.  tests/test_fmu_config.py checks them against modelDescription.xml. */
#define REAL_PARAMETERS(X)        \
    X(sample_rate, 0, 50.0)       \
    X(k_theta, 2, 0.0)            \
    X(k_alpha, 3, 0.0)            \
    X(k_theta_dot, 4, 0.0)        \
    X(k_alpha_dot, 5, 0.0)        \
    X(kp, 6, 0.0)                 \
    X(ki, 7, 0.0)                 \
    X(kd, 8, 0.0)                 \
    X(cutoff, 9, 50.0)            \
    X(u_limit, 10, 0.0)           \
    X(theta_gain, 11, 35.5145)    \
    X(theta_offset, 12, 0.0)      \
    X(alpha_gain, 13, -3.3636)    \
    X(alpha_offset, 14, 0.0)      \
    X(compute_time, 15, 0.0)      \
    X(theta_dot_start, 16, 0.0)   \
    X(alpha_dot_start, 17, 0.0)
#define INTEGER_PARAMETERS(X)     \
    X(kind, 1, 1)                 \
    X(lqg_n, 999, 0)
/* the LQG's arrays, Real parameters with start 0: X(name, value reference of the first element, rows, columns); in
   modelDescription.xml name[i,j] (a matrix) or name[i] (a vector), 1-based, value reference first + (i - 1) columns
   + (j - 1): row-major, as the ModelData array holds them */
#define ARRAY_PARAMETERS(X)           \
    X(lqg_A, 1000, NX_MAX, NX_MAX)    \
    X(lqg_B, 1200, NX_MAX, 1)         \
    X(lqg_C, 1300, 2, NX_MAX)         \
    X(lqg_L, 1400, NX_MAX, 2)         \
    X(lqg_K, 1500, 1, NX_MAX)         \
    X(lqg_N, 1600, NX_MAX, 1)         \
    X(lqg_X0, 1700, NX_MAX, 2)
#define INPUTS(X)                 \
    X(ref, 30)                    \
    X(theta_v, 31)                \
    X(alpha_v, 32)
#define OUTPUTS(X)                \
    X(u, 40)                      \
    X(theta, 41)                  \
    X(alpha, 42)                  \
    X(theta_dot, 43)              \
    X(alpha_dot, 44)

#include "variables.h"

typedef enum {
    REAL_PARAMETERS(VALUE_REFERENCE) INTEGER_PARAMETERS(VALUE_REFERENCE) INPUTS(VALUE_REFERENCE_IO)
    OUTPUTS(VALUE_REFERENCE_IO)
} ValueReference;

typedef struct {
    REAL_PARAMETERS(DECLARE_REAL)
    INTEGER_PARAMETERS(DECLARE_INTEGER)
    ARRAY_PARAMETERS(DECLARE_ARRAY)
    INPUTS(DECLARE_VARIABLE)
    OUTPUTS(DECLARE_VARIABLE) /* held between samples */
    /* state, carried from sample to sample */
    int64_t next_sample; /* index k of the next sample instant k / sample_rate not yet taken */
    int have_last;       /* a previous sample exists (the first difference is 0) */
    double last_theta, last_alpha; /* angles [rad] of the previous sample */
    double v_theta, v_alpha;       /* filtered velocities [rad/s] */
    double integral;               /* PID: integral of the error [rad s] */
    double xhat[NX_MAX];           /* LQG: the estimate of the previous sample */
    double u_prev;                 /* LQG: the previous sample's command [V] (clamped) */
    double filter_a;               /* the velocity filter's a = exp(-2 pi cutoff Ts), set at initialisation */
} ModelData;

#endif
