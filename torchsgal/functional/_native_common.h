/* What the C extensions of torchsgal share (included once by each: functional/_native.c and
 * imu/_native.c, every definition static to its module): the includes, the thresholds and series
 * (each module holds its own copy, set from numerics.py by native.set_constants), the splitting
 * of a batch over threads (run_parallel), the reading of a call's arguments (read_call), the
 * call of a batch loop with the GIL released (dispatch) and the
 * module functions set_constants and parallel_backend.  Include it before _native_sgal3.h.
 */
#ifndef TORCHSGAL_NATIVE_COMMON_H
#define TORCHSGAL_NATIVE_COMMON_H
#define PY_SSIZE_T_CLEAN
#include <Python.h>
#include <math.h>
#include <stdint.h>
#include <stdlib.h>
#include <string.h>
#ifndef _WIN32
#include <dlfcn.h>
#include <pthread.h>
#include <sched.h>
#include <time.h>
#endif

/* Loops worth vectorising wider than SSE2 get an AVX2 clone, picked at load time by the CPU
 * (GCC/Clang function multi-versioning, x86-64 with ifunc support).  No FMA contraction
 * (-ffp-contract=off): both clones round alike, element for element. */
#if defined(__x86_64__) && defined(__GNUC__) && defined(__linux__) && !defined(TORCHSGAL_NO_CLONES)
#define WIDE_LOOPS __attribute__((target_clones("avx2", "default")))
/* WIDE_TARGET: AVX2 for one of two versions of a function, the caller picking it where wide_cpu() */
#define WIDE_TARGET __attribute__((target("avx2")))
static inline int wide_cpu(void) { return __builtin_cpu_supports("avx2"); }
#else
#define WIDE_LOOPS
#endif

/* VEC4: GCC/Clang's vector of four entries of the element type, picked by the suffix SFX in force
 * where it is used (vec4_f64, vec4_f32); UNROLL: a short loop unrolled in full (GCC/Clang) */
#if defined(__GNUC__)
typedef double vec4_f64 __attribute__((vector_size(4 * sizeof(double))));
typedef float vec4_f32 __attribute__((vector_size(4 * sizeof(float))));
#define VEC4_(sfx) vec4_##sfx
#define VEC4__(sfx) VEC4_(sfx)
#define VEC4 VEC4__(SFX)
#define UNROLL _Pragma("GCC unroll 16")
#else
#define UNROLL
#endif

/* c ? a : b by masks on the bits (compilers branch on a float select, and a branch on data
 * is mispredicted half the time) */
static inline float select_f32(int c, float a, float b) {
    uint32_t ua, ub, m = (uint32_t)0 - (uint32_t)(c != 0);
    memcpy(&ua, &a, 4);
    memcpy(&ub, &b, 4);
    ub = (ua & m) | (ub & ~m);
    memcpy(&b, &ub, 4);
    return b;
}

/* atan2 for float32 (the kernels' ATAN2 there): glibc's atan2f costs 15-18 ns a call, most of an
 * SO(3) log.  Cephes' atanf (range reduction to |a| <= tan(pi/8), a degree-4 polynomial in a^2;
 * relative error below 3e-7) on min/max(|x|, |y|), then the octant and quadrant, chosen without
 * branches (select_f32), and one division.  NaN in, NaN out; infinite and huge arguments as libm.
 * Float64 keeps libm's atan2.  atan2_f32_reduced is its branch-free part, on the reduced
 * arguments mx = max(|x|, |y|) (finite, at most 1e38), mn = min(|x|, |y|) and swap = |y| > |x|:
 * it vectorises in a loop over lanes (_native_lanes_f32.h). */
static inline float atan2_f32_reduced(float y, float x, float mx, float mn, int swap) {
    const int big = mn > 0.4142135623730950f * mx;  /* mn / mx > tan(pi/8) */
    const float num = select_f32(big, mn - mx, mn), den = select_f32(big, mn + mx, mx);
    const float a = num / select_f32(den > 0.0f, den, 1.0f), z = a * a;
    float r = ((((8.05374449538e-2f * z - 1.38776856032e-1f) * z + 1.99777106478e-1f) * z
               - 3.33329491539e-1f) * z * a + a) + select_f32(big, 0.7853981633974483f, 0.0f);
    r = select_f32(swap, 1.5707963267948966f - r, r);
    r = select_f32(signbit(x) != 0, 3.1415926535897932f - r, r);
    r = copysignf(r, y);
    return select_f32((x != x) | (y != y), x + y, r);
}

static inline float atan2_f32(float y, float x) {
    const float ax = fabsf(x), ay = fabsf(y);
    const int swap = ay > ax;
    float mx = select_f32(swap, ay, ax), mn = select_f32(swap, ax, ay);
    if (mx == INFINITY) {  /* rare: the ratio by hand (inf / inf is NaN) */
        mn = mn == INFINITY ? 1.0f : 0.0f;
        mx = 1.0f;
    }
    if (mx > 1.0e38f) {  /* rare (a predictable branch): mn + mx stays finite */
        mx *= 0.25f;
        mn *= 0.25f;
    }
    return atan2_f32_reduced(y, x, mx, mn, swap);
}

#define MAX_TERMS 32
static int TAYLOR_TERMS = 0;
static double TAYLOR_C3[MAX_TERMS], TAYLOR_C4[MAX_TERMS], TAYLOR_C5[MAX_TERMS], TAYLOR_C6[MAX_TERMS];
static double INV_FACT[8];
static int N_BERNOULLI = 0;
static double BERNOULLI[MAX_TERMS];
static double SERIES_THRESHOLD, JINV_THRESHOLD, LOG_SYMMETRIC_COS, LOG_SIN_TAYLOR;
/* Sim(3)'s scale moments and series (numerics.scale_moments, sim3_coefficients); 1/j! to j = 32. */
#define MAX_MOMENT_ORDER 30
static double INV_FACT_LONG[MAX_MOMENT_ORDER + 3];
static double SCALE_UPWARD_MARGIN, SIM3_SERIES_THRESHOLD, SIM3_NORMALISE;
static int SCALE_EXTRA_ORDERS, SCALE_TAYLOR_TERMS, SIM3_SERIES_TERMS;

typedef void (*range_fn)(void **args, int64_t lo, int64_t hi);

/* Batch loops over [lo, hi) of the per-element kernels, for the including header's K() (its
 * scalar type's suffix): the one-argument maps, one(in + in_size i, out + out_size i), and the
 * Jacobians, group_jl_one(xi + dof i, inverse, out + dof^2 i). */
#define RANGE(name, one, in_size, out_size)                                               \
    static void K(name##_range)(void **a, int64_t lo, int64_t hi) {                      \
        const T *in = a[0];                                                               \
        T *out = a[1];                                                                    \
        for (int64_t i = lo; i < hi; ++i) K(one)(in + (in_size) * i, out + (out_size) * i); \
    }
#define JACOBIAN_RANGE(group, dof, inverse, name)                                        \
    static void K(name##_range)(void **a, int64_t lo, int64_t hi) {                      \
        const T *xi = a[0];                                                               \
        T *out = a[1];                                                                    \
        for (int64_t i = lo; i < hi; ++i)                                                 \
            K(group##_jl_one)(xi + (dof) * i, inverse, out + (dof) * (dof) * i);          \
    }

#define MAX_THREADS 64
/* Work per thread (elements times their cost) below which a batch runs on the calling thread. */
#define MIN_PER_THREAD 8192

/* torch's own OpenMP threads, where its runtime is loaded (libgomp, or LLVM's libomp with the
 * same entry point): work split over them does not compete with their spin-wait after torch's
 * last parallel operation, as fresh pthreads do (they cost a batched solve about 7% of its
 * time in libgomp's spin).  Looked up once, at import (after torch's);
 * TORCHSGAL_NATIVE_OPENMP=0 in the environment keeps pthreads. */
typedef void (*gomp_parallel_fn)(void (*)(void *), void *, unsigned, unsigned);
static gomp_parallel_fn gomp_parallel = NULL;

static void find_openmp(void) {
#ifndef _WIN32
    const char *off = getenv("TORCHSGAL_NATIVE_OPENMP");
    if (off && strcmp(off, "0") == 0) return;  /* pthreads instead */
    const char *names[] = {"libgomp.so.1", "libomp.so", "libomp.dylib", "libiomp5.so", NULL};
    for (int i = 0; names[i]; ++i) {
        void *h = dlopen(names[i], RTLD_LAZY | RTLD_NOLOAD);
        if (!h) continue;
        gomp_parallel = (gomp_parallel_fn)dlsym(h, "GOMP_parallel");
        if (gomp_parallel) return;
    }
#endif
}

/* A batch split over threads is handed out in chunks from a shared counter (about
 * CHUNKS_PER_THREAD per thread): a thread that loses its core to another process takes fewer
 * chunks and the others take the rest, so a call waits at most for the chunk in hand of the
 * slowest thread, not for a fixed share of the batch (a collapse on a shared machine).  Every
 * item is computed alone, so the split does not change any result. */
#define CHUNKS_PER_THREAD 8

#ifndef _WIN32
/* The pthreads backend: a pool of helper threads that sleep between calls.  A call publishes its
 * job (a new generation); the helpers that wake in time take chunks alongside the calling thread,
 * which takes chunks until none is left and then waits only for the chunks already taken.  A
 * helper that has not woken by then (its core taken by another process) finds the job over and
 * takes nothing: a call never waits for a thread that never ran, so a lost core costs its share
 * and no more.  A chunk is claimed by one compare-and-swap of a word holding the generation and
 * the next index, so a late helper cannot take a chunk of a later job with an earlier job's
 * arguments. */
#define GEN_SHIFT 32  /* 2^32 jobs before a generation tag repeats, batches below 2^32 items */
#define INDEX_MASK ((((uint64_t)1) << GEN_SHIFT) - 1)

typedef struct {
    pthread_mutex_t busy;  /* held by the calling thread of the job in progress */
    pthread_mutex_t lock;
    pthread_cond_t wake;
    uint64_t generation;   /* of the job published last (written under lock, atomic) */
    range_fn fn;           /* the job (under lock) */
    void **args;
    int64_t n, chunk;
    int helpers_wanted;    /* helpers that may take part in the job */
    uint64_t word;         /* generation << GEN_SHIFT | next index (atomic) */
    int64_t done;          /* items finished (atomic) */
    int tickets;           /* helpers that joined the job (atomic) */
    int helpers;           /* helper threads started */
} pool_t;

static pool_t pool = {PTHREAD_MUTEX_INITIALIZER, PTHREAD_MUTEX_INITIALIZER, PTHREAD_COND_INITIALIZER,
                      0, NULL, NULL, 0, 0, 0, 0, 0, 0, 0};

/* Takes chunks of generation ``gen`` until none is left; returns the items it finished. */
static int64_t pool_take(uint64_t gen, range_fn fn, void **args, int64_t n, int64_t chunk) {
    int64_t finished = 0;
    uint64_t tag = (gen & (UINT64_MAX >> GEN_SHIFT)) << GEN_SHIFT;
    for (;;) {
        uint64_t w = __atomic_load_n(&pool.word, __ATOMIC_ACQUIRE);
        if ((w & ~INDEX_MASK) != tag) return finished;  /* a later job: this one is over */
        int64_t lo = (int64_t)(w & INDEX_MASK);
        if (lo >= n) return finished;
        int64_t hi = lo + chunk < n ? lo + chunk : n;
        if (!__atomic_compare_exchange_n(&pool.word, &w, tag | (uint64_t)hi, 0, __ATOMIC_ACQ_REL,
                                         __ATOMIC_ACQUIRE))
            continue;
        fn(args, lo, hi);
        __atomic_add_fetch(&pool.done, hi - lo, __ATOMIC_RELEASE);
        finished += hi - lo;
    }
}

/* After a job a helper watches for the next one for SPIN_NS before it sleeps (back-to-back calls
 * find it awake, as torch's OpenMP threads spin after a parallel region). */
#define SPIN_NS 100000

static int64_t now_ns(void) {
    struct timespec t;
    clock_gettime(CLOCK_MONOTONIC, &t);
    return (int64_t)t.tv_sec * 1000000000 + t.tv_nsec;
}

/* A helper started before the job of generation ``before`` + 1 is published takes part in it. */
static void *pool_helper(void *before) {
    uint64_t seen = (uint64_t)(uintptr_t)before;
    for (;;) {
        int64_t until = now_ns() + SPIN_NS;
        for (int i = 1; __atomic_load_n(&pool.generation, __ATOMIC_ACQUIRE) == seen; ++i) {
#if defined(__x86_64__) || defined(__i386__)
            __builtin_ia32_pause();
#endif
            if (i % 256 == 0 && now_ns() > until) break;
        }
        pthread_mutex_lock(&pool.lock);
        while (pool.generation == seen) pthread_cond_wait(&pool.wake, &pool.lock);
        seen = pool.generation;
        range_fn fn = pool.fn;
        void **args = pool.args;
        int64_t n = pool.n, chunk = pool.chunk;
        int wanted = pool.helpers_wanted;
        pthread_mutex_unlock(&pool.lock);
        if (__atomic_fetch_add(&pool.tickets, 1, __ATOMIC_RELAXED) < wanted)
            pool_take(seen, fn, args, n, chunk);
    }
    return NULL;
}

/* After fork() the child has no helper threads: it starts its own when it needs them. */
static void pool_after_fork(void) {
    pthread_mutex_init(&pool.busy, NULL);
    pthread_mutex_init(&pool.lock, NULL);
    pthread_cond_init(&pool.wake, NULL);
    pool.helpers = 0;
}

/* The job on the pool; a call made while another thread's job runs runs on its own thread. */
static void pool_run(range_fn fn, void **args, int64_t n, int64_t chunk, int threads) {
    static int registered = 0;
    if (pthread_mutex_trylock(&pool.busy) != 0) {
        fn(args, 0, n);
        return;
    }
    pthread_mutex_lock(&pool.lock);
    if (!registered) {
        pthread_atfork(NULL, NULL, pool_after_fork);
        registered = 1;
    }
    while (pool.helpers < threads - 1) {  /* helpers are started once and kept */
        pthread_t tid;
        pthread_attr_t attr;
        pthread_attr_init(&attr);
        pthread_attr_setdetachstate(&attr, PTHREAD_CREATE_DETACHED);
        int failed = pthread_create(&tid, &attr, pool_helper, (void *)(uintptr_t)pool.generation);
        pthread_attr_destroy(&attr);
        if (failed) break;
        pool.helpers++;
    }
    uint64_t gen = pool.generation + 1;
    pool.fn = fn;
    pool.args = args;
    pool.n = n;
    pool.chunk = chunk;
    pool.helpers_wanted = threads - 1;
    __atomic_store_n(&pool.tickets, 0, __ATOMIC_RELAXED);
    __atomic_store_n(&pool.done, 0, __ATOMIC_RELAXED);
    __atomic_store_n(&pool.word, (gen & (UINT64_MAX >> GEN_SHIFT)) << GEN_SHIFT, __ATOMIC_RELEASE);
    __atomic_store_n(&pool.generation, gen, __ATOMIC_RELEASE);  /* the job, for spinning helpers */
    pthread_cond_broadcast(&pool.wake);
    pthread_mutex_unlock(&pool.lock);
    pool_take(gen, fn, args, n, chunk);  /* all of the chunks where no helper wakes in time */
    while (__atomic_load_n(&pool.done, __ATOMIC_ACQUIRE) < n) sched_yield();  /* chunks in hand */
    pthread_mutex_unlock(&pool.busy);
}
#endif

typedef struct {
    range_fn fn;
    void **args;
    int64_t n, chunk;
    int64_t next;  /* the first item not yet handed out (atomic) */
} shared_job_t;

#ifndef _WIN32
static void take_chunks_openmp(void *p) {
    shared_job_t *j = p;
    for (;;) {
        int64_t lo = __atomic_fetch_add(&j->next, j->chunk, __ATOMIC_RELAXED);
        if (lo >= j->n) return;
        j->fn(j->args, lo, lo + j->chunk < j->n ? lo + j->chunk : j->n);
    }
}
#endif

/* fn over [0, n) split over up to ``threads`` threads (torch's OpenMP threads, else the pool);
 * ``cost`` is the work of one item in units of one SGal(3) exp (1 for the group kernels, the
 * samples of a window for the IMU). */
static void run_parallel(range_fn fn, void **args, int64_t n, int64_t cost, int threads) {
#ifndef _WIN32
    if (threads > MAX_THREADS) threads = MAX_THREADS;
    if (!gomp_parallel && n >= (int64_t)INDEX_MASK) threads = 1;  /* beyond the pool's index */
    if (threads > n) threads = (int)n;
    if (threads > 1 && n / threads * cost >= MIN_PER_THREAD) {
        int64_t chunk = (n + threads * CHUNKS_PER_THREAD - 1) / (threads * CHUNKS_PER_THREAD);
        if (gomp_parallel) {
            shared_job_t job = {fn, args, n, chunk, 0};
            gomp_parallel(take_chunks_openmp, &job, (unsigned)threads, 0);
            return;
        }
        pool_run(fn, args, n, chunk, threads);
        return;
    }
#endif
    fn(args, 0, n);
}

/* Reads a call's ``np`` pointers (addresses of contiguous tensors, or 0) and then ``ni`` integers
 * (a bool reads as 0 or 1) into ptr and ints; -1 with a Python exception set on failure. */
static int read_call(PyObject *const *a, Py_ssize_t nargs, int np, void **ptr, int ni, int64_t *ints,
                     const char *name) {
    if (nargs != np + ni) {
        PyErr_Format(PyExc_TypeError, "%s takes %d arguments", name, np + ni);
        return -1;
    }
    if (TAYLOR_TERMS == 0) {
        PyErr_SetString(PyExc_RuntimeError, "torchsgal native kernels used before set_constants");
        return -1;
    }
    for (int i = 0; i < np; ++i) {
        ptr[i] = PyLong_AsVoidPtr(a[i]);
        if (ptr[i] == NULL && PyErr_Occurred()) return -1;
    }
    for (int i = 0; i < ni; ++i) ints[i] = PyLong_AsLongLong(a[np + i]);
    return PyErr_Occurred() ? -1 : 0;
}

static int read_table(PyObject *seq, double *out, int cap, const char *name) {
    PyObject *fast = PySequence_Fast(seq, name);
    if (!fast) return -1;
    Py_ssize_t len = PySequence_Fast_GET_SIZE(fast);
    if (len < 1 || len > cap) {
        Py_DECREF(fast);
        PyErr_Format(PyExc_ValueError, "%s: %zd entries, expected 1 to %d", name, len, cap);
        return -1;
    }
    for (Py_ssize_t i = 0; i < len; ++i) out[i] = PyFloat_AsDouble(PySequence_Fast_GET_ITEM(fast, i));
    Py_DECREF(fast);
    return PyErr_Occurred() ? -1 : (int)len;
}

/* fn(pointers..., n, threads, is_double) over the batch, the GIL released; at most 8 pointers,
 * ``cost`` as run_parallel's. */
static inline PyObject *dispatch(PyObject *const *a, Py_ssize_t nargs, int npointers, range_fn f64,
                                 range_fn f32, int64_t cost, const char *name) {
    void *ptr[8];
    int64_t ints[3]; /* n, threads, is_double */
    if (read_call(a, nargs, npointers, ptr, 3, ints, name) < 0) return NULL;
    Py_BEGIN_ALLOW_THREADS
    run_parallel(ints[2] ? f64 : f32, ptr, ints[0], cost, (int)ints[1]);
    Py_END_ALLOW_THREADS
    Py_RETURN_NONE;
}

/* set_constants(series_threshold, jinv_threshold, log_symmetric_cos, log_sin_taylor,
 *               taylor_c3, taylor_c4, taylor_c5, taylor_c6, inv_fact, bernoulli,
 *               scale_upward_margin, scale_extra_orders, scale_taylor_terms,
 *               sim3_series_threshold, sim3_series_terms, sim3_normalise, inv_fact_long) */
static PyObject *py_set_constants(PyObject *self, PyObject *args) {
    (void)self;
    PyObject *t3, *t4, *t5, *t6, *inv_fact, *bern, *inv_fact_long;
    double st, jt, lsc, lst, margin, sim3_threshold, sim3_normalise;
    int extra, taylor, sim3_terms;
    if (!PyArg_ParseTuple(args, "ddddOOOOOOdiididO", &st, &jt, &lsc, &lst, &t3, &t4, &t5, &t6, &inv_fact, &bern,
                          &margin, &extra, &taylor, &sim3_threshold, &sim3_terms, &sim3_normalise, &inv_fact_long))
        return NULL;
    int n3 = read_table(t3, TAYLOR_C3, MAX_TERMS, "taylor_c3"), n4 = read_table(t4, TAYLOR_C4, MAX_TERMS, "taylor_c4");
    int n5 = read_table(t5, TAYLOR_C5, MAX_TERMS, "taylor_c5"), n6 = read_table(t6, TAYLOR_C6, MAX_TERMS, "taylor_c6");
    int nf = read_table(inv_fact, INV_FACT, 8, "inv_fact"), nb = read_table(bern, BERNOULLI, MAX_TERMS, "bernoulli");
    int nl = read_table(inv_fact_long, INV_FACT_LONG, MAX_MOMENT_ORDER + 3, "inv_fact_long");
    if (n3 < 0 || n4 < 0 || n5 < 0 || n6 < 0 || nf < 0 || nb < 0 || nl < 0) return NULL;
    if (n3 != n4 || n3 != n5 || n3 != n6 || nf < 7) {
        PyErr_SetString(PyExc_ValueError, "the Taylor tables must have equal lengths and inv_fact 7 entries");
        return NULL;
    }
    if (sim3_terms < 1 || 2 * sim3_terms + 2 > MAX_MOMENT_ORDER || nl != MAX_MOMENT_ORDER + 3 || extra < 0 || taylor < 0) {
        PyErr_Format(PyExc_ValueError, "the Sim(3) series: at most %d terms and %d inverse factorials",
                     MAX_MOMENT_ORDER / 2 - 1, MAX_MOMENT_ORDER + 3);
        return NULL;
    }
    SERIES_THRESHOLD = st;
    JINV_THRESHOLD = jt;
    LOG_SYMMETRIC_COS = lsc;
    LOG_SIN_TAYLOR = lst;
    N_BERNOULLI = nb;
    TAYLOR_TERMS = n3;
    SCALE_UPWARD_MARGIN = margin;
    SCALE_EXTRA_ORDERS = extra;
    SCALE_TAYLOR_TERMS = taylor;
    SIM3_SERIES_THRESHOLD = sim3_threshold;
    SIM3_SERIES_TERMS = sim3_terms;
    SIM3_NORMALISE = sim3_normalise;
    Py_RETURN_NONE;
}

/* parallel_backend(): "openmp" (torch's OpenMP threads), "pthreads" or "none" (Windows). */
static PyObject *py_parallel_backend(PyObject *self, PyObject *unused) {
    (void)self;
    (void)unused;
#ifdef _WIN32
    return PyUnicode_FromString("none");
#else
    return PyUnicode_FromString(gomp_parallel ? "openmp" : "pthreads");
#endif
}

#endif /* TORCHSGAL_NATIVE_COMMON_H */
