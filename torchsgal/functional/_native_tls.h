/* The structured Gauss-Helmert linearisation of the SGal(3) total-least-squares conditions
 * (torchsgal/estimation/tls.py, _structured.part with the SGal(3) model) and its residual
 * update, in double (included once by _native.c, after the SGal(3) kernels it uses).
 *
 * Condition n of trial k, with s = n dtau, the drifted frame A_n = (C, v, r - s v, tau) of the
 * trial's unknown X, observation errors e = [ea, eb] (or none: the paper variant, e = 0):
 *
 *   c'  = Ad(T^-n) log(exp(-eb) M_n exp(ea) A_n)              (rho += s nu)
 *   Ga  = Ad(X^-1) Ad(T^-n) J_r(ea),  Gb = -Ad(T^-n) J_r(eb)    (rows rho += s rows nu)
 *   w   = c' - Ga ea - Gb eb,  W = [Ga Ra, Gb Rb]  (R: covariance factors, diagonal or lower)
 *   S   = W W^T = L L^T,  Li = L^-1,  rows [Li, n Li a, Li w],  G_k += rows^T rows.
 *
 * Conditions run NL at a time ("lanes", conditions n0 .. n0 + NL - 1 of one trial; a trial's
 * last block repeats its last condition): exp and log one condition at a time into lane l of
 * structure-of-arrays blocks, J_r and the linear algebra on all lanes at once (the innermost
 * loops over l vectorise; no sum runs across lanes until G's lanes are added at the end of the
 * trial).  What the residual update needs is kept in that layout, packed (only the
 * entries that can be non-zero), per trial and block of lanes, each entry's NL lanes together:
 *
 *   R (K, NB, 75, NL):  Li's lower triangle by rows (55), n Li a (10), Li w (10)
 *   W (K, NB, NW, NL):  W's entries (i, h + j) for h = 0, 10, i = 0..9, j in [lo_h(i), HI[i])
 *
 * with NB = ceil(N1 / NL), lo_h = LO with a diagonal factor and 0 with a lower one, and NW the
 * count of those entries (native.py's _TlsKernels.unpack restores the dense R and W).
 *
 * The torch code is the oracle (tests/test_native.py compares the two linearisations); it is
 * itself checked against autograd and the generic Gauss-Helmert layer in tests/test_tls.py.
 */

#define NL 4
#define LANES for (int l = 0; l < NL; ++l)
#if defined(__GNUC__)
#define LANE_ALIGN __attribute__((aligned(32)))
#else
#define LANE_ALIGN
#endif

/* dst[0 .. NL) = src: the packed state is written once and read back by the step only, after
 * every other condition's (more than the caches hold): streaming stores on x86-64 (SSE2, in
 * every clone) skip reading the lines into the cache first.  dst 16-byte aligned. */
#if defined(__x86_64__) && defined(__SSE2__)
#include <emmintrin.h>
#define LANE_STREAM_FENCE() _mm_sfence()
static inline void lane_stream(double *dst, const double *src) {
    for (int l = 0; l < NL; l += 2) _mm_stream_pd(dst + l, _mm_loadu_pd(src + l));
}
#else
#define LANE_STREAM_FENCE() ((void)0)
static inline void lane_stream(double *dst, const double *src) { memcpy(dst, src, NL * sizeof(double)); }
#endif

/* Ad(X^-1), Ad(T^-n) and J_r are block upper-triangular over [rho, nu, phi, iota], so row i of
 * Ga and Gb can be non-zero in the columns [LO[i], HI[i]) only; W's row i in [lo_h(i), HI[i])
 * (a lower factor R mixes the columns below HI[i]). */
static const int TLS_LO[10] = {0, 0, 0, 3, 3, 3, 6, 6, 6, 9};
static const int TLS_HI[10] = {10, 10, 10, 9, 9, 9, 9, 9, 9, 10};

/* W's packed entries: lo[h][i] and, for each (h, i), the offset of its first entry; returns NW. */
static inline int tls_w_layout(int diag_a, int diag_b, int lo[2][10], int off[2][10]) {
    int nw = 0;
    for (int h = 0; h < 2; ++h)
        for (int i = 0; i < 10; ++i) {
            lo[h][i] = (h ? diag_b : diag_a) ? TLS_LO[i] : 0;
            off[h][i] = nw;
            nw += TLS_HI[i] - lo[h][i];
        }
    return nw;
}

typedef struct {
    const double *M, *X, *Ad_Xinv, *a, *s, *n, *e;  /* (K,N1,5,5) (K,5,5) (K,10,10) (K,10) (K,N1) (N1) (K,N1,20)|NULL */
    const double *fa, *fb;                          /* covariance factors, see the strides */
    int64_t fa_k, fa_n, fb_k, fb_n;                 /* their strides (entries) per trial and per sample */
    int diag_a, diag_b;                             /* 1: the factor is a square-root diagonal (10) */
    double *R, *W, *G;                              /* packed (K, NB, 75, NL), (K, NB, NW, NL); (K, 12, 12) */
    int32_t *info;                                  /* (K, N1): 0, or the failing Cholesky column */
    const uint8_t *active;                          /* (K): 0 skips the trial (G, info 0); NULL: all */
    int64_t N1;
} tls_args_t;

/* O = A B for SGal(3) matrices (5x5 row-major, rows 3-4 [0 0 0 1 tau], [0 0 0 0 1]): the sums
 * of the full product in its order, less its terms that are exact zeros (the same rounding). */
static inline void tls_compose(const double *A, const double *B, double *O) {
    for (int i = 0; i < 3; ++i) {
        const double *a = A + 5 * i;
        for (int j = 0; j < 3; ++j) O[5 * i + j] = a[0] * B[j] + a[1] * B[5 + j] + a[2] * B[10 + j];
        O[5 * i + 3] = a[0] * B[3] + a[1] * B[8] + a[2] * B[13] + a[3];
        O[5 * i + 4] = a[0] * B[4] + a[1] * B[9] + a[2] * B[14] + a[3] * B[19] + a[4];
    }
    O[15] = 0; O[16] = 0; O[17] = 0; O[18] = 1; O[19] = B[19] + A[19];
    O[20] = 0; O[21] = 0; O[22] = 0; O[23] = 0; O[24] = 1;
}

/* J_l (3.21)-(3.23) on lanes, a transcription of sgal3._jl_blocks and blocks.gamma_vec_derivative
 * (the same operations in the same order; a lane of a vector operation rounds as a scalar one),
 * with the series coefficients of _native_sgal3.h one lane at a time. */
static inline void lane_cross(double (*u)[NL], double (*v)[NL], double (*o)[NL]) {
    LANES o[0][l] = u[1][l] * v[2][l] - u[2][l] * v[1][l];
    LANES o[1][l] = u[2][l] * v[0][l] - u[0][l] * v[2][l];
    LANES o[2][l] = u[0][l] * v[1][l] - u[1][l] * v[0][l];
}

static inline void lane_sym_skew(const double *d, const double *a, const double *b, double (*phi)[NL],
                                 double (*o)[NL]) {  /* d I + a phi^ + b phi phi^T */
    LANES {
        double x = phi[0][l], y = phi[1][l], z = phi[2][l], ax = a[l] * x, ay = a[l] * y, az = a[l] * z;
        double bx = b[l] * x, by = b[l] * y, bxy = bx * y, bxz = bx * z, byz = by * z;
        o[0][l] = d[l] + bx * x; o[1][l] = bxy - az; o[2][l] = bxz + ay;
        o[3][l] = bxy + az; o[4][l] = d[l] + by * y; o[5][l] = byz - ax;
        o[6][l] = bxz - ay; o[7][l] = byz + ax; o[8][l] = d[l] + b[l] * z * z;
    }
}

/* d/dphi [Gamma_L(phi) x] (gamma_vec_derivative) */
static inline void lane_gamma_vec_derivative(double (*c)[NL], int L, double (*phi)[NL], double (*x)[NL],
                                             double (*o)[NL]) {
    double px[3][NL] LANE_ALIGN, ppx[3][NL] LANE_ALIGN, u[3][NL] LANE_ALIGN, bpx[NL] LANE_ALIGN;
    lane_cross(phi, x, px);
    lane_cross(phi, px, ppx);
    const double *a = c[L + 1], *b = c[L + 2];
    LANES bpx[l] = b[l] * (phi[0][l] * x[0][l] + phi[1][l] * x[1][l] + phi[2][l] * x[2][l]);
    for (int i = 0; i < 3; ++i)
        LANES {
            double ea = (double)(L + 1) * c[L + 3][l] - c[L + 2][l], eb = (double)(L + 2) * c[L + 4][l] - c[L + 3][l];
            u[i][l] = ea * px[i][l] + eb * ppx[i][l] - 2.0 * b[l] * x[i][l];
        }
    for (int i = 0; i < 3; ++i)
        for (int j = 0; j < 3; ++j) {
            /* x^ (i, j): 0 on the diagonal, else -+x[k] */
            const int k = 3 - i - j, sg = (j == (i + 1) % 3) ? -1 : 1;
            if (i == j)
                LANES o[3 * i + j][l] = ((u[i][l] * phi[j][l] + b[l] * (phi[i][l] * x[j][l])) + bpx[l]) - a[l] * 0.0;
            else
                LANES o[3 * i + j][l] = ((u[i][l] * phi[j][l] + b[l] * (phi[i][l] * x[j][l])) + 0.0) - a[l] * (sg * x[k][l]);
        }
}

static inline void lane_skew_times_add(double (*x)[NL], double (*M)[NL], double (*o)[NL]) {  /* o += x^ M */
    for (int j = 0; j < 3; ++j)
        LANES {
            double c0 = M[j][l], c1 = M[3 + j][l], c2 = M[6 + j][l];
            o[j][l] += x[1][l] * c2 - x[2][l] * c1;
            o[3 + j][l] += x[2][l] * c0 - x[0][l] * c2;
            o[6 + j][l] += x[0][l] * c1 - x[1][l] * c0;
        }
}

/* J_l(xi) (3.21)-(3.23) of the lanes' xi (10 x NL) into J (100 x NL): the entries of the
 * block pattern only: the others are left as they are (zeros, set once by tls_range). */
static void lane_jl(double (*xi)[NL], double (*J)[NL]) {
    double (*rho)[NL] = xi, (*nu)[NL] = xi + 3, (*phi)[NL] = xi + 6, *iota = xi[9];
    double c[7][NL] LANE_ALIGN;
    for (int l = 0; l < NL; ++l) {
        double cl[7], t2 = phi[0][l] * phi[0][l] + phi[1][l] * phi[1][l] + phi[2][l] * phi[2][l];
        coefficients_f64(t2, 6, cl);
        for (int m = 0; m < 7; ++m) c[m][l] = cl[m];
    }
    double D[9][NL] LANE_ALIGN, E[9][NL] LANE_ALIGN, Mb[9][NL] LANE_ALIGN, N[9][NL] LANE_ALIGN, d2[9][NL] LANE_ALIGN;
    double pn[3][NL] LANE_ALIGN, ppn[3][NL] LANE_ALIGN, pr[3][NL] LANE_ALIGN, ppr[3][NL] LANE_ALIGN;
    double gn[3][NL] LANE_ALIGN, g2n[3][NL] LANE_ALIGN, r[3][NL] LANE_ALIGN;
    lane_sym_skew(c[1], c[2], c[3], phi, D);
    lane_sym_skew(c[2], c[3], c[4], phi, E);
    lane_cross(phi, nu, pn);
    lane_cross(phi, pn, ppn);
    lane_cross(phi, rho, pr);
    lane_cross(phi, pr, ppr);
    for (int i = 0; i < 3; ++i) {
        LANES gn[i][l] = nu[i][l] + c[2][l] * pn[i][l] + c[3][l] * ppn[i][l];      /* Gamma_1 nu */
        LANES g2n[i][l] = nu[i][l] / 2.0 + c[3][l] * pn[i][l] + c[4][l] * ppn[i][l];  /* Gamma_2 nu */
        LANES r[i][l] = (rho[i][l] + c[2][l] * pr[i][l] + c[3][l] * ppr[i][l]) + iota[l] * g2n[i][l];
    }
    lane_gamma_vec_derivative(c, 1, phi, nu, Mb);  /* q_block */
    lane_skew_times_add(gn, D, Mb);
    lane_gamma_vec_derivative(c, 1, phi, rho, N);
    lane_gamma_vec_derivative(c, 2, phi, nu, d2);
    for (int i = 0; i < 9; ++i) LANES N[i][l] += iota[l] * d2[i][l];
    lane_skew_times_add(r, D, N);
    for (int i = 0; i < 9; ++i) LANES N[i][l] -= iota[l] * Mb[i][l];
    for (int i = 0; i < 3; ++i) {
        for (int j = 0; j < 3; ++j) {
            LANES J[10 * i + j][l] = D[3 * i + j][l];
            LANES J[10 * (3 + i) + 3 + j][l] = D[3 * i + j][l];
            LANES J[10 * (6 + i) + 6 + j][l] = D[3 * i + j][l];
            LANES J[10 * i + 3 + j][l] = -iota[l] * (D[3 * i + j][l] - E[3 * i + j][l]);
            LANES J[10 * i + 6 + j][l] = N[3 * i + j][l];
            LANES J[10 * (3 + i) + 6 + j][l] = Mb[3 * i + j][l];
        }
        LANES J[10 * i + 9][l] = g2n[i][l];
    }
    LANES J[99][l] = 1;
}

/* Lane l's condition: c' (10) and, in the iterated variant, e. */
static inline void tls_condition_lane(const tls_args_t *A, int64_t k, int64_t q, int l, double (*c)[NL],
                                      double (*e)[NL]) {
    const double *X = A->X + 25 * k, s = A->s[q], *eq = A->e ? A->e + 20 * q : NULL;
    double Adrift[25], P[25], cl[10];
    memcpy(Adrift, X, sizeof Adrift);  /* A_n = (C, v, r - s v, tau) */
    for (int i = 0; i < 3; ++i) Adrift[5 * i + 4] = X[5 * i + 4] - s * X[5 * i + 3];
    if (eq) {  /* ((exp(-eb) M) exp(ea)) A */
        double Ea[25], Eb[25], T1[25], T2[25], meb[10];
        for (int i = 0; i < 10; ++i) meb[i] = -eq[10 + i];
        exp_one_f64(eq, Ea);
        exp_one_f64(meb, Eb);
        tls_compose(Eb, A->M + 25 * q, T1);
        tls_compose(T1, Ea, T2);
        tls_compose(T2, Adrift, P);
        for (int i = 0; i < 20; ++i) e[i][l] = eq[i];
    } else {
        tls_compose(A->M + 25 * q, Adrift, P);
    }
    log_one_f64(P, cl);
    for (int i = 0; i < 3; ++i) cl[i] += s * cl[3 + i];  /* Ad(T^-n) c */
    for (int i = 0; i < 10; ++i) c[i][l] = cl[i];
}

/* S[p, q] += W[p, col] W[q, col] for q <= p < n (rows 0 .. n-1 of the column; n constant where
 * it is called, so that the loops unroll). */
static inline void s_outer_leading(double (*S)[10][NL], double (*W)[20][NL], int col, const int n) {
    for (int p = 0; p < n; ++p)
        for (int q = 0; q <= p; ++q) LANES S[p][q][l] += W[p][col][l] * W[q][col][l];
}

/* Lane l of the covariance factor of condition (k, n): 10 or 100 entries. */
static inline void tls_factor_lane(const double *f, int64_t fk, int64_t fn, int diag, int64_t k, int64_t n,
                                   double (*out)[NL], int l) {
    const double *p = f + k * fk + n * fn;
    for (int i = 0; i < (diag ? 10 : 100); ++i) out[i][l] = p[i];
}

/* W[i, h + j] = (G R)[i, j] for j in [lo[i], HI[i]) (zero elsewhere): G (10x10 lanes, row i
 * zero outside [LO, HI)), R the factors of the lanes (diagonal: 10 entries; else lower 10x10). */
static inline void tls_whiten_lanes(double (*G)[NL], double (*R)[NL], int diag, const int *lo,
                                    double (*W)[20][NL], int h) {
    for (int i = 0; i < 10; ++i) {
        double (*w)[NL] = W[i] + h;
        for (int j = 0; j < 10; ++j) LANES w[j][l] = 0;
        for (int k = TLS_LO[i]; k < TLS_HI[i]; ++k) {
            const double *g = G[10 * i + k];
            if (diag) {
                LANES w[k][l] = g[l] * R[k][l];
            } else {
                for (int j = lo[i]; j <= k; ++j) LANES w[j][l] += g[l] * R[10 * k + j][l];
            }
        }
    }
}

WIDE_LOOPS static void tls_range(void **pa, int64_t lo, int64_t hi) {
    const tls_args_t *A = (const tls_args_t *)pa;
    const int64_t N1 = A->N1, NB = (N1 + NL - 1) / NL;
    const int iterated = A->e != NULL;
    int wlo[2][10], woff[2][10], rows[2][10][10], nrows[2][10];
    const int nw = tls_w_layout(A->diag_a, A->diag_b, wlo, woff);
    for (int h = 0; h < 2; ++h)
        for (int m = 0; m < 10; ++m) {
            nrows[h][m] = 0;
            for (int i = 0; i < 10; ++i)
                if (m >= wlo[h][i] && m < TLS_HI[i]) rows[h][m][nrows[h][m]++] = i;
        }
    double Ja[100][NL] LANE_ALIGN, Jb[100][NL] LANE_ALIGN;  /* J_r's zeros stay (lane_jl) */
    memset(Ja, 0, sizeof Ja);
    memset(Jb, 0, sizeof Jb);
    for (int64_t k = lo; k < hi; ++k) {
        if (A->active && !A->active[k]) {
            memset(A->G + 144 * k, 0, 144 * sizeof(double));
            memset(A->info + k * N1, 0, N1 * sizeof(int32_t));
            continue;
        }
        const double *Ad = A->Ad_Xinv + 100 * k, *a = A->a + 10 * k;
        double G[12][12][NL] LANE_ALIGN;
        memset(G, 0, sizeof G);
        for (int64_t b = 0; b < NB; ++b) {
            const int64_t n0 = b * NL;
            const int nl = N1 - n0 < NL ? (int)(N1 - n0) : NL;  /* lanes beyond nl repeat the last */
            double c[10][NL] LANE_ALIGN, e[20][NL] LANE_ALIGN, s[NL] LANE_ALIGN, na[NL] LANE_ALIGN;
            double Ga[100][NL] LANE_ALIGN, Gb[100][NL] LANE_ALIGN;
            double fa[100][NL] LANE_ALIGN, fb[100][NL] LANE_ALIGN;
            for (int l = 0; l < NL; ++l) {
                const int64_t n = n0 + (l < nl ? l : nl - 1), q = k * N1 + n;
                tls_condition_lane(A, k, q, l, c, e);
                s[l] = A->s[q];
                na[l] = A->n[n];
                tls_factor_lane(A->fa, A->fa_k, A->fa_n, A->diag_a, k, n, fa, l);
                tls_factor_lane(A->fb, A->fb_k, A->fb_n, A->diag_b, k, n, fb, l);
            }
            /* Ga = Ad(X^-1) Ad(T^-n) J_r(ea), Gb = -Ad(T^-n) J_r(eb) (zero outside [LO, HI)) */
            if (iterated) {
                double me[20][NL] LANE_ALIGN;  /* J_r(e) = J_l(-e) */
                for (int i = 0; i < 20; ++i) LANES me[i][l] = -e[i][l];
                lane_jl(me, Ja);
                lane_jl(me + 10, Jb);
                for (int i = 0; i < 3; ++i)  /* Ad(T^-n): rows rho += s rows nu */
                    for (int j = 0; j < 10; ++j) {
                        LANES Ja[10 * i + j][l] += s[l] * Ja[10 * (3 + i) + j][l];
                        LANES Jb[10 * i + j][l] += s[l] * Jb[10 * (3 + i) + j][l];
                    }
                for (int i = 0; i < 10; ++i) {
                    for (int j = 0; j < 10; ++j) LANES Ga[10 * i + j][l] = 0;
                    for (int m = TLS_LO[i]; m < TLS_HI[i]; ++m) {
                        const double d = Ad[10 * i + m];
                        for (int j = TLS_LO[m]; j < TLS_HI[m]; ++j) LANES Ga[10 * i + j][l] += d * Ja[10 * m + j][l];
                    }
                    for (int j = 0; j < 10; ++j) LANES Gb[10 * i + j][l] = -Jb[10 * i + j][l];
                }
                /* w = c' - Ga ea - Gb eb (the sums over columns j, every row's at once) */
                double acc[10][NL] LANE_ALIGN;
                memset(acc, 0, sizeof acc);
                for (int j = 0; j < 10; ++j)
                    for (int i = 0; i < 10; ++i)
                        if (j >= TLS_LO[i] && j < TLS_HI[i])
                            LANES acc[i][l] += Ga[10 * i + j][l] * e[j][l] + Gb[10 * i + j][l] * e[10 + j][l];
                for (int i = 0; i < 10; ++i) LANES c[i][l] -= acc[i][l];
            } else {  /* J_r(0) = I: Ga = Ad(X^-1) with nu columns += s rho columns, Gb = -(I + s E) */
                for (int i = 0; i < 10; ++i)
                    for (int j = 0; j < 10; ++j) {
                        const double d = Ad[10 * i + j], d3 = j >= 3 && j < 6 ? Ad[10 * i + j - 3] : 0.0;
                        LANES Ga[10 * i + j][l] = d + s[l] * d3;
                        LANES Gb[10 * i + j][l] = i == j ? -1.0 : 0.0;
                    }
                for (int i = 0; i < 3; ++i) LANES Gb[10 * i + 3 + i][l] = -s[l];
            }
            double W[10][20][NL] LANE_ALIGN;
            tls_whiten_lanes(Ga, fa, A->diag_a, wlo[0], W, 0);
            tls_whiten_lanes(Gb, fb, A->diag_b, wlo[1], W, 10);
            /* S = W W^T, lower triangle, as a sum of outer products of W's columns (each entry
             * summed in column order; the rows of column m that can be non-zero: rows[h][m]) */
            double S[10][10][NL] LANE_ALIGN;
            memset(S, 0, sizeof S);
            for (int h = 0; h < 2; ++h)
                for (int m = 0; m < 10; ++m) {
                    const int *r = rows[h][m], nr = nrows[h][m], col = 10 * h + m;
                    if (nr == 3 && r[2] == 2) {  /* rows 0-2, 0-5, 0-8 (the diagonal factors' columns) */
                        s_outer_leading(S, W, col, 3);
                    } else if (nr == 6 && r[5] == 5) {
                        s_outer_leading(S, W, col, 6);
                    } else if (nr == 9 && r[8] == 8) {
                        s_outer_leading(S, W, col, 9);
                    } else {
                        for (int p = 0; p < nr; ++p)
                            for (int q = 0; q <= p; ++q)
                                LANES S[r[p]][r[q]][l] += W[r[p]][col][l] * W[r[q]][col][l];
                    }
                }
            /* S = L L^T and Li = L^-1 (_small_linalg.cholesky_t / tril_inverse_t): info = the
             * first failing pivot (<= 0 or NaN), 1-based, 0 if none; non-finite from there on.
             * The inner sums run over all rows at once (independent chains). */
            double L[10][10][NL] LANE_ALIGN, Li[10][10][NL] LANE_ALIGN;
            int32_t info[NL] = {0};
            for (int j = 0; j < 10; ++j) {
                double acc[10][NL] LANE_ALIGN, rs[NL] LANE_ALIGN;
                for (int i = j; i < 10; ++i) LANES acc[i][l] = 0;
                for (int m = 0; m < j; ++m)
                    for (int i = j; i < 10; ++i) LANES acc[i][l] += L[i][m][l] * L[j][m][l];
                for (int i = j; i < 10; ++i) LANES L[i][j][l] = S[i][j][l] - acc[i][l];
                for (int l = 0; l < NL; ++l)
                    if (info[l] == 0 && !(L[j][j][l] > 0)) info[l] = j + 1;
                LANES rs[l] = 1.0 / sqrt(L[j][j][l]);
                for (int i = j; i < 10; ++i) LANES L[i][j][l] *= rs[l];
            }
            for (int i = 0; i < 10; ++i) {
                double acc[10][NL] LANE_ALIGN, di[NL] LANE_ALIGN;
                LANES di[l] = 1.0 / L[i][i][l];
                LANES Li[i][i][l] = di[l];
                for (int j = 0; j < i; ++j) LANES acc[j][l] = 0;
                for (int m = 0; m < i; ++m)
                    for (int j = 0; j <= m; ++j) LANES acc[j][l] += L[i][m][l] * Li[m][j][l];
                for (int j = 0; j < i; ++j) LANES Li[i][j][l] = acc[j][l] * -di[l];
            }
            /* rows [Li, n Li a, Li w], packed into R; W packed */
            double (*Rp)[NL] = (double (*)[NL])(A->R + 75 * NL * (k * NB + b));
            double (*Wp)[NL] = (double (*)[NL])(A->W + (int64_t)nw * NL * (k * NB + b));
            double la[10][NL] LANE_ALIGN, lw[10][NL] LANE_ALIGN;
            memset(la, 0, sizeof la);
            memset(lw, 0, sizeof lw);
            for (int j = 0; j < 10; ++j)
                for (int i = j; i < 10; ++i) {
                    LANES la[i][l] += Li[i][j][l] * a[j];
                    LANES lw[i][l] += Li[i][j][l] * c[j][l];
                }
            double Rl[75][NL] LANE_ALIGN;
            for (int i = 0, p = 0; i < 10; ++i) {
                for (int j = 0; j <= i; ++j, ++p) LANES Rl[p][l] = Li[i][j][l];
                LANES Rl[55 + i][l] = na[l] * la[i][l];
                LANES Rl[65 + i][l] = lw[i][l];
            }
            for (int p = 0; p < 75; ++p) lane_stream(Rp[p], Rl[p]);
            for (int h = 0; h < 2; ++h)
                for (int i = 0; i < 10; ++i)
                    for (int j = wlo[h][i], p = woff[h][i]; j < TLS_HI[i]; ++j, ++p) lane_stream(Wp[p], W[i][10 * h + j]);
            for (int l = 0; l < nl; ++l) A->info[k * N1 + n0 + l] = info[l];
            /* G += rows^T rows (upper triangle; row r of Li is zero beyond column r), the
             * repeated lanes zeroed */
            for (int r = 0, p0 = 0; r < 10; p0 += ++r) {
                double ra[NL] LANE_ALIGN, rw[NL] LANE_ALIGN;
                LANES ra[l] = l < nl ? Rl[55 + r][l] : 0.0;
                LANES rw[l] = l < nl ? Rl[65 + r][l] : 0.0;
                for (int i = 0; i <= r; ++i) {
                    double ri[NL] LANE_ALIGN;
                    LANES ri[l] = l < nl ? Rl[p0 + i][l] : 0.0;
                    for (int j = i; j <= r; ++j) LANES G[i][j][l] += ri[l] * Rl[p0 + j][l];
                    LANES G[i][10][l] += ri[l] * ra[l];
                    LANES G[i][11][l] += ri[l] * rw[l];
                }
                LANES G[10][10][l] += ra[l] * ra[l];
                LANES G[10][11][l] += ra[l] * rw[l];
                LANES G[11][11][l] += rw[l] * rw[l];
            }
        }
        double *Gk = A->G + 144 * k;
        for (int i = 0; i < 12; ++i)
            for (int j = i; j < 12; ++j) {
                double acc = 0;
                for (int l = 0; l < NL; ++l) acc += G[i][j][l];
                Gk[12 * i + j] = acc;
                Gk[12 * j + i] = acc;
            }
    }
    LANE_STREAM_FENCE();  /* the streamed state, visible before the threads join */
}

/* The residual update of post_step: e = -[Ra (W_a^T y), Rb (W_b^T y)] with y = Li^T (R [dx, 1])
 * for each condition, from the packed R and W of tls_range; dx (K, 11). */
typedef struct {
    const double *R, *W, *dx, *fa, *fb;
    int64_t fa_k, fa_n, fb_k, fb_n;
    int diag_a, diag_b;
    double *e;  /* (K, N1, 20) */
    const uint8_t *active;  /* (K): 0 skips the trial (e 0); NULL: all */
    int64_t N1;
} tls_step_args_t;

WIDE_LOOPS static void tls_step_range(void **pa, int64_t lo, int64_t hi) {
    const tls_step_args_t *A = (const tls_step_args_t *)pa;
    const int64_t N1 = A->N1, NB = (N1 + NL - 1) / NL;
    int wlo[2][10], woff[2][10];
    const int nw = tls_w_layout(A->diag_a, A->diag_b, wlo, woff);
    for (int64_t k = lo; k < hi; ++k) {
        if (A->active && !A->active[k]) {
            memset(A->e + 20 * k * N1, 0, 20 * N1 * sizeof(double));
            continue;
        }
        const double *d = A->dx + 11 * k;
        for (int64_t b = 0; b < NB; ++b) {
            const int64_t n0 = b * NL;
            const int nl = N1 - n0 < NL ? (int)(N1 - n0) : NL;
            const double (*Rp)[NL] = (const double (*)[NL])(A->R + 75 * NL * (k * NB + b));
            const double (*Wp)[NL] = (const double (*)[NL])(A->W + (int64_t)nw * NL * (k * NB + b));
            double z[10][NL] LANE_ALIGN, y[10][NL] LANE_ALIGN, u[20][NL] LANE_ALIGN;
#if defined(__GNUC__)
            for (int p = 0; p < 75 * NL; p += 8) __builtin_prefetch((const double *)Rp + 75 * NL + p);
            for (int p = 0; p < nw * NL; p += 8) __builtin_prefetch((const double *)Wp + nw * NL + p);
#endif
            for (int r = 0, p0 = 0; r < 10; p0 += ++r) {  /* z = R [dx, 1] */
                double acc[NL] LANE_ALIGN = {0};
                for (int j = 0; j <= r; ++j) LANES acc[l] += Rp[p0 + j][l] * d[j];
                LANES z[r][l] = (acc[l] + Rp[55 + r][l] * d[10]) + Rp[65 + r][l];
            }
            for (int j = 0; j < 10; ++j) LANES y[j][l] = 0;  /* y = Li^T z */
            for (int r = 0, p0 = 0; r < 10; p0 += ++r)
                for (int j = 0; j <= r; ++j) LANES y[j][l] += Rp[p0 + j][l] * z[r][l];
            for (int m = 0; m < 20; ++m) LANES u[m][l] = 0;  /* u = W^T y */
            for (int i = 0; i < 10; ++i)
                for (int h = 0; h < 2; ++h)
                    for (int j = wlo[h][i], p = woff[h][i]; j < TLS_HI[i]; ++j, ++p)
                        LANES u[10 * h + j][l] += Wp[p][l] * y[i][l];
            for (int l = 0; l < nl; ++l) {  /* e = -[Ra u_a, Rb u_b] */
                const int64_t n = n0 + l;
                double *e = A->e + 20 * (k * N1 + n);
                for (int h = 0; h < 2; ++h) {
                    const double *R = h ? A->fb + k * A->fb_k + n * A->fb_n : A->fa + k * A->fa_k + n * A->fa_n;
                    const int diag = h ? A->diag_b : A->diag_a;
                    for (int i = 0; i < 10; ++i) {
                        double acc;
                        if (diag) {
                            acc = u[10 * h + i][l] * R[i];
                        } else {
                            acc = 0;
                            for (int j = 0; j < 10; ++j) acc += R[10 * i + j] * u[10 * h + j][l];
                        }
                        e[10 * h + i] = -acc;
                    }
                }
            }
        }
    }
}
