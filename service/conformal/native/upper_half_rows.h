/* Row kernels for one value type, included once per type by upper_half.c with
 *   T      the raw value type (float or double),
 *   KEY    the signed integer of the same width (ordered keys for bisection),
 *   KEY_MAX its largest value,
 *   NEXT   nextafterf / nextafter,
 *   NAME(x) x suffixed with the type.
 * Every loop is written lane by lane (LANES independent accumulators) so that
 * compilers vectorize it without reassociating floating-point reductions. */

INLINE int64_t NAME(count_at_most)(const T *v, int64_t m, T t) {
    KEY lanes[LANES] = {0}; /* as wide as T: a comparison's result is added without a shuffle */
    int64_t i = 0, count = 0;
    for (; i + LANES <= m; i += LANES)
        for (int j = 0; j < LANES; j++) lanes[j] += v[i + j] <= t;
    for (; i < m; i++) count += v[i] <= t;
    for (int j = 0; j < LANES; j++) count += lanes[j];
    return count;
}

/* The largest value <= t and the smallest value > t. */
INLINE void NAME(neighbours)(const T *v, int64_t m, T t, T *below, T *above) {
    T low[LANES], high[LANES];
    for (int j = 0; j < LANES; j++) { low[j] = -INFINITY; high[j] = INFINITY; }
    int64_t i = 0;
    for (; i + LANES <= m; i += LANES)
        for (int j = 0; j < LANES; j++) {
            T x = v[i + j];
            T under = x <= t ? x : -INFINITY, over = x > t ? x : INFINITY;
            low[j] = under > low[j] ? under : low[j];
            high[j] = over < high[j] ? over : high[j];
        }
    for (; i < m; i++) {
        if (v[i] <= t && v[i] > low[0]) low[0] = v[i];
        if (v[i] > t && v[i] < high[0]) high[0] = v[i];
    }
    *below = low[0]; *above = high[0];
    for (int j = 1; j < LANES; j++) {
        *below = low[j] > *below ? low[j] : *below;
        *above = high[j] < *above ? high[j] : *above;
    }
}

/* Sum of the anchor weights w = (double)v - minimum with w >= median. */
INLINE double NAME(weights_at_least)(const T *v, int64_t m, double minimum, double median) {
    double lanes[LANES] = {0};
    int64_t i = 0;
    double sum = 0;
    for (; i + LANES <= m; i += LANES)
        for (int j = 0; j < LANES; j++) {
            double w = (double) v[i + j] - minimum;
            lanes[j] += w >= median ? w : 0.0;
        }
    for (; i < m; i++) {
        double w = (double) v[i] - minimum;
        sum += w >= median ? w : 0.0;
    }
    for (int j = 0; j < LANES; j++) sum += lanes[j];
    return sum;
}

/* A threshold strictly inside (low, high), halfway in the ordering of the values. */
INLINE T NAME(key_midpoint)(T low, T high) {
    KEY a, b;
    memcpy(&a, &low, sizeof a);
    memcpy(&b, &high, sizeof b);
    a = ORDERED(a);
    b = ORDERED(b);
    KEY middle = (a & b) + ((a ^ b) >> 1); /* floor((a + b) / 2) without overflow */
    middle = ORDERED(middle); /* the map is its own inverse */
    T t;
    memcpy(&t, &middle, sizeof t);
    return t;
}

/* For a bracket that stopped shrinking with count(<= high) > r + 1: snaps high to
 * the largest value <= high, then one count tells whether that value holds both
 * ranks r and r + 1 (a tie at the median, e.g. a background of exact zeros, which
 * no threshold can split) or sits just above them. Returns 1 when a and b are set. */
INLINE int NAME(settle_tie)(const T *v, int64_t m, int64_t want, T *high, int64_t *c_high, T *a, T *b) {
    T top, unused;
    NAME(neighbours)(v, m, *high, &top, &unused); /* count(<= top) == count(<= high) */
    T below = NEXT(top, -INFINITY);
    int64_t count = NAME(count_at_most)(v, m, below);
    if (count < want) { *a = *b = top; return 1; }
    if (count == want) { NAME(neighbours)(v, m, below, a, b); return 1; }
    *high = below;
    *c_high = count;
    return 0;
}

/* The values of ranks r and r + 1 when the bracket (low, high] holds at most ENDGAME
 * values, c_low of them at or below low and r + 1 < c_high at or below high: one
 * vectorized pass keeps the smallest ENDGAME values in the bracket per lane (branch-free
 * insertion), instead of the passes that regula falsi takes to split a few values. */
INLINE void NAME(endgame)(const T *v, int64_t m, int64_t r, T low, int64_t c_low, T high, T *a, T *b) {
    T kept[ENDGAME * LANES]; /* kept[e * LANES + j]: the e-th smallest of lane j */
    for (int e = 0; e < ENDGAME * LANES; e++) kept[e] = (T) INFINITY;
    int64_t i = 0;
    for (; i + LANES <= m; i += LANES)
        for (int j = 0; j < LANES; j++) {
            T y = v[i + j] > low && v[i + j] <= high ? v[i + j] : (T) INFINITY;
            for (int e = 0; e < ENDGAME; e++) {
                T smaller = y < kept[e * LANES + j] ? y : kept[e * LANES + j];
                y = y < kept[e * LANES + j] ? kept[e * LANES + j] : y;
                kept[e * LANES + j] = smaller;
            }
        }
    for (; i < m; i++) {
        T y = v[i] > low && v[i] <= high ? v[i] : (T) INFINITY;
        for (int e = 0; e < ENDGAME; e++) {
            T smaller = y < kept[e * LANES] ? y : kept[e * LANES];
            y = y < kept[e * LANES] ? kept[e * LANES] : y;
            kept[e * LANES] = smaller;
        }
    }
    /* ranks need and need + 1 (1-based) among the kept values, by selection */
    int64_t need = r + 1 - c_low;
    for (int64_t rank = 0; rank <= need; rank++) {
        int64_t smallest = rank;
        for (int64_t e = rank + 1; e < ENDGAME * LANES; e++) smallest = kept[e] < kept[smallest] ? e : smallest;
        T swap = kept[rank];
        kept[rank] = kept[smallest];
        kept[smallest] = swap;
    }
    *a = kept[need - 1];
    *b = kept[need];
}

/* The values of ranks r and r + 1 (0-based, ascending) of a row with m >= 2.
 *
 * Searches a threshold t with exactly r + 1 values <= t by counting passes:
 * regula falsi on the empirical CDF (Illinois variant), about 8 passes for the
 * 4096 values of a noisy heatmap. After a step that kept over 3/4 of the values
 * in the bracket, the next threshold bisects the ordered bit patterns; a step
 * that moved the upper end past no value tests for a tie (``settle_tie``). So
 * neither clusters nor ties stall it: O(bits(T) + log m) passes. If no
 * representable threshold separates the two ranks, they hold the same value; a
 * median inside a large tie with values on both sides (the constant background
 * some networks output) takes about 20 passes, down to the tied value. A bracket
 * down to a few values ends with ``endgame``. */
INLINE void NAME(middle_pair)(const T *v, int64_t m, int64_t r, T minimum, T maximum, T *a, T *b) {
    int64_t want = r + 1;
    T low = NEXT(minimum, -INFINITY), high = maximum;
    int64_t c_low = 0, c_high = m;
    double f_low = -(want + 0.5), f_high = m - want - 0.5;
    int last_side = 0, bisect = 0;
    for (;;) {
        if (c_high - c_low <= ENDGAME && c_high > want) {
            NAME(endgame)(v, m, r, low, c_low, high, a, b);
            return;
        }
        T t = bisect ? NAME(key_midpoint)(low, high)
                     : (T) (low + ((double) high - low) * (f_low / (f_low - f_high)));
        if (!(t > low)) t = NEXT(low, high);
        if (!(t < high)) t = NEXT(high, low);
        if (!(t > low)) { *a = *b = high; return; }
        int64_t before = c_high - c_low, count = NAME(count_at_most)(v, m, t);
        if (count == want) { NAME(neighbours)(v, m, t, a, b); return; }
        if (count < want) {
            low = t; c_low = count; f_low = count - want - 0.5;
            if (last_side < 0) f_high *= 0.5;
            last_side = -1;
        } else {
            int empty_step = count == c_high && count - c_low > 64; /* passed no value: a tie? */
            high = t; c_high = count; f_high = count - want - 0.5;
            if (last_side > 0) f_low *= 0.5;
            last_side = 1;
            if (empty_step) {
                if (NAME(settle_tie)(v, m, want, &high, &c_high, a, b)) return;
                f_high = c_high - want - 0.5;
            }
        }
        bisect = 4 * (c_high - c_low) > 3 * before; /* kept over 3/4 of the bracket */
    }
}

INLINE double NAME(upper_half_sum)(const T *v, int64_t m, double minimum, double maximum) {
    T a, b;
    NAME(middle_pair)(v, m, (m - 1) / 2, (T) minimum, (T) maximum, &a, &b);
    double below = (double) a - minimum;
    double median = m % 2 ? below : (below + ((double) b - minimum)) / 2;
    return NAME(weights_at_least)(v, m, minimum, median);
}
