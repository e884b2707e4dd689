/* Counter-based normal deviates shared by the models: splitmix64 of (stream key, index) and Box-Muller, so that
 * deviate k of a stream depends only on its key and k (the same seed gives the same bytes, whatever the step sizes
 * or the order in which deviates are asked for). */
#ifndef NOISE_H
#define NOISE_H

#include <math.h>
#include <stdint.h>

static inline uint64_t mix64(uint64_t z) { /* splitmix64 output function */
    z += 0x9E3779B97F4A7C15ULL;
    z = (z ^ (z >> 30)) * 0xBF58476D1CE4E5B9ULL;
    z = (z ^ (z >> 27)) * 0x94D049BB133111EBULL;
    return z ^ (z >> 31);
}

/* uniform in (0, 1] from stream key and counter */
static inline double uniform(uint64_t key, uint64_t counter) {
    return (double)((mix64(key + mix64(counter)) >> 11) + 1) * (1.0 / 9007199254740992.0);
}

/* standard normal deviate number k of the stream (Box-Muller) */
static inline double gauss(uint64_t key, int64_t k) {
    const double u1 = uniform(key, 2 * (uint64_t)k), u2 = uniform(key, 2 * (uint64_t)k + 1);
    return sqrt(-2.0 * log(u1)) * cos(6.283185307179586 * u2);
}

#endif
