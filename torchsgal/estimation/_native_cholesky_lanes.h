/* The lane loops of _native_cholesky.h, included by it for its element type T (suffix SFX) once
 * per lane layout: LANES systems per pass, lane w of every lane vector (LV) holding system w.  A
 * lane vector is LANE_GROUPS machine vectors (MV) of LANE_BYTES each: each step of the factor and
 * the solves is one operation on each of them, the groups' operations side by side (independent
 * chains where one system's steps wait on each other), and each sum runs in registers over its
 * terms in the order of one system's loops.  Every lane runs the same operations, so a system's
 * result does not depend on its group or on the lane layout.  The includer sets LANE_BYTES,
 * LANE_GROUPS, LANE_SFX (the suffix of the names defined here) and LANE_TARGET (the functions'
 * target attribute, or nothing); undefined at the end.  Without GCC/Clang's vector types, a
 * machine vector is one value of T.
 *
 * Lanes written one value at a time (the inputs, transposed into the lanes) are read as vectors
 * only after other work where that is cheap: a vector read of values still on their way to memory
 * waits for them. */
#define LK(name) CAT(name, LANE_SFX)
#define MV LK(lane_vec)
#define VM LK(lane_mask) /* a comparison's result: all bits set in a lane where it holds */
#define LV LK(lanes)
#define LG LANE_GROUPS
#if defined(__GNUC__)
#define VW (LANE_BYTES / (int)sizeof(T)) /* values in a machine vector */
typedef T MV __attribute__((vector_size(LANE_BYTES)));
#ifndef LANE_INTS
#define LANE_INTS
typedef int64_t lane_int_f64;
typedef int32_t lane_int_f32;
#endif
typedef CAT(lane_int, SFX) VM __attribute__((vector_size(LANE_BYTES)));
#define VLANE(v, w) ((v)[w])
#define MASK_SELECT(ok, a, b) (((ok) & (a)) | (~(ok) & (b))) /* ok ? a : b by lane, a and b VM */
#define LANE_SELECT(ok, a, b) ((MV)MASK_SELECT(ok, (VM)(a), (VM)(b)))
#else
#define VW 1
typedef T MV;
typedef int VM;
#define VLANE(v, w) (v)
#define MASK_SELECT(ok, a, b) ((ok) ? (a) : (b))
#define LANE_SELECT(ok, a, b) ((ok) ? (a) : (b))
#endif
#define LANES (LG * VW)
typedef MV LV[LG];
#define LANE(x, w) VLANE((x)[(w) / VW], (w) % VW) /* lane w of a lane vector */
#define EACH for (int u = 0; u < LG; ++u)          /* each machine vector of the lane vectors */

/* n lane vectors aligned to a machine vector (the address to free in *raw), NULL where malloc
 * fails */
static inline LV *LK(lanes_alloc)(int64_t n, void **raw) {
    *raw = malloc((size_t)n * sizeof(LV) + sizeof(MV));
    return *raw ? (LV *)(((uintptr_t)*raw + sizeof(MV) - 1) & ~(uintptr_t)(sizeof(MV) - 1)) : NULL;
}

/* rows m of the lanes' factors l (lower triangle used), pivots' reciprocals r; bad[w] = the row
 * + 1 of lane w's first pivot that is not positive (0 if none; the lane goes on with pivot 1).
 * Left-looking: entry (i, j) is A's less the products of rows i and j left of column j, four
 * rows at a time. */
LANE_TARGET static inline void LK(lanes_factor)(LV *restrict l, LV *restrict r, int32_t *restrict bad, int64_t m) {
    const MV one = (MV){0} + 1;
    VM first[LG]; /* bad, by lane */
    EACH first[u] = (VM){0};
    for (int64_t j = 0; j < m; ++j) {
        const LV *lj = l + j * m;
        MV d[LG];
        EACH d[u] = lj[j][u];
        for (int64_t p = 0; p < j; ++p) EACH d[u] -= lj[p][u] * lj[p][u];
        EACH {
            const VM ok = (d[u] > 0) & (d[u] < INFINITY), row = (VM){0} + (int32_t)(j + 1);
            MV s;
            first[u] = MASK_SELECT(ok | (first[u] != 0), first[u], row);
            d[u] = LANE_SELECT(ok, d[u], one);
            for (int w = 0; w < VW; ++w) VLANE(s, w) = SQRT(VLANE(d[u], w));
            l[j * m + j][u] = s;
            r[j][u] = 1 / s;
        }
        int64_t i = j + 1;
        for (; i + 4 <= m; i += 4) {
            const LV *l0 = l + i * m, *l1 = l0 + m, *l2 = l1 + m, *l3 = l2 + m;
            MV t0[LG], t1[LG], t2[LG], t3[LG];
            EACH {
                t0[u] = l0[j][u];
                t1[u] = l1[j][u];
                t2[u] = l2[j][u];
                t3[u] = l3[j][u];
            }
            for (int64_t p = 0; p < j; ++p) EACH {
                t0[u] -= l0[p][u] * lj[p][u];
                t1[u] -= l1[p][u] * lj[p][u];
                t2[u] -= l2[p][u] * lj[p][u];
                t3[u] -= l3[p][u] * lj[p][u];
            }
            EACH {
                l[i * m + j][u] = t0[u] * r[j][u];
                l[(i + 1) * m + j][u] = t1[u] * r[j][u];
                l[(i + 2) * m + j][u] = t2[u] * r[j][u];
                l[(i + 3) * m + j][u] = t3[u] * r[j][u];
            }
        }
        for (; i < m; ++i) {
            const LV *li = l + i * m;
            MV t[LG];
            EACH t[u] = li[j][u];
            for (int64_t p = 0; p < j; ++p) EACH t[u] -= li[p][u] * lj[p][u];
            EACH l[i * m + j][u] = t[u] * r[j][u];
        }
    }
    for (int w = 0; w < LANES; ++w) bad[w] = (int32_t)LANE(first, w);
}

/* x (m rows of kc columns) = l^-1 x, or l^-T x with ``back``: each entry of row i less its
 * products with the rows solved before (in their order), times r[i]; four columns at a time */
LANE_TARGET static inline void LK(lanes_solve)(const LV *restrict l, const LV *restrict r, LV *restrict x, int64_t m,
                                             int64_t kc, int back) {
    for (int64_t s = 0; s < m; ++s) {
        const int64_t i = back ? m - 1 - s : s;
        const int64_t p0 = back ? i + 1 : 0, p1 = back ? m : i;
        const LV *li = back ? l + i : l + i * m; /* l[i, p] (l[p, i] with back) at li[p * step] */
        const int64_t step = back ? m : 1;
        LV *xi = x + i * kc;
        int64_t c = 0;
        for (; c + 4 <= kc; c += 4) {
            MV t0[LG], t1[LG], t2[LG], t3[LG];
            EACH {
                t0[u] = xi[c][u];
                t1[u] = xi[c + 1][u];
                t2[u] = xi[c + 2][u];
                t3[u] = xi[c + 3][u];
            }
            for (int64_t p = p0; p < p1; ++p) {
                const LV *a = li + p * step, *xp = x + p * kc + c;
                EACH {
                    t0[u] -= (*a)[u] * xp[0][u];
                    t1[u] -= (*a)[u] * xp[1][u];
                    t2[u] -= (*a)[u] * xp[2][u];
                    t3[u] -= (*a)[u] * xp[3][u];
                }
            }
            EACH {
                xi[c][u] = t0[u] * r[i][u];
                xi[c + 1][u] = t1[u] * r[i][u];
                xi[c + 2][u] = t2[u] * r[i][u];
                xi[c + 3][u] = t3[u] * r[i][u];
            }
        }
        for (; c < kc; ++c) {
            MV t[LG];
            EACH t[u] = xi[c][u];
            for (int64_t p = p0; p < p1; ++p) EACH t[u] -= li[p * step][u] * x[p * kc + c][u];
            EACH xi[c][u] = t[u] * r[i][u];
        }
    }
}

/* Whole blocks of at most LANE_SMALL bytes go between memory and the lanes entry by entry, all
 * lanes at once (the few cache lines of a group together); larger ones lane by lane (one system's
 * memory in order: fewer waits on memory than all systems' in step). */
#define LANE_SMALL 288

/* lanes <- columns [c0, c0 + kc) of n systems' (m, k) blocks at src (the last system repeated) */
LANE_TARGET static inline void LK(lanes_load)(LV *restrict x, const T *restrict src, int64_t n, int64_t m, int64_t k,
                                            int64_t c0, int64_t kc) {
    if (kc == k && m * k * (int64_t)sizeof(T) <= LANE_SMALL) {
        const T *b[LANES];
        for (int w = 0; w < LANES; ++w) b[w] = src + (w < n ? w : n - 1) * m * k;
        for (int64_t i = 0; i < m * k; ++i) EACH {
            MV v;
            for (int w = 0; w < VW; ++w) VLANE(v, w) = b[u * VW + w][i];
            x[i][u] = v;
        }
        return;
    }
    for (int w = 0; w < LANES; ++w) {
        const T *b = src + (w < n ? w : n - 1) * m * k;
        if (kc == k)
            for (int64_t i = 0; i < m * k; ++i) LANE(x[i], w) = b[i];
        else
            for (int64_t i = 0; i < m; ++i)
                for (int64_t c = 0; c < kc; ++c) LANE(x[i * kc + c], w) = b[i * k + c0 + c];
    }
}

/* lanes <- the lower triangles of n systems' (m, m) matrices at src (the last system repeated);
 * below 12 unknowns the whole matrices, in one loop (fewer steps) */
LANE_TARGET static inline void LK(lanes_load_lower)(LV *restrict l, const T *restrict src, int64_t n, int64_t m) {
    if (m < 12) {
        LK(lanes_load)(l, src, n, m, m, 0, m);
        return;
    }
    for (int w = 0; w < LANES; ++w) {
        const T *b = src + (w < n ? w : n - 1) * m * m;
        for (int64_t i = 0; i < m; ++i)
            for (int64_t j = 0; j <= i; ++j) LANE(l[i * m + j], w) = b[i * m + j];
    }
}

LANE_TARGET static inline void LK(lanes_store)(const LV *restrict x, T *restrict dst, int64_t n, int64_t m, int64_t k,
                                             int64_t c0, int64_t kc) {
    if (n == LANES && kc == k && m * k * (int64_t)sizeof(T) <= LANE_SMALL) {
        for (int64_t i = 0; i < m * k; ++i) EACH {
            const MV v = x[i][u];
            for (int w = 0; w < VW; ++w) dst[(u * VW + w) * m * k + i] = VLANE(v, w);
        }
        return;
    }
    for (int64_t w = 0; w < n; ++w) {
        T *b = dst + w * m * k;
        if (kc == k)
            for (int64_t i = 0; i < m * k; ++i) b[i] = LANE(x[i], w);
        else
            for (int64_t i = 0; i < m; ++i)
                for (int64_t c = 0; c < kc; ++c) b[i * k + c0 + c] = LANE(x[i * kc + c], w);
    }
}

/* the systems [b0, b0 + n) (n <= LANES) of cholesky_solve_range, their matrices already in the
 * lanes l (lower triangle); r: m lanes, x: m * LANE_COLS lanes of workspace */
LANE_TARGET static void LK(lanes_factor_solve)(const T *R, T *L, T *X, T *Y, int32_t *info, int64_t b0, int64_t n,
                                             int64_t m, int64_t k, LV *l, LV *r, LV *x) {
    int32_t bad[LANES];
    LK(lanes_factor)(l, r, bad, m);
    for (int64_t w = 0; w < n; ++w) {
        T *Lb = L + (b0 + w) * m * m;
        info[b0 + w] = bad[w];
        if (bad[w]) {
            CAT(fill_nan, SFX)(Lb, m * m);
            continue;
        }
        for (int64_t i = 0; i < m; ++i)
            for (int64_t j = 0; j < m; ++j) Lb[i * m + j] = j <= i ? LANE(l[i * m + j], w) : 0;
    }
    for (int64_t c0 = 0; c0 < k; c0 += LANE_COLS) {
        const int64_t kc = k - c0 < LANE_COLS ? k - c0 : LANE_COLS;
        LK(lanes_load)(x, R + b0 * m * k, n, m, k, c0, kc);
        LK(lanes_solve)(l, r, x, m, kc, 0);
        LK(lanes_store)(x, X + b0 * m * k, n, m, k, c0, kc);
        if (Y) {
            LK(lanes_solve)(l, r, x, m, kc, 1);
            LK(lanes_store)(x, Y + b0 * m * k, n, m, k, c0, kc);
        }
    }
    for (int64_t w = 0; w < n; ++w)
        if (bad[w]) {
            CAT(fill_nan, SFX)(X + (b0 + w) * m * k, m * k);
            if (Y) CAT(fill_nan, SFX)(Y + (b0 + w) * m * k, m * k);
        }
}

/* cholesky_solve_range's systems [lo, hi) of at most LANE_MAX_M unknowns; 0 where the workspace
 * cannot be allocated (nothing done) */
LANE_TARGET static int LK(cholesky_solve_lanes)(void **args, int64_t lo, int64_t hi) {
    const T *A = args[0], *R = args[1];
    T *L = args[2], *X = args[3], *Y = args[4];
    int32_t *info = args[5];
    const int64_t m = *(const int64_t *)args[6], k = *(const int64_t *)args[7];
    void *raw;
    LV *l = LK(lanes_alloc)(m * m + m + m * LANE_COLS, &raw);
    if (!l) return 0;
    LV *r = l + m * m, *x = r + m;
    for (int64_t b = lo; b < hi; b += LANES) {
        const int64_t n = hi - b < LANES ? hi - b : LANES;
        LK(lanes_load_lower)(l, A + b * m * m, n, m);
        LK(lanes_factor_solve)(R, L, X, Y, info, b, n, m, k, l, r, x);
    }
    free(raw);
    return 1;
}

/* the lower triangle of A = G diag(d) G^T into the lanes l for the systems [b0, b0 + n): G (m, p)
 * per system, d (p) per system (d_stride p) or shared (d_stride 0); workspace: g and gd m * p
 * lanes (G, and d_q G[j, q]), dv p lanes (d).  Entry (i, j) sums G[i, q] (d_q G[j, q]) from 0 in
 * the order of q, four entries of a row at a time. */
LANE_TARGET static inline void LK(lanes_gram)(LV *restrict l, LV *restrict g, LV *restrict gd, LV *restrict dv,
                                            const T *restrict G, const T *restrict d, int64_t d_stride,
                                            int64_t b0, int64_t n, int64_t m, int64_t p) {
    for (int w = 0; w < LANES; ++w)
        for (int64_t q = 0; q < p; ++q) LANE(dv[q], w) = d[(b0 + (w < n ? w : n - 1)) * d_stride + q];
    LK(lanes_load)(g, G + b0 * m * p, n, m, p, 0, p);
    for (int64_t j = 0; j < m; ++j)
        for (int64_t q = 0; q < p; ++q) EACH gd[j * p + q][u] = dv[q][u] * g[j * p + q][u];
    for (int64_t i = 0; i < m; ++i) {
        const LV *gi = g + i * p;
        int64_t j = 0;
        for (; j + 4 <= i + 1; j += 4) {
            const LV *g0 = gd + j * p, *g1 = g0 + p, *g2 = g1 + p, *g3 = g2 + p;
            MV t0[LG], t1[LG], t2[LG], t3[LG];
            EACH t0[u] = t1[u] = t2[u] = t3[u] = (MV){0};
            for (int64_t q = 0; q < p; ++q) EACH {
                t0[u] += gi[q][u] * g0[q][u];
                t1[u] += gi[q][u] * g1[q][u];
                t2[u] += gi[q][u] * g2[q][u];
                t3[u] += gi[q][u] * g3[q][u];
            }
            EACH {
                l[i * m + j][u] = t0[u];
                l[i * m + j + 1][u] = t1[u];
                l[i * m + j + 2][u] = t2[u];
                l[i * m + j + 3][u] = t3[u];
            }
        }
        for (; j <= i; ++j) {
            const LV *gj = gd + j * p;
            MV t[LG];
            EACH t[u] = (MV){0};
            for (int64_t q = 0; q < p; ++q) EACH t[u] += gi[q][u] * gj[q][u];
            EACH l[i * m + j][u] = t[u];
        }
    }
}

/* gram_cholesky_solve_range's systems [lo, hi) of at most LANE_MAX_M unknowns; 0 where the
 * workspace cannot be allocated (nothing done) */
LANE_TARGET static int LK(gram_cholesky_solve_lanes)(void **args, int64_t lo, int64_t hi) {
    const T *G = args[0], *d = args[1], *R = args[2];
    T *L = args[3], *X = args[4], *Y = args[5];
    int32_t *info = args[6];
    const int64_t m = *(const int64_t *)args[7], p = *(const int64_t *)args[8];
    const int64_t k = *(const int64_t *)args[9], d_stride = *(const int64_t *)args[10];
    void *raw;
    LV *l = LK(lanes_alloc)(m * m + m + m * LANE_COLS + 2 * m * p + p, &raw);
    if (!l) return 0;
    LV *r = l + m * m, *x = r + m;
    LV *g = x + m * LANE_COLS, *gd = g + m * p, *dv = gd + m * p;
    for (int64_t b = lo; b < hi; b += LANES) {
        const int64_t n = hi - b < LANES ? hi - b : LANES;
        LK(lanes_gram)(l, g, gd, dv, G, d, d_stride, b, n, m, p);
        LK(lanes_factor_solve)(R, L, X, Y, info, b, n, m, k, l, r, x);
    }
    free(raw);
    return 1;
}

/* triangular_solve_range's systems [lo, hi) of at most LANE_MAX_M unknowns; 0 where the workspace
 * cannot be allocated (nothing done) */
LANE_TARGET static int LK(triangular_solve_lanes)(void **args, int64_t lo, int64_t hi) {
    const T *Lin = args[0], *R = args[1];
    T *X = args[2];
    const int64_t m = *(const int64_t *)args[3], k = *(const int64_t *)args[4];
    const int transpose = *(const int64_t *)args[5] != 0;
    void *raw;
    LV *l = LK(lanes_alloc)(m * m + m + m * LANE_COLS, &raw);
    if (!l) return 0;
    LV *r = l + m * m, *x = r + m;
    for (int64_t b = lo; b < hi; b += LANES) {
        const int64_t n = hi - b < LANES ? hi - b : LANES;
        LK(lanes_load_lower)(l, Lin + b * m * m, n, m);
        for (int64_t i = 0; i < m; ++i) EACH r[i][u] = 1 / l[i * m + i][u];
        for (int64_t c0 = 0; c0 < k; c0 += LANE_COLS) {
            const int64_t kc = k - c0 < LANE_COLS ? k - c0 : LANE_COLS;
            LK(lanes_load)(x, R + b * m * k, n, m, k, c0, kc);
            LK(lanes_solve)(l, r, x, m, kc, transpose);
            LK(lanes_store)(x, X + b * m * k, n, m, k, c0, kc);
        }
    }
    free(raw);
    return 1;
}

/* damped_solve_range's systems [lo, hi) of at most LANE_MAX_M unknowns; 0 where the workspace
 * cannot be allocated (nothing done).  The damping and -g go into the lanes before H; h keeps H
 * for quad. */
LANE_TARGET static int LK(damped_solve_lanes)(void **args, int64_t lo, int64_t hi) {
    const T *H = args[0], *g = args[1], *lam = args[2];
    T *delta = args[3], *quad = args[5];
    uint8_t *solved = args[4];
    const double *clamp = args[6];
    const int64_t m = *(const int64_t *)args[7], diagonal = *(const int64_t *)args[8];
    void *raw;
    LV *l = LK(lanes_alloc)(2 * m * m + 2 * m, &raw);
    if (!l) return 0;
    LV *r = l + m * m, *x = r + m, *h = x + m;
    for (int64_t b0 = lo; b0 < hi; b0 += LANES) {
        const int64_t n = hi - b0 < LANES ? hi - b0 : LANES;
        int32_t bad[LANES];
        for (int w = 0; w < LANES; ++w) {
            const int64_t b = b0 + (w < n ? w : n - 1);
            for (int64_t i = 0; i < m; ++i) {
                LANE(r[i], w) = CAT(damping_of, SFX)(H + b * m * m, i, m, lam[b], diagonal, clamp);
                LANE(x[i], w) = -g[b * m + i];
            }
        }
        LK(lanes_load)(h, H + b0 * m * m, n, m, m, 0, m);
        for (int64_t i = 0; i < m; ++i) EACH {
            for (int64_t j = 0; j < i; ++j) l[i * m + j][u] = h[i * m + j][u];
            l[i * m + i][u] = h[i * m + i][u] + r[i][u];
        }
        LK(lanes_factor)(l, r, bad, m);
        LK(lanes_solve)(l, r, x, m, 1, 0);
        LK(lanes_solve)(l, r, x, m, 1, 1);
        LV q;
        EACH q[u] = (MV){0};
        for (int64_t i = 0; i < m; ++i) {
            MV row[LG];
            EACH row[u] = (MV){0};
            for (int64_t j = 0; j < m; ++j) EACH row[u] += h[i * m + j][u] * x[j][u];
            EACH q[u] += x[i][u] * row[u];
        }
        for (int64_t w = 0; w < n; ++w) {
            const int64_t b = b0 + w;
            T *db = delta + b * m;
            for (int64_t i = 0; i < m; ++i) db[i] = LANE(x[i], w);
            CAT(damped_finish, SFX)(db, solved + b, quad + b, !bad[w], LANE(q, w), m);
        }
    }
    free(raw);
    return 1;
}

#undef EACH
#undef LANE
#undef LANES
#undef VLANE
#undef LANE_SELECT
#undef MASK_SELECT
#undef VW
#undef LG
#undef LV
#undef VM
#undef MV
#undef LK
#undef LANE_SMALL
#undef LANE_BYTES
#undef LANE_GROUPS
#undef LANE_SFX
#undef LANE_TARGET
