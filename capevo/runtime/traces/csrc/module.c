/* capevo.runtime.traces._native: what the trace writer runs per record, in C.
 *
 * - Queue (queue.c): TraceWriter's queue of kept records and rows. Each append is one C call
 *   that stamps the wall-clock time, keeps the entry and calls the writer back when its batch
 *   is full or its flush is due: the episode loop's write calls run between two robosuite steps,
 *   with every cache cold, where each Python-level statement costs far more than it does warm.
 * - encode_rows (rows.c): RecordEncoder.rows's classifying, de-duplicating and splicing.
 * - frame_batch (frame.c): a batch the queue handed over, encoded (rows spliced by rows.c, the rest
 *   by the writer's Python callback) and framed into the open MCAP chunk, with no Python object per
 *   message.
 * - pack_float32 (pack.c): the ECM input of an invocation row, packed without a numpy call.
 *
 * Each has a Python version that is its specification (queue.py, codec.py, mcapfile.py); the tests
 * run both.
 */
#include "traces.h"

static PyMethodDef methods[] = {
    {"configure_rows", cv_rows_configure, METH_VARARGS,
     "configure_rows(dumps, option, float32_array, exact_or_float32, outcomes, error_json, ndarray_type, float32, "
     "probes) -> whether numpy's array head reads as expected"},
    {"encode_rows", cv_rows_encode, METH_VARARGS,
     "encode_rows(rows, name_of) -> list of bytes or None (see codec.RecordEncoder.rows)"},
    {"frame_batch", cv_frame_batch, METH_VARARGS,
     "frame_batch(chunk, index, pending, step_channel, sequences, name_of, fallback) -> "
     "(framed, first time, last time, failure or None); see frame.c"},
    {"configure_pack", cv_configure_pack, METH_O, "configure_pack(fallback): what pack_float32 returns otherwise"},
    {"pack_float32", (PyCFunction)(void (*)(void))cv_pack_float32, METH_FASTCALL,
     "pack_float32(obs, keys) -> the float32 values of obs[k] for k in keys, as bytes; see pack.c"},
    {NULL, NULL, 0, NULL},
};

static struct PyModuleDef module = {PyModuleDef_HEAD_INIT, .m_name = "_native", .m_size = -1, .m_methods = methods};

PyMODINIT_FUNC PyInit__native(void) {
    if (cv_rows_init() < 0 || PyType_Ready(&cv_queue_type) < 0) return NULL;
    PyObject *m = PyModule_Create(&module);
    if (m == NULL) return NULL;
    if (PyModule_AddObjectRef(m, "Queue", (PyObject *)&cv_queue_type) < 0) {
        Py_DECREF(m);
        return NULL;
    }
    return m;
}
