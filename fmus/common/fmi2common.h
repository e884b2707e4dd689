/*
 * Generic FMI 2.0 co-simulation layer shared by the hand-written rig-twin FMUs.
 *
 * fmi2common.c implements the whole fmi2* API once; each model supplies a
 * config.h (MODEL_IDENTIFIER, MODEL_GUID, the ModelData struct) and a model.c
 * that implements the small interface declared below.  The layout follows the
 * Modelica Association's Reference-FMUs (own code, same division of labour).
 */
#ifndef FMI2COMMON_H
#define FMI2COMMON_H

#include <stdbool.h>
#include <stddef.h>
#include <stdio.h>

#include "fmi2Functions.h"

#include "config.h"

#if defined(__GNUC__)
#define MODEL_API __attribute__((visibility("hidden")))
#else
#define MODEL_API
#endif

/* life-cycle states (bit mask so that allowed-state checks are one AND) */
typedef enum {
    StateInstantiated = 1 << 0,
    StateInitializationMode = 1 << 1,
    StateStepComplete = 1 << 2,
    StateStepFailed = 1 << 3,
    StateTerminated = 1 << 4,
    StateError = 1 << 5
} ModelState;

typedef struct ModelInstance {
    char *instanceName;
    char *resourcePath; /* local path of the FMU's resources folder (from fmuResourceLocation), or NULL */
    fmi2CallbackLogger logger;
    fmi2CallbackAllocateMemory allocateMemory;
    fmi2CallbackFreeMemory freeMemory;
    fmi2ComponentEnvironment componentEnvironment;
    bool loggingOn;
    ModelState state;
    double time;      /* current communication point [s] */
    double startTime; /* from fmi2SetupExperiment [s] */
    ModelData data;   /* model-specific parameters, inputs, states, outputs */
} ModelInstance;

/* ---- per-model interface (implemented in <model>/model.c) ---- */

/* Write the default (start) values of all variables into comp->data. */
MODEL_API void setStartValues(ModelInstance *comp);

/* Check the parameters; on failure write one line naming the parameter into msg and return false. */
/* Inside validate(): CHECK(condition, printf-style message) returns false with the message when it fails. */
#define CHECK(cond, ...)                                                                                     \
    do {                                                                                                     \
        if (!(cond)) {                                                                                       \
            snprintf(msg, len, __VA_ARGS__);                                                                 \
            return false;                                                                                    \
        }                                                                                                    \
    } while (0)

MODEL_API bool validate(ModelInstance *comp, char *msg, size_t len);

/* Called after a successful validate() in fmi2ExitInitializationMode: precompute, set the initial
   state and the outputs at the start time.  May allocate through allocateModelMemory(). */
MODEL_API fmi2Status initialize(ModelInstance *comp);

/* Release what initialize() allocated (safe to call twice). */
MODEL_API void releaseModel(ModelInstance *comp);

#ifdef MODEL_KEEPS_MEMORY
/* Release what the model keeps across fmi2Reset (a cache), with the instance. */
MODEL_API void releaseKept(ModelInstance *comp);
#endif

/* Recompute outputs from the current state and inputs. */
MODEL_API void calculateValues(ModelInstance *comp);

MODEL_API fmi2Status getFloat64(ModelInstance *comp, fmi2ValueReference vr, double *value);
MODEL_API fmi2Status setFloat64(ModelInstance *comp, fmi2ValueReference vr, double value);
MODEL_API fmi2Status getInt32(ModelInstance *comp, fmi2ValueReference vr, int *value);
MODEL_API fmi2Status setInt32(ModelInstance *comp, fmi2ValueReference vr, int value);

/* Advance from t to t + h [s] (no allocation). */
MODEL_API fmi2Status doStep(ModelInstance *comp, double t, double h);

/* ---- services of the common layer for the models ---- */

MODEL_API void logError(ModelInstance *comp, const char *fmt, ...);
MODEL_API void logInfo(ModelInstance *comp, const char *fmt, ...);

/* true while parameters may still be set (before fmi2ExitInitializationMode) */
MODEL_API bool parametersSettable(const ModelInstance *comp);

/* Error helper for setters: logs "<what> '<name>' cannot be set ..." and returns fmi2Error. */
MODEL_API fmi2Status unknownReference(ModelInstance *comp, const char *type, fmi2ValueReference vr);
MODEL_API fmi2Status fixedAfterInit(ModelInstance *comp, const char *name);

/* Path of file `name` in the FMU's resources folder into buf; false when the importer gave no file: URI. */
MODEL_API bool resourceFile(const ModelInstance *comp, const char *name, char *buf, size_t len);

/* A sampled model's check of a communication step h [s] at sample_rate fs [Hz]: h x fs a whole number (at most 1e7)
   or the inverse of one, so that every sample instant is a communication point; else logs why and returns false. */
MODEL_API bool stepFitsSampleRate(ModelInstance *comp, double h, double fs);

MODEL_API void *allocateModelMemory(ModelInstance *comp, size_t nobj, size_t size);
MODEL_API void freeModelMemory(ModelInstance *comp, void *p);

#endif
