/* capevo.runtime.traces._native: the trace writer's hot path in C (see module.c). */
#ifndef CAPEVO_TRACES_H
#define CAPEVO_TRACES_H

#define PY_SSIZE_T_CLEAN
#include <Python.h>

/* rows.c: RecordEncoder.rows's splicer. */
PyObject *cv_rows_configure(PyObject *self, PyObject *args);
PyObject *cv_rows_encode(PyObject *self, PyObject *args);
int cv_rows_init(void);

/* frame.c: McapFileWriter.add_message for a batch. */
PyObject *cv_frame_messages(PyObject *self, PyObject *args);

/* pack.c: an ECM's input values as packed float32 bytes. */
PyObject *cv_configure_pack(PyObject *self, PyObject *fallback);
PyObject *cv_pack_float32(PyObject *self, PyObject *const *args, Py_ssize_t nargs);

/* queue.c: the writer's queue of records and rows, appended to without the writer's lock. */
extern PyTypeObject cv_queue_type;

#endif
