/* Galilean IMU preintegration of one window at a time (included once by imu/_native.c, after
 * the float64 SGal(3) kernels of functional/_native_sgal3.h, whose exp coefficients it uses).
 *
 * The arithmetic of torchsgal/imu/preintegration.py and _fast_path.py (_integrate /
 * _integrate_fast) in a loop over the samples of a window, run backwards so that nothing but
 * the current suffix product is kept:
 *
 *   H_k = exp((1/2) [0, (f_k - b_a) dt_k, (omega_k - b_g) dt_k, dt_k])   (F.exp_parts, rho = 0)
 *   mid_k = H_k S_{k+1},  S_k = H_k mid_k = E_k S_{k+1},  S_K = I,  delta = S_0,
 *
 * and the Simpson node sums of _node_moments over the nodes X^-1 for X = S_k (weights
 * (dt_k + dt_{k-1}) / 6, dt_{-1} = 0) and X = mid_k (weights 4 dt_k / 6), with the identity node
 * (weight dt_{K-1} / 6).  Increment only: E_k = exp(full tangent), S_k = E_k S_{k+1}.
 *
 * Everything is computed in double, for float32 input too (the sequential product of a window
 * would otherwise drift by K float32 roundings).  The torch code is the oracle:
 * tests/test_imu_kernels.py compares the two.  Packed layout as F.pack: C row-major (9), v, r, tau.
 */

/* The 117 node sums per window, in this order (imu/_kernels.py reads them by these offsets). */
#define IMU_W 0        /* sum w (with the identity node) */
#define IMU_WT 1       /* sum w th */
#define IMU_WTT 2      /* sum w th^2 */
#define IMU_WL 3       /* sum w lh (3) */
#define IMU_WV 6       /* sum w vh (3) */
#define IMU_OUTER 9    /* sum w [lh; vh][lh; vh]^T (6 x 6) */
#define IMU_Y 45       /* sum coef_a C^T, coef = [w, w th, w lh, w vh] (8 x 3 x 3) */
#define IMU_MOMENTS 117

typedef struct {
    double C[9], v[3], r[3], tau;
} imu_frame_t;

/* exp of [0, nu, phi, iota] (F.exp_parts with rho None). */
static inline void imu_exp(const double *nu, const double *phi, double iota, imu_frame_t *o) {
    double c[7], pn[3], ppn[3];
    coefficients_f64(dot_f64(phi, phi), 4, c);
    cross_f64(phi, nu, pn);
    cross_f64(phi, pn, ppn);
    for (int i = 0; i < 3; ++i) {
        o->v[i] = nu[i] + c[2] * pn[i] + c[3] * ppn[i];
        o->r[i] = iota * (0.5 * nu[i] + c[3] * pn[i] + c[4] * ppn[i]);
    }
    sym_skew_f64(c[0], c[1], c[2], phi, o->C);  /* Gamma_0(phi) */
    o->tau = iota;
}

/* o = P1 P2 (F.compose_packed): (C1 C2, C1 v2 + v1, C1 r2 + tau2 v1 + r1, tau1 + tau2). */
static inline void imu_compose(const imu_frame_t *P1, const imu_frame_t *P2, imu_frame_t *o) {
    const double *C1 = P1->C, *C2 = P2->C;
    for (int i = 0; i < 3; ++i) {
        const double *row = C1 + 3 * i;
        for (int j = 0; j < 3; ++j) o->C[3 * i + j] = row[0] * C2[j] + row[1] * C2[3 + j] + row[2] * C2[6 + j];
        o->v[i] = (row[0] * P2->v[0] + row[1] * P2->v[1] + row[2] * P2->v[2]) + P1->v[i];
        o->r[i] = (row[0] * P2->r[0] + row[1] * P2->r[1] + row[2] * P2->r[2]) + P1->r[i] + P2->tau * P1->v[i];
    }
    o->tau = P1->tau + P2->tau;
}

/* Add the node X^-1 of weight w to the sums m (_node_moments: vh = -C^T v, lh = -C^T r, th = -tau). */
static inline void imu_accumulate(const imu_frame_t *X, double w, double *m) {
    const double *C = X->C;
    double lv[6], coef[8];
    for (int i = 0; i < 3; ++i) {
        lv[i] = -(C[i] * X->r[0] + C[3 + i] * X->r[1] + C[6 + i] * X->r[2]);
        lv[3 + i] = -(C[i] * X->v[0] + C[3 + i] * X->v[1] + C[6 + i] * X->v[2]);
    }
    double th = -X->tau, wt = w * th;
    m[IMU_W] += w;
    m[IMU_WT] += wt;
    m[IMU_WTT] += wt * th;
    coef[0] = w;
    coef[1] = wt;
    for (int i = 0; i < 6; ++i) coef[2 + i] = w * lv[i];
    for (int i = 0; i < 3; ++i) {
        m[IMU_WL + i] += coef[2 + i];
        m[IMU_WV + i] += coef[5 + i];
    }
    for (int i = 0; i < 6; ++i)  /* upper triangle; mirrored at the end */
        for (int j = i; j < 6; ++j) m[IMU_OUTER + 6 * i + j] += coef[2 + i] * lv[j];
    for (int a = 0; a < 8; ++a) {  /* sums of coef_a C, transposed at the end of the window */
        double *Y = m + IMU_Y + 9 * a;
        for (int i = 0; i < 9; ++i) Y[i] += coef[a] * C[i];
    }
}

/* Arguments of one call; TIN is the input and output type (float or double). */
typedef struct {
    const void *gyro, *acc, *dt, *b_g, *b_a;  /* (n, K, 3), (n, K, 3), (n, K), (n, 3), (n, 3) */
    void *delta, *moments;                    /* (n, 5, 5), (n, 117) or NULL (increment only) */
    int64_t K;
} imu_args_t;

#define IMU_RANGE(SFX, TIN)                                                                       \
    WIDE_LOOPS static void imu_range_##SFX(void **pa, int64_t lo, int64_t hi) {                   \
        const imu_args_t *A = (const imu_args_t *)pa;                                             \
        const TIN *gyro = A->gyro, *acc = A->acc, *dt = A->dt, *bg = A->b_g, *ba = A->b_a;        \
        TIN *delta = A->delta, *mom = A->moments;                                                 \
        const int64_t K = A->K;                                                                   \
        const int nodes = mom != NULL;                                                            \
        const double scale = nodes ? 0.5 : 1.0;                                                   \
        for (int64_t w = lo; w < hi; ++w) {                                                       \
            const TIN *g = gyro + 3 * K * w, *f = acc + 3 * K * w, *h = dt + K * w;               \
            double b_g[3] = {bg[3 * w], bg[3 * w + 1], bg[3 * w + 2]};                             \
            double b_a[3] = {ba[3 * w], ba[3 * w + 1], ba[3 * w + 2]};                             \
            double m[IMU_MOMENTS] = {0};                                                          \
            imu_frame_t S = {{1, 0, 0, 0, 1, 0, 0, 0, 1}, {0, 0, 0}, {0, 0, 0}, 0}, H, X;         \
            for (int64_t k = K - 1; k >= 0; --k) {                                                \
                double hk = (double)h[k], half = (double)h[k] * scale, nu[3], phi[3];              \
                for (int i = 0; i < 3; ++i) {                                                     \
                    nu[i] = ((double)f[3 * k + i] - b_a[i]) * half;                                \
                    phi[i] = ((double)g[3 * k + i] - b_g[i]) * half;                               \
                }                                                                                 \
                imu_exp(nu, phi, half, &H);                                                       \
                if (!nodes) {                                                                     \
                    imu_compose(&H, &S, &X);                                                      \
                    S = X;                                                                        \
                    continue;                                                                     \
                }                                                                                 \
                imu_compose(&H, &S, &X); /* mid_k = H_k S_{k+1} */                                \
                imu_accumulate(&X, 4.0 * hk / 6.0, m);                                            \
                imu_compose(&H, &X, &S); /* S_k = H_k mid_k */                                    \
                imu_accumulate(&S, (hk + (k > 0 ? (double)h[k - 1] : 0.0)) / 6.0, m);             \
            }                                                                                     \
            TIN *o = delta + 25 * w;                                                              \
            for (int i = 0; i < 3; ++i) {                                                         \
                for (int j = 0; j < 3; ++j) o[5 * i + j] = (TIN)S.C[3 * i + j];                   \
                o[5 * i + 3] = (TIN)S.v[i];                                                       \
                o[5 * i + 4] = (TIN)S.r[i];                                                       \
            }                                                                                     \
            o[15] = 0; o[16] = 0; o[17] = 0; o[18] = 1; o[19] = (TIN)S.tau;                       \
            o[20] = 0; o[21] = 0; o[22] = 0; o[23] = 0; o[24] = 1;                                \
            if (!nodes) continue;                                                                 \
            double w_id = (double)h[K - 1] / 6.0; /* the identity node: C = I, the rest zero */   \
            m[IMU_W] += w_id;                                                                     \
            m[IMU_Y] += w_id; m[IMU_Y + 4] += w_id; m[IMU_Y + 8] += w_id;                         \
            for (int i = 0; i < 6; ++i)                                                           \
                for (int j = 0; j < i; ++j) m[IMU_OUTER + 6 * i + j] = m[IMU_OUTER + 6 * j + i];  \
            for (int a = 0; a < 8; ++a) /* sum coef_a C -> sum coef_a C^T */                      \
                for (int i = 0; i < 3; ++i)                                                       \
                    for (int j = 0; j < i; ++j) {                                                 \
                        double *Y = m + IMU_Y + 9 * a, t = Y[3 * i + j];                          \
                        Y[3 * i + j] = Y[3 * j + i];                                              \
                        Y[3 * j + i] = t;                                                         \
                    }                                                                             \
            TIN *mo = mom + IMU_MOMENTS * w;                                                      \
            for (int i = 0; i < IMU_MOMENTS; ++i) mo[i] = (TIN)m[i];                              \
        }                                                                                         \
    }

IMU_RANGE(f64, double)
IMU_RANGE(f32, float)
#undef IMU_RANGE
