/* armax: a generic discrete-time ARMAX model (FMI 2.0 co-simulation), one binary for every identified model. */
#ifndef ARMAX_CONFIG_H
#define ARMAX_CONFIG_H

#define MODEL_NAME "armax"
/* must equal the guid attribute of modelDescription.xml (harness/fmu/build.py checks it) */
#define MODEL_GUID "{5b0e7c42-9d1a-4f3e-b6a8-2c4d8e1f7a93}"

/* largest order: a[1..NMAX], b[0..NMAX], c[1..NMAX]; harness/ident/export.py has the same number
   (tests/test_export.py checks it) */
#define NMAX 16

/* resources file written by harness.ident.export (name value per line), read at instantiation */
#define COEFFICIENT_FILE "coefficients.txt"

/* value references: must equal modelDescription.xml (a[i] = VR_A + i, b[j] = VR_B + j, c[i] = VR_C + i) */
typedef enum {
    vr_Ts = 0,
    vr_na = 1, /* Integer */
    vr_nb = 2, /* Integer */
    vr_nc = 3, /* Integer */
    vr_nk = 4, /* Integer */
    vr_af = 5,
    vr_u_offset = 6,
    vr_y0 = 7,
    vr_u = 10,
    vr_y_f = 11,
    vr_y = 12,
    VR_A = 100,
    VR_B = 200,
    VR_C = 300
} ValueReference;

typedef struct {
    /* parameters */
    double Ts;
    int na, nb, nc, nk;
    double af, u_offset, y0;
    double a[NMAX + 1]; /* a[0] unused (A is monic) */
    double b[NMAX + 1];
    double c[NMAX + 1]; /* c[0] unused; C does not affect the simulation */
    /* input */
    double u;
    /* outputs at the current communication point */
    double y_f, y;
    /* state at sample k: past detrended inputs ud[j] = u_d(k - 1 - j), past outputs yf[i] = y_f(k - i) */
    double ud[NMAX + 1];
    double yf[NMAX + 1];
    long long k; /* sample index of the current communication point */
    /* a problem met while reading the coefficient file; reported by validate() */
    char load_error[256];
} ModelData;

#endif
