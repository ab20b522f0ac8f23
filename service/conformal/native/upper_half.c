/* The normalizer of the ``anchor`` heatmap normalization, exactly and fast.
 *
 * For each row of raw heatmap values v (float32 or float64) with anchor
 * weights w = (double) v - min, S = sum of the weights w >= median(w), with
 * numpy's median (the mean of the two middle weights for an even count).
 * This is what ``peak`` needs per heatmap (p* = max weight / S) and what the
 * per-heatmap reference pays an np.partition for. Order statistics commute
 * with the monotone map v -> w, so the two middle values are selected on the
 * raw values by vectorized counting passes (no sort, no partition, no
 * branches per value), and only the final masked sum is done on weights.
 * See service/conformal/kernel.py for the Python side and the measurements.
 *
 * Plain C99 plus a GCC/Clang attribute that compiles the entry points once per
 * x86 vector extension and picks one at load time; other targets get the
 * portable build. */

#include <math.h>
#include <stdint.h>
#include <string.h>

#define LANES 16

#if defined(__x86_64__) && defined(__GLIBC__) && defined(__has_attribute) /* ifunc needs glibc */
#if __has_attribute(target_clones)
#define TARGETS __attribute__((target_clones("avx512f", "avx2", "default")))
#endif
#endif
#ifndef TARGETS
#define TARGETS
#endif
/* Helpers are inlined into each compiled entry point, so they get its vector extension. */
#if defined(__GNUC__)
#define INLINE static inline __attribute__((always_inline))
#else
#define INLINE static inline
#endif

/* Signed integers that order like the floats they reinterpret (no NaN here). */
#define ORDERED(k) ((k) ^ (((k) >> (8 * sizeof(k) - 1)) & KEY_MAX))

/* Bumped whenever the entry points change, so that a stale build is not loaded. */
int cks_kernel_version(void) { return 2; }

#define T float
#define KEY int32_t
#define KEY_MAX INT32_MAX
#define NEXT nextafterf
#define NAME(x) x##_f32
#include "upper_half_rows.h"
#undef T
#undef KEY
#undef KEY_MAX
#undef NEXT
#undef NAME

#define T double
#define KEY int64_t
#define KEY_MAX INT64_MAX
#define NEXT nextafter
#define NAME(x) x##_f64
#include "upper_half_rows.h"
