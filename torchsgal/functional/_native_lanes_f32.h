/* Float32 kernels that run LOG_LANES elements per pass (included by _native.c after the float32
 * _native_sgal3.h, whose per-element loops they fall back on).
 *
 * so3_log: rotation_log's two paths (the skew part, phi = theta / sin(theta) s, and the
 * symmetric part's column of largest diagonal where cos(theta) < LOG_SYMMETRIC_COS, i.e. for
 * most rotations of random orientation) are both evaluated in every lane and one is kept by a
 * select, with atan2_f32's branch-free part, so the compiler turns the loop over the lanes into
 * vector operations.  Every lane runs rotation_log's operations in its order: the bits are
 * rotation_log_f32's (so3_log_range_f32's), wherever an element falls in the batch.  A pass with
 * a lane whose arguments of atan2 are huge or not finite (atan2_f32's rare branches, and NaN), or
 * whose matrix has an entry that is not finite (NaN out), is run again by so3_log_range_f32, as
 * is the tail of the range.
 */

#define LOG_LANES 8

WIDE_LOOPS static void so3_log_lanes_range_f32(void **a, int64_t lo, int64_t hi) {
    const float *in = a[0];
    float *out = a[1];
    const float symmetric_cos = (float)LOG_SYMMETRIC_COS, sin_taylor = (float)LOG_SIN_TAYLOR;
    int64_t i = lo;
    for (; i + LOG_LANES <= hi; i += LOG_LANES) {
        float c[9][LOG_LANES], phi[3][LOG_LANES];
        int redo = 0;
        for (int w = 0; w < LOG_LANES; ++w)
            for (int t = 0; t < 9; ++t) c[t][w] = in[9 * (i + w) + t];
        for (int w = 0; w < LOG_LANES; ++w) {
            const float c00 = c[0][w], c01 = c[1][w], c02 = c[2][w], c10 = c[3][w], c11 = c[4][w];
            const float c12 = c[5][w], c20 = c[6][w], c21 = c[7][w], c22 = c[8][w];
            const float s0 = 0.5f * (c21 - c12), s1 = 0.5f * (c02 - c20), s2 = 0.5f * (c10 - c01);
            const float cs = 0.5f * (c00 + c11 + c22 - 1.0f);
            const float ss = s0 * s0 + s1 * s1 + s2 * s2;
            const float sn = select_f32(ss > 0, sqrtf(ss), 0.0f), acs = fabsf(cs);
            const int swap = sn > acs;
            const float mx = select_f32(swap, sn, acs), mn = select_f32(swap, acs, sn);
            const float theta = atan2_f32_reduced(sn, cs, mx, mn, swap);
            const float z = c00 * 0.0f + c01 * 0.0f + c02 * 0.0f + c10 * 0.0f + c11 * 0.0f + c12 * 0.0f
                            + c20 * 0.0f + c21 * 0.0f + c22 * 0.0f;  /* NaN where an entry is not finite */
            redo |= !(mx <= 1.0e38f) | (z != z);
            /* near pi: the column of the symmetric part with the largest diagonal */
            const float d0 = c00 - cs, d1 = c11 - cs, d2 = c22 - cs;
            const float s01 = 0.5f * (c01 + c10), s02 = 0.5f * (c02 + c20), s12 = 0.5f * (c12 + c21);
            const int first = (d0 >= d1) & (d0 >= d2), second = d1 >= d2;
            const float q0 = select_f32(first, d0, select_f32(second, s01, s02));
            const float q1 = select_f32(first, s01, select_f32(second, d1, s12));
            const float q2 = select_f32(first, s02, select_f32(second, s12, d2));
            const float sign = select_f32(q0 * s0 + q1 * s1 + q2 * s2 < 0, -1.0f, 1.0f);
            const float f = sign * theta / sqrtf(q0 * q0 + q1 * q1 + q2 * q2);
            /* elsewhere: theta / sin(theta) (its series near 0) times the skew part */
            const float t2 = theta * theta;
            const float ratio = select_f32(sn < sin_taylor, 1.0f + t2 / 6.0f + 7.0f * t2 * t2 / 360.0f,
                                           theta / sn);
            const int symmetric = cs < symmetric_cos;
            phi[0][w] = select_f32(symmetric, f * q0, ratio * s0);
            phi[1][w] = select_f32(symmetric, f * q1, ratio * s1);
            phi[2][w] = select_f32(symmetric, f * q2, ratio * s2);
        }
        for (int w = 0; w < LOG_LANES; ++w)
            for (int t = 0; t < 3; ++t) out[3 * (i + w) + t] = phi[t][w];
        if (redo) so3_log_range_f32(a, i, i + LOG_LANES);
    }
    so3_log_range_f32(a, i, hi);
}
