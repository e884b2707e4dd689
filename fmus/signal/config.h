/* signal: an experiment's command, reference and tip torque, sample by sample from a table (FMI 2.0 co-simulation). */
#ifndef SIGNAL_CONFIG_H
#define SIGNAL_CONFIG_H

#include <stdint.h>

#define MODEL_NAME "signal"
/* must equal the guid attribute of modelDescription.xml (harness/fmu/build.py checks it) */
#define MODEL_GUID "{a45041ea-193f-4d3b-86de-93d97b7de7bc}"

#define TABLE_FILE "signal.csv"
#define TABLE_COLUMNS 3

/* The variables, one line each, in modelDescription.xml order: X(name, value reference, start value) for the
   parameters, X(name, value reference) for the outputs (see ../common/variables.h). */
#define REAL_PARAMETERS(X)       \
    X(sample_rate, 0, 50.0)
#define INTEGER_PARAMETERS(X)
#define INPUTS(X)
#define OUTPUTS(X)               \
    X(u, 40)                     \
    X(ref, 41)                   \
    X(tau_tip, 42)

#include "variables.h"

typedef enum { REAL_PARAMETERS(VALUE_REFERENCE) OUTPUTS(VALUE_REFERENCE_IO) } ValueReference;

typedef struct {
    REAL_PARAMETERS(DECLARE_REAL)
    OUTPUTS(DECLARE_VARIABLE) /* the row of the sample holding the current time */
    double *table;            /* n_rows x TABLE_COLUMNS, row-major */
    int64_t n_rows;
    char load_error[256];
} ModelData;

#endif
