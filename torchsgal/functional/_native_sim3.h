/* Sim(3) exp, log, J_l, J_l^-1, inverse and adjoint for one scalar type T (included per dtype by
 * functional/_native.c after _native_sgal3.h, whose series K(coefficients), rotation log and
 * 3-vector helpers it uses; T, SFX, SIN, SQRT, EXP, EXPM1, LOG and FABS are defined by the
 * includer and undefined at the end).
 *
 * sim3.py (Barfoot, "Integral Forms", Sec. 4.4, (78)-(80), (90)), tangent (7) = [rho, phi, lambda],
 * matrices (4, 4) row-major [[C, r], [0, 1/s]], s = e^lambda:
 *   exp = [[C(phi), M(phi, lambda) rho], [0, e^-lambda]],  M = m0 I + m1 phi^ + m2 phi^ phi^ (90),
 * the m_k from numerics.sim3_coefficients (without derivatives, not normalised): the scale
 * moments q_j (numerics.scale_moments, each order from the stable one of its two recursions),
 * below theta = 1 the theta^2 series with the moments as coefficients, above it the closed
 * forms in w = lambda + i theta.  Term by term the arithmetic of the tensor code, so the two
 * agree to rounding (tests/test_native_subgroups.py); the moments run SIM3_LANES elements at a
 * time, lane by lane the scalar recursion (the lanes only let its divisions vectorise). */
#define K_(name, sfx) name##_##sfx
#define K__(name, sfx) K_(name, sfx)
#define K(name) K__(name, SFX)

#ifndef SIM3_LANES
#define SIM3_LANES 8
#endif

/* numerics.scale_moments(x, order, em1) for SIM3_LANES values: q[j][w] = q_j(x[w]), j = 0..order.
 * Downward on s_j = j! q_j from s_(top + SCALE_TAYLOR_TERMS + 1) = 0 where |x| <= order + margin
 * (else x = 0 there, unused), upward from expm1(x)/x where |x| > margin (else x = 1, unused);
 * order j takes the upward value where |x| > j + margin.  With sigma (1, or e^-x where the
 * caller normalises): sigma q_j, where em1 is sigma expm1(x) (the upward recursion alone). */
WIDE_LOOPS static void K(scale_moments_lanes)(const T *x, const T *em1, const T *sigma, int order,
                                               T q[][SIM3_LANES]) {
    const T margin = (T)SCALE_UPWARD_MARGIN;
    T ax[SIM3_LANES], xd[SIM3_LANES], xu[SIM3_LANES], s[SIM3_LANES], up[SIM3_LANES];
    for (int w = 0; w < SIM3_LANES; ++w) {
        ax[w] = FABS(x[w]);
        xd[w] = ax[w] <= (T)order + margin ? x[w] : (T)0;
        xu[w] = ax[w] > margin ? x[w] : (T)1;
        s[w] = 0;
    }
    int top = order + SCALE_EXTRA_ORDERS;
    for (int j = top + SCALE_TAYLOR_TERMS + 1; j > order; --j)
        for (int w = 0; w < SIM3_LANES; ++w) s[w] = ((T)1 + xd[w] * s[w]) / (T)j;
    for (int w = 0; w < SIM3_LANES; ++w) q[order][w] = s[w] * (T)INV_FACT_LONG[order];
    for (int j = order; j > 0; --j) {
        for (int w = 0; w < SIM3_LANES; ++w) s[w] = ((T)1 + xd[w] * s[w]) / (T)j;
        if (j == 1)
            for (int w = 0; w < SIM3_LANES; ++w) q[0][w] = s[w];
        else
            for (int w = 0; w < SIM3_LANES; ++w) q[j - 1][w] = s[w] * (T)INV_FACT_LONG[j - 1];
    }
    for (int w = 0; w < SIM3_LANES; ++w) {
        up[w] = em1[w] / xu[w];
        if (ax[w] > margin) q[0][w] = up[w];
    }
    for (int j = 1; j <= order; ++j)
        for (int w = 0; w < SIM3_LANES; ++w) {
            up[w] = (up[w] - (T)INV_FACT_LONG[j] * sigma[w]) / xu[w];
            if (ax[w] > (T)j + margin) q[j][w] = up[w];
        }
}

/* The coefficients of numerics.sim3_coefficients at theta^2 = t2, lambda = lam, from the
 * moments q[j] (this element's lane, stride SIM3_LANES): m[0..3] = m0, m1, m2, m_re, and with
 * derivatives m[4..8] = p0, e1, e2, p1, p2.  sg is sigma (1 unless normalised), em1 sigma expm1(-lam). */
static inline void K(sim3_m)(T t2, T lam, T em1, T sg, int normalised, int derivatives, const T *q, T *m) {
    const int terms = SIM3_SERIES_TERMS;
#define Q(j) q[SIM3_LANES * (j)]
    T m0 = Q(0);
    m[0] = m0;
    if (derivatives) m[4] = Q(1) - Q(0);
    if (t2 < (T)(SIM3_SERIES_THRESHOLD * SIM3_SERIES_THRESHOLD)) {
        T u = -t2;
        T a1 = Q(2 * (terms - 1) + 1), a2 = Q(2 * (terms - 1) + 2);
        for (int k = terms - 2; k >= 0; --k) {
            a1 = a1 * u + Q(2 * k + 1);
            a2 = a2 * u + Q(2 * k + 2);
        }
        m[1] = a1;
        m[2] = a2;
        m[3] = m0 + u * a2;
        if (!derivatives) return;
        int k = terms - 1;
        T e1 = (T)(2 * (k + 1)) * Q(2 * k + 3), e2 = (T)(2 * (k + 1)) * Q(2 * k + 4);
        T p1 = Q(2 * k + 1) - (T)(2 * k + 2) * Q(2 * k + 2), p2 = Q(2 * k + 2) - (T)(2 * k + 3) * Q(2 * k + 3);
        for (k = terms - 2; k >= 0; --k) {
            e1 = e1 * u + (T)(2 * (k + 1)) * Q(2 * k + 3);
            e2 = e2 * u + (T)(2 * (k + 1)) * Q(2 * k + 4);
            p1 = p1 * u + (Q(2 * k + 1) - (T)(2 * k + 2) * Q(2 * k + 2));
            p2 = p2 * u + (Q(2 * k + 2) - (T)(2 * k + 3) * Q(2 * k + 3));
        }
        m[5] = -e1; m[6] = -e2; m[7] = -p1; m[8] = -p2;
        return;
    }
#undef Q
    T t = SQRT(t2), sn = SIN(t), hs = SIN((T)0.5 * t), h2 = hs * hs;
    if (normalised) {
        sn = sg * sn;
        h2 = sg * h2;
    }
    T w2 = lam * lam + t2, lw = lam / w2, tw = t / w2;
    T na = em1 + (T)2 * h2;
    T k_re = sn * tw - na * lw, k_im = sn * lw + na * tw;
    T l_m1 = k_im / t, l_m2 = (m0 - k_re) / t2;
    m[1] = l_m1;
    m[2] = l_m2;
    m[3] = k_re;
    if (!derivatives) return;
    T cs = normalised ? sg - (T)2 * h2 : (T)1 - (T)2 * h2;
    T b_re = cs - k_re, b_im = sn - k_im;
    T k1_re = b_re * lw + b_im * tw, k1_im = b_im * lw - b_re * tw;
    m[5] = (k1_re - l_m1) / t2;
    m[6] = (k1_im / t - (T)2 * l_m2) / t2;
    m[7] = (k1_im - k_im) / t;
    m[8] = (m[4] + k_re - k1_re) / t2;
}

/* The coefficients of SIM3_LANES elements at once (numerics.sim3_coefficients): x = -lambda,
 * em1 = expm1(x) per lane, the moments to order 2 SIM3_SERIES_TERMS (+ 2 with derivatives),
 * then m (9 per lane).  With ``normalise``, below lambda = -SIM3_NORMALISE every coefficient
 * is e^lambda times its value and shift[w] = lambda there (else 0); the Jacobians take them so. */
static void K(sim3_m_lanes)(const T *t2, const T *lam, int derivatives, int normalise, T m[][9], T *shift) {
    T x[SIM3_LANES], em1[SIM3_LANES], sg[SIM3_LANES], q[MAX_MOMENT_ORDER + 1][SIM3_LANES];
    int nm[SIM3_LANES];
    for (int w = 0; w < SIM3_LANES; ++w) {
        x[w] = -lam[w];
        nm[w] = normalise && x[w] > (T)SIM3_NORMALISE;
        if (normalise) shift[w] = lam[w] * (T)nm[w];
        sg[w] = nm[w] ? EXP(shift[w]) : (T)1;
        em1[w] = nm[w] ? -EXPM1(-x[w]) : EXPM1(x[w]);
    }
    K(scale_moments_lanes)(x, em1, sg, 2 * SIM3_SERIES_TERMS + (derivatives ? 2 : 0), q);
    for (int w = 0; w < SIM3_LANES; ++w)
        K(sim3_m)(t2[w], lam[w], em1[w], sg[w], normalise, derivatives, &q[0][w], m[w]);
}

/* (n0, n1, n2) with (m0 I + m1 phi^ + m2 phi^ phi^)^-1 = n0 I + n1 phi^ + n2 phi^ phi^, from
 * m = (m0, m1, m2, m_re) and theta^2 = t2 (blocks.poly_inverse). */
static inline void K(poly_inverse)(const T *m, T t2, T *n) {
    T n0 = (T)1 / m[0], b = m[1] * n0, c = m[2] * n0, re = m[3] * n0;
    T scale = n0 / (re * re + b * b * t2);
    n[0] = n0;
    n[1] = -b * scale;
    n[2] = (b * b - c * re) * scale;
}

/* exp: [[Gamma_0(phi), M rho], [0, e^-lambda]] (sim3.exp_impl), given m. */
static void K(sim3_exp_finish)(const T *x, const T *m, T *o) {
    const T *rho = x, *phi = x + 3;
    T c[7], C[9], r[3];
    K(coefficients)(K(dot)(phi, phi), 4, c);
    K(sym_skew)(c[0], c[1], c[2], phi, C);
    K(poly)(phi, rho, m[0], m[1], m[2], r);
    for (int i = 0; i < 3; ++i) {
        for (int j = 0; j < 3; ++j) o[4 * i + j] = C[3 * i + j];
        o[4 * i + 3] = r[i];
    }
    o[12] = 0; o[13] = 0; o[14] = 0; o[15] = EXP(-x[6]);
}

/* log: phi = log(C), lambda = -log M[3, 3], rho = M(phi, lambda)^-1 r with the inverse's
 * coefficients of blocks.poly_inverse (sim3.log_impl), given m. */
static void K(sim3_log_finish)(const T *M, const T *phi, T t2, const T *m, T *x) {
    T r[3] = {M[3], M[7], M[11]}, n[3];
    K(poly_inverse)(m, t2, n);
    K(poly)(phi, r, n[0], n[1], n[2], x);
    for (int i = 0; i < 3; ++i) x[3 + i] = phi[i];
}

static void K(sim3_exp_range)(void **a, int64_t lo, int64_t hi) {
    const T *in = a[0];
    T *out = a[1];
    for (int64_t i = lo; i < hi; i += SIM3_LANES) {
        int n = hi - i < SIM3_LANES ? (int)(hi - i) : SIM3_LANES;
        T t2[SIM3_LANES] = {0}, lam[SIM3_LANES] = {0}, m[SIM3_LANES][9];
        for (int w = 0; w < n; ++w) {
            const T *phi = in + 7 * (i + w) + 3;
            t2[w] = K(dot)(phi, phi);
            lam[w] = phi[3];
        }
        K(sim3_m_lanes)(t2, lam, 0, 0, m, NULL);
        for (int w = 0; w < n; ++w) K(sim3_exp_finish)(in + 7 * (i + w), m[w], out + 16 * (i + w));
    }
}

static void K(sim3_log_range)(void **a, int64_t lo, int64_t hi) {
    const T *in = a[0];
    T *out = a[1];
    for (int64_t i = lo; i < hi; i += SIM3_LANES) {
        int n = hi - i < SIM3_LANES ? (int)(hi - i) : SIM3_LANES;
        T t2[SIM3_LANES] = {0}, lam[SIM3_LANES] = {0}, phi[SIM3_LANES][3], m[SIM3_LANES][9];
        for (int w = 0; w < n; ++w) {
            const T *M = in + 16 * (i + w);
            K(rotation_log)(M, 4, phi[w]);
            t2[w] = K(dot)(phi[w], phi[w]);
            lam[w] = -LOG(M[15]);
        }
        K(sim3_m_lanes)(t2, lam, 0, 0, m, NULL);
        for (int w = 0; w < n; ++w) {
            T *x = out + 7 * (i + w);
            K(sim3_log_finish)(in + 16 * (i + w), phi[w], t2[w], m[w], x);
            x[6] = lam[w];
        }
    }
}

/* J_l = [[s M, s coupling, s lam_col], [0, Gamma_1, 0], [0, 0, 1]] and
 * J_l^-1 = [[M^-1 / s, -M^-1 coupling Gamma_1^-1, -M^-1 lam_col], [0, Gamma_1^-1, 0], [0, 0, 1]]
 * with coupling = d(M rho)/dphi + (M rho)^ Gamma_1 and lam_col = dM/dlambda rho (sim3.jl_impl,
 * jl_inv_impl, sim3._jl_parts), m normalised (s = e^(lambda - shift)). */
static void K(sim3_jl_finish)(const T *x, const T *m, T shift, int inverse, T *o) {
    const T *rho = x, *phi = x + 3;
    T lam = x[6], c[7], G1[9], r[3], D[9], S[9], coupling[9], lam_col[3];
    T t2 = K(dot)(phi, phi);
    K(coefficients)(t2, 4, c);
    K(sym_skew)(c[1], c[2], c[3], phi, G1);
    K(poly)(phi, rho, m[0], m[1], m[2], r);
    K(poly_vec_derivative)(m[1], m[2], m[5], m[6], phi, rho, D);
    K(skew_times)(r, G1, S);
    for (int i = 0; i < 9; ++i) coupling[i] = D[i] + S[i];
    K(poly)(phi, rho, m[4], m[7], m[8], lam_col);
    for (int i = 0; i < 49; ++i) o[i] = 0;
    o[48] = 1;
    if (!inverse) {
        T s = EXP(lam - shift), Mm[9];
        K(sym_skew)(m[0] - t2 * m[2], m[1], m[2], phi, Mm);
        for (int i = 0; i < 9; ++i) { Mm[i] = s * Mm[i]; coupling[i] = s * coupling[i]; }
        K(put3)(o, 7, 0, 0, Mm);
        K(put3)(o, 7, 0, 1, coupling);
        K(put3)(o, 7, 1, 1, G1);
        for (int i = 0; i < 3; ++i) o[7 * i + 6] = s * lam_col[i];
        return;
    }
    T inv_s = EXP(-(lam - shift)), Mi[9], G1i[9], t[9], R[9], y[3], n[3];
    K(poly_inverse)(m, t2, n);
    K(sym_skew)(n[0] - t2 * n[2], n[1], n[2], phi, Mi);
    K(jac_inv_mat)(phi, G1i);
    K(mat3_mul)(Mi, coupling, t);
    K(mat3_mul)(t, G1i, R);
    K(poly)(phi, lam_col, n[0], n[1], n[2], y);
    for (int i = 0; i < 9; ++i) { R[i] = -R[i]; t[i] = Mi[i] * inv_s; }
    K(put3)(o, 7, 0, 0, t);
    K(put3)(o, 7, 0, 1, R);
    K(put3)(o, 7, 1, 1, G1i);
    for (int i = 0; i < 3; ++i) o[7 * i + 6] = -y[i];
}

static void K(sim3_jacobian_range)(const T *in, T *out, int64_t lo, int64_t hi, int inverse) {
    for (int64_t i = lo; i < hi; i += SIM3_LANES) {
        int n = hi - i < SIM3_LANES ? (int)(hi - i) : SIM3_LANES;
        T t2[SIM3_LANES] = {0}, lam[SIM3_LANES] = {0}, m[SIM3_LANES][9], shift[SIM3_LANES];
        for (int w = 0; w < n; ++w) {
            const T *phi = in + 7 * (i + w) + 3;
            t2[w] = K(dot)(phi, phi);
            lam[w] = phi[3];
        }
        K(sim3_m_lanes)(t2, lam, 1, 1, m, shift);
        for (int w = 0; w < n; ++w) K(sim3_jl_finish)(in + 7 * (i + w), m[w], shift[w], inverse, out + 49 * (i + w));
    }
}

static void K(sim3_jl_range)(void **a, int64_t lo, int64_t hi) { K(sim3_jacobian_range)(a[0], a[1], lo, hi, 0); }

static void K(sim3_jl_inv_range)(void **a, int64_t lo, int64_t hi) { K(sim3_jacobian_range)(a[0], a[1], lo, hi, 1); }

/* inverse: [[C^T, -s C^T r], [0, s]], s = 1/M[3, 3] (sim3.inverse). */
static void K(sim3_inverse_one)(const T *M, T *o) {
    T s = (T)1 / M[15];
    for (int i = 0; i < 3; ++i) {
        for (int j = 0; j < 3; ++j) o[4 * i + j] = M[4 * j + i];
        o[4 * i + 3] = -s * (M[i] * M[3] + M[4 + i] * M[7] + M[8 + i] * M[11]);
    }
    o[12] = 0; o[13] = 0; o[14] = 0; o[15] = s;
}

/* adjoint: [[s C, s r^ C, -s r], [0, C, 0], [0, 0, 1]] (sim3.adjoint, (80)). */
static void K(sim3_adjoint_one)(const T *M, T *o) {
    T s = (T)1 / M[15], r[3] = {M[3], M[7], M[11]}, C[9], sC[9], S[9];
    for (int i = 0; i < 3; ++i)
        for (int j = 0; j < 3; ++j) {
            C[3 * i + j] = M[4 * i + j];
            sC[3 * i + j] = s * M[4 * i + j];
        }
    K(skew_times)(r, sC, S);
    for (int i = 0; i < 49; ++i) o[i] = 0;
    K(put3)(o, 7, 0, 0, sC);
    K(put3)(o, 7, 0, 1, S);
    K(put3)(o, 7, 1, 1, C);
    for (int i = 0; i < 3; ++i) o[7 * i + 6] = -(s * r[i]);
    o[48] = 1;
}

RANGE(sim3_inverse, sim3_inverse_one, 16, 16)
RANGE(sim3_adjoint, sim3_adjoint_one, 16, 49)

#undef K
#undef K_
#undef K__
#undef T
#undef SFX
#undef SIN
#undef SQRT
#undef EXP
#undef EXPM1
#undef LOG
#undef FABS
