/*
 * controller: a lab's digital controller, sampled at sample_rate [Hz], the loop's u = f(ref, measured angles).
 *
 * Sample k is computed at t_k + compute_time (t_k = k / sample_rate), in the fmi2DoStep(t, h) whose [t, t + h)
 * holds that instant, from the inputs set before that call; the outputs then hold it (no direct feedthrough: they
 * change only in fmi2DoStep).  With compute_time = 0 and the master's order (set ref and the DAQ's samples at t_k ->
 * controller.doStep(t_k) -> read u -> DAQ command) u_k acts over [t_k, t_k+1), as a lab controller that computes
 * and writes its command within the sample.  A master that steps every FMU at once (Jacobi) at a quarter of the
 * sample period with compute_time = half of it reads the DAQ's samples of t_k one step later and hands u_k to the
 * DAQ before the sample ends: the same loop.  Every sample instant must be a communication point: a step h with
 * h x sample_rate neither a whole number nor the inverse of one is an error.
 *
 * Angles from the DAQ's volts (the controller's own calibration, as the lab's script has it):
 *     theta = theta_gain (theta_v - theta_offset),  alpha = alpha_gain (alpha_v - alpha_offset)   [deg -> rad]
 * Velocities by filtered differences, as lab controllers compute them:
 *     v_k = a v_(k-1) + (1 - a) (x_k - x_(k-1)) / Ts,  a = exp(-2 pi cutoff Ts),  v_0 = 0
 * kind 1, state feedback on x = (theta, alpha, theta_dot, alpha_dot), x_ref = (ref, 0, 0, 0):
 *     u = k_theta (ref - theta) - k_alpha alpha - k_theta_dot theta_dot - k_alpha_dot alpha_dot
 * kind 2, PID on theta (derivative on the measurement: a step of ref gives no kick):
 *     u = kp e + ki I - kd theta_dot,  e = ref - theta,  I += Ts e after the sample unless u was limited
 * kind 3, LQG: a steady-state Kalman filter in current form on y = (theta, alpha) and state feedback on its
 * estimate, n = lqg_n states (A, B, C, L, K, N, X0 the lqg_ arrays):
 *     x_bar_k = A x_hat_(k-1) + B u_(k-1)   (the first sample: x_bar_0 = X0 y_0)
 *     x_hat_k = x_bar_k + L (y_k - C x_bar_k)
 *     u_k = K (N ref_k - x_hat_k)
 *   u_(k-1) the command the controller wrote (after its clamp)
 * then u = clamp(u, +-u_limit) (u_limit = 0: none).
 * harness.rig.controller.law is the same computation in numpy (the test oracle).
 */
#include <math.h>
#include <string.h>

#include "fmi2common.h"

#define DEG2RAD 0.017453292519943295
#define TWO_PI 6.283185307179586

void setStartValues(ModelInstance *comp) {
    ModelData *d = &comp->data;
    memset(d, 0, sizeof(*d));
    REAL_PARAMETERS(SET_START)
    INTEGER_PARAMETERS(SET_START)
}

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
    CHECK(d->kind == KIND_STATE_FEEDBACK || d->kind == KIND_PID || d->kind == KIND_LQG,
          "invalid parameter kind = %d: must be 1 (state feedback), 2 (PID) or 3 (LQG)", d->kind);
    CHECK(d->lqg_n >= 0 && d->lqg_n <= NX_MAX, "invalid parameter lqg_n = %d: must be in 0..%d", d->lqg_n, NX_MAX);
    CHECK(d->kind != KIND_LQG || d->lqg_n >= 1, "invalid parameter lqg_n = %d: an LQG (kind 3) needs >= 1 state",
          d->lqg_n);
#define ARRAY_FINITE(name, vr0, rows, cols)                                                                       \
    for (i = 0; i < (size_t)((rows) * (cols)); i++)                                                              \
        CHECK(isfinite(d->name[i]), "invalid parameter %s (element %u) = %g: must be finite", #name, (unsigned)i, \
              d->name[i]);
    ARRAY_PARAMETERS(ARRAY_FINITE)
#undef ARRAY_FINITE
    CHECK(d->sample_rate > 0, "invalid parameter sample_rate = %g: must be > 0", d->sample_rate);
    CHECK(d->cutoff > 0, "invalid parameter cutoff = %g: must be > 0", d->cutoff);
    CHECK(d->u_limit >= 0, "invalid parameter u_limit = %g: must be >= 0 (0 = none)", d->u_limit);
    CHECK(d->theta_gain != 0, "invalid parameter theta_gain = %g: must be non-zero", d->theta_gain);
    CHECK(d->alpha_gain != 0, "invalid parameter alpha_gain = %g: must be non-zero", d->alpha_gain);
    CHECK(d->compute_time >= 0 && d->compute_time * d->sample_rate < 1,
          "invalid parameter compute_time = %g: must be in [0, 1/sample_rate)", d->compute_time);
    return true;
}

/* LQG: the estimate at the measured angles th, al [rad] into xhat (from the last sample's estimate and command, or
   X0 y at the first sample), and the command K (N ref - xhat) before the clamp */
static double lqgSample(const ModelData *d, double th, double al, double *xhat) {
    const int n = d->lqg_n;
    double xbar[NX_MAX], e[2];
    double raw = 0.0;
    int i, j;
    for (i = 0; i < n; i++) {
        double acc = 0.0;
        if (d->have_last) {
            for (j = 0; j < n; j++) acc += d->lqg_A[i * NX_MAX + j] * d->xhat[j];
            acc += d->lqg_B[i] * d->u_prev;
        } else {
            acc = d->lqg_X0[i * 2] * th + d->lqg_X0[i * 2 + 1] * al;
        }
        xbar[i] = acc;
    }
    e[0] = th;
    e[1] = al;
    for (j = 0; j < n; j++) {
        e[0] -= d->lqg_C[j] * xbar[j];
        e[1] -= d->lqg_C[NX_MAX + j] * xbar[j];
    }
    for (i = 0; i < n; i++) {
        xhat[i] = xbar[i] + d->lqg_L[i * 2] * e[0] + d->lqg_L[i * 2 + 1] * e[1];
        raw += d->lqg_K[i] * (d->lqg_N[i] * d->ref - xhat[i]);
    }
    return raw;
}

/* the sample at the current inputs; commit = advance the controller's state to it */
static void takeSample(ModelData *d, int commit) {
    const double Ts = 1.0 / d->sample_rate;
    const double a = d->filter_a;
    const double lim = d->u_limit > 0 ? d->u_limit : INFINITY;
    const double th = d->theta_gain * (d->theta_v - d->theta_offset) * DEG2RAD;
    const double al = d->alpha_gain * (d->alpha_v - d->alpha_offset) * DEG2RAD;
    const double dth = d->have_last ? (th - d->last_theta) / Ts : d->theta_dot_start;
    const double dal = d->have_last ? (al - d->last_alpha) / Ts : d->alpha_dot_start;
    const double vth = a * d->v_theta + (1.0 - a) * dth;
    const double val = a * d->v_alpha + (1.0 - a) * dal;
    double raw, u;
    double xhat[NX_MAX];
    if (d->kind == KIND_STATE_FEEDBACK)
        raw = d->k_theta * (d->ref - th) - d->k_alpha * al - d->k_theta_dot * vth - d->k_alpha_dot * val;
    else if (d->kind == KIND_PID)
        raw = d->kp * (d->ref - th) + d->ki * d->integral - d->kd * vth;
    else
        raw = lqgSample(d, th, al, xhat);
    u = fmin(fmax(raw, -lim), lim);
    d->u = u;
    d->theta = th;
    d->alpha = al;
    d->theta_dot = vth;
    d->alpha_dot = val;
    if (!commit) return;
    if (d->kind == KIND_PID && u == raw) d->integral += Ts * (d->ref - th); /* anti-windup: hold while limited */
    if (d->kind == KIND_LQG) {
        memcpy(d->xhat, xhat, sizeof(xhat));
        d->u_prev = u;
    }
    d->last_theta = th;
    d->last_alpha = al;
    d->v_theta = vth;
    d->v_alpha = val;
    d->have_last = 1;
}

/* ------------------------------------------------------------ life cycle */

fmi2Status initialize(ModelInstance *comp) {
    ModelData *d = &comp->data;
    d->have_last = 0;
    d->v_theta = d->theta_dot_start; /* the velocity filter starts at the rates given (0: at rest) */
    d->v_alpha = d->alpha_dot_start;
    d->integral = 0.0;
    memset(d->xhat, 0, sizeof(d->xhat));
    d->u_prev = 0.0;
    d->filter_a = exp(-TWO_PI * d->cutoff * (1.0 / d->sample_rate)); /* with Ts as takeSample computes it */
    d->next_sample = (int64_t)ceil(comp->startTime * d->sample_rate - 1e-6);
    takeSample(d, 0); /* preview of the first sample */
    return fmi2OK;
}

void releaseModel(ModelInstance *comp) { (void)comp; }

fmi2Status doStep(ModelInstance *comp, double t, double h) {
    ModelData *d = &comp->data;
    const double fs = d->sample_rate;
    const double lag = d->compute_time * fs;      /* the computing instant after t_k, in samples */
    const double kEnd = (t + h) * fs - lag - 1e-6; /* computing instants strictly before t + h */
    int64_t k;
    if (!stepFitsSampleRate(comp, h, fs)) return fmi2Error;
    if (!isfinite(d->ref) || !isfinite(d->theta_v) || !isfinite(d->alpha_v)) {
        logError(comp, "input ref, theta_v or alpha_v is not finite at t = %g s", t);
        return fmi2Error;
    }
    k = (int64_t)ceil(t * fs - lag - 1e-6);
    if (k < d->next_sample) k = d->next_sample;
    for (; (double)k < kEnd; k++) takeSample(d, 1);
    if (k > d->next_sample) d->next_sample = k;
    return fmi2OK;
}

void calculateValues(ModelInstance *comp) { (void)comp; /* outputs change only at samples */ }

/* ------------------------------------------------------- get / set */

static double *realParameter(ModelData *d, fmi2ValueReference vr, const char **pname) {
    switch (vr) {
        REAL_PARAMETERS(PARAMETER_CASE)
    default: return NULL;
    }
}

static double *arrayParameter(ModelData *d, fmi2ValueReference vr, const char **pname) {
    ARRAY_PARAMETERS(ARRAY_CASE)
    return NULL;
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
    double *p;
    switch (vr) { /* the inputs and outputs first: the master reads them every sample */
        INPUTS(GET_CASE)
        OUTPUTS(GET_CASE)
    default: break;
    }
    p = realParameter(d, vr, &name);
    if (!p) p = arrayParameter(d, vr, &name);
    if (!p) return unknownReference(comp, "Real", vr);
    *value = *p;
    return fmi2OK;
}

fmi2Status setFloat64(ModelInstance *comp, fmi2ValueReference vr, double value) {
    ModelData *d = &comp->data;
    const char *name;
    double *p;
    switch (vr) { /* the inputs first: the master sets them every sample */
    case vr_ref: d->ref = value; return fmi2OK;
    case vr_theta_v: d->theta_v = value; return fmi2OK;
    case vr_alpha_v: d->alpha_v = value; return fmi2OK;
    default: break;
    }
    p = realParameter(d, vr, &name);
    if (!p) p = arrayParameter(d, vr, &name);
    if (p) {
        if (!parametersSettable(comp)) return fixedAfterInit(comp, name);
        *p = value;
        return fmi2OK;
    }
    if (vr >= vr_u && vr <= vr_alpha_dot) {
        logError(comp, "output value reference %u cannot be set", (unsigned)vr);
        return fmi2Error;
    }
    return unknownReference(comp, "Real", vr);
}

fmi2Status getInt32(ModelInstance *comp, fmi2ValueReference vr, int *value) {
    const char *name;
    int *p = intParameter(&comp->data, vr, &name);
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
