/* torchsgal.functional._native: the SGal(3) exp, log, their backward maps and Jacobians, and the
 * exp, log and Jacobians of its subgroups SO(3), SE(3) and SE_2(3), of SE(2) (_native_se2.h) and
 * of Sim(3) (_native_sim3.h, with its inverse and adjoint), the products of these six groups and
 * the inverses and adjoints of SGal(3), SE(3) and SE_2(3) (_native_products.h), as plain C loops:
 * the CPU implementations of the operators torchsgal::sgal3_*, so3_*, se2_*, se3_*, se23_* and
 * sim3_* (functional/ops.py), and x @ W + c over a batch of small matrices (_native_affine.h:
 * torchsgal::affine_rows, functional/affine.py; the IMU
 * preintegration kernel is torchsgal.imu._native, built from imu/_native.c on the same code).
 *
 * An optional accelerator for CPU eager code (see native.py): one call per batch instead of
 * ~170 dispatched tensor operations, so small batches do not pay torch's per-operation
 * overhead.  No torch headers: the Python side passes data pointers of contiguous CPU tensors
 * it allocated and checked.  The constants (thresholds, series) are set once from numerics.py,
 * which stays their only source.  Large batches are split over threads (torch's OpenMP threads
 * where its runtime is loaded, else a pool of POSIX threads: run_parallel, in _native_common.h).
 */
#include "_native_common.h"  /* includes, constants, threads, argument reading */

#define T double
#define SFX f64
#define SIN sin
#define COS cos
#define SQRT sqrt
#define ATAN2 atan2
#include "_native_sgal3.h"  /* undefines T, SFX and the math macros */

#define T float
#define SFX f32
#define SIN sinf
#define COS cosf
#define SQRT sqrtf
#define ATAN2 atan2_f32
#include "_native_sgal3.h"  /* undefines T, SFX and the math macros */
#include "_native_lanes_f32.h"  /* SO(3) log over lanes, on the float32 loops above */

#define T double
#define SFX f64
#define ATAN2 atan2
#include "_native_se2.h"  /* undefines T, SFX and ATAN2 */
#define T float
#define SFX f32
#define ATAN2 atan2_f32
#include "_native_se2.h"

#define T double
#define SFX f64
#define SIN sin
#define SQRT sqrt
#define EXP exp
#define EXPM1 expm1
#define LOG log
#define FABS fabs
#include "_native_sim3.h"  /* undefines T, SFX and the math macros */
#define T float
#define SFX f32
#define SIN sinf
#define SQRT sqrtf
#define EXP expf
#define EXPM1 expm1f
#define LOG logf
#define FABS fabsf
#include "_native_sim3.h"

#define T double
#define SFX f64
#include "_native_products.h"  /* compose, inverse and adjoint; undefines T and SFX */
#define T float
#define SFX f32
#include "_native_products.h"

#define T double
#define SFX f64
#include "_native_affine.h"  /* rows times a small matrix; undefines T and SFX */
#define T float
#define SFX f32
#include "_native_affine.h"

/* affine_rows(x, W, c or 0, out, dims, B, threads, is_double): dims {N, k, m, Bx} (int64) */
static PyObject *py_affine_rows(PyObject *self, PyObject *const *a, Py_ssize_t nargs) {
    (void)self;
    void *ptr[5];
    int64_t ints[3]; /* B, threads, is_double */
    if (read_call(a, nargs, 5, ptr, 3, ints, "affine_rows") < 0) return NULL;
    const int64_t *d = (const int64_t *)ptr[4];
    if (d[1] < 1 || d[2] < 1 || d[2] > AF_MAX_M || d[3] < 1 || ints[0] % d[3] != 0) {
        PyErr_Format(PyExc_ValueError, "affine_rows: k must be at least 1, m in [1, %d] and x's batch "
                     "a divisor of B = %lld, got k = %lld, m = %lld, x's batch %lld", AF_MAX_M,
                     (long long)ints[0], (long long)d[1], (long long)d[2], (long long)d[3]);
        return NULL;
    }
    const int64_t cost = d[0] * d[1] * d[2] / 400 + 1;  /* in units of one SGal(3) exp */
    Py_BEGIN_ALLOW_THREADS
    run_parallel(ints[2] ? affine_rows_for_f64(d[2]) : affine_rows_for_f32(d[2]), ptr, ints[0], cost, (int)ints[1]);
    Py_END_ALLOW_THREADS
    Py_RETURN_NONE;
}

#define WRAP(op, np)                                                                      \
    static PyObject *py_sgal3_##op(PyObject *self, PyObject *const *a, Py_ssize_t nargs) { \
        (void)self;                                                                       \
        return dispatch(a, nargs, np, op##_range_f64, op##_range_f32, 1, "sgal3_" #op);      \
    }
WRAP(exp, 2)
WRAP(log, 2)
WRAP(exp_vjp, 4)
WRAP(log_vjp, 4)
WRAP(jl, 2)
WRAP(jl_inv, 2)

/* The subgroups' one-argument kernels (xi or M -> out). */
#define WRAP_SUB(op)                                                                      \
    static PyObject *py_##op(PyObject *self, PyObject *const *a, Py_ssize_t nargs) {     \
        (void)self;                                                                       \
        return dispatch(a, nargs, 2, op##_range_f64, op##_range_f32, 1, #op);                \
    }
WRAP_SUB(sim3_exp)
WRAP_SUB(sim3_log)
WRAP_SUB(sim3_jl)
WRAP_SUB(sim3_jl_inv)
WRAP_SUB(sim3_inverse)
WRAP_SUB(sim3_adjoint)
WRAP_SUB(se2_exp)
WRAP_SUB(se2_log)
WRAP_SUB(se2_jl)
WRAP_SUB(se2_jl_inv)
WRAP_SUB(so3_exp)
static PyObject *py_so3_log(PyObject *self, PyObject *const *a, Py_ssize_t nargs) {
    (void)self;  /* float32 over lanes (_native_lanes_f32.h): the same bits as so3_log_range_f32 */
    return dispatch(a, nargs, 2, so3_log_range_f64, so3_log_lanes_range_f32, 1, "so3_log");
}
WRAP_SUB(so3_jl)
WRAP_SUB(so3_jl_inv)
WRAP_SUB(se3_exp)
WRAP_SUB(se3_log)
WRAP_SUB(se3_jl)
WRAP_SUB(se3_jl_inv)
WRAP_SUB(se23_exp)
WRAP_SUB(se23_log)
WRAP_SUB(se23_jl)
WRAP_SUB(se23_jl_inv)
WRAP_SUB(sgal3_adjoint)
WRAP_SUB(se3_adjoint)
WRAP_SUB(se23_adjoint)
WRAP_SUB(sgal3_inverse)
WRAP_SUB(se3_inverse)
WRAP_SUB(se23_inverse)

/* The products A B of n x n group matrices (A, B, out, n, threads, is_double). */
#define WRAP_COMPOSE(group, n)                                                             \
    static PyObject *py_##group##_compose(PyObject *self, PyObject *const *a, Py_ssize_t nargs) { \
        (void)self;                                                                        \
        return dispatch(a, nargs, 3, compose##n##_range_f64, compose##n##_range_f32, 1,     \
                        #group "_compose");                                                \
    }
WRAP_COMPOSE(so3, 3)
WRAP_COMPOSE(se2, 3)
WRAP_COMPOSE(sgal3, 5)
WRAP_COMPOSE(se3, 4)
WRAP_COMPOSE(sim3, 4)
WRAP_COMPOSE(se23, 5)

static PyMethodDef methods[] = {
    {"parallel_backend", py_parallel_backend, METH_NOARGS, "what splits large batches over threads"},
    {"sgal3_exp", (PyCFunction)(void (*)(void))py_sgal3_exp, METH_FASTCALL, "exp (xi, out, n, threads, is_double)"},
    {"sgal3_log", (PyCFunction)(void (*)(void))py_sgal3_log, METH_FASTCALL, "log (M, out, n, threads, is_double)"},
    {"sgal3_exp_vjp", (PyCFunction)(void (*)(void))py_sgal3_exp_vjp, METH_FASTCALL,
     "exp backward (xi, M, G, out, n, threads, is_double)"},
    {"sgal3_log_vjp", (PyCFunction)(void (*)(void))py_sgal3_log_vjp, METH_FASTCALL,
     "log backward (M, xi, g, out, n, threads, is_double)"},
    {"sgal3_jl", (PyCFunction)(void (*)(void))py_sgal3_jl, METH_FASTCALL, "J_l (xi, out, n, threads, is_double)"},
    {"sgal3_jl_inv", (PyCFunction)(void (*)(void))py_sgal3_jl_inv, METH_FASTCALL,
     "J_l^-1 (xi, out, n, threads, is_double)"},
#define SUB_ENTRY(op, doc) {#op, (PyCFunction)(void (*)(void))py_##op, METH_FASTCALL, doc " (in, out, n, threads, is_double)"},
    SUB_ENTRY(sim3_exp, "Sim(3) exp") SUB_ENTRY(sim3_log, "Sim(3) log")
    SUB_ENTRY(sim3_jl, "Sim(3) J_l") SUB_ENTRY(sim3_jl_inv, "Sim(3) J_l^-1")
    SUB_ENTRY(sim3_inverse, "Sim(3) inverse") SUB_ENTRY(sim3_adjoint, "Sim(3) adjoint")
    SUB_ENTRY(se2_exp, "SE(2) exp") SUB_ENTRY(se2_log, "SE(2) log")
    SUB_ENTRY(se2_jl, "SE(2) J_l") SUB_ENTRY(se2_jl_inv, "SE(2) J_l^-1")
    SUB_ENTRY(so3_exp, "SO(3) exp") SUB_ENTRY(so3_log, "SO(3) log")
    SUB_ENTRY(so3_jl, "SO(3) J_l") SUB_ENTRY(so3_jl_inv, "SO(3) J_l^-1")
    SUB_ENTRY(se3_exp, "SE(3) exp") SUB_ENTRY(se3_log, "SE(3) log")
    SUB_ENTRY(se3_jl, "SE(3) J_l") SUB_ENTRY(se3_jl_inv, "SE(3) J_l^-1")
    SUB_ENTRY(se23_exp, "SE_2(3) exp") SUB_ENTRY(se23_log, "SE_2(3) log")
    SUB_ENTRY(se23_jl, "SE_2(3) J_l") SUB_ENTRY(se23_jl_inv, "SE_2(3) J_l^-1")
    SUB_ENTRY(sgal3_adjoint, "SGal(3) adjoint") SUB_ENTRY(se3_adjoint, "SE(3) adjoint")
    SUB_ENTRY(se23_adjoint, "SE_2(3) adjoint")
    SUB_ENTRY(sgal3_inverse, "SGal(3) inverse") SUB_ENTRY(se3_inverse, "SE(3) inverse")
    SUB_ENTRY(se23_inverse, "SE_2(3) inverse")
    {"sgal3_compose", (PyCFunction)(void (*)(void))py_sgal3_compose, METH_FASTCALL,
     "SGal(3) product (A, B, out, n, threads, is_double)"},
    {"so3_compose", (PyCFunction)(void (*)(void))py_so3_compose, METH_FASTCALL,
     "SO(3) product (A, B, out, n, threads, is_double)"},
    {"se2_compose", (PyCFunction)(void (*)(void))py_se2_compose, METH_FASTCALL,
     "SE(2) product (A, B, out, n, threads, is_double)"},
    {"se3_compose", (PyCFunction)(void (*)(void))py_se3_compose, METH_FASTCALL,
     "SE(3) product (A, B, out, n, threads, is_double)"},
    {"sim3_compose", (PyCFunction)(void (*)(void))py_sim3_compose, METH_FASTCALL,
     "Sim(3) product (A, B, out, n, threads, is_double)"},
    {"se23_compose", (PyCFunction)(void (*)(void))py_se23_compose, METH_FASTCALL,
     "SE_2(3) product (A, B, out, n, threads, is_double)"},
#undef SUB_ENTRY
    {"affine_rows", (PyCFunction)(void (*)(void))py_affine_rows, METH_FASTCALL,
     "c + x W over a batch (x, W, c or 0, out, dims, B, threads, is_double)"},
    {"set_constants", py_set_constants, METH_VARARGS, "thresholds and series tables from numerics.py"},
    {NULL, NULL, 0, NULL},
};

static struct PyModuleDef module = {PyModuleDef_HEAD_INIT, "_native", "SGal(3), SO(3), SE(2), SE(3), SE_2(3) and Sim(3) CPU kernels", -1, methods};

PyMODINIT_FUNC PyInit__native(void) {
    find_openmp();
    return PyModule_Create(&module);
}
