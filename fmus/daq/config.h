/* daq: potentiometer, strain gauge, ADC/DAC, noise and sample-and-hold (FMI 2.0 co-simulation). */
#ifndef DAQ_CONFIG_H
#define DAQ_CONFIG_H

#include <stdint.h>

#define MODEL_NAME "daq"
/* must equal the guid attribute of modelDescription.xml (harness/build.py checks it) */
#define MODEL_GUID "{a3d5e7f9-2b4c-4d6e-8f10-3c5a7b9d1e2f}"

#define MAX_DELAY_SAMPLES 1000000

/* value references: must equal modelDescription.xml */
typedef enum {
    vr_sample_rate = 0,
    vr_dac_bits = 1, /* Integer */
    vr_dac_range = 2,
    vr_out_limit = 3,
    vr_delay_samples = 4, /* Integer */
    vr_pot_gain = 5,
    vr_pot_offset = 6,
    vr_pot_deadband = 7,
    vr_gauge_gain = 8,
    vr_gauge_offset = 9,
    vr_gauge_cubic = 10,
    vr_adc_bits = 11, /* Integer */
    vr_adc_range = 12,
    vr_noise_theta = 13,
    vr_noise_alpha = 14,
    vr_seed = 15, /* Integer */
    vr_u = 30,
    vr_theta = 31,
    vr_alpha_gauge = 32,
    vr_u_plant = 40,
    vr_theta_v = 41,
    vr_alpha_v = 42
} ValueReference;

typedef struct {
    /* parameters */
    double sample_rate;
    int dac_bits;
    double dac_range, out_limit;
    int delay_samples;
    double pot_gain, pot_offset, pot_deadband;
    double gauge_gain, gauge_offset, gauge_cubic;
    int adc_bits;
    double adc_range, noise_theta, noise_alpha;
    int seed;
    /* inputs */
    double u, theta, alpha_gauge;
    /* outputs (held between samples) */
    double u_plant, theta_v, alpha_v;
    /* state */
    double *delay_line; /* last delay_samples commands, oldest at delay_head */
    int delay_head;
    int64_t next_sample; /* index k of the next sample instant k / sample_rate not yet taken */
    uint64_t key_theta, key_alpha; /* PRNG stream keys derived from seed */
} ModelData;

#endif
