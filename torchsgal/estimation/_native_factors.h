/* The residuals and Jacobians of the factor-graph engine's built-in SE(3) priors and betweens,
 * one factor at a time (included by estimation/_native.c once per element type T with suffix SFX,
 * after functional/_native_sgal3.h, whose SE(3) closed forms it calls: se3_log_one_f64 ...).
 *
 * Matrices are row-major (4, 4) [[C, t], [0, 1]].  Prior: E = Z^-1 T; between: E = Z^-1 T_i^-1
 * T_j.  r = log(E) (6) = [rho, phi] (se3_log_one), and the Jacobians with respect to right
 * perturbations (estimation/graph/factors.py): J = J_r^-1(r) = J_l^-1(-r) for the prior and for
 * T_j; J_i = -J_l^-1(r) Ad(Z^-1) for T_i (J_r^-1(r) = J_l^-1(r) Ad(E) and E A^-1 = Z^-1, A =
 * T_i^-1 T_j), J written as [J_i | J_j] (6, 12) for a between.
 */

/* o (3, 4) = the top rows of A B, A and B (4, 4) with bottom row [0, 0, 0, 1] (A's top rows
 * given as a (3, 4) block with row stride sa) */
#define KF_(name, sfx) name##_##sfx
#define KF__(name, sfx) KF_(name, sfx)
#define K(name) KF__(name, SFX)

static inline void K(se3_top_product)(const T *A, int sa, const T *Bm, T *o) {
    for (int i = 0; i < 3; ++i)
        for (int j = 0; j < 4; ++j)
            o[4 * i + j] = A[sa * i] * Bm[j] + A[sa * i + 1] * Bm[4 + j] + A[sa * i + 2] * Bm[8 + j]
                           + (j == 3 ? A[sa * i + 3] : (T)0);
}

/* r and, unless J is null, its Jacobian; Ti null for a prior (E = Z^-1 Tj) */
static void K(se3_factor_one)(const T *Zinv, const T *Ti, const T *Tj, T *r, T *J) {
    T A[12], E[16], Jl[36];
    if (Ti) {
        T inv[16];
        K(se3_inverse_one)(Ti, inv);  /* T_i^-1 = [C^T, -C^T t] (_native_products.h) */
        K(se3_top_product)(inv, 4, Tj, A);
        T A16[16];
        for (int i = 0; i < 12; ++i) A16[i] = A[i];
        A16[12] = 0; A16[13] = 0; A16[14] = 0; A16[15] = 1;
        K(se3_top_product)(Zinv, 4, A16, E);
    } else {
        K(se3_top_product)(Zinv, 4, Tj, E);
    }
    E[12] = 0; E[13] = 0; E[14] = 0; E[15] = 1;
    K(se3_log_one)(E, r);
    if (!J) return;
    /* J_l^-1(r) = [[A, B], [0, A]]; J_r^-1(r) = J_l^-1(-r) = [[A^T, B^T], [0, A^T]] (each 3 x 3
     * block transposed: J(-phi) = J(phi)^T and Q(-rho, -phi) = Q(rho, phi)^T term by term) */
    K(se3_jl_one)(r, 1, Jl);
    const int w = Ti ? 12 : 6, off = Ti ? 6 : 0;
    for (int bi = 0; bi < 2; ++bi)
        for (int bj = 0; bj < 2; ++bj)
            for (int i = 0; i < 3; ++i)
                for (int j = 0; j < 3; ++j)
                    J[w * (3 * bi + i) + off + 3 * bj + j] = Jl[6 * (3 * bi + j) + 3 * bj + i];
    if (!Ti) return;
    /* J_i = -J_l^-1 Ad(Z^-1), Ad = [[C, t^ C], [0, C]]: [[-A C, -(A t^C + B C)], [0, -A C]] */
    T Ad[36];
    K(se3_adjoint_one)(Zinv, Ad);
    for (int i = 0; i < 3; ++i)
        for (int j = 0; j < 3; ++j) {
            T ac = 0, top = 0;
            for (int k = 0; k < 3; ++k) {
                ac += Jl[6 * i + k] * Ad[6 * k + j];
                top += Jl[6 * i + k] * Ad[6 * k + 3 + j] + Jl[6 * i + 3 + k] * Ad[6 * (3 + k) + 3 + j];
            }
            J[12 * i + j] = -ac;
            J[12 * (3 + i) + 3 + j] = -ac;
            J[12 * i + 3 + j] = -top;
            J[12 * (3 + i) + j] = 0;
        }
}

/* SE(2), matrices (3, 3) [[C, t], [0, 1]], tangent [rho, theta] (graph/log_terms.py,
 * se2_log_jacobians): theta = atan2 of E's rotation, d = (1 - h) / theta^2 with
 * h = (theta/2) cot(theta/2) (below theta^2 = series[0] the series series[1..SERIES] in theta^2),
 * rho = h t - (theta/2) J t, J_r^-1, J_l^-1 = [[h I +- (theta/2) J, d theta rho -+ (1/2) J rho],
 * [0, 1]]; a between's J_i = -J_l^-1(r) Ad(Z^-1), Ad(M) = [[C, -J t], [0, 1]]. */
#define SE2_SERIES 14

static inline void K(se2_product)(const T *A, const T *Bm, T *o) {  /* top rows of A B */
    for (int i = 0; i < 2; ++i)
        for (int j = 0; j < 3; ++j)
            o[3 * i + j] = A[3 * i] * Bm[j] + A[3 * i + 1] * Bm[3 + j] + (j == 2 ? A[3 * i + 2] : (T)0);
    o[6] = 0; o[7] = 0; o[8] = 1;
}

static void K(se2_factor_one)(const T *Zinv, const T *Ti, const T *Tj, const double *series, T *r,
                              T *J) {
    T E[9], A[9];
    if (Ti) {
        T inv[9] = {Ti[0], Ti[3], -(Ti[0] * Ti[2] + Ti[3] * Ti[5]),
                    Ti[1], Ti[4], -(Ti[1] * Ti[2] + Ti[4] * Ti[5]), 0, 0, 1};
        K(se2_product)(inv, Tj, A);
        K(se2_product)(Zinv, A, E);
    } else {
        K(se2_product)(Zinv, Tj, E);
    }
    const T theta = ATAN2((T)0.5 * (E[3] - E[1]), (T)0.5 * (E[0] + E[4]));
    const T t2 = theta * theta;
    T d;
    if (t2 < (T)series[0]) {
        T p = 1, acc = 0;
        for (int k = 0; k < SE2_SERIES; ++k) {
            acc += p * (T)series[1 + k];
            p *= t2;
        }
        d = acc;
    } else {
        const T sh = SIN((T)0.5 * theta), ch = COS((T)0.5 * theta);
        const T h = theta * ch / (2 * sh);
        d = (1 - h) / t2;
    }
    const T h = 1 - d * t2, half = (T)0.5 * theta;
    const T rho0 = h * E[2] + half * E[5], rho1 = h * E[5] - half * E[2];
    r[0] = rho0; r[1] = rho1; r[2] = theta;
    if (!J) return;
    const T u0 = d * theta * rho0, u1 = d * theta * rho1;
    const T Jr[9] = {h, -half, u0 + (T)0.5 * rho1, half, h, u1 - (T)0.5 * rho0, 0, 0, 1};
    const int w = Ti ? 6 : 3;
    for (int i = 0; i < 3; ++i)
        for (int j = 0; j < 3; ++j) J[w * i + (Ti ? 3 : 0) + j] = Jr[3 * i + j];
    if (!Ti) return;
    const T Jl[9] = {h, half, u0 - (T)0.5 * rho1, -half, h, u1 + (T)0.5 * rho0, 0, 0, 1};
    const T Ad[9] = {Zinv[0], Zinv[1], Zinv[5], Zinv[3], Zinv[4], -Zinv[2], 0, 0, 1};
    for (int i = 0; i < 3; ++i)
        for (int j = 0; j < 3; ++j)
            J[6 * i + j] = -(Jl[3 * i] * Ad[j] + Jl[3 * i + 1] * Ad[3 + j] + Jl[3 * i + 2] * Ad[6 + j]);
}

static void K(se2_factor_range)(void **a, int64_t lo, int64_t hi) {
    const T *Zinv = a[0], *Ti = a[1], *Tj = a[2];
    T *r = a[3], *J = a[4];
    const double *series = a[5];
    const int64_t width = Ti ? 18 : 9;
    for (int64_t b = lo; b < hi; ++b)
        K(se2_factor_one)(Zinv + 9 * b, Ti ? Ti + 9 * b : NULL, Tj + 9 * b, series, r + 3 * b,
                          J ? J + width * b : NULL);
}

/* args: Zinv, Ti (null for priors), Tj, r, J (null: residuals only), each (n, ...) contiguous */
static void K(se3_factor_range)(void **a, int64_t lo, int64_t hi) {
    const T *Zinv = a[0], *Ti = a[1], *Tj = a[2];
    T *r = a[3], *J = a[4];
    const int64_t width = Ti ? 72 : 36;
    for (int64_t b = lo; b < hi; ++b)
        K(se3_factor_one)(Zinv + 16 * b, Ti ? Ti + 16 * b : NULL, Tj + 16 * b, r + 6 * b, J ? J + width * b : NULL);
}

/* The whitened terms and their normal-equation blocks of one factor: r~ = L r, J~ = L J (L (m, m)
 * row-major; null: the identity), H = J~^T J~ (Dk, Dk) and g = J~^T r~ (Dk); with GCC/Clang the
 * same on vectors (whitened_normal_M_DK below) */
#if !defined(__GNUC__)
static void K(whitened_normal)(const T *r, const T *J, const T *L, int m, int Dk, T *rw, T *H, T *g) {
    T Jw[6 * 12];
    for (int i = 0; i < m; ++i) {
        if (L) {
            T acc = 0;
            for (int k = 0; k < m; ++k) acc += L[m * i + k] * r[k];
            rw[i] = acc;
            for (int c = 0; c < Dk; ++c) {
                T v = 0;
                for (int k = 0; k < m; ++k) v += L[m * i + k] * J[Dk * k + c];
                Jw[Dk * i + c] = v;
            }
        } else {
            rw[i] = r[i];
            for (int c = 0; c < Dk; ++c) Jw[Dk * i + c] = J[Dk * i + c];
        }
    }
    for (int a = 0; a < Dk; ++a) {
        for (int b = 0; b <= a; ++b) {
            T acc = 0;
            for (int i = 0; i < m; ++i) acc += Jw[Dk * i + a] * Jw[Dk * i + b];
            H[Dk * a + b] = acc;
            H[Dk * b + a] = acc;
        }
        T acc = 0;
        for (int i = 0; i < m; ++i) acc += Jw[Dk * i + a] * rw[i];
        g[a] = acc;
    }
}
#endif

#if defined(__GNUC__)
/* whitened_normal for constant sizes M and DK on GCC/Clang's vectors of four: J~'s rows as
 * WN_NB(DK) vectors, H's rows accumulated as vectors (the blocks of columns that hold some
 * b >= a) and mirrored, g as vectors; every entry is the same products summed in the same
 * order as the scalar function above, so the results are equal, bit for bit. */
#define WN_NB(DK) (((DK) + 3) / 4)
#define WN_DEF(M, DK)                                                                            \
    static inline void K(whitened_normal_##M##_##DK)(const T *r, const T *J, const T *L, T *rw,  \
                                                     T *H, T *g) {                              \
        typedef VEC4 V;                                                                         \
        T Jp[M][WN_NB(DK) * 4];                                                                 \
        V Jw[M][WN_NB(DK)], w;                                                                  \
        UNROLL for (int i = 0; i < M; ++i)                                                      \
            UNROLL for (int c = 0; c < WN_NB(DK) * 4; ++c) Jp[i][c] = c < DK ? J[DK * i + c] : 0; \
        UNROLL for (int i = 0; i < M; ++i) {                                                    \
            if (L) {                                                                            \
                T acc = 0;                                                                      \
                UNROLL for (int k = 0; k < M; ++k) acc += L[M * i + k] * r[k];                  \
                rw[i] = acc;                                                                    \
                UNROLL for (int n = 0; n < WN_NB(DK); ++n) {                                    \
                    V v = {0, 0, 0, 0};                                                         \
                    UNROLL for (int k = 0; k < M; ++k) {                                        \
                        const T l = L[M * i + k];                                               \
                        memcpy(&w, Jp[k] + 4 * n, sizeof w);                                    \
                        v += (V){l, l, l, l} * w;                                               \
                    }                                                                           \
                    Jw[i][n] = v;                                                               \
                }                                                                               \
            } else {                                                                            \
                rw[i] = r[i];                                                                   \
                UNROLL for (int n = 0; n < WN_NB(DK); ++n) memcpy(&Jw[i][n], Jp[i] + 4 * n, sizeof w); \
            }                                                                                   \
        }                                                                                       \
        V h[DK][WN_NB(DK)], gv[WN_NB(DK)];                                                      \
        UNROLL for (int n = 0; n < WN_NB(DK); ++n) {                                            \
            gv[n] = (V){0, 0, 0, 0};                                                            \
            UNROLL for (int a = 0; a < DK; ++a) h[a][n] = (V){0, 0, 0, 0};                      \
        }                                                                                       \
        UNROLL for (int i = 0; i < M; ++i) {                                                    \
            T x[WN_NB(DK) * 4];                                                                 \
            memcpy(x, Jw[i], sizeof x);                                                         \
            const T ri = rw[i];                                                                 \
            UNROLL for (int n = 0; n < WN_NB(DK); ++n) gv[n] += Jw[i][n] * (V){ri, ri, ri, ri}; \
            UNROLL for (int a = 0; a < DK; ++a) {                                               \
                const V xa = {x[a], x[a], x[a], x[a]};                                          \
                UNROLL for (int n = 0; n < WN_NB(DK); ++n)                                      \
                    if (4 * n + 3 >= a) h[a][n] += xa * Jw[i][n];                               \
            }                                                                                   \
        }                                                                                       \
        UNROLL for (int a = 0; a < DK; ++a) {                                                   \
            g[a] = gv[a / 4][a % 4];                                                            \
            UNROLL for (int b = 0; b < DK; ++b)                                                 \
                H[DK * a + b] = a <= b ? h[a][b / 4][b % 4] : h[b][a / 4][a % 4];               \
        }                                                                                       \
    }
/* GCC takes (falsely) the vectors built from entries for reads of uninitialised memory */
#if !defined(__clang__)
#pragma GCC diagnostic push
#pragma GCC diagnostic ignored "-Wmaybe-uninitialized"
#endif
WN_DEF(6, 12)
WN_DEF(6, 6)
WN_DEF(3, 6)
WN_DEF(3, 3)
#if !defined(__clang__)
#pragma GCC diagnostic pop
#endif
#undef WN_DEF
#undef WN_NB
#define WN_CALL(M, DK, r, J, L, rw, H, g) K(whitened_normal_##M##_##DK)(r, J, L, rw, H, g)
#else
#define WN_CALL(M, DK, r, J, L, rw, H, g) K(whitened_normal)(r, J, L, M, DK, rw, H, g)
#endif

/* args: Zinv, Ti (null for priors), Tj, L (null: none), rw, H, g, series (SE(2) only; see
 * se2_factor_range), each (n, ...) contiguous; L (n, m, m), or (m, m) for all with L_shared */
WIDE_LOOPS static void K(se3_factor_normal_range)(void **a, int64_t lo, int64_t hi) {
    const T *Zinv = a[0], *Ti = a[1], *Tj = a[2], *L = a[3];
    T *rw = a[4], *H = a[5], *g = a[6];
    const int64_t shared = *(const int64_t *)a[7];
    for (int64_t b = lo; b < hi; ++b) {
        T r[6], J[72];
        K(se3_factor_one)(Zinv + 16 * b, Ti ? Ti + 16 * b : NULL, Tj + 16 * b, r, J);
        if (Ti)
            WN_CALL(6, 12, r, J, L ? L + (shared ? 0 : 36 * b) : NULL, rw + 6 * b, H + 144 * b, g + 12 * b);
        else
            WN_CALL(6, 6, r, J, L ? L + (shared ? 0 : 36 * b) : NULL, rw + 6 * b, H + 36 * b, g + 6 * b);
    }
}

WIDE_LOOPS static void K(se2_factor_normal_range)(void **a, int64_t lo, int64_t hi) {
    const T *Zinv = a[0], *Ti = a[1], *Tj = a[2], *L = a[3];
    T *rw = a[4], *H = a[5], *g = a[6];
    const int64_t shared = *(const int64_t *)a[7];
    const double *series = a[8];
    for (int64_t b = lo; b < hi; ++b) {
        T r[3], J[18];
        K(se2_factor_one)(Zinv + 9 * b, Ti ? Ti + 9 * b : NULL, Tj + 9 * b, series, r, J);
        if (Ti)
            WN_CALL(3, 6, r, J, L ? L + (shared ? 0 : 9 * b) : NULL, rw + 3 * b, H + 36 * b, g + 6 * b);
        else
            WN_CALL(3, 3, r, J, L ? L + (shared ? 0 : 9 * b) : NULL, rw + 3 * b, H + 9 * b, g + 3 * b);
    }
}

/* The same terms added into a batch of problems' normal equations: args Zinv, Ti (null for
 * priors), Tj, L (null: none), rw, values, g, &shared, slots, g_slots, dims = {E, size, D},
 * series (SE(2) only).  Problem b owns factors b * E .. b * E + E - 1 of the matrices; factor e
 * adds its H (Dk * Dk, row-major) into values[b, slots[e, k]] and its g into g[b, g_slots[e, k]]
 * (every index checked by the caller).  One problem per work item: no two threads share a row. */
WIDE_LOOPS static void K(se3_factor_assemble_range)(void **a, int64_t lo, int64_t hi) {
    const T *Zinv = a[0], *Ti = a[1], *Tj = a[2], *L = a[3];
    T *rw = a[4], *values = a[5], *g = a[6];
    const int64_t shared = *(const int64_t *)a[7];
    const int64_t *slots = a[8], *g_slots = a[9], *dims = a[10];
    const int64_t E = dims[0], size = dims[1], D = dims[2];
    const int Dk = Ti ? 12 : 6;
    for (int64_t b = lo; b < hi; ++b) {
        T *vb = values + size * b, *gb = g + D * b;
        for (int64_t e = 0; e < E; ++e) {
            const int64_t f = E * b + e;
            const int64_t *s = slots + Dk * Dk * e, *t = g_slots + Dk * e;
            T r[6], J[72], H[144], gf[12];
            K(se3_factor_one)(Zinv + 16 * f, Ti ? Ti + 16 * f : NULL, Tj + 16 * f, r, J);
            if (Ti)
                WN_CALL(6, 12, r, J, L ? L + (shared ? 0 : 36 * f) : NULL, rw + 6 * f, H, gf);
            else
                WN_CALL(6, 6, r, J, L ? L + (shared ? 0 : 36 * f) : NULL, rw + 6 * f, H, gf);
            for (int k = 0; k < Dk * Dk; ++k) vb[s[k]] += H[k];
            for (int k = 0; k < Dk; ++k) gb[t[k]] += gf[k];
        }
    }
}

WIDE_LOOPS static void K(se2_factor_assemble_range)(void **a, int64_t lo, int64_t hi) {
    const T *Zinv = a[0], *Ti = a[1], *Tj = a[2], *L = a[3];
    T *rw = a[4], *values = a[5], *g = a[6];
    const int64_t shared = *(const int64_t *)a[7];
    const int64_t *slots = a[8], *g_slots = a[9], *dims = a[10];
    const double *series = a[11];
    const int64_t E = dims[0], size = dims[1], D = dims[2];
    const int Dk = Ti ? 6 : 3;
    for (int64_t b = lo; b < hi; ++b) {
        T *vb = values + size * b, *gb = g + D * b;
        for (int64_t e = 0; e < E; ++e) {
            const int64_t f = E * b + e;
            const int64_t *s = slots + Dk * Dk * e, *t = g_slots + Dk * e;
            T r[3], J[18], H[36], gf[6];
            K(se2_factor_one)(Zinv + 9 * f, Ti ? Ti + 9 * f : NULL, Tj + 9 * f, series, r, J);
            if (Ti)
                WN_CALL(3, 6, r, J, L ? L + (shared ? 0 : 9 * f) : NULL, rw + 3 * f, H, gf);
            else
                WN_CALL(3, 3, r, J, L ? L + (shared ? 0 : 9 * f) : NULL, rw + 3 * f, H, gf);
            for (int k = 0; k < Dk * Dk; ++k) vb[s[k]] += H[k];
            for (int k = 0; k < Dk; ++k) gb[t[k]] += gf[k];
        }
    }
}

#undef WN_CALL
#undef K
#undef KF__
#undef KF_
