/* Queue: TraceWriter's kept records and rows, in write order (writer.py's _PythonQueue is its
 * specification).
 *
 * Queue(step_channel, call_channel, batch, on_full, refuse, check_row)
 *   step(row), call(row)           keep an env step / invocation row: (channel, None, row, now)
 *   record(channel, encode, rec)   keep a record with its encode function
 *   take()                         every kept entry, oldest first; the queue is empty after it
 *   closed                         set: every append calls refuse(method), which raises
 *   deadline_ns                    CLOCK_MONOTONIC ns at which a timed flush is due (0: never)
 *   flushed_ns, dirty              the writer's last flush (CLOCK_MONOTONIC ns) and whether its open
 *                                  chunk holds messages since: what wait_due reads
 *   wait_due(interval_ns, grace_ns)  the writer's flush thread: sleeps without the GIL until entries
 *                                  or a dirty chunk wait and flushed_ns + interval + grace has passed
 *                                  (True), or stop() was called (False)
 *   stop()                         wakes wait_due for good
 * ``now`` is CLOCK_REALTIME ns, what time.time_ns() reads. After an append that fills the batch
 * or finds the deadline passed, the queue calls on_full() and returns what it raises. A row that
 * is not a tuple of its length goes to check_row(row, length, method), which raises Invalid.
 *
 * An append runs no Python code before its entry is kept, so under the GIL it is atomic against
 * take() from another thread: the writer's lock guards encoding, not appending (a free-threaded
 * CPython would need a mutex here; capevo runs on the GIL builds).
 *
 * wait_due runs without the GIL, so what it reads (kept, flushed_ns, dirty) is written and read with
 * atomic stores and loads: in a busy loop the writer flushes itself at the deadline and every wake
 * of the flush thread finds nothing to do; a wake that never takes the GIL costs a few µs, where
 * the Python thread's cost about 150 µs of CPU here, cold after the robosuite steps between.
 */
#include "traces.h" /* first: Python.h sets the POSIX feature macros clock_gettime needs */

#include <pthread.h>
#include <time.h>

/* A kept entry (cv_kept, traces.h) has no Python object of its own: an append in the episode loop,
 * cold, paid for a tuple and an int per entry (allocation, the GC's young count), and so did take()
 * in the flush, about 1.5 µs per T6 step; frame_batch reads the entries where they are
 * (cv_queue_detach). A row's channel is the queue's and its encode None, so neither is kept (two
 * reference counts less to write per append); a record's are owned. */

typedef struct {
    PyObject_HEAD
    cv_kept *entries; /* (channel id, encode or None, record or row, wall-clock ns), oldest first */
    Py_ssize_t capacity; /* 0: __init__ was not called */
    PyObject *step_channel, *call_channel;
    PyObject *on_full, *refuse, *check_row;
    Py_ssize_t batch;
    long long deadline_ns;
    int closed;
    /* Read by wait_due without the GIL: atomics. */
    Py_ssize_t kept; /* entries in use */
    long long flushed_ns;
    int dirty, stopping;
    pthread_mutex_t mutex; /* with cond: stop() wakes wait_due */
    pthread_cond_t cond;
    int sync_ready;
} Queue;

#define LOAD(x) __atomic_load_n(&(x), __ATOMIC_RELAXED)
#define STORE(x, v) __atomic_store_n(&(x), (v), __ATOMIC_RELAXED)

static long long clock_ns(clockid_t clock) {
    struct timespec ts;
    clock_gettime(clock, &ts);
    return (long long)ts.tv_sec * 1000000000LL + ts.tv_nsec;
}

static int initialised(Queue *q) {
    if (q->capacity > 0) return 1;
    PyErr_SetString(PyExc_RuntimeError, "Queue.__init__ was not called");
    return 0;
}

static PyObject *keep(Queue *q, int kind, PyObject *channel, PyObject *encode, PyObject *item, const char *method) {
    if (!initialised(q)) return NULL;
    if (q->closed) {
        PyObject *r = PyObject_CallFunction(q->refuse, "s", method);
        if (r == NULL) return NULL;
        Py_DECREF(r);
        PyErr_Format(PyExc_RuntimeError, "%s: the trace writer is closed", method);
        return NULL;
    }
    Py_ssize_t n = q->kept;
    if (n == q->capacity) {
        cv_kept *grown = PyMem_Realloc(q->entries, (size_t)q->capacity * 2 * sizeof(cv_kept));
        if (grown == NULL) return PyErr_NoMemory();
        q->entries = grown;
        q->capacity *= 2;
    }
    cv_kept *e = &q->entries[n];
    e->item = Py_NewRef(item);
    e->channel = Py_XNewRef(channel);
    e->encode = Py_XNewRef(encode);
    e->time = clock_ns(CLOCK_REALTIME);
    e->kind = kind;
    STORE(q->kept, n + 1);
    if (n + 1 >= q->batch || (q->deadline_ns && clock_ns(CLOCK_MONOTONIC) >= q->deadline_ns))
        return PyObject_CallNoArgs(q->on_full);
    Py_RETURN_NONE;
}

static PyObject *keep_row(Queue *q, PyObject *row, Py_ssize_t length, int kind, const char *method) {
    if (!PyTuple_CheckExact(row) || PyTuple_GET_SIZE(row) != length) {
        PyObject *r = PyObject_CallFunction(q->check_row, "Ons", row, length, method);
        if (r == NULL) return NULL;
        Py_DECREF(r);
        PyErr_Format(PyExc_TypeError, "%s takes a tuple of %zd fields", method, length);
        return NULL;
    }
    return keep(q, kind, NULL, NULL, row, method);
}

static PyObject *queue_step(Queue *q, PyObject *row) {
    return keep_row(q, row, 12, CV_KEPT_STEP, "write_env_step_row");
}

static PyObject *queue_call(Queue *q, PyObject *row) {
    return keep_row(q, row, 10, CV_KEPT_CALL, "write_invocation_row");
}

static PyObject *queue_record(Queue *q, PyObject *const *args, Py_ssize_t nargs) {
    if (nargs != 4 || !PyUnicode_Check(args[3])) {
        PyErr_SetString(PyExc_TypeError, "record(channel, encode, record, method) takes 4 arguments");
        return NULL;
    }
    const char *method = PyUnicode_AsUTF8(args[3]);
    if (method == NULL) return NULL;
    return keep(q, CV_KEPT_RECORD, args[0], args[1], args[2], method);
}

/* The kept entries, handed over: the queue goes on with a fresh array of the same capacity, so
 * whatever a garbage collection or a finalizer appends while the caller works is kept for later. */
static cv_kept *detach(Queue *q, Py_ssize_t *n) {
    if (!initialised(q)) return NULL;
    cv_kept *fresh = PyMem_Malloc((size_t)q->capacity * sizeof(cv_kept));
    if (fresh == NULL) return (cv_kept *)PyErr_NoMemory();
    cv_kept *taken = q->entries;
    *n = q->kept;
    q->entries = fresh;
    STORE(q->kept, 0);
    return taken;
}

void cv_queue_release(cv_kept *entries, Py_ssize_t n) {
    for (Py_ssize_t i = 0; i < n; i++) {
        Py_DECREF(entries[i].item);
        Py_XDECREF(entries[i].channel);
        Py_XDECREF(entries[i].encode);
    }
    PyMem_Free(entries);
}

PyObject *cv_queue_channel(PyObject *queue, const cv_kept *e) {
    const Queue *q = (const Queue *)queue;
    return e->kind == CV_KEPT_RECORD ? e->channel : e->kind == CV_KEPT_STEP ? q->step_channel : q->call_channel;
}

cv_kept *cv_queue_detach(PyObject *queue, Py_ssize_t *n) {
    if (!PyObject_TypeCheck(queue, &cv_queue_type)) {
        PyErr_SetString(PyExc_TypeError, "expected a trace Queue");
        return NULL;
    }
    return detach((Queue *)queue, n);
}

static PyObject *queue_take(Queue *q, PyObject *unused) {
    (void)unused;
    Py_ssize_t n = 0;
    cv_kept *kept = detach(q, &n);
    if (kept == NULL) return NULL;
    /* Out of memory here loses the batch: the writer fails with it either way. */
    PyObject *taken = PyList_New(n);
    for (Py_ssize_t i = 0; taken != NULL && i < n; i++) {
        const cv_kept *e = &kept[i];
        PyObject *channel = cv_queue_channel((PyObject *)q, e);
        PyObject *time = PyLong_FromLongLong(e->time);
        PyObject *entry = time == NULL ? NULL : PyTuple_Pack(4, channel, e->encode ? e->encode : Py_None, e->item, time);
        Py_XDECREF(time);
        if (entry == NULL) Py_CLEAR(taken);
        else PyList_SET_ITEM(taken, i, entry);
    }
    cv_queue_release(kept, n);
    return taken;
}

static PyObject *queue_wait_due(Queue *q, PyObject *args) {
    long long interval_ns, grace_ns;
    if (!PyArg_ParseTuple(args, "LL:wait_due", &interval_ns, &grace_ns)) return NULL;
    if (!initialised(q)) return NULL;
    if (interval_ns <= 0 || grace_ns < 0) {
        PyErr_SetString(PyExc_ValueError, "interval_ns must be positive and grace_ns not negative");
        return NULL;
    }
    int due = 0;
    Py_BEGIN_ALLOW_THREADS
    pthread_mutex_lock(&q->mutex);
    while (!q->stopping) {
        long long now = clock_ns(CLOCK_MONOTONIC), at;
        if (LOAD(q->kept) > 0 || LOAD(q->dirty)) {
            at = LOAD(q->flushed_ns) + interval_ns + grace_ns;
            if (now >= at) {
                due = 1;
                break;
            }
        } else {
            at = now + interval_ns; /* nothing waits: look again an interval on */
        }
        struct timespec until = {.tv_sec = at / 1000000000LL, .tv_nsec = at % 1000000000LL};
        pthread_cond_timedwait(&q->cond, &q->mutex, &until);
    }
    pthread_mutex_unlock(&q->mutex);
    Py_END_ALLOW_THREADS
    return PyBool_FromLong(due);
}

static PyObject *queue_stop(Queue *q, PyObject *unused) {
    (void)unused;
    if (!initialised(q)) return NULL;
    Py_BEGIN_ALLOW_THREADS /* wait_due holds the mutex only while it looks, never while it needs the GIL */
    pthread_mutex_lock(&q->mutex);
    q->stopping = 1;
    pthread_cond_broadcast(&q->cond);
    pthread_mutex_unlock(&q->mutex);
    Py_END_ALLOW_THREADS
    Py_RETURN_NONE;
}

static Py_ssize_t queue_len(Queue *q) { return initialised(q) ? q->kept : -1; }

static int queue_init(Queue *q, PyObject *args, PyObject *kwargs) {
    static char *names[] = {"step_channel", "call_channel", "batch", "on_full", "refuse", "check_row", NULL};
    PyObject *step_channel, *call_channel, *on_full, *refuse, *check_row;
    Py_ssize_t batch;
    if (!PyArg_ParseTupleAndKeywords(args, kwargs, "O!O!nOOO:Queue", names, &PyLong_Type, &step_channel,
                                     &PyLong_Type, &call_channel, &batch, &on_full, &refuse, &check_row))
        return -1;
    if (batch < 1) {
        PyErr_SetString(PyExc_ValueError, "batch must be positive");
        return -1;
    }
    if (!q->sync_ready) {
        pthread_condattr_t attr;
        if (pthread_condattr_init(&attr) || pthread_condattr_setclock(&attr, CLOCK_MONOTONIC) ||
            pthread_cond_init(&q->cond, &attr) || pthread_mutex_init(&q->mutex, NULL)) {
            PyErr_SetString(PyExc_OSError, "cannot make the queue's condition variable");
            return -1;
        }
        pthread_condattr_destroy(&attr);
        q->sync_ready = 1;
    }
    if (q->capacity == 0) {
        q->entries = PyMem_Malloc(64 * sizeof(cv_kept));
        if (q->entries == NULL) {
            PyErr_NoMemory();
            return -1;
        }
        q->capacity = 64;
        STORE(q->kept, 0);
    } else {
        Py_ssize_t n = 0;
        cv_kept *kept = detach(q, &n);
        if (kept == NULL) return -1;
        cv_queue_release(kept, n);
    }
    STORE(q->flushed_ns, 0);
    STORE(q->dirty, 0);
    q->stopping = 0;
    Py_XSETREF(q->step_channel, Py_NewRef(step_channel));
    Py_XSETREF(q->call_channel, Py_NewRef(call_channel));
    Py_XSETREF(q->on_full, Py_NewRef(on_full));
    Py_XSETREF(q->refuse, Py_NewRef(refuse));
    Py_XSETREF(q->check_row, Py_NewRef(check_row));
    q->batch = batch;
    q->deadline_ns = 0;
    q->closed = 0;
    return 0;
}

/* The writer holds the queue and the queue holds the writer's bound methods: a cycle for the GC. */
static int queue_traverse(Queue *q, visitproc visit, void *arg) {
    for (Py_ssize_t i = 0; i < q->kept; i++) {
        Py_VISIT(q->entries[i].item);
        Py_VISIT(q->entries[i].channel);
        Py_VISIT(q->entries[i].encode);
    }
    Py_VISIT(q->on_full);
    Py_VISIT(q->refuse);
    Py_VISIT(q->check_row);
    return 0;
}

static int queue_clear(Queue *q) {
    if (q->capacity > 0) {
        cv_kept *kept = q->entries;
        Py_ssize_t n = q->kept;
        q->entries = NULL;
        q->capacity = 0;
        STORE(q->kept, 0);
        cv_queue_release(kept, n);
    }
    Py_CLEAR(q->step_channel);
    Py_CLEAR(q->call_channel);
    Py_CLEAR(q->on_full);
    Py_CLEAR(q->refuse);
    Py_CLEAR(q->check_row);
    return 0;
}

static void queue_dealloc(Queue *q) {
    PyObject_GC_UnTrack(q);
    queue_clear(q);
    if (q->sync_ready) { /* no wait_due runs: it holds the queue */
        pthread_cond_destroy(&q->cond);
        pthread_mutex_destroy(&q->mutex);
    }
    Py_TYPE(q)->tp_free((PyObject *)q);
}

static PyObject *get_closed(Queue *q, void *unused) {
    (void)unused;
    return PyBool_FromLong(q->closed);
}

static int set_closed(Queue *q, PyObject *value, void *unused) {
    (void)unused;
    int truth = value == NULL ? 0 : PyObject_IsTrue(value);
    if (truth < 0) return -1;
    q->closed = truth;
    return 0;
}

static PyObject *get_deadline(Queue *q, void *unused) {
    (void)unused;
    return PyLong_FromLongLong(q->deadline_ns);
}

static int set_deadline(Queue *q, PyObject *value, void *unused) {
    (void)unused;
    long long ns = value == NULL ? 0 : PyLong_AsLongLong(value);
    if (ns == -1 && PyErr_Occurred()) return -1;
    q->deadline_ns = ns;
    return 0;
}

static PyObject *get_flushed(Queue *q, void *unused) {
    (void)unused;
    return PyLong_FromLongLong(LOAD(q->flushed_ns));
}

static int set_flushed(Queue *q, PyObject *value, void *unused) {
    (void)unused;
    long long ns = value == NULL ? 0 : PyLong_AsLongLong(value);
    if (ns == -1 && PyErr_Occurred()) return -1;
    STORE(q->flushed_ns, ns);
    return 0;
}

static PyObject *get_dirty(Queue *q, void *unused) {
    (void)unused;
    return PyBool_FromLong(LOAD(q->dirty));
}

static int set_dirty(Queue *q, PyObject *value, void *unused) {
    (void)unused;
    int truth = value == NULL ? 0 : PyObject_IsTrue(value);
    if (truth < 0) return -1;
    STORE(q->dirty, truth);
    return 0;
}

static PyMethodDef queue_methods[] = {
    {"step", (PyCFunction)queue_step, METH_O, "step(row): keep an env step row"},
    {"call", (PyCFunction)queue_call, METH_O, "call(row): keep an invocation row"},
    {"record", (PyCFunction)(void (*)(void))queue_record, METH_FASTCALL,
     "record(channel, encode, record, method): keep a record"},
    {"take", (PyCFunction)queue_take, METH_NOARGS, "take() -> every kept entry, oldest first"},
    {"wait_due", (PyCFunction)queue_wait_due, METH_VARARGS,
     "wait_due(interval_ns, grace_ns) -> True when a timed flush is due, False after stop()"},
    {"stop", (PyCFunction)queue_stop, METH_NOARGS, "stop(): wait_due returns False from now on"},
    {NULL, NULL, 0, NULL},
};

static PyGetSetDef queue_getset[] = {
    {"closed", (getter)get_closed, (setter)set_closed, "appends call refuse(method)", NULL},
    {"deadline_ns", (getter)get_deadline, (setter)set_deadline, "monotonic ns of the next timed flush (0: none)",
     NULL},
    {"flushed_ns", (getter)get_flushed, (setter)set_flushed, "monotonic ns of the writer's last flush", NULL},
    {"dirty", (getter)get_dirty, (setter)set_dirty, "the open chunk holds messages not yet flushed", NULL},
    {NULL, NULL, NULL, NULL, NULL},
};

static PySequenceMethods queue_sequence = {.sq_length = (lenfunc)queue_len};

PyTypeObject cv_queue_type = {
    PyVarObject_HEAD_INIT(NULL, 0).tp_name = "capevo.runtime.traces._native.Queue",
    .tp_basicsize = sizeof(Queue),
    .tp_flags = Py_TPFLAGS_DEFAULT | Py_TPFLAGS_HAVE_GC,
    .tp_doc = "TraceWriter's kept records and rows, in write order (see queue.c).",
    .tp_new = PyType_GenericNew,
    .tp_init = (initproc)queue_init,
    .tp_dealloc = (destructor)queue_dealloc,
    .tp_traverse = (traverseproc)queue_traverse,
    .tp_clear = (inquiry)queue_clear,
    .tp_methods = queue_methods,
    .tp_getset = queue_getset,
    .tp_as_sequence = &queue_sequence,
};
