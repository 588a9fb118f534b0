/* Rows times a small matrix, plus a row: out[b, i, :] = x[b, i, :] W[b] + c[b, :] for a batch of
 * B matrices W (k, m) with few rows k, each applied to N rows x[b, i] (torchsgal::affine_rows,
 * functional/affine.py): a group element acting on many points (the action, W = M[:rows, :k]^T
 * and c its translation column) and the Jacobian of that action (W the element times the
 * generators).  torch's batched matrix product hands each of the B small products to BLAS,
 * whose per-product cost dominates for k of 3 or 4; here each output row is formed in place,
 * with the row length m a compile-time constant for the sizes the groups' actions and their
 * Jacobians have (so that the loop over a row's entries is unrolled and vectorised).  Included
 * by functional/_native.c once per element type T with suffix SFX.
 *
 * args: x (Bx, N, k), W (B, k, m), c (B, m) or NULL, out (B, N, m), all contiguous, and dims
 * {N, k, m, Bx} with k >= 1 and B a multiple of Bx >= 1 (problem b reads x[b mod Bx]: one x
 * for several W, as forward mode's tangents of an action); the range [lo, hi) runs over b.
 */
#if defined(_MSC_VER) && !defined(restrict)
#define restrict __restrict /* C99's restrict, as MSVC spells it */
#endif
#ifndef AF_MAX_M
#define AF_MAX_M 64 /* the longest row the kernel forms (its local row) */
#endif
#define AF_(name, sfx) name##_##sfx
#define AF__(name, sfx) AF_(name, sfx)
#define AF(name) AF__(name, SFX)

/* the arguments, for a row length MM (a constant, or the runtime m) */
#define AF_ARGS(MM)                                                                              \
    const T *x = (const T *)args[0], *W = (const T *)args[1], *c = (const T *)args[2];          \
    T *out = (T *)args[3];                                                                      \
    const int64_t *d = (const int64_t *)args[4];                                                \
    const int64_t N = d[0], k = d[1], m = d[2], Bx = d[3];                                      \
    (void)m;

/* the loop over the problems, one entry of a row at a time */
#define AF_BODY(MM)                                                                              \
    for (int64_t b = lo; b < hi; ++b) {                                                         \
        const T *restrict Wb = W + b * k * (MM), *restrict cb = c ? c + b * (MM) : NULL;       \
        for (int64_t i = 0; i < N; ++i) {                                                       \
            const T *restrict xi = x + ((b % Bx) * N + i) * k;                                  \
            T o[AF_MAX_M];                                                                      \
            for (int64_t j = 0; j < (MM); ++j) o[j] = xi[0] * Wb[j];                            \
            for (int64_t a = 1; a < k; ++a) {                                                   \
                const T xa = xi[a];                                                             \
                for (int64_t j = 0; j < (MM); ++j) o[j] += xa * Wb[a * (MM) + j];               \
            }                                                                                   \
            T *restrict oi = out + (b * N + i) * (MM);                                          \
            if (cb) /* the product first, then the row: as x @ W + c */                         \
                for (int64_t j = 0; j < (MM); ++j) oi[j] = o[j] + cb[j];                        \
            else                                                                                \
                for (int64_t j = 0; j < (MM); ++j) oi[j] = o[j];                                \
        }                                                                                       \
    }

#if defined(__GNUC__)
/* The same loop on GCC/Clang's vectors of four, for a constant row length MM and rows x of at
 * most AF_VEC_MAX_K entries: W[b] and c[b] copied once per problem into rows padded to whole
 * vectors, each output row formed as AF_NB(MM) vectors (2-3.5x faster than one entry at a
 * time); every entry is the same operations in the same order, so the results are equal, bit for
 * bit. */
#define AF_VEC_MAX_K 8
#define AF_NB(MM) (((MM) + 3) / 4)
#define AF_VECTOR_BODY(MM)                                                                       \
    for (int64_t b = lo; b < hi; ++b) {                                                         \
        T wp[AF_VEC_MAX_K][AF_NB(MM) * 4], cp[AF_NB(MM) * 4];                                   \
        for (int64_t a = 0; a < k; ++a)                                                         \
            UNROLL for (int j = 0; j < AF_NB(MM) * 4; ++j)                                      \
                wp[a][j] = j < (MM) ? W[(b * k + a) * (MM) + j] : 0;                            \
        UNROLL for (int j = 0; j < AF_NB(MM) * 4; ++j) cp[j] = c && j < (MM) ? c[b * (MM) + j] : 0; \
        for (int64_t i = 0; i < N; ++i) {                                                       \
            const T *xi = x + ((b % Bx) * N + i) * k;                                           \
            VEC4 o[AF_NB(MM)], w;                                                               \
            const VEC4 x0 = {xi[0], xi[0], xi[0], xi[0]};                                       \
            UNROLL for (int n = 0; n < AF_NB(MM); ++n) {                                        \
                memcpy(&w, wp[0] + 4 * n, sizeof w);                                            \
                o[n] = x0 * w;                                                                  \
            }                                                                                   \
            for (int64_t a = 1; a < k; ++a) {                                                   \
                const VEC4 xa = {xi[a], xi[a], xi[a], xi[a]};                                   \
                UNROLL for (int n = 0; n < AF_NB(MM); ++n) {                                    \
                    memcpy(&w, wp[a] + 4 * n, sizeof w);                                        \
                    o[n] += xa * w;                                                             \
                }                                                                               \
            }                                                                                   \
            if (c) /* the product first, then the row: as x @ W + c */                          \
                UNROLL for (int n = 0; n < AF_NB(MM); ++n) {                                    \
                    memcpy(&w, cp + 4 * n, sizeof w);                                           \
                    o[n] += w;                                                                  \
                }                                                                               \
            T *oi = out + (b * N + i) * (MM);                                                   \
            UNROLL for (int n = 0; n < (MM) / 4; ++n) memcpy(oi + 4 * n, &o[n], sizeof o[n]);    \
            UNROLL for (int j = ((MM) / 4) * 4; j < (MM); ++j) oi[j] = o[j / 4][j % 4];          \
        }                                                                                       \
    }
#define AF_FIXED(MM)                                                                             \
    WIDE_LOOPS static void AF(affine_rows_##MM)(void **args, int64_t lo, int64_t hi) {          \
        AF_ARGS(MM)                                                                             \
        if (k <= AF_VEC_MAX_K) {                                                                \
            AF_VECTOR_BODY(MM)                                                                  \
        } else {                                                                                \
            AF_BODY(MM)                                                                         \
        }                                                                                       \
    }
#else
#define AF_FIXED(MM)                                                                             \
    WIDE_LOOPS static void AF(affine_rows_##MM)(void **args, int64_t lo, int64_t hi) {          \
        AF_ARGS(MM)                                                                             \
        AF_BODY(MM)                                                                             \
    }
#endif
AF_FIXED(2)
AF_FIXED(3)
AF_FIXED(4)
AF_FIXED(6)
AF_FIXED(9)
AF_FIXED(18)
AF_FIXED(21)
AF_FIXED(27)
AF_FIXED(40)
#undef AF_FIXED

/* any other row length (at most AF_MAX_M) */
WIDE_LOOPS static void AF(affine_rows_any)(void **args, int64_t lo, int64_t hi) {
    const int64_t mm = ((const int64_t *)args[4])[2];
    AF_ARGS(mm)
    AF_BODY(mm)
}
#undef AF_ARGS
#undef AF_BODY
#ifdef AF_VECTOR_BODY
#undef AF_VECTOR_BODY
#undef AF_VEC_MAX_K
#undef AF_NB
#endif

static range_fn AF(affine_rows_for)(int64_t m) {
    switch (m) {
        case 2: return AF(affine_rows_2);
        case 3: return AF(affine_rows_3);
        case 4: return AF(affine_rows_4);
        case 6: return AF(affine_rows_6);
        case 9: return AF(affine_rows_9);
        case 18: return AF(affine_rows_18);
        case 21: return AF(affine_rows_21);
        case 27: return AF(affine_rows_27);
        case 40: return AF(affine_rows_40);
        default: return AF(affine_rows_any);
    }
}

#undef AF
#undef AF__
#undef AF_
#undef T
#undef SFX
