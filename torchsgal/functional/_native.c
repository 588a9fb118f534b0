/* torchsgal.functional._native: the SGal(3) exp, log and their backward maps and the SGal(3)
 * TLS linearisation of torchsgal.estimation, as plain C loops (the IMU preintegration kernel is
 * torchsgal.imu._native, built from imu/_native.c on the same shared code).
 *
 * An optional accelerator for CPU eager code (see native.py): one call per batch instead of
 * ~170 dispatched tensor operations, so small batches no longer pay torch's per-operation
 * overhead.  No torch headers: the Python side passes data pointers of contiguous CPU tensors
 * it allocated and checked.  The constants (thresholds, series) are set once from numerics.py,
 * which stays their only source.  Large batches are split over threads (torch's OpenMP threads
 * where its runtime is loaded, else pthreads: run_parallel, in _native_common.h).
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
#define ATAN2 atan2f
#include "_native_sgal3.h"  /* undefines T, SFX and the math macros */

#include "_native_tls.h"  /* the TLS linearisation, in double: uses the f64 kernels above */

/* fn(pointers..., n, threads, is_double) over the batch, the GIL released. */
static PyObject *dispatch(PyObject *const *a, Py_ssize_t nargs, int npointers, range_fn f64, range_fn f32,
                          const char *name) {
    void *ptr[8];
    int64_t ints[3];  /* n, threads, is_double */
    if (read_call(a, nargs, npointers, ptr, 3, ints, name) < 0) return NULL;
    Py_BEGIN_ALLOW_THREADS
    run_parallel(ints[2] ? f64 : f32, ptr, ints[0], 1, (int)ints[1]);
    Py_END_ALLOW_THREADS
    Py_RETURN_NONE;
}

#define WRAP(op, np)                                                                      \
    static PyObject *py_sgal3_##op(PyObject *self, PyObject *const *a, Py_ssize_t nargs) { \
        (void)self;                                                                       \
        return dispatch(a, nargs, np, op##_range_f64, op##_range_f32, "sgal3_" #op);      \
    }
WRAP(exp, 2)
WRAP(log, 2)
WRAP(exp_vjp, 4)
WRAP(log_vjp, 4)

/* tls_sgal3(M, X, Ad_Xinv, a, s, n, e, fa, fb, R, W, G, info, active,
 *           fa_k, fa_n, fb_k, fb_n, diag_a, diag_b, K, N1, threads): see _native_tls.h; e 0
 * (a null pointer) for the paper variant, active 0 for all trials.  float64 only. */
static PyObject *py_tls_sgal3(PyObject *self, PyObject *const *a, Py_ssize_t nargs) {
    (void)self;
    void *ptr[14];
    int64_t ints[9];
    if (read_call(a, nargs, 14, ptr, 9, ints, "tls_sgal3") < 0) return NULL;
    tls_args_t args = {ptr[0], ptr[1], ptr[2], ptr[3], ptr[4], ptr[5], ptr[6], ptr[7], ptr[8],
                       ints[0], ints[1], ints[2], ints[3], (int)ints[4], (int)ints[5],
                       ptr[9], ptr[10], ptr[11], ptr[12], ptr[13], ints[7]};
    /* one condition costs about as much as 32 SGal(3) exps */
    Py_BEGIN_ALLOW_THREADS
    run_parallel(tls_range, (void **)&args, ints[6], 32 * ints[7], (int)ints[8]);
    Py_END_ALLOW_THREADS
    Py_RETURN_NONE;
}

/* tls_sgal3_step(R, W, dx, fa, fb, e, active, fa_k, fa_n, fb_k, fb_n, diag_a, diag_b, K, N1,
 *                threads) */
static PyObject *py_tls_sgal3_step(PyObject *self, PyObject *const *a, Py_ssize_t nargs) {
    (void)self;
    void *ptr[7];
    int64_t ints[9];
    if (read_call(a, nargs, 7, ptr, 9, ints, "tls_sgal3_step") < 0) return NULL;
    tls_step_args_t args = {ptr[0], ptr[1], ptr[2], ptr[3], ptr[4], ints[0], ints[1], ints[2], ints[3],
                            (int)ints[4], (int)ints[5], ptr[5], ptr[6], ints[7]};
    Py_BEGIN_ALLOW_THREADS
    run_parallel(tls_step_range, (void **)&args, ints[6], 4 * ints[7], (int)ints[8]);
    Py_END_ALLOW_THREADS
    Py_RETURN_NONE;
}

static PyMethodDef methods[] = {
    {"parallel_backend", py_parallel_backend, METH_NOARGS, "what splits large batches over threads"},
    {"sgal3_exp", (PyCFunction)(void (*)(void))py_sgal3_exp, METH_FASTCALL, "exp (xi, out, n, threads, is_double)"},
    {"sgal3_log", (PyCFunction)(void (*)(void))py_sgal3_log, METH_FASTCALL, "log (M, out, n, threads, is_double)"},
    {"sgal3_exp_vjp", (PyCFunction)(void (*)(void))py_sgal3_exp_vjp, METH_FASTCALL,
     "exp backward (xi, M, G, out, n, threads, is_double)"},
    {"sgal3_log_vjp", (PyCFunction)(void (*)(void))py_sgal3_log_vjp, METH_FASTCALL,
     "log backward (M, xi, g, out, n, threads, is_double)"},
    {"tls_sgal3", (PyCFunction)(void (*)(void))py_tls_sgal3, METH_FASTCALL,
     "SGal(3) TLS linearisation (see _native_tls.h)"},
    {"tls_sgal3_step", (PyCFunction)(void (*)(void))py_tls_sgal3_step, METH_FASTCALL,
     "SGal(3) TLS residual update (see _native_tls.h)"},
    {"set_constants", py_set_constants, METH_VARARGS, "thresholds and series tables from numerics.py"},
    {NULL, NULL, 0, NULL},
};

static struct PyModuleDef module = {PyModuleDef_HEAD_INIT, "_native", "SGal(3) CPU kernels", -1, methods};

PyMODINIT_FUNC PyInit__native(void) {
    find_openmp();
    return PyModule_Create(&module);
}
