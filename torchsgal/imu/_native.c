/* torchsgal.imu._native: the Galilean IMU preintegration of torchsgal.imu as a plain C loop, one
 * window at a time (_native_imu.h), registered as the CPU kernel of the torch operator
 * torchsgal::imu_preintegrate (imu/_kernels.py).
 *
 * No torch headers: the Python side passes data pointers of contiguous CPU tensors it allocated
 * and checked.  It shares the threads, the argument reading and the constants (set from
 * numerics.py by functional/native.py's set_constants) with the core kernels, and takes the
 * float64 SGal(3) closed forms from functional/_native_sgal3.h.
 */
#include "../functional/_native_common.h"

#if defined(__GNUC__)
#pragma GCC diagnostic push
#pragma GCC diagnostic ignored "-Wunused-function"  /* only exp's coefficients are used here */
#endif
#define T double
#define SFX f64
#define SIN sin
#define COS cos
#define SQRT sqrt
#define ATAN2 atan2
#include "../functional/_native_sgal3.h"  /* undefines T, SFX and the math macros */
#if defined(__GNUC__)
#pragma GCC diagnostic pop
#endif

#include "_native_imu.h"

/* imu_preintegrate(gyro, acc, dt, b_g, b_a, delta, moments, n, K, threads, is_double): n windows
 * of K samples (_native_imu.h); moments 0 (a null pointer) for the increment only. */
static PyObject *py_imu_preintegrate(PyObject *self, PyObject *const *a, Py_ssize_t nargs) {
    (void)self;
    void *ptr[7];
    int64_t ints[4];  /* n, K, threads, is_double */
    if (read_call(a, nargs, 7, ptr, 4, ints, "imu_preintegrate") < 0) return NULL;
    if (ints[1] < 1) {
        PyErr_SetString(PyExc_ValueError, "imu_preintegrate needs K >= 1 samples per window");
        return NULL;
    }
    imu_args_t args = {ptr[0], ptr[1], ptr[2], ptr[3], ptr[4], ptr[5], ptr[6], ints[1]};
    Py_BEGIN_ALLOW_THREADS
    run_parallel(ints[3] ? imu_range_f64 : imu_range_f32, (void **)&args, ints[0], ints[1], (int)ints[2]);
    Py_END_ALLOW_THREADS
    Py_RETURN_NONE;
}

static PyMethodDef methods[] = {
    {"parallel_backend", py_parallel_backend, METH_NOARGS, "what splits large batches over threads"},
    {"imu_preintegrate", (PyCFunction)(void (*)(void))py_imu_preintegrate, METH_FASTCALL,
     "IMU windows (gyro, acc, dt, b_g, b_a, delta, moments, n, K, threads, is_double)"},
    {"set_constants", py_set_constants, METH_VARARGS, "thresholds and series tables from numerics.py"},
    {NULL, NULL, 0, NULL},
};

static struct PyModuleDef module = {PyModuleDef_HEAD_INIT, "_native", "IMU preintegration CPU kernel", -1,
                                    methods};

PyMODINIT_FUNC PyInit__native(void) {
    find_openmp();
    return PyModule_Create(&module);
}
