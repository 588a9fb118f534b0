/* SE(2) exp, log and left Jacobians for one scalar type T (included per dtype by
 * functional/_native.c after _native_sgal3.h, whose series K(coefficients) it uses; T, SFX and
 * ATAN2 are defined by the includer and undefined at the end).
 *
 * se2.py (Barfoot, "Integral Forms", Section 4.5 and Table 1), tangent (3) = [rho (2), theta],
 * matrices (3, 3) row-major [[C, r], [0, 1]].  With J = [[0, -1], [1, 0]] and the series c_m at
 * theta^2: C = c_0 I + theta c_1 J, V = c_1 I + theta c_2 J, W = c_2 I + theta c_3 J,
 * J_l = [[V, -J W rho], [0, 1]], V^-1 = (c_1 I - theta c_2 J) / (2 c_2).  Term by term the
 * arithmetic of se2.py, so the two agree to rounding (tests/test_native_subgroups.py). */
#define K_(name, sfx) name##_##sfx
#define K__(name, sfx) K_(name, sfx)
#define K(name) K__(name, SFX)

/* [[a I + b J, (u, v)], [0, 1]] as 3 x 3 row-major entries. */
static inline void K(se2_put)(T a, T b, T u, T v, T *o) {
    o[0] = a; o[1] = -b; o[2] = u;
    o[3] = b; o[4] = a; o[5] = v;
    o[6] = 0; o[7] = 0; o[8] = 1;
}

/* exp: C = c_0 I + theta c_1 J, r = V rho (se2.exp_impl). */
static void K(se2_exp_one)(const T *x, T *o) {
    T t = x[2], c[7];
    K(coefficients)(t * t, 4, c);
    T a = c[1], b = t * c[2];
    K(se2_put)(c[0], t * c[1], a * x[0] - b * x[1], b * x[0] + a * x[1], o);
}

/* log: theta = atan2 of the rotation, rho = V^-1 r (se2.log_impl). */
static void K(se2_log_one)(const T *M, T *x) {
    T t = ATAN2((T)0.5 * (M[3] - M[1]), (T)0.5 * (M[0] + M[4])), c[7];
    T z = M[0] * 0 + M[1] * 0 + M[3] * 0 + M[4] * 0;  /* NaN where a rotation entry is not finite */
    if (z != z) t = (T)NAN;  /* atan2 reads an infinite entry as a quarter or half turn */
    K(coefficients)(t * t, 4, c);
    T a = c[1] / ((T)2 * c[2]), b = -t * c[2] / ((T)2 * c[2]);
    x[0] = a * M[2] - b * M[5];
    x[1] = b * M[2] + a * M[5];
    x[2] = t;
}

/* J_l = [[V, q], [0, 1]] with q = -J W rho, and J_l^-1 = [[V^-1, -V^-1 q], [0, 1]]
 * (se2.jl_impl, jl_inv_impl). */
static void K(se2_jl_one)(const T *x, int inverse, T *o) {
    T t = x[2], c[7];
    K(coefficients)(t * t, 4, c);
    T a = c[1], b = t * c[2];
    T wx = c[2] * x[0] - t * c[3] * x[1], wy = t * c[3] * x[0] + c[2] * x[1];
    T qx = wy, qy = -wx;
    if (inverse) {
        T ai = a / ((T)2 * c[2]), bi = -b / ((T)2 * c[2]);
        T px = ai * qx - bi * qy, py = bi * qx + ai * qy;
        K(se2_put)(ai, bi, -px, -py, o);
        return;
    }
    K(se2_put)(a, b, qx, qy, o);
}

RANGE(se2_exp, se2_exp_one, 3, 9)
RANGE(se2_log, se2_log_one, 9, 3)
JACOBIAN_RANGE(se2, 3, 0, se2_jl)
JACOBIAN_RANGE(se2, 3, 1, se2_jl_inv)

#undef K
#undef K_
#undef K__
#undef T
#undef SFX
#undef ATAN2
