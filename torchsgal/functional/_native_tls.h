/* The structured Gauss-Helmert linearisation of the SGal(3) total-least-squares conditions
 * (torchsgal/estimation/tls.py, _structured.part with the SGal(3) model), one condition at a
 * time, in double (included once by _native.c, after the SGal(3) kernels it uses).
 *
 * Condition n of trial k, with s = n dtau, the drifted frame A_n = (C, v, r - s v, tau) of the
 * trial's unknown X, observation errors e = [ea, eb] (or none: the paper variant, e = 0):
 *
 *   c'  = Ad(T^-n) log(exp(-eb) M_n exp(ea) A_n)              (rho += s nu)
 *   Ga  = Ad(X^-1) Ad(T^-n) J_r(ea),  Gb = -Ad(T^-n) J_r(eb)    (rows rho += s rows nu)
 *   w   = c' - Ga ea - Gb eb,  W = [Ga Ra, Gb Rb]  (R: covariance factors, diagonal or lower)
 *   S   = W W^T = L L^T,  Li = L^-1,  rows [Li, n Li a, Li w],  G_k += rows^T rows.
 *
 * The torch code is the oracle (tests/test_native.py compares the two linearisations); it is
 * itself checked against autograd and the generic Gauss-Helmert layer in tests/test_tls.py.
 */

typedef struct {
    const double *M, *X, *Ad_Xinv, *a, *s, *n, *e;  /* (K,N1,5,5) (K,5,5) (K,10,10) (K,10) (K,N1) (N1) (K,N1,20)|NULL */
    const double *fa, *fb;                          /* covariance factors, see the strides */
    int64_t fa_k, fa_n, fb_k, fb_n;                 /* their strides (entries) per trial and per sample */
    int diag_a, diag_b;                             /* 1: the factor is a square-root diagonal (10) */
    double *R, *W, *G;                              /* (K, N1*10, 12), (K, N1, 10, 20), (K, 12, 12) */
    int32_t *info;                                  /* (K, N1): 0, or the failing Cholesky column */
    int64_t N1;
} tls_args_t;

/* O = A B for 5x5 row-major matrices (the full product, as torch's matmul). */
static inline void tls_mul5(const double *A, const double *B, double *O) {
    for (int i = 0; i < 5; ++i)
        for (int j = 0; j < 5; ++j) {
            double acc = 0;
            for (int k = 0; k < 5; ++k) acc += A[5 * i + k] * B[5 * k + j];
            O[5 * i + j] = acc;
        }
}

/* J_r(x) = J_l(-x) (10x10, row-major). */
static inline void tls_jr(const double *x, double *J) { jl_matrix_one_f64(x, -1.0, J); }

/* G R for a 10x10 G and the factor R (diagonal: its 10 entries; else 10x10 row-major), into
 * the columns [col, col + 10) of the 10x20 row-major W. */
static inline void tls_whiten(const double *G, const double *R, int diag, double *W, int col) {
    for (int i = 0; i < 10; ++i)
        for (int j = 0; j < 10; ++j) {
            double acc;
            if (diag) {
                acc = G[10 * i + j] * R[j];
            } else {
                acc = 0;
                for (int k = 0; k < 10; ++k) acc += G[10 * i + k] * R[10 * k + j];
            }
            W[20 * i + col + j] = acc;
        }
}

/* S = W W^T (10x10) for W = [Ga Da, Gb Db] with diagonal factors: Ga and Gb (Ad(X^-1), J_r and
 * Ad(T^-n) are block upper-triangular over [rho, nu, phi, iota]) have zero blocks that diagonal
 * factors keep: row block nu (3-5) is zero outside the columns 3-8 of each half, phi (6-8)
 * outside 6-8, iota (9) outside 9.  Only the products of the columns that can be non-zero in
 * both rows are summed, in the order of the dense loop (the same rounding). */
static inline void tls_s_block_sparse(const double *W, double *S) {
    /* As outer products of W's columns (no reduction chains): column m of either half can be
     * non-zero in rows 0-2 (m < 3), 0-5 (m < 6), 0-8 (m < 9), or 0-2 and 9 (m = 9). */
    for (int i = 0; i < 100; ++i) S[i] = 0;
    for (int h = 0; h < 20; h += 10)
        for (int m = 0; m < 10; ++m) {
            int nr = m < 3 ? 3 : m < 6 ? 6 : m < 9 ? 9 : 3;
            double col[9];
            for (int r = 0; r < nr; ++r) col[r] = W[20 * r + h + m];
            for (int r = 0; r < nr; ++r)
                for (int c = 0; c < nr; ++c) S[10 * r + c] += col[r] * col[c];
            if (m == 9) {
                double w9 = W[20 * 9 + h + 9];
                for (int r = 0; r < 3; ++r) {
                    S[10 * r + 9] += col[r] * w9;
                    S[90 + r] += w9 * col[r];
                }
                S[99] += w9 * w9;
            }
        }
}

/* Li = L^-1 with S = L L^T (10x10), as _small_linalg.cholesky_t / tril_inverse_t: the first
 * failing pivot (<= 0 or NaN) is returned (1-based), 0 if none; entries from there on are
 * non-finite. */
static inline int32_t tls_inverse_cholesky(const double *S, double *Li) {
    double L[100] = {0};
    int32_t info = 0;
    for (int j = 0; j < 10; ++j) {
        double v[10];
        for (int i = j; i < 10; ++i) {
            double acc = 0;
            for (int k = 0; k < j; ++k) acc += L[10 * i + k] * L[10 * j + k];
            v[i] = S[10 * i + j] - acc;
        }
        double piv = v[j];
        if (info == 0 && !(piv > 0)) info = j + 1;
        double rs = 1.0 / sqrt(piv);
        for (int i = j; i < 10; ++i) L[10 * i + j] = v[i] * rs;
    }
    for (int i = 0; i < 100; ++i) Li[i] = 0;
    for (int i = 0; i < 10; ++i) {
        double di = 1.0 / L[11 * i];
        Li[11 * i] = di;
        for (int j = 0; j < i; ++j) {
            double acc = 0;
            for (int k = j; k < i; ++k) acc += L[10 * i + k] * Li[10 * k + j];
            Li[10 * i + j] = acc * -di;
        }
    }
    return info;
}

WIDE_LOOPS static void tls_range(void **pa, int64_t lo, int64_t hi) {
    const tls_args_t *A = (const tls_args_t *)pa;
    const int64_t N1 = A->N1;
    for (int64_t k = lo; k < hi; ++k) {
        const double *X = A->X + 25 * k, *Ad = A->Ad_Xinv + 100 * k, *a = A->a + 10 * k;
        double G[144] = {0};
        for (int64_t n = 0; n < N1; ++n) {
            const int64_t q = k * N1 + n;
            const double s = A->s[q], *e = A->e ? A->e + 20 * q : NULL;
            double Adrift[25], P[25], T1[25], T2[25], c[10], Ga[100], Gb[100];
            memcpy(Adrift, X, sizeof Adrift);  /* A_n = (C, v, r - s v, tau) */
            for (int i = 0; i < 3; ++i) Adrift[5 * i + 4] = X[5 * i + 4] - s * X[5 * i + 3];
            if (e) {  /* ((exp(-eb) M) exp(ea)) A */
                double Ea[25], Eb[25], meb[10];
                for (int i = 0; i < 10; ++i) meb[i] = -e[10 + i];
                exp_one_f64(e, Ea);
                exp_one_f64(meb, Eb);
                tls_mul5(Eb, A->M + 25 * q, T1);
                tls_mul5(T1, Ea, T2);
                tls_mul5(T2, Adrift, P);
            } else {
                tls_mul5(A->M + 25 * q, Adrift, P);
            }
            log_one_f64(P, c);
            for (int i = 0; i < 3; ++i) c[i] += s * c[3 + i];  /* Ad(T^-n) c */
            if (e) {
                double Ja[100], Jb[100];
                tls_jr(e, Ja);
                tls_jr(e + 10, Jb);
                for (int i = 0; i < 3; ++i)
                    for (int j = 0; j < 10; ++j) {
                        Ja[10 * i + j] += s * Ja[10 * (3 + i) + j];
                        Jb[10 * i + j] += s * Jb[10 * (3 + i) + j];
                    }
                for (int i = 0; i < 10; ++i) {  /* Ga = Ad Ja, a row at a time (no reduction chains) */
                    double *g = Ga + 10 * i;
                    for (int j = 0; j < 10; ++j) g[j] = Ad[10 * i] * Ja[j];
                    for (int m = 1; m < 10; ++m)
                        for (int j = 0; j < 10; ++j) g[j] += Ad[10 * i + m] * Ja[10 * m + j];
                    for (int j = 0; j < 10; ++j) Gb[10 * i + j] = -Jb[10 * i + j];
                }
                for (int i = 0; i < 10; ++i) {  /* w = c' - Ga ea - Gb eb */
                    double acc = 0;
                    for (int j = 0; j < 10; ++j) acc += Ga[10 * i + j] * e[j] + Gb[10 * i + j] * e[10 + j];
                    c[i] -= acc;
                }
            } else {  /* J_r(0) = I: Ga = Ad(X^-1) with nu columns += s rho columns, Gb = -(I + s E) */
                for (int i = 0; i < 10; ++i)
                    for (int j = 0; j < 10; ++j) {
                        Ga[10 * i + j] = Ad[10 * i + j] + (j >= 3 && j < 6 ? s * Ad[10 * i + j - 3] : 0.0);
                        Gb[10 * i + j] = i == j ? -1.0 : 0.0;
                    }
                for (int i = 0; i < 3; ++i) Gb[10 * i + 3 + i] = -s;
            }
            double *W = A->W + 200 * q, S[100], Li[100];
            tls_whiten(Ga, A->fa + k * A->fa_k + n * A->fa_n, A->diag_a, W, 0);
            tls_whiten(Gb, A->fb + k * A->fb_k + n * A->fb_n, A->diag_b, W, 10);
            if (A->diag_a && A->diag_b) {
                tls_s_block_sparse(W, S);
            } else {
                double Wt[200];  /* S = W W^T as a sum of outer products of W's columns */
                for (int i = 0; i < 10; ++i)
                    for (int m = 0; m < 20; ++m) Wt[10 * m + i] = W[20 * i + m];
                for (int i = 0; i < 10; ++i)
                    for (int j = 0; j < 10; ++j) S[10 * i + j] = Wt[i] * Wt[j];
                for (int m = 1; m < 20; ++m) {
                    const double *col = Wt + 10 * m;
                    for (int i = 0; i < 10; ++i)
                        for (int j = 0; j < 10; ++j) S[10 * i + j] += col[i] * col[j];
                }
            }
            A->info[q] = tls_inverse_cholesky(S, Li);
            double *R = A->R + 120 * q, na = A->n[n];
            for (int i = 0; i < 10; ++i) {
                double la = 0, lw = 0;
                for (int j = 0; j <= i; ++j) {
                    la += Li[10 * i + j] * a[j];
                    lw += Li[10 * i + j] * c[j];
                }
                for (int j = 0; j < 10; ++j) R[12 * i + j] = Li[10 * i + j];
                R[12 * i + 10] = na * la;
                R[12 * i + 11] = lw;
            }
            for (int r = 0; r < 10; ++r) {  /* G += rows^T rows (upper triangle); row r of Li */
                const double *row = R + 12 * r;  /* is zero beyond column r */
                int idx[12], len = 0;
                for (int i = 0; i <= r; ++i) idx[len++] = i;
                idx[len++] = 10;
                idx[len++] = 11;
                for (int p = 0; p < len; ++p) {
                    double ri = row[idx[p]];
                    double *Gi = G + 12 * idx[p];
                    for (int q = p; q < len; ++q) Gi[idx[q]] += ri * row[idx[q]];
                }
            }
        }
        double *Gk = A->G + 144 * k;
        for (int i = 0; i < 12; ++i)
            for (int j = 0; j < 12; ++j) Gk[12 * i + j] = j >= i ? G[12 * i + j] : G[12 * j + i];
    }
}

/* The residual update of post_step: e = -[Ra (W_a^T y), Rb (W_b^T y)] with y = Li^T (R [dx, 1])
 * for each condition (R's first 10 columns are Li); dx (K, 11). */
typedef struct {
    const double *R, *W, *dx, *fa, *fb;
    int64_t fa_k, fa_n, fb_k, fb_n;
    int diag_a, diag_b;
    double *e;  /* (K, N1, 20) */
    int64_t N1;
} tls_step_args_t;

static inline void tls_unwhiten(const double *u, const double *R, int diag, double *o) {
    for (int i = 0; i < 10; ++i) {  /* o = -(R u): R diagonal or lower (row-major) */
        double acc;
        if (diag) {
            acc = u[i] * R[i];
        } else {
            acc = 0;
            for (int k = 0; k < 10; ++k) acc += R[10 * i + k] * u[k];
        }
        o[i] = -acc;
    }
}

WIDE_LOOPS static void tls_step_range(void **pa, int64_t lo, int64_t hi) {
    const tls_step_args_t *A = (const tls_step_args_t *)pa;
    const int64_t N1 = A->N1;
    for (int64_t k = lo; k < hi; ++k) {
        const double *d = A->dx + 11 * k;
        for (int64_t n = 0; n < N1; ++n) {
            const int64_t q = k * N1 + n;
            const double *R = A->R + 120 * q, *W = A->W + 200 * q;
            double z[10], y[10] = {0}, u[20] = {0};
            for (int r = 0; r < 10; ++r) {
                double acc = 0;
                for (int j = 0; j < 11; ++j) acc += R[12 * r + j] * d[j];
                z[r] = acc + R[12 * r + 11];
            }
            for (int r = 0; r < 10; ++r)
                for (int j = 0; j < 10; ++j) y[j] += R[12 * r + j] * z[r];
            for (int i = 0; i < 10; ++i)
                for (int j = 0; j < 20; ++j) u[j] += W[20 * i + j] * y[i];
            double *e = A->e + 20 * q;
            tls_unwhiten(u, A->fa + k * A->fa_k + n * A->fa_n, A->diag_a, e);
            tls_unwhiten(u + 10, A->fb + k * A->fb_k + n * A->fb_n, A->diag_b, e + 10);
        }
    }
}
