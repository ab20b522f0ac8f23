/* The entry points for one value type, included after upper_half_rows.h with the same
 * macros (T, KEY, KEY_MAX, NEXT, NAME): per row, numpy's extremes, then ``peak``'s
 * normalizer and first maximum, or the top-K selection and its weighted spread for
 * ``var`` and ``cov``. Weights are w = (double) v - minimum, the anchor weights numpy
 * computes; selections and sums are defined on them, so the results are those of the
 * numpy path (statistics.py), not an approximation. */

/* numpy's min and max of a row (NaN for both when it holds a NaN), from the ordered
 * integer keys of the values, which vectorize where float comparisons with NaN
 * semantics do not. Returns whether both are finite. */
INLINE int NAME(row_extremes)(const T *v, int64_t m, double *minimum, double *maximum) {
    KEY low[LANES], high[LANES], first, above, below;
    T infinity = (T) INFINITY, negative_infinity = (T) -INFINITY;
    memcpy(&above, &infinity, sizeof above);
    memcpy(&below, &negative_infinity, sizeof below);
    above = ORDERED(above);
    below = ORDERED(below);
    memcpy(&first, v, sizeof first);
    for (int j = 0; j < LANES; j++) low[j] = high[j] = ORDERED(first);
    int64_t i = 0;
    for (; i + LANES <= m; i += LANES)
        for (int j = 0; j < LANES; j++) {
            KEY key;
            memcpy(&key, v + i + j, sizeof key);
            key = ORDERED(key);
            low[j] = key < low[j] ? key : low[j];
            high[j] = key > high[j] ? key : high[j];
        }
    for (; i < m; i++) {
        KEY key;
        memcpy(&key, v + i, sizeof key);
        key = ORDERED(key);
        low[0] = key < low[0] ? key : low[0];
        high[0] = key > high[0] ? key : high[0];
    }
    for (int j = 1; j < LANES; j++) {
        low[0] = low[j] < low[0] ? low[j] : low[0];
        high[0] = high[j] > high[0] ? high[j] : high[0];
    }
    if (low[0] < below || high[0] > above) { /* the keys of NaNs lie beyond the infinities' */
        *minimum = *maximum = NAN;
        return 0;
    }
    T lowest, highest;
    low[0] = ORDERED(low[0]); /* the map is its own inverse */
    high[0] = ORDERED(high[0]);
    memcpy(&lowest, &low[0], sizeof lowest);
    memcpy(&highest, &high[0], sizeof highest);
    *minimum = (double) lowest;
    *maximum = (double) highest;
    return isfinite(*minimum) && isfinite(*maximum);
}

/* SAMPLE values spread over the row, m >= SAMPLE: an odd stride, wrapping around the
 * row, does not alias with the heatmap's width. */
INLINE void NAME(take_sample)(const T *v, int64_t m, T *sample) {
    int64_t stride = (m / SAMPLE) | 1, at = 0, taken = 0;
    for (; taken < SAMPLE; at -= m)
        for (; at < m && taken < SAMPLE; at += stride) sample[taken++] = v[at];
}

/* A threshold with at least `fewest` and at most `most` of the m values above it, by
 * counting passes (regula falsi, Illinois variant, on the count above a threshold).
 * Only a guess: when GUESS_PASSES passes did not find one, the lower end of the
 * bracket, which has at least `fewest` values above it. */
INLINE T NAME(guess_threshold)(const T *v, int64_t m, T minimum, T maximum, int64_t fewest, int64_t most) {
    T low = NEXT(minimum, -INFINITY), high = maximum;
    double target = 0.5 * ((double) fewest + (double) most), f_low = m - target, f_high = -target;
    int last_side = 0;
    for (int pass = 0; pass < GUESS_PASSES; pass++) {
        T t = (T) (low + ((double) high - low) * (f_low / (f_low - f_high)));
        if (!(t > low && t < high)) t = (T) (0.5 * low + 0.5 * (double) high);
        if (!(t > low && t < high)) break;
        int64_t above = m - NAME(count_at_most)(v, m, t);
        if (above >= fewest && above <= most) return t;
        if (above > most) {
            low = t;
            f_low = above - target;
            if (last_side > 0) f_high *= 0.5;
            last_side = 1;
        } else {
            high = t;
            f_high = above - target;
            if (last_side < 0) f_low *= 0.5;
            last_side = -1;
        }
    }
    return low;
}

/* Number of weights strictly above t. */
INLINE int64_t NAME(count_weights_above)(const T *v, int64_t m, double minimum, double t) {
    int32_t lanes[LANES] = {0}; /* the caller keeps m < 2^31 */
    int64_t i = 0, count = 0;
    for (; i + LANES <= m; i += LANES)
        for (int j = 0; j < LANES; j++) lanes[j] += (double) v[i + j] - minimum > t;
    for (; i < m; i++) count += (double) v[i] - minimum > t;
    for (int j = 0; j < LANES; j++) count += lanes[j];
    return count;
}

/* Writes to indices, ascending, the columns[j] of the values[j] whose weight is > kth and
 * of the first ones whose weight is == kth, k in all (given `greater` weights > kth).
 * Branch-free per value: which values qualify is data, not a predictable pattern.
 * Returns the number written, k for consistent arguments. */
INLINE int64_t NAME(select_from)(const T *values, const int32_t *columns, int64_t count, int64_t k,
                                 double minimum, double kth, int64_t greater, int64_t *indices) {
    int64_t ties = k - greater, taken = 0;
    for (int64_t j = 0; j < count && taken < k; j++) {
        double w = (double) values[j] - minimum;
        int64_t tie = (w == kth) & (ties > 0);
        ties -= tie;
        indices[taken] = columns ? columns[j] : j;
        taken += (w > kth) | tie;
    }
    return taken;
}

/* Copies the values > t, and their columns, in order; -1 when there are more than
 * `capacity`. A vectorized pass marks them, 8 marks are tested at once, and a group
 * with a mark is copied without a branch per value. */
INLINE int64_t NAME(gather_above)(const T *v, int64_t m, T t, T *values, int32_t *columns,
                                  int64_t capacity) {
    uint8_t marks[GATHER_CHUNK];
    int64_t kept = 0;
    for (int64_t start = 0; start < m; start += GATHER_CHUNK) {
        int64_t size = m - start < GATHER_CHUNK ? m - start : GATHER_CHUNK;
        for (int64_t i = 0; i < size; i++) marks[i] = v[start + i] > t;
        for (int64_t i = size; i % 8; i++) marks[i] = 0;
        for (int64_t i = 0; i < size; i += 8) {
            uint64_t group;
            memcpy(&group, marks + i, sizeof group);
            if (!group) continue;
            if (kept + 8 > capacity) return -1;
            for (int64_t j = i; j < i + 8 && j < size; j++) {
                values[kept] = v[start + j];
                columns[kept] = (int32_t) (start + j); /* the caller keeps m < 2^31 */
                kept += marks[j];
            }
        }
    }
    return kept;
}

/* The top-k selection by counting passes over the whole row: the k-th largest weight
 * is the weight of the k-th largest raw value (w is monotone in v); rounding can give
 * distinct raw values one weight, so the ties are counted on the weights. */
INLINE int64_t NAME(top_k_full)(const T *v, int64_t m, int64_t k, double minimum, double maximum,
                                int64_t *indices) {
    T a = (T) maximum, b;
    if (k > 1) NAME(middle_pair)(v, m, m - k, (T) minimum, (T) maximum, &a, &b);
    double kth = (double) a - minimum;
    int64_t greater = k > 1 ? NAME(count_weights_above)(v, m, minimum, kth) : 0;
    return NAME(select_from)(v, NULL, m, k, minimum, kth, greater, indices);
}

/* The same selection with one pass over the row when a guess from a sample holds: the
 * values above a threshold guessed from a sample (2 to 5 k of them, usually) are
 * copied out and searched. Returns 0 when the guess kept fewer than k values or more
 * than CANDIDATES, or when a value at or below it could weigh as much as the k-th. */
INLINE int64_t NAME(top_k_sampled)(const T *v, int64_t m, int64_t k, double minimum, double maximum,
                                   int64_t *indices) {
    T sample[SAMPLE], values[CANDIDATES];
    int32_t columns[CANDIDATES];
    NAME(take_sample)(v, m, sample);
    /* e sampled values are expected among the top k: ask for 3 standard deviations more. */
    double expected = (double) k * SAMPLE / m;
    int64_t fewest = (int64_t) (expected + 3 * sqrt(expected)) + 2;
    T guess = NAME(guess_threshold)(sample, SAMPLE, (T) minimum, (T) maximum, fewest, fewest + fewest / 2);

    int64_t kept = NAME(gather_above)(v, m, guess, values, columns, CANDIDATES);
    if (kept < k) return 0;
    T a = (T) maximum, b; /* every kept value is > guess, so guess bounds them below */
    if (k > 1) NAME(middle_pair)(values, kept, kept - k, guess, (T) maximum, &a, &b);
    double kth = (double) a - minimum;
    if (!((double) guess - minimum < kth)) return 0;
    int64_t greater = NAME(count_weights_above)(values, kept, minimum, kth);
    return NAME(select_from)(values, columns, kept, k, minimum, kth, greater, indices);
}

/* Indices (ascending) of the k largest weights of a row, 1 <= k <= m; ties at the
 * k-th largest weight go to the lowest indices. Returns the number written (k). */
INLINE int64_t NAME(top_k_row)(const T *v, int64_t m, int64_t k, double minimum, double maximum,
                               int64_t *indices) {
    if (k == m) {
        for (int64_t i = 0; i < m; i++) indices[i] = i;
        return m;
    }
    int sampled = m >= 4 * SAMPLE && 8 * k <= m && 3 * k <= CANDIDATES;
    if (sampled && NAME(top_k_sampled)(v, m, k, minimum, maximum, indices) == k) return k;
    return NAME(top_k_full)(v, m, k, minimum, maximum, indices);
}

/* The weighted mean and covariance of the pixel centres of the selected weights,
 * normalized to sum to 1: out = (mean x, mean y, Sxx, Sxy, Syy). Each sum adds term j
 * to lane j % SUM_LANES and combines the lanes with sum_lanes, and each term is formed
 * as statistics._spread forms it: the same bits. */
INLINE void NAME(spread_row)(const T *v, const int64_t *indices, int64_t k, int64_t grid_width,
                             double minimum, double *out) {
    double total[SUM_LANES] = {0};
    for (int64_t j = 0; j < k; j++) total[j % SUM_LANES] += (double) v[indices[j]] - minimum;
    double sum = sum_lanes(total);

    double mean_x[SUM_LANES] = {0}, mean_y[SUM_LANES] = {0};
    int64_t row = 0, row_start = 0; /* indices ascend: a division per new grid row only */
    for (int64_t j = 0; j < k; j++) {
        if (indices[j] - row_start >= grid_width) {
            row = indices[j] / grid_width;
            row_start = row * grid_width;
        }
        double p = ((double) v[indices[j]] - minimum) / sum;
        mean_x[j % SUM_LANES] += p * ((double) (indices[j] - row_start) + 0.5);
        mean_y[j % SUM_LANES] += p * ((double) row + 0.5);
    }
    double mx = sum_lanes(mean_x), my = sum_lanes(mean_y);

    double xx[SUM_LANES] = {0}, xy[SUM_LANES] = {0}, yy[SUM_LANES] = {0};
    row = row_start = 0;
    for (int64_t j = 0; j < k; j++) {
        if (indices[j] - row_start >= grid_width) {
            row = indices[j] / grid_width;
            row_start = row * grid_width;
        }
        double p = ((double) v[indices[j]] - minimum) / sum;
        double dx = ((double) (indices[j] - row_start) + 0.5) - mx, dy = ((double) row + 0.5) - my;
        double pdx = p * dx, pdy = p * dy;
        xx[j % SUM_LANES] += pdx * dx;
        xy[j % SUM_LANES] += pdx * dy;
        yy[j % SUM_LANES] += pdy * dy;
    }
    out[0] = mx;
    out[1] = my;
    out[2] = sum_lanes(xx);
    out[3] = sum_lanes(xy);
    out[4] = sum_lanes(yy);
}

/* The first index of the largest weight (-1 if none), which precedes the first index of the
 * largest raw value when rounding gives both one weight: vectorized counts find the
 * chunk that holds it. */
INLINE int64_t NAME(first_maximum)(const T *v, int64_t m, double minimum, double maximum) {
    double top = maximum - minimum, below = nextafter(top, -INFINITY);
    int64_t i = 0;
    while (i + ARGMAX_CHUNK <= m && !NAME(count_weights_above)(v + i, ARGMAX_CHUNK, minimum, below))
        i += ARGMAX_CHUNK;
    while (i < m && (double) v[i] - minimum < top) i++;
    return i < m ? i : -1;
}

TARGETS int NAME(cks_anchor_peaks)(const T *values, int64_t rows, int64_t width, double *minimum,
                                   double *maximum, double *sums, int64_t *argmax) {
    if (width < 2) return -1;
    for (int64_t row = 0; row < rows; row++) {
        const T *v = values + row * width;
        sums[row] = 0;
        argmax[row] = 0;
        if (!NAME(row_extremes)(v, width, minimum + row, maximum + row)) continue;
        sums[row] = NAME(upper_half_sum)(v, width, minimum[row], maximum[row]);
        argmax[row] = NAME(first_maximum)(v, width, minimum[row], maximum[row]);
        if (argmax[row] < 0) return -2;
    }
    return 0;
}

TARGETS int NAME(cks_top_k_spread)(const T *values, int64_t rows, int64_t width, int64_t k,
                                   int64_t grid_width, double *minimum, double *maximum,
                                   int64_t *indices, double *spread) {
    if (width < 1 || k < 1 || k > width || grid_width < 1) return -1;
    for (int64_t row = 0; row < rows; row++) {
        const T *v = values + row * width;
        int64_t *selected = indices + row * k;
        memset(selected, 0, sizeof *selected * k);
        memset(spread + 5 * row, 0, sizeof *spread * 5);
        if (!NAME(row_extremes)(v, width, minimum + row, maximum + row)) continue;
        if (NAME(top_k_row)(v, width, k, minimum[row], maximum[row], selected) != k) return -2;
        NAME(spread_row)(v, selected, k, grid_width, minimum[row], spread + 5 * row);
    }
    return 0;
}
