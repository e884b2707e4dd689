/* daq: potentiometer, strain gauge, ADC/DAC, noise and sample-and-hold (FMI 2.0 co-simulation). */
#ifndef DAQ_CONFIG_H
#define DAQ_CONFIG_H

#include <stdint.h>

#define MODEL_NAME "daq"
/* must equal the guid attribute of modelDescription.xml (harness/fmu/build.py checks it) */
#define MODEL_GUID "{a3d5e7f9-2b4c-4d6e-8f10-3c5a7b9d1e2f}"

#define MAX_DELAY_SAMPLES 1000000

enum { NOISE_THETA = 0, NOISE_ALPHA = 1 }; /* the noise streams */
#define NOISE_TABLES 16        /* streams whose deviates an instance keeps across fmi2Reset */
#define NOISE_TABLE_MAX 262144 /* deviates kept per stream at most (later ones are drawn each time) */
#define MODEL_KEEPS_MEMORY     /* releaseKept() frees the tables with the instance */

/* the deviates 0..n-1 of the noise stream key, drawn once and kept: a fit replays the same draws many times */
typedef struct {
    uint64_t key;
    int used;
    int64_t n, cap;
    double *v;
} NoiseTable;

/* The variables, one line each, in modelDescription.xml order: X(name, value reference, start value) for the
   parameters, X(name, value reference) for inputs and outputs.  These lists are the C side's only copy of the
   variable table: they declare the ModelData fields and the value references, and drive the start values, the
   finiteness check and get/set in model.c.  tests/test_fmu_config.py checks them against modelDescription.xml. */
#define REAL_PARAMETERS(X)       \
    X(sample_rate, 0, 50.0)      \
    X(dac_range, 2, 10.0)        \
    X(out_limit, 3, 10.0)        \
    X(pot_gain, 5, 35.5145)      \
    X(pot_offset, 6, 0.0)        \
    X(pot_deadband, 7, 8.0)      \
    X(gauge_gain, 8, -3.3636)    \
    X(gauge_offset, 9, 0.0)      \
    X(gauge_cubic, 10, 0.0)      \
    X(adc_range, 12, 10.0)       \
    X(noise_theta, 13, 0.0)      \
    X(noise_alpha, 14, 0.0)      \
    X(encoder_counts, 17, 4096.0) \
    X(pot_bow, 18, 0.0)          \
    X(gauge_drift, 19, 0.0)      \
    X(gauge_tau, 20, 0.0)
#define INTEGER_PARAMETERS(X)    \
    X(dac_bits, 1, 0)            \
    X(delay_samples, 4, 0)       \
    X(adc_bits, 11, 0)           \
    X(seed, 15, 0)               \
    X(theta_sensor, 16, 0)       \
    X(gauge_delay, 21, 0)
#define INPUTS(X)                \
    X(u, 30)                     \
    X(theta, 31)                 \
    X(alpha_gauge, 32)
#define OUTPUTS(X)               \
    X(u_plant, 40)               \
    X(theta_v, 41)               \
    X(alpha_v, 42)

#include "variables.h"

typedef enum {
    REAL_PARAMETERS(VALUE_REFERENCE) INTEGER_PARAMETERS(VALUE_REFERENCE) INPUTS(VALUE_REFERENCE_IO)
    OUTPUTS(VALUE_REFERENCE_IO)
} ValueReference;

typedef struct {
    REAL_PARAMETERS(DECLARE_REAL)
    INTEGER_PARAMETERS(DECLARE_INTEGER)
    INPUTS(DECLARE_VARIABLE)
    OUTPUTS(DECLARE_VARIABLE) /* held between samples */
    /* state */
    double *delay_line; /* last delay_samples commands, oldest at delay_head */
    int delay_head;
    int64_t next_sample; /* index k of the next sample instant k / sample_rate not yet taken */
    uint64_t key_theta, key_alpha; /* PRNG stream keys derived from seed */
    NoiseTable noise[NOISE_TABLES]; /* kept across fmi2Reset, freed with the instance */
    int noise_next;                 /* the table a stream not kept takes next (in turn) */
    int noise_slot[2];              /* the table of each stream (NOISE_THETA, NOISE_ALPHA) */
    double gauge_c;    /* the gauge low-pass's gain per sample, 1 - exp(-1 / (sample_rate gauge_tau)) */
    double gauge_lp;   /* its output at the last sample taken for real [V] */
    int gauge_lp_set;  /* a sample has been taken for real: gauge_lp and gauge_line hold */
    double *gauge_line; /* the gauge's last gauge_delay readings [V], oldest at gauge_head */
    int gauge_head;
    int inputs_changed; /* inputs set since the last sample: reading theta_v or alpha_v previews the next one */
    int previewed;      /* the readings are a preview of sample preview_k from the inputs as they are */
    int64_t preview_k;
    double preview_va;  /* that preview's gauge voltage before the gauge's filters [V] */
} ModelData;

#endif
