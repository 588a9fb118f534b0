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

/* h += J_e^T J_e and v += J_e^T r_e over the m rows of one factor, entry a of row i read as
 * ENTRY (NP_ROWS writes it twice, for unit and for other column strides, so that the first is
 * vectorised) */
#define NP_ROWS_AT(KK, ENTRY)                                                                    \
    for (int64_t i = 0; i < m; ++i) {                                                            \
        T x[KK];                                                                                 \
        for (int a = 0; a < KK; ++a) x[a] = ENTRY;                                               \
        const T ri = re_[i * rm];                                                                \
        for (int a = 0; a < KK; ++a) {                                                           \
            v[a] += x[a] * ri;                                                                   \
            for (int c = 0; c < KK; ++c) h[a * KK + c] += x[a] * x[c];                           \
        }                                                                                        \
    }
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
        for (int a = 0; a < KK; ++a) {                                                           \
            gb[gs[a]] += v[a];                                                                   \
            for (int c = 0; c < KK; ++c) vb[hs[a * KK + c]] += a <= c ? h[a * KK + c] : h[c * KK + a]; \
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
                T h[KK * KK] = {0}, v[KK] = {0};                                                \
                for (int64_t e = 0; e < E; ++e) {                                               \
                    const T *Je = J + b * jb + e * je, *re_ = r + b * rb + e * re;              \
                    NP_ROWS(KK)                                                                 \
                }                                                                               \
                if (E > 0) NP_SCATTER(KK, 0)                                                    \
            } else {                                                                            \
                for (int64_t e = 0; e < E; ++e) {                                               \
                    T h[KK * KK] = {0}, v[KK] = {0};                                            \
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
#undef NP_FIXED
#undef NP_ROWS
#undef NP_ROWS_AT
#undef NP_SCATTER

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
