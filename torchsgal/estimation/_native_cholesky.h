/* Batched Cholesky factorisation and triangular solves of small dense systems (included by
 * estimation/_native.c once per element type T with suffix SFX): eight systems per pass, one per
 * vector lane (below), or, where the lanes' workspace is not wanted or not allocated, one system
 * at a time.
 *
 * Row-major storage throughout.  A (m, m) symmetric positive definite (its lower triangle is
 * read), L its lower Cholesky factor (A = L L^T, the strict upper triangle written as zeros),
 * R (m, k) right-hand sides.  One system at a time, the factor is the right-looking
 * (outer-product) form and the solves forward and back substitution, all by contiguous row
 * operations.  A pivot that is not positive (or not finite) stops the factorisation of that
 * matrix: info = its row + 1 (LAPACK's potrf convention) and the matrix's outputs are NaN;
 * info = 0 otherwise.
 */
#if defined(_MSC_VER) && !defined(restrict)
#define restrict __restrict /* C99's restrict, as MSVC spells it */
#endif
#define CAT_(a, b) a##_##b
#define CAT(a, b) CAT_(a, b)

/* L of A; 0, or the row + 1 of the first pivot that is not positive.  Right-looking, on the
 * upper factor U = L^T in L's memory: after each pivot the rows below it are updated by
 * contiguous row operations (they vectorise), then U is transposed into L. */
static inline int32_t CAT(cholesky_one, SFX)(const T *A, T *L, int64_t m) {
    for (int64_t i = 0; i < m; ++i)  /* the lower triangle of A, transposed: U's start */
        for (int64_t j = 0; j <= i; ++j) L[j * m + i] = A[i * m + j];
    for (int64_t k = 0; k < m; ++k) {
        T *Uk = L + k * m;
        const T d = Uk[k];
        if (!(d > 0) || !(d < INFINITY)) return (int32_t)(k + 1);
        Uk[k] = SQRT(d);
        const T r = 1 / Uk[k];
        for (int64_t j = k + 1; j < m; ++j) Uk[j] *= r;
        for (int64_t i = k + 1; i < m; ++i) {
            T *Ui = L + i * m;
            const T u = Uk[i];
            for (int64_t j = i; j < m; ++j) Ui[j] -= u * Uk[j];
        }
    }
    for (int64_t i = 0; i < m; ++i)
        for (int64_t j = i + 1; j < m; ++j) {
            L[j * m + i] = L[i * m + j];
            L[i * m + j] = 0;
        }
    return 0;
}

/* X = L^-1 R (forward substitution); X may be R */
static inline void CAT(forward_one, SFX)(const T *L, const T *R, T *X, int64_t m, int64_t k) {
    for (int64_t i = 0; i < m; ++i) {
        T *xi = X + i * k;
        if (X != R) memcpy(xi, R + i * k, (size_t)k * sizeof(T));
        for (int64_t j = 0; j < i; ++j) {
            const T l = L[i * m + j], *xj = X + j * k;
            for (int64_t c = 0; c < k; ++c) xi[c] -= l * xj[c];
        }
        const T r = 1 / L[i * m + i];
        for (int64_t c = 0; c < k; ++c) xi[c] *= r;
    }
}

/* Y = L^-T X (back substitution); Y may be X */
static inline void CAT(back_one, SFX)(const T *L, const T *X, T *Y, int64_t m, int64_t k) {
    for (int64_t i = m - 1; i >= 0; --i) {
        T *yi = Y + i * k;
        if (Y != X) memcpy(yi, X + i * k, (size_t)k * sizeof(T));
        for (int64_t j = i + 1; j < m; ++j) {
            const T l = L[j * m + i], *yj = Y + j * k;
            for (int64_t c = 0; c < k; ++c) yi[c] -= l * yj[c];
        }
        const T r = 1 / L[i * m + i];
        for (int64_t c = 0; c < k; ++c) yi[c] *= r;
    }
}

static void CAT(fill_nan, SFX)(T *p, int64_t n) {
    for (int64_t i = 0; i < n; ++i) p[i] = (T)NAN;
}

/* after cholesky_one's factor L (status f) of one system: X = L^-1 R and, with Y, Y = L^-T X;
 * a failed factor (f != 0) leaves NaN in L, X and Y */
static inline void CAT(solve_one, SFX)(int32_t f, T *L, const T *R, T *X, T *Y, int64_t m, int64_t k) {
    if (f) {
        CAT(fill_nan, SFX)(L, m * m);
        CAT(fill_nan, SFX)(X, m * k);
        if (Y) CAT(fill_nan, SFX)(Y, m * k);
        return;
    }
    CAT(forward_one, SFX)(L, R, X, m, k);
    if (Y) CAT(back_one, SFX)(L, X, Y, m, k);
}

/* Systems of at most LANE_MAX_M unknowns go LANES at a time, lane w of every array holding
 * system w: each step of the factor and the solves is one operation on LANES values (vector
 * instructions, and LANES independent chains where one system's steps wait on each other).
 * Every lane runs the same operations, so a system's result does not depend on its group. */
#ifndef LANES
#define LANES 8
#define LANE_MAX_M 64
#define LANE_COLS 16 /* right-hand-side columns per pass */
#endif

/* rows m of the lanes' factors l (lower triangle used), pivots' reciprocals r; bad[w] = the row
 * + 1 of lane w's first pivot that is not positive (0 if none; the lane goes on with pivot 1) */
static inline void CAT(lanes_factor, SFX)(T (*restrict l)[LANES], T (*restrict r)[LANES], int32_t *restrict bad,
                                         int64_t m) {
    for (int w = 0; w < LANES; ++w) bad[w] = 0;
    for (int64_t j = 0; j < m; ++j) {
        T d[LANES];
        for (int w = 0; w < LANES; ++w) d[w] = l[j * m + j][w];
        for (int64_t p = 0; p < j; ++p)
            for (int w = 0; w < LANES; ++w) d[w] -= l[j * m + p][w] * l[j * m + p][w];
        for (int w = 0; w < LANES; ++w) {
            const int ok = d[w] > 0 && d[w] < INFINITY;
            if (!ok && !bad[w]) bad[w] = (int32_t)(j + 1);
            d[w] = ok ? d[w] : 1;
        }
        for (int w = 0; w < LANES; ++w) {
            l[j * m + j][w] = SQRT(d[w]);
            r[j][w] = 1 / l[j * m + j][w];
        }
        for (int64_t i = j + 1; i < m; ++i) {
            T t[LANES];
            for (int w = 0; w < LANES; ++w) t[w] = l[i * m + j][w];
            for (int64_t p = 0; p < j; ++p)
                for (int w = 0; w < LANES; ++w) t[w] -= l[i * m + p][w] * l[j * m + p][w];
            for (int w = 0; w < LANES; ++w) l[i * m + j][w] = t[w] * r[j][w];
        }
    }
}

/* x (m rows of kc columns) = l^-1 x, or l^-T x with ``back`` */
static inline void CAT(lanes_solve, SFX)(T (*restrict l)[LANES], T (*restrict r)[LANES], T (*restrict x)[LANES], int64_t m,
                                        int64_t kc, int back) {
    for (int64_t s = 0; s < m; ++s) {
        const int64_t i = back ? m - 1 - s : s;
        T(*xi)[LANES] = x + i * kc;
        const int64_t p0 = back ? i + 1 : 0, p1 = back ? m : i;
        for (int64_t p = p0; p < p1; ++p) {
            const T *lp = back ? l[p * m + i] : l[i * m + p];
            T(*xp)[LANES] = x + p * kc;
            for (int64_t c = 0; c < kc; ++c)
                for (int w = 0; w < LANES; ++w) xi[c][w] -= lp[w] * xp[c][w];
        }
        for (int64_t c = 0; c < kc; ++c)
            for (int w = 0; w < LANES; ++w) xi[c][w] *= r[i][w];
    }
}

/* lanes <- columns [c0, c0 + kc) of n systems' (m, k) blocks at src (the last system repeated) */
static inline void CAT(lanes_load, SFX)(T (*restrict x)[LANES], const T *restrict src, int64_t n, int64_t m, int64_t k,
                                       int64_t c0, int64_t kc) {
    for (int w = 0; w < LANES; ++w) {
        const T *b = src + (w < n ? w : n - 1) * m * k;
        for (int64_t i = 0; i < m; ++i)
            for (int64_t c = 0; c < kc; ++c) x[i * kc + c][w] = b[i * k + c0 + c];
    }
}

static inline void CAT(lanes_store, SFX)(T (*restrict x)[LANES], T *restrict dst, int64_t n, int64_t m, int64_t k,
                                        int64_t c0, int64_t kc) {
    for (int64_t w = 0; w < n; ++w) {
        T *b = dst + w * m * k;
        for (int64_t i = 0; i < m; ++i)
            for (int64_t c = 0; c < kc; ++c) b[i * k + c0 + c] = x[i * kc + c][w];
    }
}

/* the systems [b0, b0 + n) (n <= LANES) of cholesky_solve_range, their matrices already in the
 * lanes l (lower triangle) */
WIDE_LANES static void CAT(lanes_factor_solve, SFX)(const T *R, T *L, T *X, T *Y, int32_t *info,
                                        int64_t b0, int64_t n, int64_t m, int64_t k, T (*l)[LANES],
                                        T (*r)[LANES], T (*x)[LANES]) {
    int32_t bad[LANES];
    CAT(lanes_factor, SFX)(l, r, bad, m);
    for (int64_t w = 0; w < n; ++w) {
        T *Lb = L + (b0 + w) * m * m;
        info[b0 + w] = bad[w];
        for (int64_t i = 0; i < m; ++i)
            for (int64_t j = 0; j < m; ++j) Lb[i * m + j] = bad[w] ? (T)NAN : j <= i ? l[i * m + j][w] : 0;
    }
    for (int64_t c0 = 0; c0 < k; c0 += LANE_COLS) {
        const int64_t kc = k - c0 < LANE_COLS ? k - c0 : LANE_COLS;
        CAT(lanes_load, SFX)(x, R + b0 * m * k, n, m, k, c0, kc);
        CAT(lanes_solve, SFX)(l, r, x, m, kc, 0);
        CAT(lanes_store, SFX)(x, X + b0 * m * k, n, m, k, c0, kc);
        if (Y) {
            CAT(lanes_solve, SFX)(l, r, x, m, kc, 1);
            CAT(lanes_store, SFX)(x, Y + b0 * m * k, n, m, k, c0, kc);
        }
    }
    for (int64_t w = 0; w < n; ++w)
        if (bad[w]) {
            CAT(fill_nan, SFX)(X + (b0 + w) * m * k, m * k);
            if (Y) CAT(fill_nan, SFX)(Y + (b0 + w) * m * k, m * k);
        }
}

/* the systems [b0, b0 + n) (n <= LANES) of cholesky_solve_range */
WIDE_LANES static void CAT(lanes_cholesky_solve, SFX)(const T *A, const T *R, T *L, T *X, T *Y, int32_t *info,
                                          int64_t b0, int64_t n, int64_t m, int64_t k, T (*l)[LANES],
                                          T (*r)[LANES], T (*x)[LANES]) {
    CAT(lanes_load, SFX)(l, A + b0 * m * m, n, m, m, 0, m);
    CAT(lanes_factor_solve, SFX)(R, L, X, Y, info, b0, n, m, k, l, r, x);
}

/* the lower triangle of A = G diag(d) G^T into the lanes l for the systems [b0, b0 + n): G (m, p)
 * per system, d (p) per system (d_stride p) or shared (d_stride 0); g: m * p lanes of workspace */
static inline void CAT(lanes_gram, SFX)(T (*restrict l)[LANES], T (*restrict g)[LANES], const T *restrict G,
                                       const T *restrict d, int64_t d_stride, int64_t b0, int64_t n,
                                       int64_t m, int64_t p) {
    CAT(lanes_load, SFX)(g, G + b0 * m * p, n, m, p, 0, p);
    T dw[LANES];
    for (int64_t i = 0; i < m; ++i)
        for (int64_t j = 0; j <= i; ++j)
            for (int w = 0; w < LANES; ++w) l[i * m + j][w] = 0;
    for (int64_t q = 0; q < p; ++q) {
        for (int w = 0; w < LANES; ++w) dw[w] = d[(b0 + (w < n ? w : n - 1)) * d_stride + q];
        for (int64_t j = 0; j < m; ++j) {
            T u[LANES];  /* d_q G[j, q] */
            for (int w = 0; w < LANES; ++w) u[w] = dw[w] * g[j * p + q][w];
            for (int64_t i = j; i < m; ++i)
                for (int w = 0; w < LANES; ++w) l[i * m + j][w] += g[i * p + q][w] * u[w];
        }
    }
}

/* the systems [b0, b0 + n) (n <= LANES) of gram_cholesky_solve_range */
WIDE_LANES static void CAT(lanes_gram_cholesky_solve, SFX)(const T *G, const T *d, int64_t d_stride, const T *R, T *L,
                                               T *X, T *Y, int32_t *info, int64_t b0, int64_t n, int64_t m,
                                               int64_t p, int64_t k, T (*l)[LANES], T (*r)[LANES],
                                               T (*x)[LANES], T (*g)[LANES]) {
    CAT(lanes_gram, SFX)(l, g, G, d, d_stride, b0, n, m, p);
    CAT(lanes_factor_solve, SFX)(R, L, X, Y, info, b0, n, m, k, l, r, x);
}

/* the systems [b0, b0 + n) (n <= LANES) of triangular_solve_range */
WIDE_LANES static void CAT(lanes_triangular_solve, SFX)(const T *Lin, const T *R, T *X, int64_t b0, int64_t n,
                                            int64_t m, int64_t k, int transpose, T (*l)[LANES],
                                            T (*r)[LANES], T (*x)[LANES]) {
    CAT(lanes_load, SFX)(l, Lin + b0 * m * m, n, m, m, 0, m);
    for (int64_t i = 0; i < m; ++i)
        for (int w = 0; w < LANES; ++w) r[i][w] = 1 / l[i * m + i][w];
    for (int64_t c0 = 0; c0 < k; c0 += LANE_COLS) {
        const int64_t kc = k - c0 < LANE_COLS ? k - c0 : LANE_COLS;
        CAT(lanes_load, SFX)(x, R + b0 * m * k, n, m, k, c0, kc);
        CAT(lanes_solve, SFX)(l, r, x, m, kc, transpose);
        CAT(lanes_store, SFX)(x, X + b0 * m * k, n, m, k, c0, kc);
    }
}

/* args: A, R, L, X, Y (null: not wanted), info, and m, k, lanes as int64 (lanes 0: one system at
 * a time, also where the lanes' workspace cannot be allocated) */
WIDE_LOOPS static void CAT(cholesky_solve_range, SFX)(void **args, int64_t lo, int64_t hi) {
    const T *A = args[0], *R = args[1];
    T *L = args[2], *X = args[3], *Y = args[4];
    int32_t *info = args[5];
    const int64_t m = *(const int64_t *)args[6], k = *(const int64_t *)args[7];
    T(*lanes)[LANES] = *(const int64_t *)args[8] && m <= LANE_MAX_M ? malloc((size_t)(m * m + m + m * LANE_COLS) * sizeof(T[LANES])) : NULL;
    if (lanes) {
        for (int64_t b = lo; b < hi; b += LANES)
            CAT(lanes_cholesky_solve, SFX)(A, R, L, X, Y, info, b, hi - b < LANES ? hi - b : LANES, m, k,
                                           lanes, lanes + m * m, lanes + m * m + m);
        free(lanes);
        return;
    }
    for (int64_t b = lo; b < hi; ++b) {
        T *Lb = L + b * m * m, *Xb = X + b * m * k, *Yb = Y ? Y + b * m * k : NULL;
        info[b] = CAT(cholesky_one, SFX)(A + b * m * m, Lb, m);
        CAT(solve_one, SFX)(info[b], Lb, R + b * m * k, Xb, Yb, m, k);
    }
}

/* args: G, d, R, L, X, Y (null: not wanted), info, and m, p, k, d_stride as int64: cholesky_solve_range
 * of A = G diag(d) G^T, formed in the lanes (one system at a time, A formed in L's memory and
 * factored there, where the lanes' workspace cannot be allocated) */
WIDE_LOOPS static void CAT(gram_cholesky_solve_range, SFX)(void **args, int64_t lo, int64_t hi) {
    const T *G = args[0], *d = args[1], *R = args[2];
    T *L = args[3], *X = args[4], *Y = args[5];
    int32_t *info = args[6];
    const int64_t m = *(const int64_t *)args[7], p = *(const int64_t *)args[8];
    const int64_t k = *(const int64_t *)args[9], d_stride = *(const int64_t *)args[10];
    T(*lanes)[LANES] = m <= LANE_MAX_M ? malloc((size_t)(m * m + m + m * LANE_COLS + m * p) * sizeof(T[LANES])) : NULL;
    if (lanes) {
        for (int64_t b = lo; b < hi; b += LANES)
            CAT(lanes_gram_cholesky_solve, SFX)(G, d, d_stride, R, L, X, Y, info, b, hi - b < LANES ? hi - b : LANES,
                                                m, p, k, lanes, lanes + m * m, lanes + m * m + m,
                                                lanes + m * m + m + m * LANE_COLS);
        free(lanes);
        return;
    }
    for (int64_t b = lo; b < hi; ++b) {
        T *Lb = L + b * m * m, *Xb = X + b * m * k, *Yb = Y ? Y + b * m * k : NULL;
        const T *Gb = G + b * m * p, *db = d + b * d_stride;
        for (int64_t i = 0; i < m; ++i)  /* A's lower triangle in L's memory: factored in place */
            for (int64_t j = 0; j <= i; ++j) {
                T acc = 0;
                for (int64_t q = 0; q < p; ++q) acc += Gb[i * p + q] * db[q] * Gb[j * p + q];
                Lb[i * m + j] = acc;
            }
        info[b] = CAT(cholesky_one, SFX)(Lb, Lb, m);
        CAT(solve_one, SFX)(info[b], Lb, R + b * m * k, Xb, Yb, m, k);
    }
}

/* args: L, R, X, and m, k, transpose, lanes as int64: X = L^-1 R, or L^-T R */
WIDE_LOOPS static void CAT(triangular_solve_range, SFX)(void **args, int64_t lo, int64_t hi) {
    const T *L = args[0], *R = args[1];
    T *X = args[2];
    const int64_t m = *(const int64_t *)args[3], k = *(const int64_t *)args[4];
    const int64_t transpose = *(const int64_t *)args[5];
    T(*lanes)[LANES] = *(const int64_t *)args[6] && m <= LANE_MAX_M ? malloc((size_t)(m * m + m + m * LANE_COLS) * sizeof(T[LANES])) : NULL;
    if (lanes) {
        for (int64_t b = lo; b < hi; b += LANES)
            CAT(lanes_triangular_solve, SFX)(L, R, X, b, hi - b < LANES ? hi - b : LANES, m, k, (int)transpose,
                                             lanes, lanes + m * m, lanes + m * m + m);
        free(lanes);
        return;
    }
    for (int64_t b = lo; b < hi; ++b) {
        if (transpose)
            CAT(back_one, SFX)(L + b * m * m, R + b * m * k, X + b * m * k, m, k);
        else
            CAT(forward_one, SFX)(L + b * m * m, R + b * m * k, X + b * m * k, m, k);
    }
}

/* The damped normal equations of a Levenberg-Marquardt step, n systems (estimation/graph/
 * damped_solve.py): (H + lam D) delta = -g, D = I, or with ``diagonal`` D = diag(H) clamped to
 * [clamp[0], clamp[1]]; solved = the factor succeeded and delta is finite (else delta = 0),
 * quad = delta^T H delta (the undamped H, all of it read).  args: H (n, m, m), g (n, m),
 * lam (n), delta (n, m), solved (n) uint8, quad (n), clamp (2 doubles), and m, diagonal as
 * int64.  Where the lanes' workspace cannot be allocated, one system at a time in a buffer of
 * m * m (and where not even that can be, every step unsolved). */
static inline T CAT(damping_of, SFX)(const T *Hb, int64_t i, int64_t m, T lam, int64_t diagonal,
                                    const double *clamp) {
    if (!diagonal) return lam;
    const T d = Hb[i * m + i], lo = (T)clamp[0], hi = (T)clamp[1];
    return lam * (d < lo ? lo : d > hi ? hi : d); /* clamp: NaN stays NaN */
}

static inline void CAT(damped_finish, SFX)(const T *Hb, T *db, uint8_t *solved, T *quad, int ok, int64_t m) {
    for (int64_t i = 0; i < m; ++i) ok = ok && isfinite(db[i]);
    solved[0] = (uint8_t)ok;
    T q = 0;
    for (int64_t i = 0; i < m; ++i) {
        if (!ok) db[i] = 0;
    }
    if (ok)
        for (int64_t i = 0; i < m; ++i) {
            T row = 0;
            for (int64_t j = 0; j < m; ++j) row += Hb[i * m + j] * db[j];
            q += db[i] * row;
        }
    quad[0] = q;
}

WIDE_LOOPS static void CAT(damped_solve_range, SFX)(void **args, int64_t lo, int64_t hi) {
    const T *H = args[0], *g = args[1], *lam = args[2];
    T *delta = args[3], *quad = args[5];
    uint8_t *solved = args[4];
    const double *clamp = args[6];
    const int64_t m = *(const int64_t *)args[7], diagonal = *(const int64_t *)args[8];
    T(*lanes)[LANES] = m <= LANE_MAX_M ? malloc((size_t)(m * m + 2 * m) * sizeof(T[LANES])) : NULL;
    if (lanes) {
        T(*l)[LANES] = lanes, (*r)[LANES] = lanes + m * m, (*x)[LANES] = lanes + m * m + m;
        for (int64_t b0 = lo; b0 < hi; b0 += LANES) {
            const int64_t n = hi - b0 < LANES ? hi - b0 : LANES;
            int32_t bad[LANES];
            CAT(lanes_load, SFX)(l, H + b0 * m * m, n, m, m, 0, m);
            for (int w = 0; w < LANES; ++w) {
                const int64_t b = b0 + (w < n ? w : n - 1);
                for (int64_t i = 0; i < m; ++i) {
                    l[i * m + i][w] += CAT(damping_of, SFX)(H + b * m * m, i, m, lam[b], diagonal, clamp);
                    x[i][w] = -g[b * m + i];
                }
            }
            CAT(lanes_factor, SFX)(l, r, bad, m);
            CAT(lanes_solve, SFX)(l, r, x, m, 1, 0);
            CAT(lanes_solve, SFX)(l, r, x, m, 1, 1);
            for (int64_t w = 0; w < n; ++w) {
                const int64_t b = b0 + w;
                T *db = delta + b * m;
                for (int64_t i = 0; i < m; ++i) db[i] = x[i][w];
                CAT(damped_finish, SFX)(H + b * m * m, db, solved + b, quad + b, !bad[w], m);
            }
        }
        free(lanes);
        return;
    }
    T *Wb = malloc((size_t)(m * m > 0 ? m * m : 1) * sizeof(T));
    for (int64_t b = lo; b < hi; ++b) { /* one system at a time: the damped H in Wb, factored in place */
        const T *Hb = H + b * m * m;
        T *db = delta + b * m;
        if (!Wb) {
            for (int64_t i = 0; i < m; ++i) db[i] = 0;
            solved[b] = 0;
            quad[b] = 0;
            continue;
        }
        for (int64_t i = 0; i < m * m; ++i) Wb[i] = Hb[i];
        for (int64_t i = 0; i < m; ++i) {
            Wb[i * m + i] += CAT(damping_of, SFX)(Hb, i, m, lam[b], diagonal, clamp);
            db[i] = -g[b * m + i];
        }
        const int32_t f = CAT(cholesky_one, SFX)(Wb, Wb, m);
        if (!f) {
            CAT(forward_one, SFX)(Wb, db, db, m, 1);
            CAT(back_one, SFX)(Wb, db, db, m, 1);
        }
        CAT(damped_finish, SFX)(Hb, db, solved + b, quad + b, !f, m);
    }
    free(Wb);
}

#undef CAT
#undef CAT_
#undef T
#undef SFX
#undef SQRT
