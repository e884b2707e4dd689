/*
 * daq: the rig's sensors and data acquisition, sampled and held at sample_rate [Hz].
 *
 * A sample is taken at every instant t_k = k / sample_rate with t_k in [t, t + h) of fmi2DoStep(t, h),
 * from the inputs set before that call; the outputs then hold that sample.  So with the master's order
 * (set inputs at t_k -> daq.doStep(t_k) -> read outputs) the outputs are the samples taken at t_k.
 * fmi2ExitInitializationMode previews the first sample from the inputs set before it (without pushing
 * it into the delay line; the doStep at the start time takes it for real, with the same noise).  Likewise,
 * reading theta_v or alpha_v at a sample instant after theta or alpha_gauge were set and before the next doStep
 * previews the readings of that sample (same noise, nothing committed): direct feedthrough at the sample instants;
 * between them the readings hold, whatever is set.
 *
 * The command of sample k is the last u set before the sample ends (before t_(k+1)): at a communication step of
 * 1 / sample_rate the u set at t_k, at a finer step the controller's command written within the sample.  u_plant
 * is the command over [t, next communication point): after fmi2DoStep(t, h) the command of the sample holding
 * t + h.  With delay_samples = d >= 1 that is the command of d samples before, known since that sample ended: no
 * direct feedthrough, the same in a master that steps every FMU at once (Jacobi) as in one that orders them.
 * With d = 0 the DAC writes u as soon as it is set (u_plant follows u on fmi2SetReal: direct feedthrough), so only
 * a master that sets u before it reads u_plant gives a loop without latency.
 * Every sample instant must be a communication point: a step h with h x sample_rate neither a whole number nor
 * the inverse of one is an error.
 *
 * Command path:  u -> DAC quantisation (dac_bits over +-dac_range, 0 = ideal) -> clamp +-out_limit
 *                -> delay by delay_samples samples (zeros before the first command) -> u_plant [V].
 * Potentiometer: theta [rad] -> degrees wrapped to [-180, 180); on the track v = wrapped / pot_gain +
 *                pot_offset; in the dead band (|wrapped| > 180 - pot_deadband / 2) the wiper is off the
 *                track and reads the track end sign(wrapped) (180 - pot_deadband / 2) / pot_gain + offset.
 * Encoder (theta_sensor = 1): theta in degrees rounded to whole counts of 360 / encoder_counts, no wrap, no
 *                dead band, no noise, no ADC; reported on the pot's scale, v = counted / pot_gain + pot_offset,
 *                so that one calibration reads both.
 *                A linearity error (pot_bow) bows the track: wrapped + pot_bow 180 sin(pi wrapped / 180) degrees.
 * Strain gauge:  v = gauge_offset + alpha_deg / gauge_gain (1 + gauge_cubic (alpha_deg/10)^2): the bridge's
 *                zero error (gauge_offset) is electrical, outside its nonlinearity;
 *                a gain drift (gauge_drift [1/s]) scales it about the offset: offset + (v - offset)(1 + drift t_k);
 *                then the amplifier's first-order low-pass of time constant gauge_tau [s], taken at the samples
 *                (y_k = y_(k-1) + (1 - exp(-1 / (sample_rate gauge_tau))) (v_k - y_(k-1)), y_0 = v_0; 0 = none),
 *                read gauge_delay samples late (y_(k - gauge_delay); y_0 before the first sample).
 * Then white Gaussian noise (noise_theta, noise_alpha V rms), then ADC quantisation (round to
 * LSB = 2 adc_range / 2^adc_bits and clamp to +-adc_range; 0 bits = ideal, no clamp).
 * Noise: counter-based generator, splitmix64 of (seed, stream, sample index) + Box-Muller, so the noise
 * of sample k depends only on seed and k (same seed -> identical bytes, independent of step sizes).  The
 * deviates of the last NOISE_TABLES streams are kept across fmi2Reset (a fit replays the same seeds many times)
 * and freed with the instance.
 */
#include <math.h>
#include <stdio.h>
#include <string.h>

#include "fmi2common.h"
#include "noise.h"

#define RAD2DEG 57.29577951308232
#define PI 3.141592653589793

void setStartValues(ModelInstance *comp) {
    ModelData *d = &comp->data;
    double *line = d->delay_line, *gline = d->gauge_line; /* keep the pointers: releaseModel frees them */
    NoiseTable noise[NOISE_TABLES];                        /* and the noise tables, kept across fmi2Reset */
    const int next = d->noise_next;
    memcpy(noise, d->noise, sizeof(noise));
    memset(d, 0, sizeof(*d));
    d->delay_line = line;
    d->gauge_line = gline;
    memcpy(d->noise, noise, sizeof(noise));
    d->noise_next = next;
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
    CHECK(d->sample_rate > 0, "invalid parameter sample_rate = %g: must be > 0", d->sample_rate);
    CHECK(d->dac_bits >= 0 && d->dac_bits <= 52, "invalid parameter dac_bits = %d: must be in 0..52 (0 = ideal)",
          d->dac_bits);
    CHECK(d->dac_range > 0, "invalid parameter dac_range = %g: must be > 0", d->dac_range);
    CHECK(d->out_limit > 0, "invalid parameter out_limit = %g: must be > 0", d->out_limit);
    CHECK(d->delay_samples >= 0 && d->delay_samples <= MAX_DELAY_SAMPLES,
          "invalid parameter delay_samples = %d: must be in 0..%d", d->delay_samples, MAX_DELAY_SAMPLES);
    CHECK(d->pot_gain != 0, "invalid parameter pot_gain = %g: must be non-zero", d->pot_gain);
    CHECK(d->pot_deadband >= 0 && d->pot_deadband < 360, "invalid parameter pot_deadband = %g: must be in [0, 360)",
          d->pot_deadband);
    CHECK(d->gauge_gain != 0, "invalid parameter gauge_gain = %g: must be non-zero", d->gauge_gain);
    CHECK(d->gauge_delay >= 0 && d->gauge_delay <= MAX_DELAY_SAMPLES,
          "invalid parameter gauge_delay = %d: must be in 0..%d", d->gauge_delay, MAX_DELAY_SAMPLES);
    CHECK(d->gauge_tau >= 0, "invalid parameter gauge_tau = %g: must be >= 0", d->gauge_tau);
    CHECK(d->adc_bits >= 0 && d->adc_bits <= 52, "invalid parameter adc_bits = %d: must be in 0..52 (0 = ideal)",
          d->adc_bits);
    CHECK(d->adc_range > 0, "invalid parameter adc_range = %g: must be > 0", d->adc_range);
    CHECK(d->noise_theta >= 0, "invalid parameter noise_theta = %g: must be >= 0", d->noise_theta);
    CHECK(d->noise_alpha >= 0, "invalid parameter noise_alpha = %g: must be >= 0", d->noise_alpha);
    CHECK(d->theta_sensor == 0 || d->theta_sensor == 1,
          "invalid parameter theta_sensor = %d: must be 0 (potentiometer) or 1 (encoder)", d->theta_sensor);
    CHECK(d->encoder_counts > 0, "invalid parameter encoder_counts = %g: must be > 0", d->encoder_counts);
    return true;
}

/* ---------------------------------------------------------------- noise */

/* the table kept for stream key: the one that holds it, else the next in turn, emptied for it */
static int noiseTable(ModelData *d, uint64_t key) {
    int i;
    for (i = 0; i < NOISE_TABLES; i++)
        if (d->noise[i].used && d->noise[i].key == key) return i;
    i = d->noise_next;
    d->noise_next = (i + 1) % NOISE_TABLES;
    d->noise[i].key = key;
    d->noise[i].used = 1;
    d->noise[i].n = 0;
    return i;
}

/* gauss(key, k) of stream s (NOISE_THETA, NOISE_ALPHA) from its table, which takes the deviates in order */
static double streamGauss(ModelInstance *comp, int s, uint64_t key, int64_t k) {
    NoiseTable *t = &comp->data.noise[comp->data.noise_slot[s]];
    if (k < t->n) return t->v[k];
    if (k != t->n || k >= NOISE_TABLE_MAX) return gauss(key, k); /* not the next in order: drawn alone */
    if (t->n == t->cap) {
        const int64_t cap = t->cap ? (2 * t->cap < NOISE_TABLE_MAX ? 2 * t->cap : NOISE_TABLE_MAX) : 4096;
        double *v = (double *)allocateModelMemory(comp, (size_t)cap, sizeof(double));
        if (!v) return gauss(key, k);
        if (t->n) memcpy(v, t->v, (size_t)t->n * sizeof(double));
        freeModelMemory(comp, t->v);
        t->v = v;
        t->cap = cap;
    }
    t->v[t->n++] = gauss(key, k);
    return t->v[k];
}

/* ------------------------------------------------------------ converters */

static double quantize(double v, int bits, double range) {
    double lsb;
    if (bits <= 0) return v;
    lsb = 2.0 * range / ldexp(1.0, bits);
    v = round(v / lsb) * lsb;
    return fmin(fmax(v, -range), range);
}

static double potVoltage(const ModelData *d, double theta) {
    const double edge = 180.0 - 0.5 * d->pot_deadband;
    double w = fmod(theta * RAD2DEG + 180.0, 360.0);
    if (w < 0) w += 360.0;
    w -= 180.0; /* [-180, 180) */
    if (fabs(w) > edge) w = (w > 0 ? edge : -edge);
    if (d->pot_bow != 0) w += d->pot_bow * 180.0 * sin(PI * w / 180.0); /* linearity error */
    return w / d->pot_gain + d->pot_offset;
}

/* the gauge's reading of deflection alpha [rad] at time t [s] */
static double gaugeVoltage(const ModelData *d, double alpha, double t) {
    const double a = alpha * RAD2DEG;
    const double r = a / 10.0;
    const double v = d->gauge_offset + a / d->gauge_gain * (1.0 + d->gauge_cubic * r * r);
    if (d->gauge_drift == 0) return v;
    return d->gauge_offset + (v - d->gauge_offset) * (1.0 + d->gauge_drift * t); /* gain drift about the offset */
}

static double command(const ModelData *d, double u) {
    const double v = quantize(u, d->dac_bits, d->dac_range);
    return fmin(fmax(v, -d->out_limit), d->out_limit);
}

static double encoderVoltage(const ModelData *d, double theta) {
    const double step = 360.0 / d->encoder_counts;
    return round(theta * RAD2DEG / step) * step / d->pot_gain + d->pot_offset;
}

/* the gauge's low-pass output for the next sample from its input v; commit: that sample is taken for real */
static double gaugeLowPass(ModelData *d, double v, int commit) {
    const double y = (d->gauge_tau > 0 && d->gauge_lp_set) ? d->gauge_lp + d->gauge_c * (v - d->gauge_lp) : v;
    if (commit) {
        d->gauge_lp = y;
        d->gauge_lp_set = 1;
    }
    return y;
}

/* the gauge's reading gauge_delay samples before the one of input v (before the first sample: the first's) */
static double gaugeDelay(ModelData *d, double v, int commit, int first) {
    double y;
    int i;
    if (d->gauge_delay == 0) return v;
    if (first) { /* no sample taken yet: the line fills with the first */
        if (commit)
            for (i = 0; i < d->gauge_delay; i++) d->gauge_line[i] = v;
        return v;
    }
    y = d->gauge_line[d->gauge_head];
    if (commit) {
        d->gauge_line[d->gauge_head] = v;
        d->gauge_head = (d->gauge_head + 1) % d->gauge_delay;
    }
    return y;
}

/* the readings theta_v, alpha_v of sample number k of the inputs (commit 0: a preview, nothing kept but itself; a
   commit of the sample just previewed from the same inputs keeps its readings and commits the gauge's filters) */
static void sampleSensors(ModelInstance *comp, int64_t k, int commit) {
    ModelData *d = &comp->data;
    const int first = !d->gauge_lp_set; /* no sample taken for real yet */
    const int previewed = commit && d->previewed && d->preview_k == k;
    double va = previewed ? d->preview_va : gaugeVoltage(d, d->alpha_gauge, (double)k / d->sample_rate);
    d->previewed = !commit, d->preview_k = k, d->preview_va = va;
    va = gaugeDelay(d, gaugeLowPass(d, va, commit), commit, first);
    d->inputs_changed = 0;
    if (previewed) return; /* its readings stand */
    if (d->noise_alpha > 0) va += d->noise_alpha * streamGauss(comp, NOISE_ALPHA, d->key_alpha, k);
    d->alpha_v = quantize(va, d->adc_bits, d->adc_range);
    if (d->theta_sensor == 1) {
        d->theta_v = encoderVoltage(d, d->theta);
    } else {
        double vt = potVoltage(d, d->theta);
        if (d->noise_theta > 0) vt += d->noise_theta * streamGauss(comp, NOISE_THETA, d->key_theta, k);
        d->theta_v = quantize(vt, d->adc_bits, d->adc_range);
    }
}

/* the end of sample k-1: its command (the last u set) enters the delay line */
static void commitCommand(ModelData *d) {
    if (d->delay_samples > 0) {
        d->delay_line[d->delay_head] = command(d, d->u);
        d->delay_head = (d->delay_head + 1) % d->delay_samples;
    }
}

/* u_plant: the command of delay_samples samples before (the oldest in the line), or u itself without delay */
static void holdCommand(ModelData *d) {
    d->u_plant = d->delay_samples > 0 ? d->delay_line[d->delay_head] : command(d, d->u);
}

/* ------------------------------------------------------------ life cycle */

fmi2Status initialize(ModelInstance *comp) {
    ModelData *d = &comp->data;
    const uint64_t s = mix64((uint64_t)(int64_t)d->seed);
    releaseModel(comp);
    if (d->delay_samples > 0) {
        d->delay_line = (double *)allocateModelMemory(comp, (size_t)d->delay_samples, sizeof(double));
        if (!d->delay_line) {
            logError(comp, "out of memory for delay_samples = %d", d->delay_samples);
            return fmi2Error;
        }
        memset(d->delay_line, 0, (size_t)d->delay_samples * sizeof(double));
    }
    d->delay_head = 0;
    if (d->gauge_delay > 0) {
        d->gauge_line = (double *)allocateModelMemory(comp, (size_t)d->gauge_delay, sizeof(double));
        if (!d->gauge_line) {
            logError(comp, "out of memory for gauge_delay = %d", d->gauge_delay);
            return fmi2Error;
        }
    }
    d->gauge_head = 0;
    d->key_theta = mix64(s ^ 0x7468657461ULL); /* "theta" */
    d->key_alpha = mix64(s ^ 0x616c706861ULL); /* "alpha" */
    if (d->noise_theta > 0) d->noise_slot[NOISE_THETA] = noiseTable(d, d->key_theta);
    if (d->noise_alpha > 0) d->noise_slot[NOISE_ALPHA] = noiseTable(d, d->key_alpha);
    d->next_sample = (int64_t)ceil(comp->startTime * d->sample_rate - 1e-6);
    holdCommand(d);
    d->gauge_c = d->gauge_tau > 0 ? 1.0 - exp(-1.0 / (d->sample_rate * d->gauge_tau)) : 1.0;
    d->gauge_lp_set = 0;
    sampleSensors(comp, d->next_sample, 0); /* preview of the first sample */
    return fmi2OK;
}

void releaseModel(ModelInstance *comp) {
    ModelData *d = &comp->data;
    if (d->delay_line) {
        freeModelMemory(comp, d->delay_line);
        d->delay_line = NULL;
    }
    if (d->gauge_line) {
        freeModelMemory(comp, d->gauge_line);
        d->gauge_line = NULL;
    }
}

void releaseKept(ModelInstance *comp) {
    int i;
    for (i = 0; i < NOISE_TABLES; i++) {
        freeModelMemory(comp, comp->data.noise[i].v);
        comp->data.noise[i] = (NoiseTable){0};
    }
}

fmi2Status doStep(ModelInstance *comp, double t, double h) {
    ModelData *d = &comp->data;
    const double fs = d->sample_rate;
    const double kEnd = (t + h) * fs - 1e-6; /* sample instants strictly before t + h */
    int64_t k, kNext;
    if (!stepFitsSampleRate(comp, h, fs)) return fmi2Error;
    if (!isfinite(d->u) || !isfinite(d->theta) || !isfinite(d->alpha_gauge)) {
        logError(comp, "input u, theta or alpha_gauge is not finite at t = %g s", t);
        return fmi2Error;
    }
    k = (int64_t)ceil(t * fs - 1e-6);
    if (k < d->next_sample) k = d->next_sample;
    for (; (double)k < kEnd; k++) sampleSensors(comp, k, 1);
    if (k > d->next_sample) d->next_sample = k;
    /* the samples that end within (t, t + h]: their command is the u set now */
    kNext = (int64_t)floor((t + h) * fs + 1e-6);
    for (k = (int64_t)floor(t * fs + 1e-6); k < kNext; k++) commitCommand(d);
    holdCommand(d);
    d->inputs_changed = 0;
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
    if ((vr == vr_theta_v || vr == vr_alpha_v) && d->inputs_changed && comp->state == StateStepComplete &&
        fabs(comp->time * d->sample_rate - (double)d->next_sample) < 1e-6)
        sampleSensors(comp, d->next_sample, 0); /* at its instant: preview of the next sample's readings */
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
    case vr_u:
        d->u = value;
        if (d->delay_samples == 0 && comp->state == StateStepComplete) d->u_plant = command(d, value);
        return fmi2OK;
    case vr_theta: d->theta = value; d->inputs_changed = 1; d->previewed = 0; return fmi2OK;
    case vr_alpha_gauge: d->alpha_gauge = value; d->inputs_changed = 1; d->previewed = 0; return fmi2OK;
    case vr_u_plant:
    case vr_theta_v:
    case vr_alpha_v: logError(comp, "output value reference %u cannot be set", (unsigned)vr); return fmi2Error;
    default: break;
    }
    p = realParameter(d, vr, &name);
    if (!p) return unknownReference(comp, "Real", vr);
    if (!parametersSettable(comp)) return fixedAfterInit(comp, name);
    *p = value;
    return fmi2OK;
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
