/*
 * signal: an experiment's inputs as a source for any co-simulation master, read from resources/signal.csv.
 *
 * The table has one row per sample k = 0, 1, ... (t_k = k / sample_rate) and three columns: the command u [V], the
 * reference ref [rad] and the tip torque tau_tip [N m]; lines starting with '#' and a header line of names are
 * skipped.  The outputs hold row k over [t_k, t_k+1) (zero-order hold, the last row after the table ends): after
 * fmi2DoStep(t, h) they are the row of the sample holding t + h.  No inputs; without a table (the bare FMU) every
 * output is 0.  Numbers are read with strtod, so a table written with 17 significant digits gives the same doubles.
 */
#include <ctype.h>
#include <math.h>
#include <stdlib.h>
#include <string.h>

#include "fmi2common.h"

void setStartValues(ModelInstance *comp) {
    ModelData *d = &comp->data;
    double *table = d->table; /* keep the pointer: releaseModel frees it */
    memset(d, 0, sizeof(*d));
    d->table = table;
    REAL_PARAMETERS(SET_START)
}

bool validate(ModelInstance *comp, char *msg, size_t len) {
    const ModelData *d = &comp->data;
    CHECK(isfinite(d->sample_rate) && d->sample_rate > 0, "invalid parameter sample_rate = %g: must be > 0",
          d->sample_rate);
    return true;
}

/* one data row of the table into row[]; 0 when the line is blank, a comment or the header, -1 when malformed */
static int parseRow(const char *line, double *row) {
    const char *p = line + strspn(line, " \t");
    char *end;
    int i;
    if (*p == '#' || *p == '\r' || *p == '\n' || *p == '\0' || isalpha((unsigned char)*p)) return 0;
    for (i = 0; i < TABLE_COLUMNS; i++) {
        row[i] = strtod(p, &end);
        if (end == p || !isfinite(row[i])) return -1;
        p = end + strspn(end, " \t");
        if (i < TABLE_COLUMNS - 1) {
            if (*p != ',') return -1;
            p++;
        }
    }
    return (*p == '\r' || *p == '\n' || *p == '\0') ? 1 : -1;
}

static void loadTable(ModelInstance *comp) {
    ModelData *d = &comp->data;
    char path[4096], line[512];
    double row[TABLE_COLUMNS];
    int64_t n = 0, lineno = 0;
    FILE *f;
    if (!resourceFile(comp, TABLE_FILE, path, sizeof(path))) return;
    f = fopen(path, "r");
    if (!f) return; /* the bare FMU: outputs 0 */
    while (fgets(line, sizeof(line), f)) n += parseRow(line, row) != 0;
    d->table = (double *)allocateModelMemory(comp, (size_t)(n > 0 ? n : 1) * TABLE_COLUMNS, sizeof(double));
    if (!d->table) {
        snprintf(d->load_error, sizeof(d->load_error), "out of memory for %lld rows of %s", (long long)n, TABLE_FILE);
        fclose(f);
        return;
    }
    rewind(f);
    n = 0;
    while (fgets(line, sizeof(line), f)) {
        int r = parseRow(line, row);
        lineno++;
        if (r < 0) {
            snprintf(d->load_error, sizeof(d->load_error), "%s line %lld: expected %d numbers separated by commas",
                     TABLE_FILE, (long long)lineno, TABLE_COLUMNS);
            break;
        }
        if (r > 0) memcpy(d->table + TABLE_COLUMNS * n++, row, sizeof(row));
    }
    fclose(f);
    d->n_rows = n;
}

/* the outputs: the row of the sample holding time t */
static void holdRow(ModelData *d, double t) {
    int64_t k = (int64_t)floor(t * d->sample_rate + 1e-6);
    if (d->n_rows == 0) return;
    if (k < 0) k = 0;
    if (k >= d->n_rows) k = d->n_rows - 1;
    d->u = d->table[TABLE_COLUMNS * k];
    d->ref = d->table[TABLE_COLUMNS * k + 1];
    d->tau_tip = d->table[TABLE_COLUMNS * k + 2];
}

/* ------------------------------------------------------------ life cycle */

fmi2Status initialize(ModelInstance *comp) {
    ModelData *d = &comp->data;
    releaseModel(comp);
    d->load_error[0] = '\0';
    d->n_rows = 0;
    loadTable(comp);
    if (d->load_error[0]) {
        logError(comp, "%s", d->load_error);
        return fmi2Error;
    }
    holdRow(d, comp->startTime);
    return fmi2OK;
}

void releaseModel(ModelInstance *comp) {
    ModelData *d = &comp->data;
    if (d->table) {
        freeModelMemory(comp, d->table);
        d->table = NULL;
    }
}

fmi2Status doStep(ModelInstance *comp, double t, double h) {
    holdRow(&comp->data, t + h);
    return fmi2OK;
}

void calculateValues(ModelInstance *comp) { (void)comp; /* outputs change only in fmi2DoStep */ }

/* ------------------------------------------------------- get / set */

fmi2Status getFloat64(ModelInstance *comp, fmi2ValueReference vr, double *value) {
    ModelData *d = &comp->data;
    switch (vr) {
    case vr_sample_rate: *value = d->sample_rate; return fmi2OK;
        OUTPUTS(GET_CASE)
    default: return unknownReference(comp, "Real", vr);
    }
}

fmi2Status setFloat64(ModelInstance *comp, fmi2ValueReference vr, double value) {
    ModelData *d = &comp->data;
    if (vr == vr_sample_rate) {
        if (!parametersSettable(comp)) return fixedAfterInit(comp, "sample_rate");
        d->sample_rate = value;
        return fmi2OK;
    }
    if (vr == vr_u || vr == vr_ref || vr == vr_tau_tip) {
        logError(comp, "output value reference %u cannot be set", (unsigned)vr);
        return fmi2Error;
    }
    return unknownReference(comp, "Real", vr);
}

fmi2Status getInt32(ModelInstance *comp, fmi2ValueReference vr, int *value) {
    (void)value;
    return unknownReference(comp, "Integer", vr);
}

fmi2Status setInt32(ModelInstance *comp, fmi2ValueReference vr, int value) {
    (void)value;
    return unknownReference(comp, "Integer", vr);
}
