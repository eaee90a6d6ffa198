/* capevo.runtime.traces._native: the trace writer's hot path in C (see module.c). */
#ifndef CAPEVO_TRACES_H
#define CAPEVO_TRACES_H

#define PY_SSIZE_T_CLEAN
#include <Python.h>

#include <string.h>

/* A growing byte buffer (PyMem); cv_put appends, -1 with MemoryError set when it cannot grow. */
typedef struct {
    char *data;
    Py_ssize_t size, capacity;
} cv_buffer;
int cv_put_growing(cv_buffer *out, const char *data, Py_ssize_t n);

/* Inline: a row's payload is some forty puts, most of a literal's few bytes. */
static inline int cv_put(cv_buffer *out, const char *data, Py_ssize_t n) {
    if (out->size + n > out->capacity) return cv_put_growing(out, data, n);
    memcpy(out->data + out->size, data, (size_t)n);
    out->size += n;
    return 0;
}

/* rows.c: RecordEncoder.rows's splicer. A batch's rows are planned and their vectors printed once
 * (cv_rows_prepare, NULL with an exception set); cv_rows_splice appends row r's payload to out
 * (1), or leaves it to the row's record path (0), or fails (-1, exception set). */
typedef struct cv_rows cv_rows;
cv_rows *cv_rows_prepare(PyObject *const *rows, const char *is_step, Py_ssize_t n_rows, PyObject *name_of);
int cv_rows_splice(const cv_rows *t, Py_ssize_t r, cv_buffer *out);
void cv_rows_free(cv_rows *t);
PyObject *cv_rows_configure(PyObject *self, PyObject *args);
PyObject *cv_rows_encode(PyObject *self, PyObject *args);
int cv_rows_init(void);

/* frame.c: a batch of the writer's queue encoded and framed into the open MCAP chunk. */
PyObject *cv_frame_batch(PyObject *self, PyObject *args);

/* pack.c: an ECM's input values as packed float32 bytes. */
PyObject *cv_configure_pack(PyObject *self, PyObject *fallback);
PyObject *cv_pack_float32(PyObject *self, PyObject *const *args, Py_ssize_t nargs);

/* queue.c: the writer's queue of records and rows, appended to without the writer's lock. A kept
 * entry: the record or row, a record's channel id and encode function (owned; NULL for a row, whose
 * channel is the queue's and encode None), wall-clock ns. cv_queue_detach hands over every kept
 * entry, oldest first (NULL with an exception set: not a Queue, or no memory), the queue going on
 * empty; cv_queue_release drops them; cv_queue_channel is an entry's channel id (borrowed). */
enum { CV_KEPT_RECORD, CV_KEPT_STEP, CV_KEPT_CALL };
typedef struct {
    PyObject *item, *channel, *encode;
    long long time;
    int kind;
} cv_kept;
extern PyTypeObject cv_queue_type;
cv_kept *cv_queue_detach(PyObject *queue, Py_ssize_t *n);
void cv_queue_release(cv_kept *entries, Py_ssize_t n);
PyObject *cv_queue_channel(PyObject *queue, const cv_kept *e);

#endif
