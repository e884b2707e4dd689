/* The co-simulation master's step loops (not an FMU): the plant, DAQ and controller FMUs coupled sample by
 * sample through their own fmi2GetReal / fmi2SetReal / fmi2DoStep, which the caller (harness/fmu/cosim.py) hands
 * over as function pointers of the loaded binaries. The order of the calls is the one the module docstring of
 * cosim.py states; these loops only keep Python's interpreter out of the per-sample calls.
 *
 * Every doStep status above fmi2Warning stops the loop: the return value says which FMU refused (FAIL_*) and
 * *at is the sample; the caller reads that FMU's log. A closed loop that leaves the rig's range returns DIVERGED
 * with *at the sample and div[0..2] = theta, reference, alpha [rad].
 */
#include <math.h>
#include <stddef.h>

typedef int (*GetReal)(void *c, const unsigned int *vr, size_t n, double *value);
typedef int (*SetReal)(void *c, const unsigned int *vr, size_t n, const double *value);
typedef int (*DoStep)(void *c, double t, double h, int no_set_prior_state);

/* one loaded FMU instance: its component and the three functions of its binary */
typedef struct {
    void *component;
    GetReal get;
    SetReal set;
    DoStep step;
} Unit;

enum { DONE = 0, FAIL_PLANT = 1, FAIL_DAQ = 2, FAIL_CONTROLLER = 3, DIVERGED = 4 };

#if defined(_WIN32)
#define EXPORT __declspec(dllexport)
#else
#define EXPORT
#endif

/* Open loop, n samples at Ts [s]. vr: plant in (u, tau_tip), plant out (theta, alpha, alpha_gauge, theta_dot),
 * DAQ in (u, theta, alpha_gauge), DAQ out (u_plant, theta_v, alpha_v). out: n x 6 row-major
 * (u_plant, theta_v, alpha_v, theta, alpha, theta_dot), angles in rad. */
EXPORT int run_open(const Unit *pl, const Unit *dq, const unsigned int *p_in, const unsigned int *p_out,
                    const unsigned int *d_in, const unsigned int *d_out, const double *u, const double *tau, long n,
                    double Ts, double *out, long *at, int *status) {
    double pin[2], pout[4], din[3], dout[3], up;
    for (long k = 0; k < n; k++) {
        double t = (double)k * Ts;
        pl->get(pl->component, p_out, 4, pout);
        din[0] = u[k]; din[1] = pout[0]; din[2] = pout[2];
        dq->set(dq->component, d_in, 3, din);
        dq->get(dq->component, d_out, 1, &up); /* the command over [t_k, t_k+1) */
        int s = dq->step(dq->component, t, Ts, 1);
        if (s > 1) { *at = k; *status = s; return FAIL_DAQ; }
        dq->get(dq->component, d_out, 3, dout);
        dout[0] = up;
        pin[0] = up; pin[1] = tau[k];
        pl->set(pl->component, p_in, 2, pin);
        double *row = out + 6 * k;
        row[0] = dout[0]; row[1] = dout[1]; row[2] = dout[2]; row[3] = pout[0]; row[4] = pout[1]; row[5] = pout[3];
        s = pl->step(pl->component, t, Ts, 1);
        if (s > 1) { *at = k; *status = s; return FAIL_PLANT; }
    }
    return DONE;
}

/* Closed loop, n samples at Ts [s] tracking ref [rad]. vr as run_open plus: DAQ measured inputs (theta,
 * alpha_gauge), DAQ samples (theta_v, alpha_v), DAQ command u, controller in (ref, theta_v, alpha_v) and out (u).
 * The loop has diverged when |alpha| > lim_alpha or |theta - ref| > lim_theta [rad] before a step. out: n x 7
 * (u, u_plant, theta_v, alpha_v, theta, alpha, theta_dot). */
EXPORT int run_closed(const Unit *pl, const Unit *dq, const Unit *ct, const unsigned int *p_in,
                      const unsigned int *p_out, const unsigned int *d_meas, const unsigned int *d_samp,
                      const unsigned int *d_u, const unsigned int *d_out, const unsigned int *c_in,
                      const unsigned int *c_out, const double *ref, long n, double Ts, double lim_alpha,
                      double lim_theta, double *out, long *at, int *status, double *div) {
    double pin[2] = {0.0, 0.0}, pout[4], meas[2], samp[2], cin[3], cu[1], dout[3], up;
    for (long k = 0; k < n; k++) {
        double t = (double)k * Ts;
        pl->get(pl->component, p_out, 4, pout);
        if (fabs(pout[1]) > lim_alpha || fabs(pout[0] - ref[k]) > lim_theta) {
            *at = k; div[0] = pout[0]; div[1] = ref[k]; div[2] = pout[1];
            return DIVERGED;
        }
        meas[0] = pout[0]; meas[1] = pout[2];
        dq->set(dq->component, d_meas, 2, meas);
        dq->get(dq->component, d_samp, 2, samp); /* the DAQ's preview of its samples at t_k */
        cin[0] = ref[k]; cin[1] = samp[0]; cin[2] = samp[1];
        ct->set(ct->component, c_in, 3, cin);
        int s = ct->step(ct->component, t, Ts, 1);
        if (s > 1) { *at = k; *status = s; return FAIL_CONTROLLER; }
        ct->get(ct->component, c_out, 1, cu);
        dq->set(dq->component, d_u, 1, cu);
        dq->get(dq->component, d_out, 1, &up); /* the command over [t_k, t_k+1) */
        s = dq->step(dq->component, t, Ts, 1);
        if (s > 1) { *at = k; *status = s; return FAIL_DAQ; }
        dq->get(dq->component, d_out, 3, dout);
        dout[0] = up;
        pin[0] = up;
        pl->set(pl->component, p_in, 2, pin);
        double *row = out + 7 * k;
        row[0] = cu[0]; row[1] = dout[0]; row[2] = dout[1]; row[3] = dout[2];
        row[4] = pout[0]; row[5] = pout[1]; row[6] = pout[3];
        s = pl->step(pl->component, t, Ts, 1);
        if (s > 1) { *at = k; *status = s; return FAIL_PLANT; }
    }
    return DONE;
}
