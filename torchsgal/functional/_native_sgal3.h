/* SGal(3) kernels for one scalar type T (included twice by _native.c, for double and float).
 *
 * Line-by-line transcriptions of the torch closed forms in sgal3.py, blocks.py and numerics.py
 * (same thresholds, same series, same order of operations where it matters), one batch element
 * at a time.  The torch code is the oracle: tests/test_native.py compares the two at every
 * angle band.  Equation numbers: Kelly-Giamou (kelly-giamou-uncertainty-sgal3.txt).
 *
 * Tangent (10) = [rho, nu, phi, iota]; matrices (5, 5) row-major [[C, v, r], [0, 1, tau], [0, 0, 1]].
 */

#define K_(name, sfx) name##_##sfx
#define K__(name, sfx) K_(name, sfx)
#define K(name) K__(name, SFX)  /* K(exp) -> exp_f64 / exp_f32 */

static inline void K(cross)(const T *u, const T *v, T *o) {
    o[0] = u[1] * v[2] - u[2] * v[1];
    o[1] = u[2] * v[0] - u[0] * v[2];
    o[2] = u[0] * v[1] - u[1] * v[0];
}

static inline T K(dot)(const T *u, const T *v) { return u[0] * v[0] + u[1] * v[1] + u[2] * v[2]; }

/* numerics.series_coefficients: c_0 .. c_order (order 4 or 6) at theta^2. */
static inline void K(coefficients)(T t2, int order, T *c) {
    if (t2 < (T)(SERIES_THRESHOLD * SERIES_THRESHOLD)) {
        const double *hi = order == 6 ? TAYLOR_C6 : TAYLOR_C4, *lo = order == 6 ? TAYLOR_C5 : TAYLOR_C3;
        T a_lo = (T)lo[TAYLOR_TERMS - 1], a_hi = (T)hi[TAYLOR_TERMS - 1];
        for (int k = TAYLOR_TERMS - 2; k >= 0; --k) {
            a_lo = (T)lo[k] + a_lo * t2;
            a_hi = (T)hi[k] + a_hi * t2;
        }
        c[order - 1] = a_lo;
        c[order] = a_hi;
        for (int m = order - 2; m >= 0; --m) c[m] = (T)INV_FACT[m] - t2 * c[m + 2];
    } else {
        T theta = SQRT(t2), inv_t2 = (T)1 / t2, half = (T)0.5 * theta;
        T hs = SIN(half), hc = COS(half);
        T two_hs2 = (T)2 * hs * hs;
        c[0] = (T)1 - two_hs2;
        c[1] = (T)2 * hs * hc / theta;
        c[2] = two_hs2 * inv_t2;
        for (int m = 3; m <= order; ++m) c[m] = ((T)INV_FACT[m - 2] - c[m - 2]) * inv_t2;
    }
}

/* numerics.jinv_coefficient: (1 - (theta/2) cot(theta/2)) / theta^2. */
static inline T K(jinv_coefficient)(T t2) {
    if (t2 < (T)(JINV_THRESHOLD * JINV_THRESHOLD)) {
        T acc = (T)BERNOULLI[N_BERNOULLI - 1];
        for (int k = N_BERNOULLI - 2; k >= 0; --k) acc = acc * t2 + (T)BERNOULLI[k];
        return acc;
    }
    T theta = SQRT(t2), half = (T)0.5 * theta;
    return (T)1 / t2 - COS(half) / ((T)2 * theta * SIN(half));
}

/* x + a (phi x x) + b phi x (phi x x) (gamma_vec, jac_inv_vec). */
static inline void K(poly)(const T *phi, const T *x, T x_scale, T a, T b, T *o) {
    T p[3], pp[3];
    K(cross)(phi, x, p);
    K(cross)(phi, p, pp);
    for (int i = 0; i < 3; ++i) o[i] = x_scale * x[i] + a * p[i] + b * pp[i];
}

/* blocks.rotation_log: phi = log(C)^vee, accurate near 0 and near pi.  M: row-major n x n,
 * C = M[:3, :3] (n = 5 for SGal(3), 4 for SE(3)). */
static inline void K(rotation_log)(const T *M, int n, T *phi) {
    T c00 = M[0], c01 = M[1], c02 = M[2], c10 = M[n], c11 = M[n + 1], c12 = M[n + 2];
    T c20 = M[2 * n], c21 = M[2 * n + 1], c22 = M[2 * n + 2];
    /* an infinite entry gives NaN, as a NaN one does: x * 0 is NaN for both, 0 otherwise */
    T z = c00 * 0 + c01 * 0 + c02 * 0 + c10 * 0 + c11 * 0 + c12 * 0 + c20 * 0 + c21 * 0 + c22 * 0;
    if (z != z) {
        phi[0] = phi[1] = phi[2] = (T)NAN;
        return;
    }
    T s[3] = {(T)0.5 * (c21 - c12), (T)0.5 * (c02 - c20), (T)0.5 * (c10 - c01)};
    T cs = (T)0.5 * (c00 + c11 + c22 - (T)1);
    T ss = K(dot)(s, s);
    T sn = ss > 0 ? SQRT(ss) : (T)0;
    T theta = ATAN2(sn, cs);
    if (cs < (T)LOG_SYMMETRIC_COS) {
        T d0 = c00 - cs, d1 = c11 - cs, d2 = c22 - cs;
        T s01 = (T)0.5 * (c01 + c10), s02 = (T)0.5 * (c02 + c20), s12 = (T)0.5 * (c12 + c21);
        T col[3];
        if (d0 >= d1 && d0 >= d2) { col[0] = d0; col[1] = s01; col[2] = s02; }
        else if (d1 >= d2) { col[0] = s01; col[1] = d1; col[2] = s12; }
        else { col[0] = s02; col[1] = s12; col[2] = d2; }
        T sign = K(dot)(col, s) < 0 ? (T)-1 : (T)1;
        T f = sign * theta / SQRT(K(dot)(col, col));
        for (int i = 0; i < 3; ++i) phi[i] = f * col[i];
        return;
    }
    T ratio;
    if (sn < (T)LOG_SIN_TAYLOR) {
        T t2 = theta * theta;
        ratio = (T)1 + t2 / (T)6 + (T)7 * t2 * t2 / (T)360;
    } else {
        ratio = theta / sn;
    }
    for (int i = 0; i < 3; ++i) phi[i] = ratio * s[i];
}

/* Entries (row-major 3x3) of d I + a phi^ + b phi phi^T (blocks.sym_skew_entries). */
static inline void K(sym_skew)(T d, T a, T b, const T *phi, T *o) {
    T x = phi[0], y = phi[1], z = phi[2], ax = a * x, ay = a * y, az = a * z, bx = b * x, by = b * y;
    T bxy = bx * y, bxz = bx * z, byz = by * z;
    o[0] = d + bx * x; o[1] = bxy - az; o[2] = bxz + ay;
    o[3] = bxy + az; o[4] = d + by * y; o[5] = byz - ax;
    o[6] = bxz - ay; o[7] = byz + ax; o[8] = d + b * z * z;
}

/* exp (3.6): C = Gamma_0(phi), v = Gamma_1 nu, r = Gamma_1 rho + iota Gamma_2 nu, tau = iota. */
static void K(exp_one)(const T *x, T *o) {
    const T *rho = x, *nu = x + 3, *phi = x + 6;
    T iota = x[9], c[7];
    K(coefficients)(K(dot)(phi, phi), 4, c);
    T pn[3], ppn[3], pr[3], ppr[3];
    K(cross)(phi, nu, pn);
    K(cross)(phi, pn, ppn);
    K(cross)(phi, rho, pr);
    K(cross)(phi, pr, ppr);
    T C[9];
    K(sym_skew)(c[0], c[1], c[2], phi, C);  /* Gamma_0(phi) */
    for (int i = 0; i < 3; ++i)
        for (int j = 0; j < 3; ++j) o[5 * i + j] = C[3 * i + j];
    for (int i = 0; i < 3; ++i) {
        o[5 * i + 3] = nu[i] + c[2] * pn[i] + c[3] * ppn[i];
        o[5 * i + 4] = (rho[i] + c[2] * pr[i] + c[3] * ppr[i])
                       + iota * ((T)0.5 * nu[i] + c[3] * pn[i] + c[4] * ppn[i]);
    }
    o[15] = 0; o[16] = 0; o[17] = 0; o[18] = 1; o[19] = iota;
    o[20] = 0; o[21] = 0; o[22] = 0; o[23] = 0; o[24] = 1;
}

/* log (3.13): phi = log(C), nu = D^-1 v, rho = D^-1 (r - tau E nu), iota = tau. */
static void K(log_one)(const T *M, T *x) {
    T *rho = x, *nu = x + 3, *phi = x + 6;
    T v[3] = {M[3], M[8], M[13]}, r[3] = {M[4], M[9], M[14]}, tau = M[19], c[7];
    K(rotation_log)(M, 5, phi);
    T t2 = K(dot)(phi, phi);
    T d = K(jinv_coefficient)(t2);
    K(poly)(phi, v, (T)1, (T)-0.5, d, nu);
    K(coefficients)(t2, 4, c);
    T e_nu[3], y[3];
    K(poly)(phi, nu, (T)0.5, c[3], c[4], e_nu);
    for (int i = 0; i < 3; ++i) y[i] = r[i] - tau * e_nu[i];
    K(poly)(phi, y, (T)1, (T)-0.5, d, rho);
    x[9] = tau;
}

/* Shared by the transposed products of (3.23) at xi = [rho, nu, phi, iota] (_transpose_parts). */
typedef struct {
    T rho[3], nu[3], phi[3], iota, c[7], pr[3], ppr[3], pn[3], ppn[3], g1n[3], g2n[3], r[3];
} K(parts_t);

static inline void K(transpose_parts)(const T *xi, T sign, K(parts_t) *P) {
    for (int i = 0; i < 3; ++i) {
        P->rho[i] = sign * xi[i];
        P->nu[i] = sign * xi[3 + i];
        P->phi[i] = sign * xi[6 + i];
    }
    P->iota = sign * xi[9];
    K(coefficients)(K(dot)(P->phi, P->phi), 6, P->c);
    K(cross)(P->phi, P->rho, P->pr);
    K(cross)(P->phi, P->nu, P->pn);
    K(cross)(P->phi, P->pr, P->ppr);
    K(cross)(P->phi, P->pn, P->ppn);
    const T *c = P->c;
    for (int i = 0; i < 3; ++i) {
        P->g1n[i] = P->nu[i] + c[2] * P->pn[i] + c[3] * P->ppn[i];
        P->g2n[i] = (T)0.5 * P->nu[i] + c[3] * P->pn[i] + c[4] * P->ppn[i];
        P->r[i] = P->rho[i] + c[2] * P->pr[i] + c[3] * P->ppr[i] + P->iota * P->g2n[i];
    }
}

/* _coupling_t: (S, z) with N^T a + M^T b = S + D^T z. */
static inline void K(coupling_t)(const K(parts_t) *P, const T *a, const T *b, T *S, T *z) {
    const T *c = P->c, *phi = P->phi, *rho = P->rho, *nu = P->nu;
    T iota = P->iota;
    T e2 = 2 * c[4] - c[3], e3 = 3 * c[5] - c[4], e4 = 4 * c[6] - c[5];
    T bp[3], u1[3], u2[3], u3[3], u4[3];
    for (int i = 0; i < 3; ++i) {
        bp[i] = b[i] - iota * a[i];
        u1[i] = iota * e3 * a[i] + e2 * bp[i];
        u2[i] = iota * e4 * a[i] + e3 * bp[i];
        u3[i] = iota * c[4] * a[i] + c[3] * bp[i];
        u4[i] = iota * c[3] * a[i] + c[2] * bp[i];
    }
    T scal = e2 * K(dot)(P->pr, a) + e3 * K(dot)(P->ppr, a) - (T)2 * c[3] * K(dot)(rho, a)
             + K(dot)(P->pn, u1) + K(dot)(P->ppn, u2) - (T)2 * K(dot)(nu, u3);
    T ra[3], nu4[3], z1[3], z2[3];
    K(cross)(rho, a, ra);
    K(cross)(nu, u4, nu4);
    T phi_rho = K(dot)(phi, rho), phi_a = K(dot)(phi, a), phi_nu = K(dot)(phi, nu), phi_u3 = K(dot)(phi, u3);
    for (int i = 0; i < 3; ++i)
        S[i] = phi[i] * scal + c[2] * ra[i] + nu4[i] + c[3] * (phi_rho * a[i] + rho[i] * phi_a)
               + phi_nu * u3[i] + nu[i] * phi_u3;
    K(cross)(a, P->r, z1);
    K(cross)(bp, P->g1n, z2);
    for (int i = 0; i < 3; ++i) z[i] = z1[i] + z2[i];
}

/* Gamma_1(-phi) x = x - c1' (phi x x) + c2' phi x (phi x x) with Gamma_1's coefficients. */
static inline void K(gamma1_t)(const K(parts_t) *P, const T *x, T *o) {
    T mphi[3] = {-P->phi[0], -P->phi[1], -P->phi[2]};
    K(poly)(mphi, x, (T)1, P->c[2], P->c[3], o);
}

/* _jl_tmv: J_l(xi)^T w, with the parts P of xi (transpose_parts). */
static void K(jl_tmv_parts)(const K(parts_t) *Pp, const T *w, T *o) {
    const T *c = Pp->c, *w_rho = w, *w_nu = w + 3, *w_phi = w + 6;
    T p[3], pp[3], DT[3], ET[3], g[3], o_nu[3], S[3], z[3], zw[3], g2[3];
    K(cross)(Pp->phi, w_rho, p);
    K(cross)(Pp->phi, p, pp);
    for (int i = 0; i < 3; ++i) {
        DT[i] = w_rho[i] - c[2] * p[i] + c[3] * pp[i];
        ET[i] = (T)0.5 * w_rho[i] - c[3] * p[i] + c[4] * pp[i];
    }
    K(gamma1_t)(Pp, w_nu, g);
    for (int i = 0; i < 3; ++i) o_nu[i] = g[i] - Pp->iota * (DT[i] - ET[i]);
    K(coupling_t)(Pp, w_rho, w_nu, S, z);
    for (int i = 0; i < 3; ++i) zw[i] = z[i] + w_phi[i];
    K(gamma1_t)(Pp, zw, g2);
    for (int i = 0; i < 3; ++i) {
        o[i] = DT[i];
        o[3 + i] = o_nu[i];
        o[6 + i] = S[i] + g2[i];
    }
    o[9] = K(dot)(Pp->g2n, w_rho) + w[9];
}

/* _jl_tmv: J_l(xi)^T w, at xi = sign * x. */
static void K(jl_tmv_one)(const T *x, T sign, const T *w, T *o) {
    K(parts_t) P;
    K(transpose_parts)(x, sign, &P);
    K(jl_tmv_parts)(&P, w, o);
}

/* _jl_inv_tmv: J_l(xi)^-T g, with the parts P of xi and d = jinv_coefficient(|phi|^2). */
static void K(jl_inv_tmv_parts)(const K(parts_t) *Pp, T d, const T *g, T *o) {
    const T *c = Pp->c;
    T mphi[3] = {-Pp->phi[0], -Pp->phi[1], -Pp->phi[2]};
    T y_rho[3], p[3], pp[3], t[3], y_nu[3], S[3], z[3], y_phi[3];
    K(poly)(mphi, g, (T)1, (T)-0.5, d, y_rho);
    K(cross)(Pp->phi, y_rho, p);
    K(cross)(Pp->phi, p, pp);
    for (int i = 0; i < 3; ++i)
        t[i] = g[3 + i] + Pp->iota * ((T)0.5 * y_rho[i] - (c[2] - c[3]) * p[i] + (c[3] - c[4]) * pp[i]);
    K(poly)(mphi, t, (T)1, (T)-0.5, d, y_nu);
    K(coupling_t)(Pp, y_rho, y_nu, S, z);
    for (int i = 0; i < 3; ++i) t[i] = g[6 + i] - S[i];
    K(poly)(mphi, t, (T)1, (T)-0.5, d, y_phi);
    for (int i = 0; i < 3; ++i) {
        o[i] = y_rho[i];
        o[3 + i] = y_nu[i];
        o[6 + i] = y_phi[i] - z[i];
    }
    o[9] = g[9] - K(dot)(Pp->g2n, y_rho);
}

/* _jl_inv_tmv: J_l(xi)^-T g, at xi = sign * x. */
static void K(jl_inv_tmv_one)(const T *x, T sign, const T *g, T *o) {
    K(parts_t) P;
    K(transpose_parts)(x, sign, &P);
    K(jl_inv_tmv_parts)(&P, K(jinv_coefficient)(K(dot)(P.phi, P.phi)), g, o);
}

/* exp's backward: J_r(xi)^T hat^T(M^T G) = J_l(-xi)^T (_exp_pullback). */
static void K(exp_vjp_one)(const T *xi, const T *M, const T *G, T *o) {
    T w[10];
    for (int i = 0; i < 3; ++i) {
        w[i] = M[i] * G[4] + M[5 + i] * G[9] + M[10 + i] * G[14];        /* C^T G[:3, 4] */
        w[3 + i] = M[i] * G[3] + M[5 + i] * G[8] + M[10 + i] * G[13];    /* C^T G[:3, 3] */
    }
    T acc[3] = {0, 0, 0}, t[3];
    for (int k = 0; k < 3; ++k) {  /* sum_k G[k, :3] x C[k, :] */
        K(cross)(G + 5 * k, M + 5 * k, t);
        for (int i = 0; i < 3; ++i) acc[i] += t[i];
    }
    for (int i = 0; i < 3; ++i) w[6 + i] = acc[i];
    w[9] = (M[3] * G[4] + M[8] * G[9] + M[13] * G[14]) + G[19];
    K(jl_tmv_one)(xi, (T)-1, w, o);
}

/* log's backward: M^-T vee^T(J_r(xi)^-T g) (_log_pullback of J_l(-xi)^-T g). */
static void K(log_vjp_one)(const T *M, const T *xi, const T *g, T *O) {
    T w[10];
    K(jl_inv_tmv_one)(xi, (T)-1, g, w);
    const T *rho = w, *nu = w + 3;
    T half[3] = {(T)0.5 * w[6], (T)0.5 * w[7], (T)0.5 * w[8]}, iota = w[9];
    T v[3] = {M[3], M[8], M[13]}, r[3] = {M[4], M[9], M[14]}, tau = M[19];
    T a[3], b[3], ah[3], bh[3], row[3];
    for (int i = 0; i < 3; ++i) {  /* a = -C^T v, b = -C^T (r - tau v) */
        a[i] = -(M[i] * v[0] + M[5 + i] * v[1] + M[10 + i] * v[2]);
        b[i] = -(M[i] * (r[0] - tau * v[0]) + M[5 + i] * (r[1] - tau * v[1])
                 + M[10 + i] * (r[2] - tau * v[2]));
    }
    for (int i = 0; i < 3; ++i) {
        K(cross)(M + 5 * i, half, row);  /* row i of C half^ */
        O[5 * i] = row[0]; O[5 * i + 1] = row[1]; O[5 * i + 2] = row[2];
        O[5 * i + 3] = K(dot)(M + 5 * i, nu);
        O[5 * i + 4] = K(dot)(M + 5 * i, rho);
    }
    K(cross)(a, half, ah);
    K(cross)(b, half, bh);
    O[15] = ah[0]; O[16] = ah[1]; O[17] = ah[2]; O[18] = K(dot)(a, nu); O[19] = K(dot)(a, rho) + iota;
    O[20] = bh[0]; O[21] = bh[1]; O[22] = bh[2]; O[23] = K(dot)(b, nu); O[24] = K(dot)(b, rho) - tau * iota;
}

/* SO(3) (so3.py), tangent phi (3), matrices (3, 3) row-major: the rotation block of the groups
 * above, with the same series.  exp: Rodrigues' formula C = Gamma_0(phi) (3.7); log: (3.10)-(3.11),
 * accurate near 0 and pi (blocks.rotation_log). */
static void K(so3_exp_one)(const T *phi, T *o) {
    T c[7];
    K(coefficients)(K(dot)(phi, phi), 4, c);
    K(sym_skew)(c[0], c[1], c[2], phi, o);
}

static void K(so3_log_one)(const T *M, T *phi) { K(rotation_log)(M, 3, phi); }

/* SE(3) (se3.py; Barfoot, Table 1), tangent (6) = [rho, phi], matrices (4, 4) row-major
 * [[C, r], [0, 1]]: a subgroup of SGal(3), with the same series.
 * exp: C = Gamma_0(phi), r = Gamma_1(phi) rho (se3.exp_impl). */
static void K(se3_exp_one)(const T *x, T *o) {
    const T *rho = x, *phi = x + 3;
    T c[7], r[3], C[9];
    K(coefficients)(K(dot)(phi, phi), 4, c);
    K(sym_skew)(c[0], c[1], c[2], phi, C);  /* Gamma_0(phi) */
    K(poly)(phi, rho, (T)1, c[2], c[3], r);  /* Gamma_1(phi) rho */
    for (int i = 0; i < 3; ++i) {
        for (int j = 0; j < 3; ++j) o[4 * i + j] = C[3 * i + j];
        o[4 * i + 3] = r[i];
    }
    o[12] = 0; o[13] = 0; o[14] = 0; o[15] = 1;
}

/* log: phi = log(C), rho = Gamma_1(phi)^-1 r (se3.log_impl, blocks.jac_inv_vec). */
static void K(se3_log_one)(const T *M, T *x) {
    T *rho = x, *phi = x + 3;
    T r[3] = {M[3], M[7], M[11]};
    K(rotation_log)(M, 4, phi);
    K(poly)(phi, r, (T)1, (T)-0.5, K(jinv_coefficient)(K(dot)(phi, phi)), rho);
}

/* SE_2(3) (se23.py), tangent (9) = [rho, nu, phi], matrices (5, 5) row-major
 * [[C, v, r], [0, 1, 0], [0, 0, 1]]: the subgroup iota = 0 of SGal(3).
 * exp: C = Gamma_0(phi), v = Gamma_1(phi) nu, r = Gamma_1(phi) rho (se23.exp_impl). */
static void K(se23_exp_one)(const T *x, T *o) {
    const T *rho = x, *nu = x + 3, *phi = x + 6;
    T c[7], v[3], r[3], C[9];
    K(coefficients)(K(dot)(phi, phi), 4, c);
    K(sym_skew)(c[0], c[1], c[2], phi, C);  /* Gamma_0(phi) */
    K(poly)(phi, nu, (T)1, c[2], c[3], v);  /* Gamma_1(phi) nu */
    K(poly)(phi, rho, (T)1, c[2], c[3], r);  /* Gamma_1(phi) rho */
    for (int i = 0; i < 3; ++i) {
        for (int j = 0; j < 3; ++j) o[5 * i + j] = C[3 * i + j];
        o[5 * i + 3] = v[i];
        o[5 * i + 4] = r[i];
    }
    o[15] = 0; o[16] = 0; o[17] = 0; o[18] = 1; o[19] = 0;
    o[20] = 0; o[21] = 0; o[22] = 0; o[23] = 0; o[24] = 1;
}

/* log: phi = log(C), nu = Gamma_1(phi)^-1 v, rho = Gamma_1(phi)^-1 r (se23.log_impl). */
static void K(se23_log_one)(const T *M, T *x) {
    T *rho = x, *nu = x + 3, *phi = x + 6;
    T v[3] = {M[3], M[8], M[13]}, r[3] = {M[4], M[9], M[14]};
    K(rotation_log)(M, 5, phi);
    T d = K(jinv_coefficient)(K(dot)(phi, phi));
    K(poly)(phi, r, (T)1, (T)-0.5, d, rho);
    K(poly)(phi, v, (T)1, (T)-0.5, d, nu);
}

/* ----- the left Jacobians and their inverses in block form (the tensor code's _jl_blocks) ----- */

/* 3x3 row-major helpers. */
static inline void K(mat3_mul)(const T *A, const T *Bm, T *o) {
    for (int i = 0; i < 3; ++i)
        for (int j = 0; j < 3; ++j)
            o[3 * i + j] = A[3 * i] * Bm[j] + A[3 * i + 1] * Bm[3 + j] + A[3 * i + 2] * Bm[6 + j];
}

/* Gamma_l(phi) x (blocks.gamma_vec): x / l! + c_(l+1) phi^x + c_(l+2) phi^phi^x. */
static inline void K(gamma_vec)(const T *c, int l, const T *phi, const T *x, T *o) {
    T p[3], pp[3];
    K(cross)(phi, x, p);
    K(cross)(phi, p, pp);
    for (int i = 0; i < 3; ++i) o[i] = (l < 2 ? x[i] : x[i] / (T)2) + c[l + 1] * p[i] + c[l + 2] * pp[i];
}

/* d/dphi [(m1 phi^ + m2 phi^ phi^) x] (blocks.poly_vec_derivative), e_k = m_k'(theta)/theta:
 * (e1 phi^x + e2 phi^phi^x - 2 m2 x) phi^T + m2 phi x^T + m2 (phi . x) I - m1 x^. */
static inline void K(poly_vec_derivative)(T m1, T m2, T e1, T e2, const T *phi, const T *x, T *o) {
    T p[3], pp[3], u[3];
    K(cross)(phi, x, p);
    K(cross)(phi, p, pp);
    for (int i = 0; i < 3; ++i) u[i] = e1 * p[i] + e2 * pp[i] - (T)2 * m2 * x[i];
    T bd = m2 * K(dot)(phi, x);
    for (int i = 0; i < 3; ++i)
        for (int j = 0; j < 3; ++j) o[3 * i + j] = u[i] * phi[j] + m2 * (phi[i] * x[j]) + (i == j ? bd : (T)0);
    o[1] += m1 * x[2]; o[2] -= m1 * x[1];  /* - m1 x^ */
    o[3] -= m1 * x[2]; o[5] += m1 * x[0];
    o[6] += m1 * x[1]; o[7] -= m1 * x[0];
}

/* d/dphi [Gamma_l(phi) x] (blocks.gamma_vec_derivative): the same algebra with a = c_(l+1),
 * b = c_(l+2) and e_m = m c_(m+2) - c_(m+1). */
static inline void K(gamma_vec_derivative)(const T *c, int l, const T *phi, const T *x, T *o) {
    T ea = (T)(l + 1) * c[l + 3] - c[l + 2], eb = (T)(l + 2) * c[l + 4] - c[l + 3];
    K(poly_vec_derivative)(c[l + 1], c[l + 2], ea, eb, phi, x, o);
}

/* r^ M, column by column (blocks.skew_times). */
static inline void K(skew_times)(const T *r, const T *M, T *o) {
    for (int j = 0; j < 3; ++j) {
        T col[3] = {M[j], M[3 + j], M[6 + j]}, out[3];
        K(cross)(r, col, out);
        o[j] = out[0]; o[3 + j] = out[1]; o[6 + j] = out[2];
    }
}

/* Q(x, phi) = d(Gamma_1 x)/dphi + (Gamma_1 x)^ Gamma_1 (blocks.q_block; J = Gamma_1(phi)). */
static inline void K(q_block)(const T *c, const T *phi, const T *x, const T *J, T *o) {
    T g[3], S[9];
    K(gamma_vec_derivative)(c, 1, phi, x, o);
    K(gamma_vec)(c, 1, phi, x, g);
    K(skew_times)(g, J, S);
    for (int i = 0; i < 9; ++i) o[i] += S[i];
}

/* D^-1(phi) = (1 - d theta^2) I - phi^/2 + d phi phi^T (blocks.jac_inv_mat, (3.12)). */
static inline void K(jac_inv_mat)(const T *phi, T *o) {
    T t2 = K(dot)(phi, phi), d = K(jinv_coefficient)(t2);
    K(sym_skew)((T)1 - d * t2, (T)-0.5, d, phi, o);
}

/* -A Q A for 3x3 A, Q (the off-diagonal blocks of the subgroups' J_l^-1). */
static inline void K(neg_sandwich)(const T *A, const T *Q, T *o) {
    T t[9];
    K(mat3_mul)(A, Q, t);
    K(mat3_mul)(t, A, o);
    for (int i = 0; i < 9; ++i) o[i] = -o[i];
}

/* Writes the 3x3 block Bk at block (bi, bj) of an n x n row-major matrix (3-sized blocks). */
static inline void K(put3)(T *o, int n, int bi, int bj, const T *Bk) {
    for (int i = 0; i < 3; ++i)
        for (int j = 0; j < 3; ++j) o[n * (3 * bi + i) + 3 * bj + j] = Bk[3 * i + j];
}

/* SE(3), [rho, phi]: J_l = [[J, Q], [0, J]], J_l^-1 = [[J^-1, -J^-1 Q J^-1], [0, J^-1]]
 * (se3.jl_impl, jl_inv_impl; Barfoot, Table 1). */
static void K(se3_jl_one)(const T *x, int inverse, T *o) {
    const T *rho = x, *phi = x + 3;
    T c[7], J[9], Q[9], Ji[9], R[9];
    for (int i = 0; i < 36; ++i) o[i] = 0;
    K(coefficients)(K(dot)(phi, phi), 6, c);
    K(sym_skew)(c[1], c[2], c[3], phi, J);  /* Gamma_1(phi) */
    K(q_block)(c, phi, rho, J, Q);
    if (!inverse) {
        K(put3)(o, 6, 0, 0, J); K(put3)(o, 6, 1, 1, J); K(put3)(o, 6, 0, 1, Q);
        return;
    }
    K(jac_inv_mat)(phi, Ji);
    K(neg_sandwich)(Ji, Q, R);
    K(put3)(o, 6, 0, 0, Ji); K(put3)(o, 6, 1, 1, Ji); K(put3)(o, 6, 0, 1, R);
}

/* SO(3): J_l = D(phi) = Gamma_1(phi) (3.8) and D^-1(phi) (3.12) (so3.jl_impl, jl_inv_impl). */
static void K(so3_jl_one)(const T *phi, int inverse, T *o) {
    if (inverse) {
        K(jac_inv_mat)(phi, o);
        return;
    }
    T c[7];
    K(coefficients)(K(dot)(phi, phi), 4, c);
    K(sym_skew)(c[1], c[2], c[3], phi, o);
}

/* SE_2(3), [rho, nu, phi]: J_l = [[J, 0, Q_rho], [0, J, Q_nu], [0, 0, J]] and its inverse
 * (se23.jl_impl, jl_inv_impl). */
static void K(se23_jl_one)(const T *x, int inverse, T *o) {
    const T *rho = x, *nu = x + 3, *phi = x + 6;
    T c[7], J[9], Qr[9], Qn[9], Ji[9], R[9];
    for (int i = 0; i < 81; ++i) o[i] = 0;
    K(coefficients)(K(dot)(phi, phi), 6, c);
    K(sym_skew)(c[1], c[2], c[3], phi, J);
    K(q_block)(c, phi, rho, J, Qr);
    K(q_block)(c, phi, nu, J, Qn);
    if (!inverse) {
        for (int k = 0; k < 3; ++k) K(put3)(o, 9, k, k, J);
        K(put3)(o, 9, 0, 2, Qr); K(put3)(o, 9, 1, 2, Qn);
        return;
    }
    K(jac_inv_mat)(phi, Ji);
    for (int k = 0; k < 3; ++k) K(put3)(o, 9, k, k, Ji);
    K(neg_sandwich)(Ji, Qr, R); K(put3)(o, 9, 0, 2, R);
    K(neg_sandwich)(Ji, Qn, R); K(put3)(o, 9, 1, 2, R);
}

/* SGal(3), [rho, nu, phi, iota]: (3.23) from the blocks of sgal3._jl_blocks, D = Gamma_1,
 * E = Gamma_2, L = D - E (3.24), M (3.25), N (3.26):
 *   J_l    = [[D, -iota L, N, E nu], [0, D, M, 0], [0, 0, D, 0], [0, 0, 0, 1]],
 *   J_l^-1 = [[D^-1, iota D^-1 L D^-1, Y, -D^-1 E nu], [0, D^-1, -P, 0], [0, 0, D^-1, 0], [0, 0, 0, 1]]
 * with P = D^-1 M D^-1 and Y = -D^-1 (iota L P + N D^-1) (sgal3.jl_impl, jl_inv_impl). */
static void K(sgal3_jl_one)(const T *x, int inverse, T *o) {
    const T *rho = x, *nu = x + 3, *phi = x + 6;
    T iota = x[9], c[7], D[9], E[9], L[9], Mb[9], N[9], g2n[3], r[3], dr[9], dn[9], S[9];
    for (int i = 0; i < 100; ++i) o[i] = 0;
    K(coefficients)(K(dot)(phi, phi), 6, c);
    K(sym_skew)(c[1], c[2], c[3], phi, D);
    K(sym_skew)(c[2], c[3], c[4], phi, E);
    for (int i = 0; i < 9; ++i) L[i] = D[i] - E[i];
    K(q_block)(c, phi, nu, D, Mb);
    K(gamma_vec)(c, 2, phi, nu, g2n);
    K(gamma_vec)(c, 1, phi, rho, r);
    for (int i = 0; i < 3; ++i) r[i] += iota * g2n[i];
    K(gamma_vec_derivative)(c, 1, phi, rho, dr);
    K(gamma_vec_derivative)(c, 2, phi, nu, dn);
    K(skew_times)(r, D, S);
    for (int i = 0; i < 9; ++i) N[i] = (dr[i] + iota * dn[i]) + S[i] - iota * Mb[i];
    o[99] = 1;
    if (!inverse) {
        T mL[9];
        for (int i = 0; i < 9; ++i) mL[i] = -iota * L[i];
        K(put3)(o, 10, 0, 0, D); K(put3)(o, 10, 1, 1, D); K(put3)(o, 10, 2, 2, D);
        K(put3)(o, 10, 0, 1, mL); K(put3)(o, 10, 0, 2, N); K(put3)(o, 10, 1, 2, Mb);
        for (int i = 0; i < 3; ++i) o[10 * i + 9] = g2n[i];
        return;
    }
    T Di[9], P[9], t[9], LP[9], ND[9], Y[9], DLD[9], mP[9];
    K(jac_inv_mat)(phi, Di);
    K(mat3_mul)(Di, Mb, t);
    K(mat3_mul)(t, Di, P);
    K(mat3_mul)(L, P, LP);
    K(mat3_mul)(N, Di, ND);
    for (int i = 0; i < 9; ++i) t[i] = iota * LP[i] + ND[i];
    K(mat3_mul)(Di, t, Y);
    for (int i = 0; i < 9; ++i) Y[i] = -Y[i];
    K(mat3_mul)(Di, L, t);
    K(mat3_mul)(t, Di, DLD);
    for (int i = 0; i < 9; ++i) { DLD[i] = iota * DLD[i]; mP[i] = -P[i]; }
    K(put3)(o, 10, 0, 0, Di); K(put3)(o, 10, 1, 1, Di); K(put3)(o, 10, 2, 2, Di);
    K(put3)(o, 10, 0, 1, DLD); K(put3)(o, 10, 0, 2, Y); K(put3)(o, 10, 1, 2, mP);
    for (int i = 0; i < 3; ++i)
        o[10 * i + 9] = -(Di[3 * i] * g2n[0] + Di[3 * i + 1] * g2n[1] + Di[3 * i + 2] * g2n[2]);
}

JACOBIAN_RANGE(so3, 3, 0, so3_jl)
JACOBIAN_RANGE(so3, 3, 1, so3_jl_inv)
JACOBIAN_RANGE(se3, 6, 0, se3_jl)
JACOBIAN_RANGE(se3, 6, 1, se3_jl_inv)
JACOBIAN_RANGE(se23, 9, 0, se23_jl)
JACOBIAN_RANGE(se23, 9, 1, se23_jl_inv)
JACOBIAN_RANGE(sgal3, 10, 0, jl)
JACOBIAN_RANGE(sgal3, 10, 1, jl_inv)

RANGE(exp, exp_one, 10, 25)
RANGE(log, log_one, 25, 10)
RANGE(se23_exp, se23_exp_one, 9, 25)
RANGE(se23_log, se23_log_one, 25, 9)
RANGE(so3_exp, so3_exp_one, 3, 9)
RANGE(so3_log, so3_log_one, 9, 3)
RANGE(se3_exp, se3_exp_one, 6, 16)
RANGE(se3_log, se3_log_one, 16, 6)

static void K(exp_vjp_range)(void **a, int64_t lo, int64_t hi) {
    const T *xi = a[0], *M = a[1], *G = a[2];
    T *out = a[3];
    for (int64_t i = lo; i < hi; ++i) K(exp_vjp_one)(xi + 10 * i, M + 25 * i, G + 25 * i, out + 10 * i);
}

static void K(log_vjp_range)(void **a, int64_t lo, int64_t hi) {
    const T *M = a[0], *xi = a[1], *g = a[2];
    T *out = a[3];
    for (int64_t i = lo; i < hi; ++i) K(log_vjp_one)(M + 25 * i, xi + 10 * i, g + 10 * i, out + 25 * i);
}

#undef K
#undef K_
#undef K__
#undef T
#undef SFX
#undef SIN
#undef COS
#undef SQRT
#undef ATAN2
