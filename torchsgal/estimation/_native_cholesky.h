/* Batched Cholesky factorisation and triangular solves of small dense systems (included by
 * estimation/_native.c once per element type T with suffix SFX): a vector's width of systems per
 * pass, one per vector lane (_native_cholesky_lanes.h), or, where the lanes' workspace is not
 * wanted or not allocated, one system at a time.
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

/* the damping added to H's diagonal entry i (damped_solve_range) */
static inline T CAT(damping_of, SFX)(const T *Hb, int64_t i, int64_t m, T lam, int64_t diagonal,
                                    const double *clamp) {
    if (!diagonal) return lam;
    const T d = Hb[i * m + i], lo = (T)clamp[0], hi = (T)clamp[1];
    return lam * (d < lo ? lo : d > hi ? hi : d); /* clamp: NaN stays NaN */
}

/* delta^T H delta: row i of H times delta, summed in the order of i (the lane loop sums alike) */
static inline T CAT(damped_quad, SFX)(const T *Hb, const T *db, int64_t m) {
    T q = 0;
    for (int64_t i = 0; i < m; ++i) {
        T row = 0;
        for (int64_t j = 0; j < m; ++j) row += Hb[i * m + j] * db[j];
        q += db[i] * row;
    }
    return q;
}

/* solved, delta and quad of one system from its factor's status ok and its quad q */
static inline void CAT(damped_finish, SFX)(T *db, uint8_t *solved, T *quad, int ok, T q, int64_t m) {
    for (int64_t i = 0; i < m; ++i) ok = ok && isfinite(db[i]);
    solved[0] = (uint8_t)ok;
    if (!ok)
        for (int64_t i = 0; i < m; ++i) db[i] = 0;
    quad[0] = ok ? q : 0;
}

/* Systems of at most LANE_MAX_M unknowns go a lane vector at a time, one per lane
 * (_native_cholesky_lanes.h), its machine vectors as wide as the code is built for (a vector type
 * wider than the machine's compiles to slow code): two of 16 bytes of T side by side, or where
 * the CPU has AVX2 (wide_cpu) one of 32 bytes, or two where a system's steps mostly wait on each
 * other (at most LANE_PAIR_M unknowns and fewer than 4 right-hand sides; larger systems measured
 * slower in pairs).  Every choice gives every system the same result. */
#ifndef LANE_MAX_M
#define LANE_MAX_M 64
#define LANE_COLS 16 /* right-hand-side columns per pass */
#define LANE_PAIR_M 8
#endif
#define LANE_BYTES 16
#define LANE_GROUPS 2
#define LANE_SFX SFX
#define LANE_TARGET
#include "_native_cholesky_lanes.h"
#if defined(WIDE_TARGET)
#define LANE_BYTES 32
#define LANE_GROUPS 1
#define LANE_SFX CAT(SFX, wide)
#define LANE_TARGET WIDE_TARGET
#include "_native_cholesky_lanes.h"
#define LANE_BYTES 32
#define LANE_GROUPS 2
#define LANE_SFX CAT(SFX, wide_pair)
#define LANE_TARGET WIDE_TARGET
#include "_native_cholesky_lanes.h"
#define LANES_RUN(name, m, k, args, lo, hi)                                                        \
    (!wide_cpu()                       ? CAT(name, SFX)                                             \
     : (m) <= LANE_PAIR_M && (k) < 4 ? CAT(name, CAT(SFX, wide_pair))                             \
                                       : CAT(name, CAT(SFX, wide)))(args, lo, hi)
#else
#define LANES_RUN(name, m, k, args, lo, hi) CAT(name, SFX)(args, lo, hi)
#endif

/* args: A, R, L, X, Y (null: not wanted), info, and m, k, lanes as int64 (lanes 0: one system at
 * a time, also where the lanes' workspace cannot be allocated) */
WIDE_LOOPS static void CAT(cholesky_solve_range, SFX)(void **args, int64_t lo, int64_t hi) {
    const T *A = args[0], *R = args[1];
    T *L = args[2], *X = args[3], *Y = args[4];
    int32_t *info = args[5];
    const int64_t m = *(const int64_t *)args[6], k = *(const int64_t *)args[7];
    if (*(const int64_t *)args[8] && m <= LANE_MAX_M && LANES_RUN(cholesky_solve_lanes, m, k, args, lo, hi)) return;
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
    if (m <= LANE_MAX_M && LANES_RUN(gram_cholesky_solve_lanes, m, k, args, lo, hi)) return;
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
    if (*(const int64_t *)args[6] && m <= LANE_MAX_M && LANES_RUN(triangular_solve_lanes, m, k, args, lo, hi)) return;
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
WIDE_LOOPS static void CAT(damped_solve_range, SFX)(void **args, int64_t lo, int64_t hi) {
    const T *H = args[0], *g = args[1], *lam = args[2];
    T *delta = args[3], *quad = args[5];
    uint8_t *solved = args[4];
    const double *clamp = args[6];
    const int64_t m = *(const int64_t *)args[7], diagonal = *(const int64_t *)args[8];
    if (m <= LANE_MAX_M && LANES_RUN(damped_solve_lanes, m, 1, args, lo, hi)) return;
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
        CAT(damped_finish, SFX)(db, solved + b, quad + b, !f, f ? 0 : CAT(damped_quad, SFX)(Hb, db, m), m);
    }
    free(Wb);
}

#undef LANES_RUN
#undef CAT
#undef CAT_
#undef T
#undef SFX
#undef SQRT
