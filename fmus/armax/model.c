/*
 * armax: a generic discrete-time ARMAX model (identified by harness.ident.armax) as an FMI 2.0 co-simulation FMU.
 *
 * Model, q^-1 the backward shift by one sample of Ts [s]:
 *     A(q) y_f(k) = B(q) u_d(k),   u_d = u - u_offset [V]
 *     A = 1 + a[1] q^-1 + .. + a[na] q^-na,   B = b[nk] q^-nk + .. + b[nk+nb-1] q^-(nk+nb-1)   (nk >= 1)
 * y_f is the identified domain (the preprocessed angle, units of y per sample).  The output y [deg] adds the
 * integrator and the preprocessing inverse back, H(z) = (1 - af)(z - 1)/(z - af) (this is the C copy of H;
 * the Python definition is harness.ident.preprocess.filter_coefficients):
 *     y(k) = y(k-1) + (y_f(k) - af y_f(k-1)) / (1 - af),   y(-1) = y0, y_f(-1) = 0,
 * so y(0) = y0 (as harness.ident.preprocess.diff_filter(..., initial="rest")).  C (c[i]) is stored for completeness
 * and does not affect the simulation.  All signals are zero before the record (zero initial state).
 *
 * Timing: after fmi2ExitInitializationMode the outputs are the values at t_0 (y_f = 0, y = y0).  The master
 * sets u(t_k) and calls fmi2DoStep(t_k, h): the model advances to t_k + h and the outputs are those at
 * t_k + h.  h must be a whole multiple m of Ts: the step then runs m samples with u held (zero-order hold).
 * nk >= 1 makes the model causal (no direct feedthrough: outputs at t_k do not depend on u(t_k)).
 *
 * Coefficients: one binary serves every model.  At instantiation (and fmi2Reset) the start values are the
 * compiled defaults below (equal to fmus/armax/modelDescription.xml), then overridden by the lines
 * "name value" of resources/coefficients.txt when the FMU carries one: harness.ident.export writes it with the
 * same full-precision (repr) values as the start attributes of the exported modelDescription.xml, so the
 * FMU runs the identified model with no parameter set by the importer.  The resources folder is the one the
 * importer passes as fmuResourceLocation to fmi2Instantiate.
 *
 * validate() rejects nk < 1, orders above NMAX, non-finite numbers, Ts <= 0, af outside [0, 1), nonzero
 * coefficients outside the declared orders and an unstable A ("model is unstable", Schur-Cohn test).
 */
#include <errno.h>
#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#include "fmi2common.h"

/* ---------------------------------------------------------- coefficient file */

static double *realParameter(ModelData *d, fmi2ValueReference vr) {
    switch (vr) {
    case vr_Ts: return &d->Ts;
    case vr_af: return &d->af;
    case vr_u_offset: return &d->u_offset;
    case vr_y0: return &d->y0;
    default: break;
    }
    if (vr >= VR_A + 1 && vr <= VR_A + NMAX) return &d->a[vr - VR_A];
    if (vr >= VR_B && vr <= VR_B + NMAX) return &d->b[vr - VR_B];
    if (vr >= VR_C + 1 && vr <= VR_C + NMAX) return &d->c[vr - VR_C];
    return NULL;
}

static int *intParameter(ModelData *d, fmi2ValueReference vr) {
    switch (vr) {
    case vr_na: return &d->na;
    case vr_nb: return &d->nb;
    case vr_nc: return &d->nc;
    case vr_nk: return &d->nk;
    default: return NULL;
    }
}

/* Name of a parameter value reference ("a[3]", "Ts", ...) into buf. */
static const char *parameterName(fmi2ValueReference vr, char *buf, size_t len) {
    static const char *names[] = {"Ts", "na", "nb", "nc", "nk", "af", "u_offset", "y0"};
    if (vr <= vr_y0) return names[vr];
    if (vr >= VR_C) snprintf(buf, len, "c[%u]", (unsigned)(vr - VR_C));
    else if (vr >= VR_B) snprintf(buf, len, "b[%u]", (unsigned)(vr - VR_B));
    else snprintf(buf, len, "a[%u]", (unsigned)(vr - VR_A));
    return buf;
}

/* Value reference of a parameter name; -1 when unknown. */
static long parameterReference(const char *name) {
    static const char *names[] = {"Ts", "na", "nb", "nc", "nk", "af", "u_offset", "y0"};
    char arr, close, extra;
    int idx;
    size_t i;
    for (i = 0; i < sizeof(names) / sizeof(names[0]); i++)
        if (strcmp(name, names[i]) == 0) return (long)i;
    if (sscanf(name, "%c[%d%c%c", &arr, &idx, &close, &extra) != 3 || close != ']' || idx < 0 || idx > NMAX)
        return -1;
    if (arr == 'a' && idx >= 1) return VR_A + idx;
    if (arr == 'b') return VR_B + idx;
    if (arr == 'c' && idx >= 1) return VR_C + idx;
    return -1;
}

/* Read "name value" lines; on a problem write one line into d->load_error. */
static void loadCoefficients(ModelInstance *comp) {
    ModelData *d = &comp->data;
    char path[4096], line[512], name[64], value[128], *end;
    int lineno = 0;
    FILE *f;
    if (!resourceFile(comp, COEFFICIENT_FILE, path, sizeof(path))) return;
    f = fopen(path, "r");
    if (!f) return; /* the generic FMU: compiled defaults */
    while (fgets(line, sizeof(line), f)) {
        long vr;
        lineno++;
        if (line[0] == '#' || line[strspn(line, " \t\r\n")] == '\0') continue;
        if (sscanf(line, "%63s %127s", name, value) != 2) {
            snprintf(d->load_error, sizeof(d->load_error), "%s line %d: expected 'name value'", COEFFICIENT_FILE,
                     lineno);
            break;
        }
        vr = parameterReference(name);
        errno = 0;
        if (vr < 0) {
            snprintf(d->load_error, sizeof(d->load_error), "%s line %d: unknown parameter '%s'", COEFFICIENT_FILE,
                     lineno, name);
            break;
        }
        if (intParameter(d, (fmi2ValueReference)vr)) {
            long v = strtol(value, &end, 10);
            if (*end != '\0' || errno || v < -1000000 || v > 1000000) {
                snprintf(d->load_error, sizeof(d->load_error), "%s line %d: %s = '%s' is not an integer",
                         COEFFICIENT_FILE, lineno, name, value);
                break;
            }
            *intParameter(d, (fmi2ValueReference)vr) = (int)v;
        } else {
            double v = strtod(value, &end);
            if (*end != '\0') {
                snprintf(d->load_error, sizeof(d->load_error), "%s line %d: %s = '%s' is not a number",
                         COEFFICIENT_FILE, lineno, name, value);
                break;
            }
            *realParameter(d, (fmi2ValueReference)vr) = v;
        }
    }
    fclose(f);
}

/* ------------------------------------------------------------- life cycle */

void setStartValues(ModelInstance *comp) {
    ModelData *d = &comp->data;
    memset(d, 0, sizeof(*d));
    d->Ts = 0.02;
    d->na = 1;
    d->nb = 1;
    d->nc = 0;
    d->nk = 1;
    d->af = 0.8;
    d->a[1] = -0.5;
    d->b[1] = 0.5;
    loadCoefficients(comp);
}

/* Schur-Cohn (step-down) test: true when every root of 1 + a1 z^-1 + .. + an z^-n lies inside |z| < 1.
   On failure *kbad is the first reflection coefficient with |k| >= 1 (or nan). */
static bool stableA(const double *a, int n, double *kbad) {
    double p[NMAX + 1], q[NMAX + 1];
    int m, i;
    p[0] = 1.0;
    for (i = 1; i <= n; i++) p[i] = a[i];
    for (m = n; m >= 1; m--) {
        const double k = p[m];
        const double den = 1.0 - k * k;
        if (!(fabs(k) < 1.0) || !(den > 0.0)) {
            *kbad = k;
            return false;
        }
        for (i = 0; i < m; i++) q[i] = (p[i] - k * p[m - i]) / den;
        for (i = 0; i < m; i++) p[i] = q[i];
    }
    return true;
}

bool validate(ModelInstance *comp, char *msg, size_t len) {
    const ModelData *d = &comp->data;
    double kbad = 0.0;
    int i;
    CHECK(d->load_error[0] == '\0', "%s", d->load_error);
    CHECK(isfinite(d->Ts) && d->Ts > 0, "invalid parameter Ts = %g: must be a finite time > 0 s", d->Ts);
    CHECK(d->na >= 0 && d->na <= NMAX, "invalid parameter na = %d: must be in 0..%d", d->na, NMAX);
    CHECK(d->nc >= 0 && d->nc <= NMAX, "invalid parameter nc = %d: must be in 0..%d", d->nc, NMAX);
    CHECK(d->nk >= 1, "invalid parameter nk = %d: must be >= 1 (causal: y(t_k) may not depend on u(t_k))", d->nk);
    CHECK(d->nb >= 0 && d->nk + d->nb - 1 <= NMAX,
          "invalid parameters nb = %d, nk = %d: need nb >= 0 and nk + nb - 1 <= %d", d->nb, d->nk, NMAX);
    CHECK(isfinite(d->af) && d->af >= 0 && d->af < 1, "invalid parameter af = %g: must be in [0, 1)", d->af);
    CHECK(isfinite(d->u_offset), "invalid parameter u_offset = %g: must be finite", d->u_offset);
    CHECK(isfinite(d->y0), "invalid parameter y0 = %g: must be finite", d->y0);
    for (i = 0; i <= NMAX; i++) {
        CHECK(isfinite(d->a[i]), "invalid parameter a[%d] = %g: must be finite", i, d->a[i]);
        CHECK(isfinite(d->b[i]), "invalid parameter b[%d] = %g: must be finite", i, d->b[i]);
        CHECK(isfinite(d->c[i]), "invalid parameter c[%d] = %g: must be finite", i, d->c[i]);
        CHECK(i <= d->na || d->a[i] == 0, "invalid parameter a[%d] = %g: must be 0 beyond na = %d", i, d->a[i], d->na);
        CHECK(i <= d->nc || d->c[i] == 0, "invalid parameter c[%d] = %g: must be 0 beyond nc = %d", i, d->c[i], d->nc);
        CHECK((i >= d->nk && i < d->nk + d->nb) || d->b[i] == 0,
              "invalid parameter b[%d] = %g: must be 0 outside nk..nk+nb-1 = %d..%d", i, d->b[i], d->nk,
              d->nk + d->nb - 1);
    }
    CHECK(stableA(d->a, d->na, &kbad),
          "model is unstable: A(q) has a root on or outside the unit circle (Schur-Cohn reflection coefficient %g)",
          kbad);
    return true;
}

fmi2Status initialize(ModelInstance *comp) {
    ModelData *d = &comp->data;
    memset(d->ud, 0, sizeof(d->ud));
    memset(d->yf, 0, sizeof(d->yf));
    d->k = 0;
    d->y_f = 0.0; /* nk >= 1 and zero initial state */
    d->y = d->y0;
    return fmi2OK;
}

void releaseModel(ModelInstance *comp) { (void)comp; /* nothing allocated */ }

void calculateValues(ModelInstance *comp) { (void)comp; /* outputs change only at samples (doStep) */ }

/* One sample: u(k) -> outputs at k + 1.  ud[j] = u_d(k - j), yf[i] = y_f(k + 1 - i). */
static void sample(ModelData *d, double u) {
    const int jend = d->nk + d->nb;
    double acc = 0.0;
    int i, j;
    for (j = NMAX; j > 0; j--) d->ud[j] = d->ud[j - 1];
    d->ud[0] = u - d->u_offset;
    for (j = d->nk; j < jend; j++) acc += d->b[j] * d->ud[j - 1]; /* u_d(k + 1 - j) */
    for (i = NMAX; i > 1; i--) d->yf[i] = d->yf[i - 1];
    d->yf[1] = d->y_f; /* y_f(k) */
    for (i = 1; i <= d->na; i++) acc -= d->a[i] * d->yf[i];
    d->y += (acc - d->af * d->y_f) / (1.0 - d->af);
    d->y_f = acc;
    d->k++;
}

fmi2Status doStep(ModelInstance *comp, double t, double h) {
    ModelData *d = &comp->data;
    const double m = floor(h / d->Ts + 0.5);
    const double expected = comp->startTime + (double)d->k * d->Ts;
    long long i;
    if (m < 1 || fabs(h - m * d->Ts) > 1e-6 * d->Ts) {
        logError(comp, "fmi2DoStep: communication step %.17g s is not a whole multiple of Ts = %.17g s", h, d->Ts);
        return fmi2Error;
    }
    if (fabs(t - expected) > 1e-3 * d->Ts) {
        logError(comp, "fmi2DoStep: t = %.17g s does not continue the last communication point %.17g s", t,
                 expected);
        return fmi2Error;
    }
    if (!isfinite(d->u)) {
        logError(comp, "input u is not finite at t = %g s", t);
        return fmi2Error;
    }
    for (i = 0; i < (long long)m; i++) sample(d, d->u);
    return fmi2OK;
}

/* ------------------------------------------------------------ get / set */

fmi2Status getFloat64(ModelInstance *comp, fmi2ValueReference vr, double *value) {
    ModelData *d = &comp->data;
    double *p = realParameter(d, vr);
    if (p) {
        *value = *p;
        return fmi2OK;
    }
    switch (vr) {
    case vr_u: *value = d->u; return fmi2OK;
    case vr_y_f: *value = d->y_f; return fmi2OK;
    case vr_y: *value = d->y; return fmi2OK;
    default: return unknownReference(comp, "Real", vr);
    }
}

fmi2Status setFloat64(ModelInstance *comp, fmi2ValueReference vr, double value) {
    ModelData *d = &comp->data;
    char buf[16];
    double *p = realParameter(d, vr);
    if (p) {
        if (!parametersSettable(comp)) return fixedAfterInit(comp, parameterName(vr, buf, sizeof(buf)));
        *p = value;
        return fmi2OK;
    }
    switch (vr) {
    case vr_u: d->u = value; return fmi2OK;
    case vr_y_f:
    case vr_y: logError(comp, "output value reference %u cannot be set", (unsigned)vr); return fmi2Error;
    default: return unknownReference(comp, "Real", vr);
    }
}

fmi2Status getInt32(ModelInstance *comp, fmi2ValueReference vr, int *value) {
    int *p = intParameter(&comp->data, vr);
    if (!p) return unknownReference(comp, "Integer", vr);
    *value = *p;
    return fmi2OK;
}

fmi2Status setInt32(ModelInstance *comp, fmi2ValueReference vr, int value) {
    char buf[16];
    int *p = intParameter(&comp->data, vr);
    if (!p) return unknownReference(comp, "Integer", vr);
    if (!parametersSettable(comp)) return fixedAfterInit(comp, parameterName(vr, buf, sizeof(buf)));
    *p = value;
    return fmi2OK;
}
