/* The normal equations of a block of factors, added into each problem's linear system
 * (torchsgal::normal_assemble, estimation/graph/normal_kernel.py; included by
 * estimation/_native.c once per element type T with suffix SFX).
 *
 * J (B, E, m, Dk) and r (B, E, m) are read through their strides (expanded, transposed or
 * moved axes need no copy); for every factor e of problem b, H = J^T J (Dk, Dk) is added to
 * values[b] at slots[e] and J^T r to g[b] at g_slots[e] (or, ``summed``, the sums over all
 * factors at slots[0] and g_slots[0]).  Dk is at most NORMAL_MAX_DK: the accumulation runs on a
 * local square of fixed size that the compiler unrolls and vectorises; the upper triangle is
 * written to both halves, so the blocks are exactly symmetric.
 */
#ifndef NORMAL_MAX_DK
#define NORMAL_MAX_DK 12
#endif
#define NP_(name, sfx) name##_##sfx
#define NP__(name, sfx) NP_(name, sfx)
#define NP(name) NP__(name, SFX)

/* Each factor's sums accumulate row by row: h[a][c] += x_a x_c and v[a] += x_a r_i over its m
 * rows, x row i of J_e (entry a read as ENTRY), of which the entries a <= c are used.  For 3 to 12
 * columns with GCC/Clang's vector types (NP_VEC) the accumulators are vectors of four: NP_NB(KK)
 * per row a of h (the blocks of columns that hold some c >= a, hv) and NP_NB(KK) for v (vv),
 * one vector product per block instead of one scalar product per entry (2-5x faster); each entry
 * is summed in the same order either way, so the results are equal, bit for bit.  NP_ROWS writes
 * the loop twice, for unit and for other column strides, so that the first reads contiguous
 * rows. */
#define NP_NB(KK) (((KK) + 3) / 4)
#define NP_SCALAR_ROWS(KK, ENTRY)                                                                \
    for (int64_t i = 0; i < m; ++i) {                                                            \
        T x[KK];                                                                                 \
        for (int a = 0; a < KK; ++a) x[a] = ENTRY;                                               \
        const T ri = re_[i * rm];                                                                \
        for (int a = 0; a < KK; ++a) {                                                           \
            v[a] += x[a] * ri;                                                                   \
            for (int c = 0; c < KK; ++c) h[a * KK + c] += x[a] * x[c];                           \
        }                                                                                        \
    }
#if defined(__GNUC__)
/* GCC takes (falsely) the vectors built from x's entries for reads of uninitialised memory */
#if !defined(__clang__)
#pragma GCC diagnostic push
#pragma GCC diagnostic ignored "-Wmaybe-uninitialized"
#endif
#define NP_VEC(KK) ((KK) >= 3)
#define NP_ACC(KK) T h[KK * KK], v[KK]; VEC4 hv[KK][NP_NB(KK)], vv[NP_NB(KK)];
#define NP_ZERO(KK)                                                                              \
    for (int a = 0; a < KK * KK; ++a) h[a] = 0;                                                  \
    for (int a = 0; a < KK; ++a) v[a] = 0;                                                       \
    UNROLL for (int n = 0; n < NP_NB(KK); ++n) {                                                \
        vv[n] = (VEC4){0, 0, 0, 0};                                                              \
        UNROLL for (int a = 0; a < KK; ++a) hv[a][n] = (VEC4){0, 0, 0, 0};                      \
    }
#define NP_VECTOR_ROWS(KK, ENTRY)                                                                \
    for (int64_t i = 0; i < m; ++i) {                                                            \
        T x[NP_NB(KK) * 4];                                                                      \
        UNROLL for (int a = 0; a < NP_NB(KK) * 4; ++a) x[a] = a < KK ? ENTRY : 0;                \
        const T ri = re_[i * rm];                                                                \
        const VEC4 rv = {ri, ri, ri, ri};                                                        \
        VEC4 xs[NP_NB(KK)];                                                                      \
        UNROLL for (int n = 0; n < NP_NB(KK); ++n) {                                             \
            xs[n] = (VEC4){x[4 * n], x[4 * n + 1], x[4 * n + 2], x[4 * n + 3]};                  \
            vv[n] += xs[n] * rv;                                                                 \
        }                                                                                        \
        UNROLL for (int a = 0; a < KK; ++a) {                                                    \
            const VEC4 xa = {x[a], x[a], x[a], x[a]};                                            \
            UNROLL for (int n = 0; n < NP_NB(KK); ++n)                                          \
                if (4 * n + 3 >= a) hv[a][n] += xa * xs[n]; /* the blocks with some c >= a */    \
        }                                                                                        \
    }
#define NP_ROWS_AT(KK, ENTRY)                                                                    \
    if (NP_VEC(KK)) {                                                                            \
        NP_VECTOR_ROWS(KK, ENTRY)                                                                \
    } else {                                                                                     \
        NP_SCALAR_ROWS(KK, ENTRY)                                                                \
    }
/* entry (a, c) of h for a <= c, entry a of v */
#define NP_H(KK, a, c) (NP_VEC(KK) ? hv[a][(c) / 4][(c) % 4] : h[(a) * KK + (c)])
#define NP_V(KK, a) (NP_VEC(KK) ? vv[(a) / 4][(a) % 4] : v[a])
#else
#define NP_ACC(KK) T h[KK * KK], v[KK];
#define NP_ZERO(KK)                                                                              \
    for (int a = 0; a < KK * KK; ++a) h[a] = 0;                                                  \
    for (int a = 0; a < KK; ++a) v[a] = 0;
#define NP_ROWS_AT(KK, ENTRY) NP_SCALAR_ROWS(KK, ENTRY)
#define NP_H(KK, a, c) h[(a) * KK + (c)]
#define NP_V(KK, a) v[a]
#endif
#define NP_ROWS(KK)                                                                              \
    if (jk == 1)                                                                                 \
        NP_ROWS_AT(KK, Je[i * jm + a])                                                           \
    else                                                                                         \
        NP_ROWS_AT(KK, Je[i * jm + a * jk])

/* the upper triangle of h (and its mirror) and v added at factor e's slots of problem b (inline,
 * so that h and v stay in registers) */
#define NP_SCATTER(KK, e)                                                                        \
    {                                                                                            \
        const int64_t *hs = slots + (e) * KK * KK, *gs = g_slots + (e) * KK;                     \
        T *vb = values + b * size, *gb = g + b * D;                                              \
        UNROLL for (int a = 0; a < KK; ++a) {                                                    \
            gb[gs[a]] += NP_V(KK, a);                                                                \
            UNROLL for (int c = 0; c < KK; ++c)                                                  \
                vb[hs[a * KK + c]] += a <= c ? NP_H(KK, a, c) : NP_H(KK, c, a);                  \
        }                                                                                        \
    }

/* The problems lo..hi for KK columns: args J, r, values, g, slots, g_slots, dims {E, m, k, size,
 * D, summed, J strides (b, e, m, k), r strides (b, e, m)}.  A summed block whose factors follow
 * each other in memory (E m rows at one stride) runs as one factor of E m rows. */
#define NP_FIXED(KK)                                                                             \
    WIDE_LOOPS static void NP(normal_assemble_##KK)(void **args, int64_t lo, int64_t hi) {      \
        const T *J = (const T *)args[0], *r = (const T *)args[1];                               \
        T *values = (T *)args[2], *g = (T *)args[3];                                            \
        const int64_t *slots = (const int64_t *)args[4], *g_slots = (const int64_t *)args[5];   \
        const int64_t *d = (const int64_t *)args[6];                                            \
        int64_t E = d[0], m = d[1];                                                             \
        const int64_t size = d[3], D = d[4], summed = d[5];                                     \
        const int64_t jb = d[6], jm = d[8], jk = d[9], rb = d[10], rm = d[12];                  \
        int64_t je = d[7], re = d[11];                                                          \
        if (summed && E > 1 && je == m * jm && re == m * rm) {                                  \
            m *= E;                                                                             \
            E = 1;                                                                              \
        }                                                                                       \
        for (int64_t b = lo; b < hi; ++b) {                                                     \
            if (summed) {                                                                       \
                NP_ACC(KK)                                                                      \
                NP_ZERO(KK)                                                                     \
                for (int64_t e = 0; e < E; ++e) {                                               \
                    const T *Je = J + b * jb + e * je, *re_ = r + b * rb + e * re;              \
                    NP_ROWS(KK)                                                                 \
                }                                                                               \
                if (E > 0) NP_SCATTER(KK, 0)                                                    \
            } else {                                                                            \
                for (int64_t e = 0; e < E; ++e) {                                               \
                    NP_ACC(KK)                                                                  \
                    NP_ZERO(KK)                                                                 \
                    const T *Je = J + b * jb + e * je, *re_ = r + b * rb + e * re;              \
                    NP_ROWS(KK)                                                                 \
                    NP_SCATTER(KK, e)                                                           \
                }                                                                               \
            }                                                                                   \
        }                                                                                       \
    }
NP_FIXED(1)
NP_FIXED(2)
NP_FIXED(3)
NP_FIXED(4)
NP_FIXED(5)
NP_FIXED(6)
NP_FIXED(7)
NP_FIXED(8)
NP_FIXED(9)
NP_FIXED(10)
NP_FIXED(11)
NP_FIXED(12)
#if defined(__GNUC__) && !defined(__clang__)
#pragma GCC diagnostic pop
#endif
#undef NP_FIXED
#undef NP_ROWS
#undef NP_ROWS_AT
#undef NP_SCATTER
#undef NP_NB
#undef NP_ACC
#undef NP_VEC
#undef NP_SCALAR_ROWS
#undef NP_VECTOR_ROWS
#undef NP_ZERO
#undef NP_H
#undef NP_V

/* the range function for k columns (1 <= k <= NORMAL_MAX_DK) */
static range_fn NP(normal_assemble_for)(int64_t k) {
    static const range_fn fns[NORMAL_MAX_DK] = {
        NP(normal_assemble_1), NP(normal_assemble_2), NP(normal_assemble_3),
        NP(normal_assemble_4), NP(normal_assemble_5), NP(normal_assemble_6),
        NP(normal_assemble_7), NP(normal_assemble_8), NP(normal_assemble_9),
        NP(normal_assemble_10), NP(normal_assemble_11), NP(normal_assemble_12)};
    return fns[k - 1];
}

#undef NP
#undef NP__
#undef NP_
