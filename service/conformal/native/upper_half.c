/* Exact anchor statistics of heatmap rows, fast: per row (float32 or float64 raw
 * values v, anchor weights w = (double) v - min), numpy's min and max; for ``peak``,
 * S = the sum of the weights w >= median(w) (numpy's median, the mean of the two
 * middle weights for an even count) and the first index of the largest weight; for
 * ``var`` and ``cov``, the K largest weights (ties to the lowest index) and the
 * weighted mean and covariance of their pixel centres.
 *
 * numpy's exact tools (np.median, np.argpartition) cost about as much per map as a
 * whole per-heatmap loop. Order statistics commute with the monotone map v -> w, so
 * they are selected on the raw values by vectorized counting passes (no sort, no
 * partition; upper_half_rows.h); the top K are first cut down to a few hundred
 * candidates with a threshold guessed on a sample (anchor_rows.h). Ties and sums
 * are decided on the weights, the spread's sums in an order that statistics._spread
 * repeats in numpy, so both give the same bits.
 * See service/conformal/kernel.py for the Python side and the measurements.
 *
 * Plain C99 plus a GCC/Clang attribute that compiles the entry points once per
 * x86 vector extension and picks one at load time; other targets get the
 * portable build. */

#include <math.h>
#include <stdint.h>
#include <string.h>

#define LANES 16
#define SUM_LANES 8 /* statistics._SUM_LANES: the order of the spread's sums */
#define SAMPLE 512 /* values per row sampled to guess where the top K starts */
#define CANDIDATES 2048 /* values above that guess searched apart from the row, at most */
#define GATHER_CHUNK 1024 /* values marked per vectorized pass (a multiple of 8) */
#define GUESS_PASSES 24 /* counting passes over the sample, at most */
#define ENDGAME 2 /* values in a bracket that one pass splits (4 costs more than the passes it saves) */
#define ARGMAX_CHUNK 256 /* values counted at once while looking for the first maximum */

#ifdef __FAST_MATH__
#error "the spread sums must be IEEE operations in program order: build without -ffast-math"
#endif
#ifdef __clang__
#pragma STDC FP_CONTRACT OFF /* GCC ignores the pragma: pyproject.toml passes -ffp-contract=off */
#endif

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

/* Signed integers that order like the floats they reinterpret; NaNs lie beyond the infinities. */
#define ORDERED(k) ((k) ^ (((k) >> (8 * sizeof(k) - 1)) & KEY_MAX))

/* Bumped whenever the entry points change, so that a stale build is not loaded. */
int cks_kernel_version(void) { return 4; }

/* The lanes of a sum combined pairwise, as statistics._lane_sums combines them. */
INLINE double sum_lanes(const double lanes[SUM_LANES]) {
    double a0 = lanes[0] + lanes[4], a1 = lanes[1] + lanes[5];
    double a2 = lanes[2] + lanes[6], a3 = lanes[3] + lanes[7];
    return (a0 + a2) + (a1 + a3);
}

#define T float
#define KEY int32_t
#define KEY_MAX INT32_MAX
#define NEXT nextafterf
#define NAME(x) x##_f32
#include "upper_half_rows.h"
#include "anchor_rows.h"
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
#include "anchor_rows.h"
