/* Batched Cholesky solves of block-sparse systems sharing one pattern (included by
 * estimation/_native.c once per element type T with suffix SFX; the operator
 * torchsgal::block_cholesky_solve, estimation/block_cholesky.py, which builds the pattern).
 *
 * The pattern S (int64, block_cholesky.py's ``Structure.packed``): the header n (blocks), D
 * (unknowns), P (stored values), U (updates), M (update rows), Rt (panel rows), flops, then per block
 * column t in elimination order its size, first unknown, panel offset, panel rows and first
 * panel row; each panel row's unknown (Rt); per column the range of its updates (n + 1); per
 * update the source column, the source panel's first row of column t and the offset of the
 * update's row map; the row maps (M).
 *
 * Panel t holds L's block column t row-major: the diagonal block (s x s), then the blocks of the
 * rows below in elimination order.  Left-looking: column t subtracts, for every earlier column k
 * whose panel reaches block t, the product of k's rows from block t on with L_tk^T (scattered by
 * the row map into panel t), then factors its diagonal block and solves the rows below by it.
 * The solves run forward and back over the panels; Q holds each solution column's x^T A x (from
 * A's lower triangle, as the factorisation).  A
 * pivot that is not positive (or not finite) stops that system: info = its row + 1 in
 * elimination order, L, X and Q NaN.
 */
#define CAT_(a, b) a##_##b
#define CAT(a, b) CAT_(a, b)

#ifndef BLOCK_STRUCTURE_VALID
#define BLOCK_STRUCTURE_VALID
/* 1 if the pattern S of ``numel`` entries is consistent (every index the kernel follows lies in
 * its array), else 0: the operator is public, so a malformed structure is refused, not run. */
static int block_structure_valid(const int64_t *S, int64_t numel) {
    if (numel < 7) return 0;
    const int64_t n = S[0], D = S[1], P = S[2], U = S[3], M = S[4], Rt = S[5];
    if (n < 1 || D < 1 || P < 0 || U < 0 || M < 0 || Rt < 0 || S[6] < 0) return 0;
    if (numel != 7 + 5 * n + Rt + (n + 1) + 3 * U + M) return 0;
    const int64_t *size = S + 7, *eoff = size + n, *poff = eoff + n, *prows = poff + n;
    const int64_t *rbase = prows + n, *rindex = rbase + n, *uptr = rindex + Rt, *uk = uptr + n + 1;
    const int64_t *ustart = uk + U, *umap = ustart + U, *maps = umap + U;
    for (int64_t t = 0; t < n; ++t) {
        const int64_t s = size[t];
        if (s < 1 || eoff[t] < 0 || eoff[t] + s > D || prows[t] < s || poff[t] < 0
            || poff[t] + prows[t] * s > P || rbase[t] < 0 || rbase[t] + prows[t] > Rt)
            return 0;
        if (uptr[t] < 0 || uptr[t] > uptr[t + 1]) return 0;
    }
    if (uptr[0] != 0 || uptr[n] != U) return 0;
    for (int64_t i = 0; i < Rt; ++i)
        if (rindex[i] < 0 || rindex[i] >= D) return 0;
    for (int64_t t = 0; t < n; ++t)
        for (int64_t u = uptr[t]; u < uptr[t + 1]; ++u) {
            const int64_t src = uk[u], first = ustart[u];
            if (src < 0 || src >= t || first < size[src] || first + size[t] > prows[src]) return 0;
            if (umap[u] < 0 || umap[u] + (prows[src] - first) > M) return 0;
            for (int64_t r = 0; r < prows[src] - first; ++r)
                if (maps[umap[u] + r] < 0 || maps[umap[u] + r] >= prows[t]) return 0;
        }
    return 1;
}
#endif

/* Q_c = x_c^T A x_c (k columns) from A's stored lower triangle: each diagonal block's lower
 * triangle (its diagonal once, the rest twice), twice the blocks below */
static void CAT(block_quadratic, SFX)(const int64_t *S, const T *A, const T *X, T *Q, int64_t k) {
    const int64_t n = S[0];
    const int64_t *size = S + 7, *eoff = size + n, *poff = eoff + n, *prows = poff + n;
    const int64_t *rbase = prows + n, *rindex = rbase + n;
    for (int64_t c = 0; c < k; ++c) Q[c] = 0;
    for (int64_t t = 0; t < n; ++t) {
        const int64_t s = size[t];
        const T *At = A + poff[t], *xt = X + eoff[t] * k;
        for (int64_t r = 0; r < prows[t]; ++r) {
            const T *xr = X + rindex[rbase[t] + r] * k;
            const int64_t width = r < s ? r : s; /* the diagonal block: left of its diagonal */
            for (int64_t c = 0; c < k; ++c) {
                T acc = 0;
                for (int64_t j = 0; j < width; ++j) acc += At[r * s + j] * xt[j * k + c];
                Q[c] += 2 * xr[c] * acc + (r < s ? At[r * s + r] * xr[c] * xr[c] : 0);
            }
        }
    }
}

WIDE_LANES static void CAT(block_cholesky_one, SFX)(const int64_t *S, const T *A, const T *R, T *L, T *X,
                                         T *Q, int32_t *info, int64_t k) {
    const int64_t n = S[0], D = S[1], P = S[2], U = S[3], Rt = S[5];
    const int64_t *size = S + 7, *eoff = size + n, *poff = eoff + n, *prows = poff + n;
    const int64_t *rbase = prows + n, *rindex = rbase + n, *uptr = rindex + Rt, *uk = uptr + n + 1;
    const int64_t *ustart = uk + U, *umap = ustart + U, *maps = umap + U;
    int32_t bad = 0;
    memcpy(L, A, (size_t)P * sizeof(T));
    for (int64_t t = 0; t < n && !bad; ++t) {
        const int64_t s = size[t], rows = prows[t];
        T *Pt = L + poff[t];
        for (int64_t u = uptr[t]; u < uptr[t + 1]; ++u) {
            const int64_t src = uk[u], sk = size[src], first = ustart[u];
            const T *Pk = L + poff[src], *Ltk = Pk + first * sk;
            const int64_t *map = maps + umap[u];
            for (int64_t r = first; r < prows[src]; ++r) {
                const T *a = Pk + r * sk;
                T *dst = Pt + map[r - first] * s;
                for (int64_t c = 0; c < s; ++c) {
                    const T *b = Ltk + c * sk;
                    T acc = 0;
                    for (int64_t q = 0; q < sk; ++q) acc += a[q] * b[q];
                    dst[c] -= acc;
                }
            }
        }
        for (int64_t j = 0; j < s && !bad; ++j) { /* the diagonal block, lower, by rows */
            T d = Pt[j * s + j];
            for (int64_t p = 0; p < j; ++p) d -= Pt[j * s + p] * Pt[j * s + p];
            if (!(d > 0) || !(d < INFINITY)) {
                bad = (int32_t)(eoff[t] + j + 1);
                break;
            }
            const T ljj = SQRT(d), rj = 1 / ljj;
            Pt[j * s + j] = ljj;
            for (int64_t i = j + 1; i < s; ++i) {
                T v = Pt[i * s + j];
                for (int64_t p = 0; p < j; ++p) v -= Pt[i * s + p] * Pt[j * s + p];
                Pt[i * s + j] = v * rj;
            }
            for (int64_t i = 0; i < j; ++i) Pt[i * s + j] = 0; /* the strict upper triangle */
        }
        if (bad) break;
        for (int64_t r = s; r < rows; ++r) { /* rows below: x L_tt^T = p, forward */
            T *x = Pt + r * s;
            for (int64_t j = 0; j < s; ++j) {
                T v = x[j];
                for (int64_t p = 0; p < j; ++p) v -= x[p] * Pt[j * s + p];
                x[j] = v / Pt[j * s + j];
            }
        }
    }
    *info = bad;
    if (bad) {
        for (int64_t i = 0; i < P; ++i) L[i] = (T)NAN;
        for (int64_t i = 0; i < D * k; ++i) X[i] = (T)NAN;
        for (int64_t c = 0; c < k; ++c) Q[c] = (T)NAN;
        return;
    }
    memcpy(X, R, (size_t)(D * k) * sizeof(T));
    for (int64_t t = 0; t < n; ++t) { /* L y = x */
        const int64_t s = size[t];
        const T *Pt = L + poff[t];
        T *xt = X + eoff[t] * k;
        for (int64_t j = 0; j < s; ++j) {
            for (int64_t p = 0; p < j; ++p)
                for (int64_t c = 0; c < k; ++c) xt[j * k + c] -= Pt[j * s + p] * xt[p * k + c];
            for (int64_t c = 0; c < k; ++c) xt[j * k + c] /= Pt[j * s + j];
        }
        for (int64_t r = s; r < prows[t]; ++r) {
            T *xr = X + rindex[rbase[t] + r] * k;
            for (int64_t j = 0; j < s; ++j)
                for (int64_t c = 0; c < k; ++c) xr[c] -= Pt[r * s + j] * xt[j * k + c];
        }
    }
    for (int64_t t = n - 1; t >= 0; --t) { /* L^T x = y */
        const int64_t s = size[t];
        const T *Pt = L + poff[t];
        T *xt = X + eoff[t] * k;
        for (int64_t r = s; r < prows[t]; ++r) {
            const T *xr = X + rindex[rbase[t] + r] * k;
            for (int64_t j = 0; j < s; ++j)
                for (int64_t c = 0; c < k; ++c) xt[j * k + c] -= Pt[r * s + j] * xr[c];
        }
        for (int64_t j = s - 1; j >= 0; --j) {
            for (int64_t p = j + 1; p < s; ++p)
                for (int64_t c = 0; c < k; ++c) xt[j * k + c] -= Pt[p * s + j] * xt[p * k + c];
            for (int64_t c = 0; c < k; ++c) xt[j * k + c] /= Pt[j * s + j];
        }
    }
    CAT(block_quadratic, SFX)(S, A, X, Q, k);
}

/* The same on BC_LANES systems at once, lane w of every array holding system w (the last system
 * repeated where fewer are left): each step is one operation on BC_LANES values (vector
 * instructions).  A lane whose pivot fails goes on with pivot 1 and is set to NaN at the end; every
 * lane runs the same operations, so a system's result does not depend on its group. */
#ifndef BC_LANES
#define BC_LANES 8
#define BC_LANES_MAX_BYTES (8 << 20) /* the lanes' workspace at most (else one system at a time) */
#endif

WIDE_LANES static void CAT(block_cholesky_lanes, SFX)(const int64_t *S, const T *A, const T *R, T *L, T *X, T *Q,
                                           int32_t *info, int64_t k, int64_t nsys, T (*restrict l)[BC_LANES],
                                           T (*restrict x)[BC_LANES]) {
    const int64_t n = S[0], D = S[1], P = S[2], U = S[3], Rt = S[5];
    const int64_t *size = S + 7, *eoff = size + n, *poff = eoff + n, *prows = poff + n;
    const int64_t *rbase = prows + n, *rindex = rbase + n, *uptr = rindex + Rt, *uk = uptr + n + 1;
    const int64_t *ustart = uk + U, *umap = ustart + U, *maps = umap + U;
    int32_t bad[BC_LANES];
    for (int w = 0; w < BC_LANES; ++w) {
        const T *a = A + (w < nsys ? w : nsys - 1) * P, *r = R + (w < nsys ? w : nsys - 1) * D * k;
        for (int64_t i = 0; i < P; ++i) l[i][w] = a[i];
        for (int64_t i = 0; i < D * k; ++i) x[i][w] = r[i];
        bad[w] = 0;
    }
    for (int64_t t = 0; t < n; ++t) {
        const int64_t s = size[t], rows = prows[t];
        T(*Pt)[BC_LANES] = l + poff[t];
        for (int64_t u = uptr[t]; u < uptr[t + 1]; ++u) {
            const int64_t src = uk[u], sk = size[src], first = ustart[u];
            T(*Pk)[BC_LANES] = l + poff[src];
            const int64_t *map = maps + umap[u];
            for (int64_t r = first; r < prows[src]; ++r) {
                T(*a)[BC_LANES] = Pk + r * sk;
                T(*dst)[BC_LANES] = Pt + map[r - first] * s;
                for (int64_t c = 0; c < s; ++c) {
                    T(*b)[BC_LANES] = Pk + (first + c) * sk;
                    T acc[BC_LANES] = {0};
                    for (int64_t q = 0; q < sk; ++q)
                        for (int w = 0; w < BC_LANES; ++w) acc[w] += a[q][w] * b[q][w];
                    for (int w = 0; w < BC_LANES; ++w) dst[c][w] -= acc[w];
                }
            }
        }
        for (int64_t j = 0; j < s; ++j) {
            T d[BC_LANES], rj[BC_LANES];
            for (int w = 0; w < BC_LANES; ++w) d[w] = Pt[j * s + j][w];
            for (int64_t p = 0; p < j; ++p)
                for (int w = 0; w < BC_LANES; ++w) d[w] -= Pt[j * s + p][w] * Pt[j * s + p][w];
            for (int w = 0; w < BC_LANES; ++w) {
                const int ok = d[w] > 0 && d[w] < INFINITY;
                if (!ok && !bad[w]) bad[w] = (int32_t)(eoff[t] + j + 1);
                Pt[j * s + j][w] = ok ? SQRT(d[w]) : 1;
                rj[w] = 1 / Pt[j * s + j][w];
            }
            for (int64_t i = j + 1; i < s; ++i) {
                T v[BC_LANES];
                for (int w = 0; w < BC_LANES; ++w) v[w] = Pt[i * s + j][w];
                for (int64_t p = 0; p < j; ++p)
                    for (int w = 0; w < BC_LANES; ++w) v[w] -= Pt[i * s + p][w] * Pt[j * s + p][w];
                for (int w = 0; w < BC_LANES; ++w) Pt[i * s + j][w] = v[w] * rj[w];
            }
            for (int64_t i = 0; i < j; ++i)
                for (int w = 0; w < BC_LANES; ++w) Pt[i * s + j][w] = 0;
        }
        for (int64_t r = s; r < rows; ++r) {
            T(*xr)[BC_LANES] = Pt + r * s;
            for (int64_t j = 0; j < s; ++j) {
                T v[BC_LANES];
                for (int w = 0; w < BC_LANES; ++w) v[w] = xr[j][w];
                for (int64_t p = 0; p < j; ++p)
                    for (int w = 0; w < BC_LANES; ++w) v[w] -= xr[p][w] * Pt[j * s + p][w];
                for (int w = 0; w < BC_LANES; ++w) xr[j][w] = v[w] / Pt[j * s + j][w];
            }
        }
    }
    for (int64_t t = 0; t < n; ++t) { /* L y = x */
        const int64_t s = size[t];
        T(*Pt)[BC_LANES] = l + poff[t];
        T(*xt)[BC_LANES] = x + eoff[t] * k;
        for (int64_t j = 0; j < s; ++j) {
            for (int64_t p = 0; p < j; ++p)
                for (int64_t c = 0; c < k; ++c)
                    for (int w = 0; w < BC_LANES; ++w) xt[j * k + c][w] -= Pt[j * s + p][w] * xt[p * k + c][w];
            for (int64_t c = 0; c < k; ++c)
                for (int w = 0; w < BC_LANES; ++w) xt[j * k + c][w] /= Pt[j * s + j][w];
        }
        for (int64_t r = s; r < prows[t]; ++r) {
            T(*xr)[BC_LANES] = x + rindex[rbase[t] + r] * k;
            for (int64_t j = 0; j < s; ++j)
                for (int64_t c = 0; c < k; ++c)
                    for (int w = 0; w < BC_LANES; ++w) xr[c][w] -= Pt[r * s + j][w] * xt[j * k + c][w];
        }
    }
    for (int64_t t = n - 1; t >= 0; --t) { /* L^T x = y */
        const int64_t s = size[t];
        T(*Pt)[BC_LANES] = l + poff[t];
        T(*xt)[BC_LANES] = x + eoff[t] * k;
        for (int64_t r = s; r < prows[t]; ++r) {
            T(*xr)[BC_LANES] = x + rindex[rbase[t] + r] * k;
            for (int64_t j = 0; j < s; ++j)
                for (int64_t c = 0; c < k; ++c)
                    for (int w = 0; w < BC_LANES; ++w) xt[j * k + c][w] -= Pt[r * s + j][w] * xr[c][w];
        }
        for (int64_t j = s - 1; j >= 0; --j) {
            for (int64_t p = j + 1; p < s; ++p)
                for (int64_t c = 0; c < k; ++c)
                    for (int w = 0; w < BC_LANES; ++w) xt[j * k + c][w] -= Pt[p * s + j][w] * xt[p * k + c][w];
            for (int64_t c = 0; c < k; ++c)
                for (int w = 0; w < BC_LANES; ++w) xt[j * k + c][w] /= Pt[j * s + j][w];
        }
    }
    for (int64_t w = 0; w < nsys; ++w) { /* out, and Q from the systems' own A */
        T *Lw = L + w * P, *Xw = X + w * D * k, *Qw = Q + w * k;
        info[w] = bad[w];
        if (bad[w]) {
            for (int64_t i = 0; i < P; ++i) Lw[i] = (T)NAN;
            for (int64_t i = 0; i < D * k; ++i) Xw[i] = (T)NAN;
            for (int64_t c = 0; c < k; ++c) Qw[c] = (T)NAN;
            continue;
        }
        for (int64_t i = 0; i < P; ++i) Lw[i] = l[i][w];
        for (int64_t i = 0; i < D * k; ++i) Xw[i] = x[i][w];
        CAT(block_quadratic, SFX)(S, A + w * P, Xw, Qw, k);
    }
}

/* args: values, rhs, structure, L, X, Q, info, and k as int64 */
WIDE_LOOPS static void CAT(block_cholesky_range, SFX)(void **args, int64_t lo, int64_t hi) {
    const T *A = args[0], *R = args[1];
    const int64_t *S = args[2];
    T *L = args[3], *X = args[4], *Q = args[5];
    int32_t *info = args[6];
    const int64_t k = *(const int64_t *)args[7], D = S[1], P = S[2];
    const size_t bytes = (size_t)(P + D * k) * sizeof(T[BC_LANES]);
    T(*lanes)[BC_LANES] = hi - lo > 1 && bytes <= BC_LANES_MAX_BYTES ? malloc(bytes) : NULL;
    if (lanes) {
        for (int64_t b = lo; b < hi; b += BC_LANES)
            CAT(block_cholesky_lanes, SFX)(S, A + b * P, R + b * D * k, L + b * P, X + b * D * k,
                                           Q + b * k, info + b, k, hi - b < BC_LANES ? hi - b : BC_LANES,
                                           lanes, lanes + P);
        free(lanes);
        return;
    }
    for (int64_t b = lo; b < hi; ++b)
        CAT(block_cholesky_one, SFX)(S, A + b * P, R + b * D * k, L + b * P, X + b * D * k, Q + b * k,
                                     info + b, k);
}

#undef CAT
#undef CAT_
