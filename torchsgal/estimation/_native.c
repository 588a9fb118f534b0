/* torchsgal.estimation._native: the estimation engine's CPU kernels: batched Cholesky
 * factorisations and triangular solves of small dense systems (_native_cholesky.h; the operators
 * torchsgal::cholesky_solve, gram_cholesky_solve and triangular_solve, estimation/dense_solve.py,
 * and damped_solve, estimation/graph/damped_solve.py), and the
 * batched Cholesky solves of block-sparse systems sharing one pattern (_native_block_cholesky.h;
 * torchsgal::block_cholesky_solve, estimation/block_cholesky.py), and the
 * residuals and Jacobians of the built-in SE(3) and SE(2) priors and betweens (_native_factors.h,
 * SE(3) on the closed forms of functional/_native_sgal3.h; torchsgal::se3_factor_terms and
 * se2_factor_terms, estimation/graph/factor_kernels.py), and the blocks J^T J and J^T r of
 * any factor's normal equations (_native_normal.h; torchsgal::normal_assemble,
 * estimation/graph/normal_kernel.py), and a Levenberg-Marquardt round's verdict and bookkeeping
 * per problem (_native_round.h; torchsgal::lm_round_update, estimation/graph/round_update.py).
 *
 * No torch headers: the Python side passes data pointers of CPU tensors it checked: contiguous
 * ones it allocated, and for normal_assemble the caller's J and r with their strides.  The splitting of a batch over threads is the core kernels' (_native_common.h).
 */
#include "../functional/_native_common.h"

#if defined(__GNUC__)
#pragma GCC diagnostic push
#pragma GCC diagnostic ignored "-Wunused-function"  /* only SE(3)'s closed forms are used here */
#endif
#define T double
#define SFX f64
#define SIN sin
#define COS cos
#define SQRT sqrt
#define ATAN2 atan2
#include "../functional/_native_sgal3.h"  /* undefines T, SFX and the math macros */
#define T double
#define SFX f64
#include "../functional/_native_products.h"  /* SE(3)'s inverse and adjoint; undefines T, SFX */
#define T float
#define SFX f32
#define SIN sinf
#define COS cosf
#define SQRT sqrtf
#define ATAN2 atan2_f32
#include "../functional/_native_sgal3.h"
#define T float
#define SFX f32
#include "../functional/_native_products.h"
#if defined(__GNUC__)
#pragma GCC diagnostic pop
#endif

/* The out-of-line lane loops of the block Cholesky solves get an AVX2 clone too in float64; in
 * float32 their AVX2 clone measured up to 12% slower.  (The dense solves' lane loops pick their
 * vector width by the CPU themselves: _native_cholesky.h.) */
#define WIDE_LANES WIDE_LOOPS
#define T double
#define SFX f64
#define SQRT sqrt
#define SIN sin
#define COS cos
#define ATAN2 atan2
#include "_native_factors.h"
#include "_native_normal.h"
#include "_native_round.h"
#include "_native_block_cholesky.h"
#include "_native_cholesky.h"  /* undefines T, SFX and SQRT */
#undef SIN
#undef COS
#undef ATAN2
#undef WIDE_LANES
#define WIDE_LANES
#define T float
#define SFX f32
#define SQRT sqrtf
#define SIN sinf
#define COS cosf
#define ATAN2 atan2_f32
#include "_native_factors.h"
#include "_native_normal.h"
#include "_native_round.h"
#include "_native_block_cholesky.h"
#include "_native_cholesky.h"
#undef SIN
#undef COS
#undef ATAN2

/* work of one m x m system with k right-hand sides, in units of one SGal(3) exp (~400 flops) */
static int64_t solve_cost(int64_t m, int64_t k, int back) {
    int64_t flops = m * m * m / 3 + (back ? 2 : 1) * m * m * k;
    return flops / 400 + 1;
}

/* cholesky_solve(A, R, L, X, Y, info, n, m, k, lanes, threads, is_double): Y 0 (a null pointer)
 * for the factor and the forward solve only; lanes 1 runs systems of up to LANE_MAX_M unknowns
 * LANES at a time */
static PyObject *py_cholesky_solve(PyObject *self, PyObject *const *a, Py_ssize_t nargs) {
    (void)self;
    void *ptr[6];
    int64_t ints[6]; /* n, m, k, lanes, threads, is_double */
    if (read_call(a, nargs, 6, ptr, 6, ints, "cholesky_solve") < 0) return NULL;
    void *args[9] = {ptr[0], ptr[1], ptr[2], ptr[3], ptr[4], ptr[5], &ints[1], &ints[2], &ints[3]};
    Py_BEGIN_ALLOW_THREADS
    run_parallel(ints[5] ? cholesky_solve_range_f64 : cholesky_solve_range_f32, args, ints[0],
                 solve_cost(ints[1], ints[2], ptr[4] != NULL), (int)ints[4]);
    Py_END_ALLOW_THREADS
    Py_RETURN_NONE;
}

/* damped_solve(H, g, lam, delta, solved, quad, clamp, n, m, diagonal, threads, is_double):
 * _native_cholesky.h's damped_solve_range */
static PyObject *py_damped_solve(PyObject *self, PyObject *const *a, Py_ssize_t nargs) {
    (void)self;
    void *ptr[7];
    int64_t ints[5]; /* n, m, diagonal, threads, is_double */
    if (read_call(a, nargs, 7, ptr, 5, ints, "damped_solve") < 0) return NULL;
    void *args[9] = {ptr[0], ptr[1], ptr[2], ptr[3], ptr[4], ptr[5], ptr[6], &ints[1], &ints[2]};
    Py_BEGIN_ALLOW_THREADS
    run_parallel(ints[4] ? damped_solve_range_f64 : damped_solve_range_f32, args, ints[0],
                 solve_cost(ints[1], 1, 1), (int)ints[3]);
    Py_END_ALLOW_THREADS
    Py_RETURN_NONE;
}

/* gram_cholesky_solve(G, d, R, L, X, Y, info, n, m, p, k, d_stride, threads, is_double):
 * cholesky_solve of A = G diag(d) G^T, A formed per system in the kernel; Y 0 (a null pointer)
 * for the factor and the forward solve only */
static PyObject *py_gram_cholesky_solve(PyObject *self, PyObject *const *a, Py_ssize_t nargs) {
    (void)self;
    void *ptr[7];
    int64_t ints[7]; /* n, m, p, k, d_stride, threads, is_double */
    if (read_call(a, nargs, 7, ptr, 7, ints, "gram_cholesky_solve") < 0) return NULL;
    void *args[11] = {ptr[0], ptr[1], ptr[2], ptr[3], ptr[4], ptr[5], ptr[6],
                      &ints[1], &ints[2], &ints[3], &ints[4]};
    Py_BEGIN_ALLOW_THREADS
    run_parallel(ints[6] ? gram_cholesky_solve_range_f64 : gram_cholesky_solve_range_f32, args, ints[0],
                 solve_cost(ints[1], ints[3], ptr[5] != NULL) + ints[1] * ints[1] * ints[2] / 800,
                 (int)ints[5]);
    Py_END_ALLOW_THREADS
    Py_RETURN_NONE;
}

/* triangular_solve(L, R, X, n, m, k, transpose, lanes, threads, is_double) */
static PyObject *py_triangular_solve(PyObject *self, PyObject *const *a, Py_ssize_t nargs) {
    (void)self;
    void *ptr[3];
    int64_t ints[7]; /* n, m, k, transpose, lanes, threads, is_double */
    if (read_call(a, nargs, 3, ptr, 7, ints, "triangular_solve") < 0) return NULL;
    void *args[7] = {ptr[0], ptr[1], ptr[2], &ints[1], &ints[2], &ints[3], &ints[4]};
    Py_BEGIN_ALLOW_THREADS
    run_parallel(ints[6] ? triangular_solve_range_f64 : triangular_solve_range_f32, args, ints[0],
                 ints[1] * ints[1] * ints[2] / 400 + 1, (int)ints[5]);
    Py_END_ALLOW_THREADS
    Py_RETURN_NONE;
}

/* block_cholesky_solve(values, rhs, structure, L, X, Q, info, n, k, cost, threads, is_double,
 * structure_numel): n systems of one block pattern (_native_block_cholesky.h); cost: the work of
 * one system in units of one SGal(3) exp.  A malformed structure raises ValueError. */
static PyObject *py_block_cholesky_solve(PyObject *self, PyObject *const *a, Py_ssize_t nargs) {
    (void)self;
    void *ptr[7];
    int64_t ints[6]; /* n, k, cost, threads, is_double, structure_numel */
    if (read_call(a, nargs, 7, ptr, 6, ints, "block_cholesky_solve") < 0) return NULL;
    if (!block_structure_valid((const int64_t *)ptr[2], ints[5])) {
        PyErr_SetString(PyExc_ValueError, "structure is not a consistent block pattern "
                                          "(block_cholesky.analyse makes one)");
        return NULL;
    }
    void *args[8] = {ptr[0], ptr[1], ptr[2], ptr[3], ptr[4], ptr[5], ptr[6], &ints[1]};
    Py_BEGIN_ALLOW_THREADS
    run_parallel(ints[4] ? block_cholesky_range_f64 : block_cholesky_range_f32, args, ints[0],
                 ints[2], (int)ints[3]);
    Py_END_ALLOW_THREADS
    Py_RETURN_NONE;
}

/* se3_factor_terms(Zinv, Ti, Tj, r, J, n, threads, is_double): Ti 0 for priors, J 0 for the
 * residuals alone (_native_factors.h) */
static PyObject *py_se3_factor_terms(PyObject *self, PyObject *const *a, Py_ssize_t nargs) {
    (void)self;
    return dispatch(a, nargs, 5, se3_factor_range_f64, se3_factor_range_f32, 3, "se3_factor_terms");
}

/* se2_factor_terms(Zinv, Ti, Tj, r, J, series, n, threads, is_double): as se3_factor_terms;
 * series (1 + SE2_SERIES doubles): the squared threshold of the series, then its coefficients */
static PyObject *py_se2_factor_terms(PyObject *self, PyObject *const *a, Py_ssize_t nargs) {
    (void)self;
    return dispatch(a, nargs, 6, se2_factor_range_f64, se2_factor_range_f32, 1, "se2_factor_terms");
}

/* se3_factor_normal(Zinv, Ti, Tj, L, rw, H, g, n, shared, threads, is_double) and
 * se2_factor_normal(Zinv, Ti, Tj, L, rw, H, g, series, n, shared, threads, is_double): the whitened
 * residuals and each factor's normal-equation blocks (_native_factors.h); Ti 0 for priors, L 0 for
 * none, shared 1 for one L (m, m) for all factors */
static PyObject *factor_normal(PyObject *const *a, Py_ssize_t nargs, int npointers, range_fn f64,
                               range_fn f32, int64_t cost, const char *name) {
    void *ptr[8];
    int64_t ints[4]; /* n, shared, threads, is_double */
    if (read_call(a, nargs, npointers, ptr, 4, ints, name) < 0) return NULL;
    void *args[9] = {ptr[0], ptr[1], ptr[2], ptr[3], ptr[4], ptr[5], ptr[6], &ints[1],
                     npointers > 7 ? ptr[7] : NULL};
    Py_BEGIN_ALLOW_THREADS
    run_parallel(ints[3] ? f64 : f32, args, ints[0], cost, (int)ints[2]);
    Py_END_ALLOW_THREADS
    Py_RETURN_NONE;
}

static PyObject *py_se3_factor_normal(PyObject *self, PyObject *const *a, Py_ssize_t nargs) {
    (void)self;
    return factor_normal(a, nargs, 7, se3_factor_normal_range_f64, se3_factor_normal_range_f32, 4,
                         "se3_factor_normal");
}

static PyObject *py_se2_factor_normal(PyObject *self, PyObject *const *a, Py_ssize_t nargs) {
    (void)self;
    return factor_normal(a, nargs, 8, se2_factor_normal_range_f64, se2_factor_normal_range_f32, 1,
                         "se2_factor_normal");
}

/* se3_factor_assemble(Zinv, Ti, Tj, L, rw, values, g, slots, g_slots, B, E, size, D, shared,
 * threads, is_double) and se2_factor_assemble(..., g_slots, series, B, ...): the factors' whitened
 * residuals, their blocks added into each problem's values (B, size) and g (B, D) at slots (E,
 * Dk * Dk) and g_slots (E, Dk) (_native_factors.h); an index out of range raises ValueError. */
static PyObject *factor_assemble(PyObject *const *a, Py_ssize_t nargs, int npointers, int m,
                                 range_fn f64, range_fn f32, int64_t cost, const char *name) {
    void *ptr[10];
    int64_t ints[7]; /* B, E, size, D, shared, threads, is_double */
    if (read_call(a, nargs, npointers, ptr, 7, ints, name) < 0) return NULL;
    const int64_t Dk = (ptr[1] ? 2 : 1) * m, E = ints[1];
    const int64_t *slots = ptr[7], *g_slots = ptr[8];
    for (int64_t i = 0; i < E * Dk * Dk; ++i)
        if (slots[i] < 0 || slots[i] >= ints[2]) {
            PyErr_Format(PyExc_ValueError, "%s: slots must lie in [0, %lld), got %lld", name,
                         (long long)ints[2], (long long)slots[i]);
            return NULL;
        }
    for (int64_t i = 0; i < E * Dk; ++i)
        if (g_slots[i] < 0 || g_slots[i] >= ints[3]) {
            PyErr_Format(PyExc_ValueError, "%s: g_slots must lie in [0, %lld), got %lld", name,
                         (long long)ints[3], (long long)g_slots[i]);
            return NULL;
        }
    int64_t dims[3] = {E, ints[2], ints[3]};
    void *args[12] = {ptr[0], ptr[1], ptr[2], ptr[3], ptr[4], ptr[5], ptr[6], &ints[4], ptr[7],
                      ptr[8], dims, npointers > 9 ? ptr[9] : NULL};
    Py_BEGIN_ALLOW_THREADS
    run_parallel(ints[6] ? f64 : f32, args, ints[0], cost * (E > 0 ? E : 1), (int)ints[5]);
    Py_END_ALLOW_THREADS
    Py_RETURN_NONE;
}

static PyObject *py_se3_factor_assemble(PyObject *self, PyObject *const *a, Py_ssize_t nargs) {
    (void)self;
    return factor_assemble(a, nargs, 9, 6, se3_factor_assemble_range_f64,
                           se3_factor_assemble_range_f32, 4, "se3_factor_assemble");
}

static PyObject *py_se2_factor_assemble(PyObject *self, PyObject *const *a, Py_ssize_t nargs) {
    (void)self;
    return factor_assemble(a, nargs, 10, 3, se2_factor_assemble_range_f64,
                           se2_factor_assemble_range_f32, 1, "se2_factor_assemble");
}

/* normal_assemble(J, r, values, g, slots, g_slots, dims, B, cost, threads, is_double): dims (13
 * int64) as _native_normal.h reads them; cost: the work of one problem in units of one SGal(3)
 * exp.  A slot out of range, or more than NORMAL_MAX_DK columns, raises ValueError. */
static PyObject *py_normal_assemble(PyObject *self, PyObject *const *a, Py_ssize_t nargs) {
    (void)self;
    void *ptr[7];
    int64_t ints[4]; /* B, cost, threads, is_double */
    if (read_call(a, nargs, 7, ptr, 4, ints, "normal_assemble") < 0) return NULL;
    const int64_t *d = (const int64_t *)ptr[6];
    const int64_t k = d[2], rows = d[5] ? 1 : d[0];
    if (k < 1 || k > NORMAL_MAX_DK) {
        PyErr_Format(PyExc_ValueError, "normal_assemble: Dk must lie in [1, %d], got %lld",
                     NORMAL_MAX_DK, (long long)k);
        return NULL;
    }
    const int64_t *slots = ptr[4], *g_slots = ptr[5];
    for (int64_t i = 0; i < rows * k * k; ++i)
        if (slots[i] < 0 || slots[i] >= d[3]) {
            PyErr_Format(PyExc_ValueError, "normal_assemble: slots must lie in [0, %lld), got %lld",
                         (long long)d[3], (long long)slots[i]);
            return NULL;
        }
    for (int64_t i = 0; i < rows * k; ++i)
        if (g_slots[i] < 0 || g_slots[i] >= d[4]) {
            PyErr_Format(PyExc_ValueError, "normal_assemble: g_slots must lie in [0, %lld), got %lld",
                         (long long)d[4], (long long)g_slots[i]);
            return NULL;
        }
    Py_BEGIN_ALLOW_THREADS
    run_parallel(ints[3] ? normal_assemble_for_f64(k) : normal_assemble_for_f32(k), ptr, ints[0],
                 ints[1], (int)ints[2]);
    Py_END_ALLOW_THREADS
    Py_RETURN_NONE;
}

/* lm_round_update(14 pointers, 9 params, n, 5 codes, is_double): _native_round.h; one pass over
 * the n problems (no threads: a few operations each) */
static PyObject *py_lm_round_update(PyObject *self, PyObject *const *a, Py_ssize_t nargs) {
    (void)self;
    enum { NP = 14, NF = 9, NC = 5 };
    if (nargs != NP + NF + 1 + NC + 1) {
        PyErr_Format(PyExc_TypeError, "lm_round_update takes %d arguments", NP + NF + NC + 2);
        return NULL;
    }
    void *ptr[NP];
    double params[NF];
    int64_t codes[NC];
    for (int i = 0; i < NP; ++i) ptr[i] = PyLong_AsVoidPtr(a[i]);
    for (int i = 0; i < NF; ++i) params[i] = PyFloat_AsDouble(a[NP + i]);
    const int64_t n = PyLong_AsLongLong(a[NP + NF]);
    for (int i = 0; i < NC; ++i) codes[i] = PyLong_AsLongLong(a[NP + NF + 1 + i]);
    const int is_double = PyObject_IsTrue(a[NP + NF + 1 + NC]);
    if (PyErr_Occurred() || is_double < 0) return NULL;
    (is_double ? lm_round_update_f64 : lm_round_update_f32)(ptr, params, codes, n);
    Py_RETURN_NONE;
}

static PyMethodDef methods[] = {
    {"parallel_backend", py_parallel_backend, METH_NOARGS, "what splits large batches over threads"},
    {"cholesky_solve", (PyCFunction)(void (*)(void))py_cholesky_solve, METH_FASTCALL,
     "batched Cholesky and solves (A, R, L, X, Y, info, n, m, k, lanes, threads, is_double)"},
    {"damped_solve", (PyCFunction)(void (*)(void))py_damped_solve, METH_FASTCALL,
     "a Levenberg-Marquardt step's damped normal equations (H, g, lam, delta, solved, quad, clamp, n, m, diagonal, threads, is_double)"},
    {"gram_cholesky_solve", (PyCFunction)(void (*)(void))py_gram_cholesky_solve, METH_FASTCALL,
     "batched Cholesky and solves of G diag(d) G^T (G, d, R, L, X, Y, info, n, m, p, k, d_stride, threads, is_double)"},
    {"triangular_solve", (PyCFunction)(void (*)(void))py_triangular_solve, METH_FASTCALL,
     "batched triangular solves (L, R, X, n, m, k, transpose, lanes, threads, is_double)"},
    {"block_cholesky_solve", (PyCFunction)(void (*)(void))py_block_cholesky_solve, METH_FASTCALL,
     "batched block-sparse Cholesky solves (values, rhs, structure, L, X, Q, info, n, k, cost, threads, is_double, structure_numel)"},
    {"se3_factor_terms", (PyCFunction)(void (*)(void))py_se3_factor_terms, METH_FASTCALL,
     "SE(3) prior and between residuals and Jacobians (Zinv, Ti, Tj, r, J, n, threads, is_double)"},
    {"se2_factor_terms", (PyCFunction)(void (*)(void))py_se2_factor_terms, METH_FASTCALL,
     "SE(2) prior and between residuals and Jacobians (Zinv, Ti, Tj, r, J, series, n, threads, is_double)"},
    {"se3_factor_normal", (PyCFunction)(void (*)(void))py_se3_factor_normal, METH_FASTCALL,
     "SE(3) whitened residuals and normal-equation blocks (Zinv, Ti, Tj, L, rw, H, g, n, shared, threads, is_double)"},
    {"se2_factor_normal", (PyCFunction)(void (*)(void))py_se2_factor_normal, METH_FASTCALL,
     "SE(2) whitened residuals and normal-equation blocks (Zinv, Ti, Tj, L, rw, H, g, series, n, shared, threads, is_double)"},
    {"se3_factor_assemble", (PyCFunction)(void (*)(void))py_se3_factor_assemble, METH_FASTCALL,
     "SE(3) normal-equation blocks added into the problems' values (Zinv, Ti, Tj, L, rw, values, g, slots, g_slots, B, E, size, D, shared, threads, is_double)"},
    {"se2_factor_assemble", (PyCFunction)(void (*)(void))py_se2_factor_assemble, METH_FASTCALL,
     "SE(2) normal-equation blocks added into the problems' values (Zinv, Ti, Tj, L, rw, values, g, slots, g_slots, series, B, E, size, D, shared, threads, is_double)"},
    {"normal_assemble", (PyCFunction)(void (*)(void))py_normal_assemble, METH_FASTCALL,
     "normal-equation blocks J^T J, J^T r added into the problems' values and g (J, r, values, g, slots, g_slots, dims, B, cost, threads, is_double)"},
    {"lm_round_update", (PyCFunction)(void (*)(void))py_lm_round_update, METH_FASTCALL,
     "a Levenberg-Marquardt round's verdict and bookkeeping per problem (14 pointers, 9 params, n, 5 codes, is_double)"},
    {"set_constants", py_set_constants, METH_VARARGS, "thresholds and series tables from numerics.py"},
    {NULL, NULL, 0, NULL},
};

static struct PyModuleDef module = {PyModuleDef_HEAD_INIT, "_native",
                                    "batched small Cholesky solves, CPU kernels", -1, methods};

PyMODINIT_FUNC PyInit__native(void) {
    find_openmp();
    return PyModule_Create(&module);
}
