/* Threads that keep this process's other cores awake while a lone model run spreads over them
 * (service/infra/keep_awake.py). Each runs at the lowest priority (SCHED_IDLE), sleeps on a futex
 * while no run wants the cores and busy-waits while one does, without ever taking the
 * interpreter lock: a thread of that priority waiting for it could hold up every other thread. */
#define _GNU_SOURCE
#define PY_SSIZE_T_CLEAN
#include <Python.h>
#include <linux/futex.h>
#include <pthread.h>
#include <sched.h>
#include <signal.h>
#include <stdatomic.h>
#include <sys/syscall.h>
#include <unistd.h>

#if defined(__x86_64__) || defined(__i386__)
#include <immintrin.h>
#define RELAX() _mm_pause()
#elif defined(__aarch64__)
#define RELAX() __asm__ __volatile__("yield")
#else
#define RELAX() ((void)0)
#endif

#define VERSION 2

static _Atomic int wanted = 0;   /* runs holding the cores awake */
static _Atomic int threads = 0;  /* threads started */
static pthread_mutex_t starting = PTHREAD_MUTEX_INITIALIZER;

static void *keep_awake(void *unused) {
    (void)unused;
    struct sched_param lowest = {0};
    pthread_setname_np(pthread_self(), "keep-awake");
    if (pthread_setschedparam(pthread_self(), SCHED_IDLE, &lowest) != 0)
        return NULL; /* never busy-wait at the priority of real work */
    for (;;) {
        if (atomic_load_explicit(&wanted, memory_order_relaxed) == 0)
            syscall(SYS_futex, &wanted, FUTEX_WAIT_PRIVATE, 0, NULL, NULL, 0);
        else
            RELAX();
    }
    return NULL;
}

static PyObject *start(PyObject *self, PyObject *args) {
    int count;
    if (!PyArg_ParseTuple(args, "i", &count)) return NULL;
    if (atomic_load(&threads) >= count) return PyLong_FromLong(atomic_load(&threads)); /* every run */
    /* The threads block every signal (inherited from here): the interpreter's handlers are the
     * main thread's business, and a signal would wake a sleeping thread for nothing. */
    sigset_t every, kept;
    sigfillset(&every);
    pthread_sigmask(SIG_BLOCK, &every, &kept);
    pthread_mutex_lock(&starting);
    while (atomic_load(&threads) < count) {
        pthread_t thread;
        pthread_attr_t attributes;
        pthread_attr_init(&attributes);
        pthread_attr_setdetachstate(&attributes, PTHREAD_CREATE_DETACHED);
        pthread_attr_setstacksize(&attributes, 64 * 1024);
        int failed = pthread_create(&thread, &attributes, keep_awake, NULL);
        pthread_attr_destroy(&attributes);
        if (failed) break;
        atomic_fetch_add(&threads, 1);
    }
    pthread_mutex_unlock(&starting);
    pthread_sigmask(SIG_SETMASK, &kept, NULL);
    return PyLong_FromLong(atomic_load(&threads));
}

static PyObject *begin(PyObject *self, PyObject *unused) {
    if (atomic_fetch_add(&wanted, 1) == 0)
        syscall(SYS_futex, &wanted, FUTEX_WAKE_PRIVATE, INT_MAX, NULL, NULL, 0);
    Py_RETURN_NONE;
}

static PyObject *end(PyObject *self, PyObject *unused) {
    atomic_fetch_sub(&wanted, 1);
    Py_RETURN_NONE;
}

static PyMethodDef methods[] = {
    {"start", start, METH_VARARGS, "start(count): at least count threads (started once); how many run"},
    {"begin", begin, METH_NOARGS, "A run wants the other cores awake until its end()."},
    {"end", end, METH_NOARGS, "The run that called begin() is over."},
    {NULL, NULL, 0, NULL},
};

static struct PyModuleDef module = {PyModuleDef_HEAD_INIT, "_keep_awake", NULL, -1, methods};

PyMODINIT_FUNC PyInit__keep_awake(void) {
    PyObject *created = PyModule_Create(&module);
    if (created != NULL && PyModule_AddIntConstant(created, "VERSION", VERSION) < 0) {
        Py_DECREF(created);
        return NULL;
    }
    return created;
}
