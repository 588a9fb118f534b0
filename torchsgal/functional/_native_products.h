/* Products of SO(3), SE(2), SGal(3), SE(3) and SE_2(3) matrices, inverses and adjoints of the last three, for one scalar type T
 * (included per dtype by functional/_native.c, and by estimation/_native.c for the factor kernels'
 * SE(3) inverse and adjoint, after _native_sgal3.h, whose skew_times and put3 it uses;
 * undefines T and SFX).
 *
 * compose: the matrix product A B of n x n row-major matrices (n = 3: SO(3), SE(2); n = 4: SE(3); n = 5:
 * SGal(3), SE_2(3)), PRODUCT_LANES products per pass with lane w of every array holding product w, so
 * that each multiply-add is one operation on PRODUCT_LANES values (torch's batched matmul pays
 * ~100 ns of call overhead per product at these sizes).  Every entry sums a_r0 b_0c + a_r1 b_1c
 * + ... in that order, in the lanes and in the tail alike: the bits do not depend on where an
 * element falls in the batch.
 *
 * inverse and adjoint: the closed forms of sgal3.inverse_impl and adjoint_impl (3.16), and of
 * se3's and se23's, the blocks written directly.
 */

#define K_(name, sfx) name##_##sfx
#define K__(name, sfx) K_(name, sfx)
#define K(name) K__(name, SFX)

#ifndef PRODUCT_LANES
#define PRODUCT_LANES 8
#endif

#define COMPOSE_RANGE(n)                                                                       \
    WIDE_LOOPS static void K(compose##n##_range)(void **a, int64_t lo, int64_t hi) {          \
        const T *A = a[0], *Bm = a[1];                                                         \
        T *O = a[2];                                                                           \
        int64_t i = lo;                                                                        \
        for (; i + PRODUCT_LANES <= hi; i += PRODUCT_LANES) {                                  \
            T x[(n) * (n)][PRODUCT_LANES], y[(n) * (n)][PRODUCT_LANES];                        \
            for (int w = 0; w < PRODUCT_LANES; ++w)                                            \
                for (int t = 0; t < (n) * (n); ++t) {                                          \
                    x[t][w] = A[(i + w) * (n) * (n) + t];                                      \
                    y[t][w] = Bm[(i + w) * (n) * (n) + t];                                     \
                }                                                                              \
            for (int r = 0; r < (n); ++r)                                                      \
                for (int c = 0; c < (n); ++c) {                                                \
                    T acc[PRODUCT_LANES];                                                      \
                    for (int w = 0; w < PRODUCT_LANES; ++w) acc[w] = x[r * (n)][w] * y[c][w]; \
                    for (int k = 1; k < (n); ++k)                                              \
                        for (int w = 0; w < PRODUCT_LANES; ++w)                                \
                            acc[w] += x[r * (n) + k][w] * y[k * (n) + c][w];                   \
                    for (int w = 0; w < PRODUCT_LANES; ++w)                                    \
                        O[(i + w) * (n) * (n) + r * (n) + c] = acc[w];                         \
                }                                                                              \
        }                                                                                      \
        for (; i < hi; ++i) {                                                                  \
            const T *x = A + i * (n) * (n), *y = Bm + i * (n) * (n);                           \
            for (int r = 0; r < (n); ++r)                                                      \
                for (int c = 0; c < (n); ++c) {                                                \
                    T acc = x[r * (n)] * y[c];                                                 \
                    for (int k = 1; k < (n); ++k) acc += x[r * (n) + k] * y[k * (n) + c];      \
                    O[i * (n) * (n) + r * (n) + c] = acc;                                      \
                }                                                                              \
        }                                                                                      \
    }
COMPOSE_RANGE(3)
COMPOSE_RANGE(4)
COMPOSE_RANGE(5)
#undef COMPOSE_RANGE

/* The rotation C (3x3 row-major) of an n x n group matrix. */
static inline void K(rotation_of)(const T *M, int n, T *C) {
    for (int i = 0; i < 3; ++i)
        for (int j = 0; j < 3; ++j) C[3 * i + j] = M[n * i + j];
}

/* SGal(3) (3.16), [rho, nu, phi, iota]:
 * [[C, -tau C, (r - tau v)^ C, v], [0, C, v^ C, 0], [0, 0, C, 0], [0, 0, 0, 1]]. */
static void K(sgal3_adjoint_one)(const T *M, T *o) {
    T C[9], v[3], r[3], S[9];
    T tau = M[19];
    K(rotation_of)(M, 5, C);
    for (int i = 0; i < 3; ++i) { v[i] = M[5 * i + 3]; r[i] = M[5 * i + 4]; }
    for (int i = 0; i < 100; ++i) o[i] = 0;
    K(put3)(o, 10, 0, 0, C); K(put3)(o, 10, 1, 1, C); K(put3)(o, 10, 2, 2, C);
    for (int i = 0; i < 9; ++i) S[i] = -tau * C[i];
    K(put3)(o, 10, 0, 1, S);
    T w[3] = {r[0] - tau * v[0], r[1] - tau * v[1], r[2] - tau * v[2]};
    K(skew_times)(w, C, S);
    K(put3)(o, 10, 0, 2, S);
    K(skew_times)(v, C, S);
    K(put3)(o, 10, 1, 2, S);
    for (int i = 0; i < 3; ++i) o[10 * i + 9] = v[i];
    o[99] = 1;
}

/* SE(3), [rho, phi]: [[C, r^ C], [0, C]]. */
static void K(se3_adjoint_one)(const T *M, T *o) {
    T C[9], r[3] = {M[3], M[7], M[11]}, S[9];
    K(rotation_of)(M, 4, C);
    for (int i = 0; i < 36; ++i) o[i] = 0;
    K(put3)(o, 6, 0, 0, C); K(put3)(o, 6, 1, 1, C);
    K(skew_times)(r, C, S);
    K(put3)(o, 6, 0, 1, S);
}

/* SE_2(3), [rho, nu, phi]: [[C, 0, r^ C], [0, C, v^ C], [0, 0, C]]. */
static void K(se23_adjoint_one)(const T *M, T *o) {
    T C[9], v[3] = {M[3], M[8], M[13]}, r[3] = {M[4], M[9], M[14]}, S[9];
    K(rotation_of)(M, 5, C);
    for (int i = 0; i < 81; ++i) o[i] = 0;
    K(put3)(o, 9, 0, 0, C); K(put3)(o, 9, 1, 1, C); K(put3)(o, 9, 2, 2, C);
    K(skew_times)(r, C, S);
    K(put3)(o, 9, 0, 2, S);
    K(skew_times)(v, C, S);
    K(put3)(o, 9, 1, 2, S);
}

/* C^T and -C^T x (x a column of M) into the n x n inverse o (sgal3.inverse_impl: the same
 * order of operations, -((C^T)_i0 x_0 + (C^T)_i1 x_1 + (C^T)_i2 x_2)). */
static inline void K(inverse_rotation)(const T *M, int n, T *o) {
    for (int i = 0; i < 3; ++i)
        for (int j = 0; j < 3; ++j) o[n * i + j] = M[n * j + i];
}

static inline void K(inverse_column)(const T *M, int n, const T *x, T *o, int col) {
    for (int i = 0; i < 3; ++i) o[n * i + col] = -(M[i] * x[0] + M[n + i] * x[1] + M[2 * n + i] * x[2]);
}

/* SGal(3): [[C^T, -C^T v, -C^T (r - tau v)], [0, 1, -tau], [0, 0, 1]]. */
static void K(sgal3_inverse_one)(const T *M, T *o) {
    T tau = M[19];
    T v[3] = {M[3], M[8], M[13]};
    T w[3] = {M[4] - tau * v[0], M[9] - tau * v[1], M[14] - tau * v[2]};
    for (int i = 0; i < 25; ++i) o[i] = 0;
    K(inverse_rotation)(M, 5, o);
    K(inverse_column)(M, 5, v, o, 3);
    K(inverse_column)(M, 5, w, o, 4);
    o[18] = 1; o[19] = -tau; o[24] = 1;
}

/* SE(3): [[C^T, -C^T r], [0, 1]]. */
static void K(se3_inverse_one)(const T *M, T *o) {
    T r[3] = {M[3], M[7], M[11]};
    for (int i = 0; i < 16; ++i) o[i] = 0;
    K(inverse_rotation)(M, 4, o);
    K(inverse_column)(M, 4, r, o, 3);
    o[15] = 1;
}

/* SE_2(3): [[C^T, -C^T v, -C^T r], [0, 1, 0], [0, 0, 1]]. */
static void K(se23_inverse_one)(const T *M, T *o) {
    T v[3] = {M[3], M[8], M[13]}, r[3] = {M[4], M[9], M[14]};
    for (int i = 0; i < 25; ++i) o[i] = 0;
    K(inverse_rotation)(M, 5, o);
    K(inverse_column)(M, 5, v, o, 3);
    K(inverse_column)(M, 5, r, o, 4);
    o[18] = 1; o[24] = 1;
}

#define INVERSE_RANGE(group, n)                                                           \
    static void K(group##_inverse_range)(void **a, int64_t lo, int64_t hi) {             \
        const T *M = a[0];                                                               \
        T *out = a[1];                                                                   \
        for (int64_t i = lo; i < hi; ++i) K(group##_inverse_one)(M + (n) * (n) * i, out + (n) * (n) * i); \
    }
INVERSE_RANGE(sgal3, 5)
INVERSE_RANGE(se3, 4)
INVERSE_RANGE(se23, 5)
#undef INVERSE_RANGE

#define ADJOINT_RANGE(group, n, dof)                                                      \
    static void K(group##_adjoint_range)(void **a, int64_t lo, int64_t hi) {             \
        const T *M = a[0];                                                               \
        T *out = a[1];                                                                   \
        for (int64_t i = lo; i < hi; ++i)                                                \
            K(group##_adjoint_one)(M + (n) * (n) * i, out + (dof) * (dof) * i);          \
    }
ADJOINT_RANGE(sgal3, 5, 10)
ADJOINT_RANGE(se3, 4, 6)
ADJOINT_RANGE(se23, 5, 9)
#undef ADJOINT_RANGE

#undef K
#undef K_
#undef K__
#undef T
#undef SFX
