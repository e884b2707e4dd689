/*
 * Helpers for a model's variable lists (config.h): REAL_PARAMETERS(X) and INTEGER_PARAMETERS(X) with
 * X(name, value reference, start value), INPUTS(X) and OUTPUTS(X) with X(name, value reference).  Each
 * macro below is one use of a list: a ModelData field, a value reference, a start value, a get/set case.
 */
#ifndef VARIABLES_H
#define VARIABLES_H

/* ModelData fields (inputs and outputs are Real) */
#define DECLARE_REAL(name, vr, start) double name;
#define DECLARE_INTEGER(name, vr, start) int name;
#define DECLARE_VARIABLE(name, vr) double name;
#define DECLARE_ARRAY(name, vr, rows, cols) double name[(rows) * (cols)];

/* enum ValueReference members vr_<name> */
#define VALUE_REFERENCE(name, vr, start) vr_##name = vr,
#define VALUE_REFERENCE_IO(name, vr) vr_##name = vr,

/* inside setStartValues(): ModelData *d */
#define SET_START(name, vr, start) d->name = start;

/* inside a switch on the value reference: the address and name of a parameter (p, pname) */
#define PARAMETER_CASE(name, vr, start) \
    case vr_##name:                     \
        *pname = #name;                 \
        return &d->name;

/* inside a switch on the value reference in a getter: *value = the variable */
#define GET_CASE(name, vr)    \
    case vr_##name:           \
        *value = d->name;     \
        return fmi2OK;

/* inside a lookup of an array parameter's element (ModelData *d, value reference vr): its address and name */
#define ARRAY_CASE(name, vr0, rows, cols)                        \
    if (vr >= (vr0) && vr < (vr0) + (rows) * (cols)) {           \
        *pname = #name;                                          \
        return &d->name[vr - (vr0)];                             \
    }

/* {"name", value} pairs of the Real parameters, for the finiteness check of validate() */
#define NAME_VALUE(name, vr, start) {#name, d->name},

#endif
