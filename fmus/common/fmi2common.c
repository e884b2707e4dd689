/*
 * FMI 2.0 co-simulation API on top of the per-model interface in fmi2common.h.
 * Unsupported optional calls (FMU state, directional derivatives, input derivatives,
 * asynchronous steps) return fmi2Error with a logged message.
 */
#include "fmi2common.h"

#include <math.h>
#include <stdarg.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#define ALL_STATES                                                                                   \
    (StateInstantiated | StateInitializationMode | StateStepComplete | StateStepFailed |            \
     StateTerminated | StateError)

/* ------------------------------------------------------------------ logging */

static void vlog(ModelInstance *comp, fmi2Status status, const char *category, const char *fmt,
                 va_list args) {
    char buf[1024], esc[2048];
    size_t i, j = 0;
    if (!comp || !comp->logger) return;
    vsnprintf(buf, sizeof(buf), fmt, args);
    /* pass the formatted text as the message itself ('%' doubled): importers without varargs
       support show it verbatim, importers that format it get the same text back */
    for (i = 0; buf[i] && j + 2 < sizeof(esc); i++) {
        if (buf[i] == '%') esc[j++] = '%';
        esc[j++] = buf[i];
    }
    esc[j] = '\0';
    comp->logger(comp->componentEnvironment, comp->instanceName, status, category, esc);
}

void logError(ModelInstance *comp, const char *fmt, ...) {
    va_list args;
    va_start(args, fmt);
    vlog(comp, fmi2Error, "logStatusError", fmt, args); /* errors are always reported */
    va_end(args);
}

void logInfo(ModelInstance *comp, const char *fmt, ...) {
    va_list args;
    if (!comp || !comp->loggingOn) return;
    va_start(args, fmt);
    vlog(comp, fmi2OK, "logEvents", fmt, args);
    va_end(args);
}

bool parametersSettable(const ModelInstance *comp) {
    return (comp->state & (StateInstantiated | StateInitializationMode)) != 0;
}

fmi2Status unknownReference(ModelInstance *comp, const char *type, fmi2ValueReference vr) {
    logError(comp, "unknown %s value reference %u", type, (unsigned)vr);
    return fmi2Error;
}

fmi2Status fixedAfterInit(ModelInstance *comp, const char *name) {
    logError(comp, "parameter '%s' is fixed: it can only be set before fmi2ExitInitializationMode", name);
    return fmi2Error;
}

void *allocateModelMemory(ModelInstance *comp, size_t nobj, size_t size) {
    if (comp->allocateMemory) return comp->allocateMemory(nobj, size);
    return calloc(nobj, size);
}

void freeModelMemory(ModelInstance *comp, void *p) {
    if (!p) return;
    if (comp->freeMemory)
        comp->freeMemory(p);
    else
        free(p);
}

/* Returns true (and logs) when comp is NULL or the call is not allowed in the current state. */
static bool invalidState(ModelInstance *comp, const char *f, int allowed) {
    if (!comp) return true;
    if (!(comp->state & allowed)) {
        logError(comp, "%s: not allowed in the current state", f);
        return true;
    }
    return false;
}

static bool nullPointer(ModelInstance *comp, const char *f, const char *arg, const void *p) {
    if (!p) {
        logError(comp, "%s: argument %s must not be NULL", f, arg);
        return true;
    }
    return false;
}

/* ------------------------------------------------------------- inquiry */

const char *fmi2GetTypesPlatform(void) { return fmi2TypesPlatform; }

const char *fmi2GetVersion(void) { return fmi2Version; }

fmi2Status fmi2SetDebugLogging(fmi2Component c, fmi2Boolean loggingOn, size_t nCategories,
                               const fmi2String categories[]) {
    ModelInstance *comp = (ModelInstance *)c;
    (void)nCategories;
    (void)categories;
    if (invalidState(comp, "fmi2SetDebugLogging", ALL_STATES)) return fmi2Error;
    comp->loggingOn = loggingOn ? true : false;
    return fmi2OK;
}

/* ---------------------------------------------------------- resources */

static int hexValue(char c) {
    if (c >= '0' && c <= '9') return c - '0';
    if (c >= 'a' && c <= 'f') return c - 'a' + 10;
    if (c >= 'A' && c <= 'F') return c - 'A' + 10;
    return -1;
}

/* Local path of a file: URI (file:///abs, file:/abs or file://localhost/abs; %XX decoded), or NULL. */
static char *uriToPath(ModelInstance *comp, const char *uri) {
    const char *p;
    char *path, *q;
    if (!uri || strncmp(uri, "file:", 5) != 0) return NULL;
    p = uri + 5;
    if (strncmp(p, "//localhost/", 12) == 0) p += 11;
    else if (strncmp(p, "///", 3) == 0) p += 2;
    else if (strncmp(p, "//", 2) == 0) return NULL; /* a remote host */
#if defined(_WIN32)
    if (p[0] == '/' && p[1] && p[2] == ':') p++; /* /C:/dir -> C:/dir */
#endif
    path = (char *)allocateModelMemory(comp, strlen(p) + 1, 1);
    if (!path) return NULL;
    for (q = path; *p; p++) {
        if (p[0] == '%' && hexValue(p[1]) >= 0 && hexValue(p[2]) >= 0) {
            *q++ = (char)(hexValue(p[1]) * 16 + hexValue(p[2]));
            p += 2;
        } else {
            *q++ = *p;
        }
    }
    *q = '\0';
    if (q > path && q[-1] == '/') q[-1] = '\0';
    return path;
}

bool stepFitsSampleRate(ModelInstance *comp, double h, double fs) {
    const double ratio = h * fs;
    if (ratio > 1e7) {
        logError(comp, "communication step %g s spans more than 1e7 samples", h);
        return false;
    }
    if (fabs(ratio - round(ratio)) > 1e-6 * ratio && fabs(1.0 / ratio - round(1.0 / ratio)) > 1e-6 / ratio) {
        logError(comp,
                 "communication step %g s does not fit sample_rate = %g Hz: step at 1/sample_rate = %g s or a whole "
                 "fraction of it, so that every sample instant is a communication point",
                 h, fs, 1.0 / fs);
        return false;
    }
    return true;
}

bool resourceFile(const ModelInstance *comp, const char *name, char *buf, size_t len) {
    if (!comp->resourcePath || strlen(comp->resourcePath) + 1 + strlen(name) >= len) return false;
    snprintf(buf, len, "%s/%s", comp->resourcePath, name);
    return true;
}

/* ---------------------------------------------------------- life cycle */

fmi2Component fmi2Instantiate(fmi2String instanceName, fmi2Type fmuType, fmi2String fmuGUID,
                              fmi2String fmuResourceLocation, const fmi2CallbackFunctions *functions,
                              fmi2Boolean visible, fmi2Boolean loggingOn) {
    ModelInstance tmp;
    ModelInstance *comp;
    (void)visible;

    if (!functions || !functions->logger) return NULL;
    memset(&tmp, 0, sizeof(tmp));
    tmp.logger = functions->logger;
    tmp.componentEnvironment = functions->componentEnvironment;
    tmp.instanceName = (char *)(instanceName ? instanceName : "?");

    if (!instanceName || !instanceName[0]) {
        logError(&tmp, "fmi2Instantiate: missing instance name");
        return NULL;
    }
    if (fmuType != fmi2CoSimulation) {
        logError(&tmp, "fmi2Instantiate: %s supports co-simulation only", MODEL_NAME);
        return NULL;
    }
    if (!fmuGUID || strcmp(fmuGUID, MODEL_GUID) != 0) {
        logError(&tmp, "fmi2Instantiate: GUID '%s' does not match %s", fmuGUID ? fmuGUID : "(null)",
                 MODEL_GUID);
        return NULL;
    }

    tmp.allocateMemory = functions->allocateMemory;
    tmp.freeMemory = functions->freeMemory;
    comp = (ModelInstance *)allocateModelMemory(&tmp, 1, sizeof(ModelInstance));
    if (!comp) {
        logError(&tmp, "fmi2Instantiate: out of memory");
        return NULL;
    }
    memset(comp, 0, sizeof(*comp));
    comp->logger = tmp.logger;
    comp->componentEnvironment = tmp.componentEnvironment;
    comp->allocateMemory = tmp.allocateMemory;
    comp->freeMemory = tmp.freeMemory;
    comp->instanceName = (char *)allocateModelMemory(comp, strlen(instanceName) + 1, 1);
    if (!comp->instanceName) {
        freeModelMemory(comp, comp);
        return NULL;
    }
    strcpy(comp->instanceName, instanceName);
    comp->resourcePath = uriToPath(comp, fmuResourceLocation);
    comp->loggingOn = loggingOn ? true : false;
    comp->state = StateInstantiated;
    setStartValues(comp);
    return comp;
}

void fmi2FreeInstance(fmi2Component c) {
    ModelInstance *comp = (ModelInstance *)c;
    if (!comp) return;
    releaseModel(comp);
#ifdef MODEL_KEEPS_MEMORY
    releaseKept(comp);
#endif
    freeModelMemory(comp, comp->resourcePath);
    freeModelMemory(comp, comp->instanceName);
    freeModelMemory(comp, comp);
}

fmi2Status fmi2SetupExperiment(fmi2Component c, fmi2Boolean toleranceDefined, fmi2Real tolerance,
                               fmi2Real startTime, fmi2Boolean stopTimeDefined, fmi2Real stopTime) {
    ModelInstance *comp = (ModelInstance *)c;
    (void)toleranceDefined;
    (void)tolerance;
    (void)stopTimeDefined;
    (void)stopTime;
    if (invalidState(comp, "fmi2SetupExperiment", StateInstantiated)) return fmi2Error;
    if (!isfinite(startTime)) {
        logError(comp, "fmi2SetupExperiment: startTime must be finite");
        return fmi2Error;
    }
    comp->startTime = startTime;
    comp->time = startTime;
    return fmi2OK;
}

fmi2Status fmi2EnterInitializationMode(fmi2Component c) {
    ModelInstance *comp = (ModelInstance *)c;
    if (invalidState(comp, "fmi2EnterInitializationMode", StateInstantiated)) return fmi2Error;
    comp->state = StateInitializationMode;
    return fmi2OK;
}

fmi2Status fmi2ExitInitializationMode(fmi2Component c) {
    ModelInstance *comp = (ModelInstance *)c;
    char msg[512];
    fmi2Status status;
    if (invalidState(comp, "fmi2ExitInitializationMode", StateInitializationMode)) return fmi2Error;
    msg[0] = '\0';
    if (!validate(comp, msg, sizeof(msg))) {
        logError(comp, "%s", msg);
        comp->state = StateError;
        return fmi2Error;
    }
    comp->time = comp->startTime;
    status = initialize(comp);
    if (status > fmi2Warning) {
        comp->state = StateError;
        return status;
    }
    calculateValues(comp);
    comp->state = StateStepComplete;
    return status;
}

fmi2Status fmi2Terminate(fmi2Component c) {
    ModelInstance *comp = (ModelInstance *)c;
    if (invalidState(comp, "fmi2Terminate", StateStepComplete | StateStepFailed)) return fmi2Error;
    comp->state = StateTerminated;
    return fmi2OK;
}

fmi2Status fmi2Reset(fmi2Component c) {
    ModelInstance *comp = (ModelInstance *)c;
    if (invalidState(comp, "fmi2Reset", ALL_STATES)) return fmi2Error;
    releaseModel(comp);
    comp->time = 0.0;
    comp->startTime = 0.0;
    comp->state = StateInstantiated;
    setStartValues(comp);
    return fmi2OK;
}

/* ------------------------------------------------------ getters/setters */

#define GET_STATES (StateInitializationMode | StateStepComplete | StateStepFailed | StateTerminated | StateError)
#define SET_STATES (StateInstantiated | StateInitializationMode | StateStepComplete)

fmi2Status fmi2GetReal(fmi2Component c, const fmi2ValueReference vr[], size_t nvr, fmi2Real value[]) {
    ModelInstance *comp = (ModelInstance *)c;
    size_t i;
    if (invalidState(comp, "fmi2GetReal", GET_STATES | StateInstantiated)) return fmi2Error;
    if (nvr == 0) return fmi2OK;
    if (nullPointer(comp, "fmi2GetReal", "vr", vr) || nullPointer(comp, "fmi2GetReal", "value", value))
        return fmi2Error;
    for (i = 0; i < nvr; i++) {
        if (getFloat64(comp, vr[i], &value[i]) != fmi2OK) return fmi2Error;
    }
    return fmi2OK;
}

fmi2Status fmi2GetInteger(fmi2Component c, const fmi2ValueReference vr[], size_t nvr, fmi2Integer value[]) {
    ModelInstance *comp = (ModelInstance *)c;
    size_t i;
    if (invalidState(comp, "fmi2GetInteger", GET_STATES | StateInstantiated)) return fmi2Error;
    if (nvr == 0) return fmi2OK;
    if (nullPointer(comp, "fmi2GetInteger", "vr", vr) || nullPointer(comp, "fmi2GetInteger", "value", value))
        return fmi2Error;
    for (i = 0; i < nvr; i++) {
        int v = 0;
        if (getInt32(comp, vr[i], &v) != fmi2OK) return fmi2Error;
        value[i] = v;
    }
    return fmi2OK;
}

fmi2Status fmi2GetBoolean(fmi2Component c, const fmi2ValueReference vr[], size_t nvr, fmi2Boolean value[]) {
    ModelInstance *comp = (ModelInstance *)c;
    (void)value;
    if (invalidState(comp, "fmi2GetBoolean", GET_STATES | StateInstantiated)) return fmi2Error;
    if (nvr == 0) return fmi2OK;
    if (nullPointer(comp, "fmi2GetBoolean", "vr", vr)) return fmi2Error;
    return unknownReference(comp, "Boolean", vr[0]); /* no Boolean variables */
}

fmi2Status fmi2GetString(fmi2Component c, const fmi2ValueReference vr[], size_t nvr, fmi2String value[]) {
    ModelInstance *comp = (ModelInstance *)c;
    (void)value;
    if (invalidState(comp, "fmi2GetString", GET_STATES | StateInstantiated)) return fmi2Error;
    if (nvr == 0) return fmi2OK;
    if (nullPointer(comp, "fmi2GetString", "vr", vr)) return fmi2Error;
    return unknownReference(comp, "String", vr[0]); /* no String variables */
}

fmi2Status fmi2SetReal(fmi2Component c, const fmi2ValueReference vr[], size_t nvr, const fmi2Real value[]) {
    ModelInstance *comp = (ModelInstance *)c;
    size_t i;
    if (invalidState(comp, "fmi2SetReal", SET_STATES)) return fmi2Error;
    if (nvr == 0) return fmi2OK;
    if (nullPointer(comp, "fmi2SetReal", "vr", vr) || nullPointer(comp, "fmi2SetReal", "value", value))
        return fmi2Error;
    for (i = 0; i < nvr; i++) {
        if (setFloat64(comp, vr[i], value[i]) != fmi2OK) return fmi2Error;
    }
    return fmi2OK;
}

fmi2Status fmi2SetInteger(fmi2Component c, const fmi2ValueReference vr[], size_t nvr,
                          const fmi2Integer value[]) {
    ModelInstance *comp = (ModelInstance *)c;
    size_t i;
    if (invalidState(comp, "fmi2SetInteger", SET_STATES)) return fmi2Error;
    if (nvr == 0) return fmi2OK;
    if (nullPointer(comp, "fmi2SetInteger", "vr", vr) || nullPointer(comp, "fmi2SetInteger", "value", value))
        return fmi2Error;
    for (i = 0; i < nvr; i++) {
        if (setInt32(comp, vr[i], (int)value[i]) != fmi2OK) return fmi2Error;
    }
    return fmi2OK;
}

fmi2Status fmi2SetBoolean(fmi2Component c, const fmi2ValueReference vr[], size_t nvr,
                          const fmi2Boolean value[]) {
    ModelInstance *comp = (ModelInstance *)c;
    (void)value;
    if (invalidState(comp, "fmi2SetBoolean", SET_STATES)) return fmi2Error;
    if (nvr == 0) return fmi2OK;
    if (nullPointer(comp, "fmi2SetBoolean", "vr", vr)) return fmi2Error;
    return unknownReference(comp, "Boolean", vr[0]);
}

fmi2Status fmi2SetString(fmi2Component c, const fmi2ValueReference vr[], size_t nvr, const fmi2String value[]) {
    ModelInstance *comp = (ModelInstance *)c;
    (void)value;
    if (invalidState(comp, "fmi2SetString", SET_STATES)) return fmi2Error;
    if (nvr == 0) return fmi2OK;
    if (nullPointer(comp, "fmi2SetString", "vr", vr)) return fmi2Error;
    return unknownReference(comp, "String", vr[0]);
}

/* ----------------------------------------------- unsupported optional API */

static fmi2Status unsupported(fmi2Component c, const char *f) {
    ModelInstance *comp = (ModelInstance *)c;
    if (comp) logError(comp, "%s is not supported by %s", f, MODEL_NAME);
    return fmi2Error;
}

fmi2Status fmi2GetFMUstate(fmi2Component c, fmi2FMUstate *FMUstate) {
    (void)FMUstate;
    return unsupported(c, "fmi2GetFMUstate");
}

fmi2Status fmi2SetFMUstate(fmi2Component c, fmi2FMUstate FMUstate) {
    (void)FMUstate;
    return unsupported(c, "fmi2SetFMUstate");
}

fmi2Status fmi2FreeFMUstate(fmi2Component c, fmi2FMUstate *FMUstate) {
    (void)FMUstate;
    return unsupported(c, "fmi2FreeFMUstate");
}

fmi2Status fmi2SerializedFMUstateSize(fmi2Component c, fmi2FMUstate FMUstate, size_t *size) {
    (void)FMUstate;
    (void)size;
    return unsupported(c, "fmi2SerializedFMUstateSize");
}

fmi2Status fmi2SerializeFMUstate(fmi2Component c, fmi2FMUstate FMUstate, fmi2Byte serializedState[],
                                 size_t size) {
    (void)FMUstate;
    (void)serializedState;
    (void)size;
    return unsupported(c, "fmi2SerializeFMUstate");
}

fmi2Status fmi2DeSerializeFMUstate(fmi2Component c, const fmi2Byte serializedState[], size_t size,
                                   fmi2FMUstate *FMUstate) {
    (void)serializedState;
    (void)size;
    (void)FMUstate;
    return unsupported(c, "fmi2DeSerializeFMUstate");
}

fmi2Status fmi2GetDirectionalDerivative(fmi2Component c, const fmi2ValueReference vUnknown_ref[],
                                        size_t nUnknown, const fmi2ValueReference vKnown_ref[], size_t nKnown,
                                        const fmi2Real dvKnown[], fmi2Real dvUnknown[]) {
    (void)vUnknown_ref;
    (void)nUnknown;
    (void)vKnown_ref;
    (void)nKnown;
    (void)dvKnown;
    (void)dvUnknown;
    return unsupported(c, "fmi2GetDirectionalDerivative");
}

fmi2Status fmi2SetRealInputDerivatives(fmi2Component c, const fmi2ValueReference vr[], size_t nvr,
                                       const fmi2Integer order[], const fmi2Real value[]) {
    (void)vr;
    (void)nvr;
    (void)order;
    (void)value;
    return unsupported(c, "fmi2SetRealInputDerivatives");
}

fmi2Status fmi2GetRealOutputDerivatives(fmi2Component c, const fmi2ValueReference vr[], size_t nvr,
                                        const fmi2Integer order[], fmi2Real value[]) {
    (void)vr;
    (void)nvr;
    (void)order;
    (void)value;
    return unsupported(c, "fmi2GetRealOutputDerivatives");
}

fmi2Status fmi2CancelStep(fmi2Component c) { return unsupported(c, "fmi2CancelStep"); }

/* ---------------------------------------------------------- stepping */

fmi2Status fmi2DoStep(fmi2Component c, fmi2Real currentCommunicationPoint, fmi2Real communicationStepSize,
                      fmi2Boolean noSetFMUStatePriorToCurrentPoint) {
    ModelInstance *comp = (ModelInstance *)c;
    fmi2Status status;
    (void)noSetFMUStatePriorToCurrentPoint;
    if (invalidState(comp, "fmi2DoStep", StateStepComplete)) return fmi2Error;
    if (!(communicationStepSize > 0.0) || !isfinite(communicationStepSize)) {
        logError(comp, "fmi2DoStep: communication step size must be > 0 (got %g)", communicationStepSize);
        return fmi2Error;
    }
    if (!isfinite(currentCommunicationPoint)) {
        logError(comp, "fmi2DoStep: current communication point is not finite");
        return fmi2Error;
    }
    status = doStep(comp, currentCommunicationPoint, communicationStepSize);
    if (status > fmi2Warning) {
        comp->state = StateStepFailed;
        return status;
    }
    comp->time = currentCommunicationPoint + communicationStepSize;
    calculateValues(comp);
    return status;
}

fmi2Status fmi2GetStatus(fmi2Component c, const fmi2StatusKind s, fmi2Status *value) {
    ModelInstance *comp = (ModelInstance *)c;
    (void)s;
    (void)value;
    if (!comp) return fmi2Error;
    logError(comp, "fmi2GetStatus: no asynchronous step is ever pending in %s", MODEL_NAME);
    return fmi2Discard;
}

fmi2Status fmi2GetRealStatus(fmi2Component c, const fmi2StatusKind s, fmi2Real *value) {
    ModelInstance *comp = (ModelInstance *)c;
    if (!comp || !value) return fmi2Error;
    if (s == fmi2LastSuccessfulTime) {
        *value = comp->time;
        return fmi2OK;
    }
    logError(comp, "fmi2GetRealStatus: unsupported status kind %d", (int)s);
    return fmi2Discard;
}

fmi2Status fmi2GetIntegerStatus(fmi2Component c, const fmi2StatusKind s, fmi2Integer *value) {
    (void)s;
    (void)value;
    return unsupported(c, "fmi2GetIntegerStatus");
}

fmi2Status fmi2GetBooleanStatus(fmi2Component c, const fmi2StatusKind s, fmi2Boolean *value) {
    ModelInstance *comp = (ModelInstance *)c;
    if (!comp || !value) return fmi2Error;
    if (s == fmi2Terminated) {
        *value = fmi2False; /* the FMU never requests termination */
        return fmi2OK;
    }
    logError(comp, "fmi2GetBooleanStatus: unsupported status kind %d", (int)s);
    return fmi2Discard;
}

fmi2Status fmi2GetStringStatus(fmi2Component c, const fmi2StatusKind s, fmi2String *value) {
    (void)s;
    (void)value;
    return unsupported(c, "fmi2GetStringStatus");
}
