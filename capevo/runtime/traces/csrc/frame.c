/* frame_batch: TraceWriter's batch, from the queue's entries to MCAP Message records, in one C call.
 *
 * frame_batch(chunk, index, pending, step_channel, sequences, name_of, fallback) takes the writer's
 * C Queue, whose entries it takes (as take() would, without a tuple per entry), or what take()
 * returned, a list of (channel id, encode or None, record or row, wall-clock ns); it appends to the
 * bytearray ``chunk`` one Message record per entry that encodes, in order, with log and publish
 * time the entry's time and the sequence ``sequences[channel id]`` (then incremented modulo
 * 2**32). Rows (encode None; an env step row when the channel is ``step_channel``) are spliced by
 * rows.c; every other entry, and every row rows.c leaves to the record path, is
 * ``fallback(entry)`` (the entry as a tuple), which returns the payload bytes or the Invalid that
 * drops the entry (no message, no sequence number). For each message it appends the packed little-endian u64 pair
 * (log time, offset of the record in the chunk) to the bytearray ``index[channel id]`` (created
 * for a new channel). Returns (messages framed, smallest log time, largest log time, the first
 * fallback's Invalid or None).
 *
 * An exception while encoding (a fallback that raised, no memory) leaves chunk, index and
 * sequences as they were (a Queue's entries are taken either way, as take() and a failed
 * _frame_in_python would leave them). The Python version, its specification, is
 * TraceWriter._frame_in_python (RecordEncoder.rows_in_python, then McapFileWriter.add_messages):
 * tests/runtime/traces/test_trace_frame.py compares chunk, index, sequences and dropped entries of
 * both, and the Queue's entries with the list take() gives.
 */
#include <stdint.h>
#include <string.h>

#include "traces.h"

#define MESSAGE_OPCODE 0x05
#define MESSAGE_HEAD 31  /* opcode u8, record length u64, channel u16, sequence u32, two times u64 */
#define MESSAGE_FIXED 22 /* the record length counts what follows it: head minus 9, plus the payload */
#define INDEX_PAIR 16    /* (log time, offset) */

static void put_le(unsigned char *at, uint64_t value, int bytes) {
    for (int i = 0; i < bytes; i++) at[i] = (unsigned char)(value >> (8 * i));
}

/* An entry, wherever it is kept (borrowed references; encode NULL for a row). */
typedef struct {
    PyObject *channel, *encode, *item;
    unsigned long long time;
} entry_view;

typedef struct {
    Py_ssize_t channel; /* index into sequences; -1: the entry was dropped */
    unsigned long long time;
    Py_ssize_t at; /* offset of its record in the batch's framed bytes */
} framed;

static int read_entry(PyObject *entry, entry_view *v) {
    if (!PyTuple_CheckExact(entry) || PyTuple_GET_SIZE(entry) != 4) {
        PyErr_SetString(PyExc_TypeError, "an entry is (channel id, encode or None, record or row, time ns)");
        return -1;
    }
    v->channel = PyTuple_GET_ITEM(entry, 0);
    v->encode = PyTuple_GET_ITEM(entry, 1) == Py_None ? NULL : PyTuple_GET_ITEM(entry, 1);
    v->item = PyTuple_GET_ITEM(entry, 2);
    v->time = PyLong_AsUnsignedLongLong(PyTuple_GET_ITEM(entry, 3));
    return PyErr_Occurred() ? -1 : 0;
}

static int channel_index(const entry_view *v, Py_ssize_t channels, Py_ssize_t *channel) {
    *channel = PyLong_AsSsize_t(v->channel);
    if (*channel == -1 && PyErr_Occurred()) return -1;
    if (*channel < 0 || *channel > 0xFFFF || *channel >= channels) {
        PyErr_Format(PyExc_ValueError, "channel id %zd has no sequence", *channel);
        return -1;
    }
    return 0;
}

/* The entry as take() gives it, for the fallback: the list's own tuple, or one built for it. */
static PyObject *entry_tuple(PyObject *pending, Py_ssize_t i, const entry_view *v) {
    if (PyList_Check(pending)) return Py_NewRef(PyList_GET_ITEM(pending, i));
    PyObject *time = PyLong_FromUnsignedLongLong(v->time);
    if (time == NULL) return NULL;
    PyObject *entry = PyTuple_Pack(4, v->channel, v->encode ? v->encode : Py_None, v->item, time);
    Py_DECREF(time);
    return entry;
}

/* Append every framed message's index pair to index[channel]: what add_message does per message. */
static int add_index(PyObject *index, const entry_view *views, const framed *ms, Py_ssize_t n, Py_ssize_t base) {
    for (Py_ssize_t i = 0; i < n; i++) {
        if (ms[i].channel < 0) continue;
        PyObject *key = views[i].channel;
        PyObject *pairs = PyDict_GetItemWithError(index, key);
        if (pairs == NULL) {
            if (PyErr_Occurred()) return -1;
            pairs = PyByteArray_FromStringAndSize(NULL, 0);
            if (pairs == NULL) return -1;
            int failed = PyDict_SetItem(index, key, pairs);
            Py_DECREF(pairs); /* the dict holds it */
            if (failed) return -1;
        }
        if (!PyByteArray_Check(pairs)) {
            PyErr_SetString(PyExc_TypeError, "index values must be bytearrays");
            return -1;
        }
        Py_ssize_t size = PyByteArray_GET_SIZE(pairs);
        if (PyByteArray_Resize(pairs, size + INDEX_PAIR) < 0) return -1;
        unsigned char *at = (unsigned char *)PyByteArray_AS_STRING(pairs) + size;
        put_le(at, ms[i].time, 8);
        put_le(at + 8, (uint64_t)(base + ms[i].at), 8);
    }
    return 0;
}

PyObject *cv_frame_batch(PyObject *self, PyObject *args) {
    (void)self;
    PyObject *chunk, *index, *pending, *sequences, *name_of, *fallback;
    Py_ssize_t step_channel;
    if (!PyArg_ParseTuple(args, "O!O!OnO!OO:frame_batch", &PyByteArray_Type, &chunk, &PyDict_Type, &index,
                          &pending, &step_channel, &PyList_Type, &sequences, &name_of, &fallback))
        return NULL;
    /* The entries: a Queue's, taken here (released at the end), or a list's. */
    cv_kept *queued = NULL;
    Py_ssize_t n = 0;
    if (PyList_Check(pending)) {
        n = PyList_GET_SIZE(pending);
    } else if ((queued = cv_queue_detach(pending, &n)) == NULL) {
        return NULL;
    }
    Py_ssize_t channels = PyList_GET_SIZE(sequences), n_rows = 0, count = 0;
    entry_view *views = NULL;
    PyObject *result = NULL, *failure = NULL, **rows = NULL;
    char *is_step = NULL;
    Py_ssize_t *row_of = NULL;
    unsigned long *seq = NULL;
    framed *ms = NULL;
    cv_rows *t = NULL;
    cv_buffer out = {0};
    unsigned long long first = 0, last = 0;
    size_t slots = (size_t)(n ? n : 1);
    rows = PyMem_Malloc(slots * sizeof(PyObject *));
    is_step = PyMem_Malloc(slots);
    row_of = PyMem_Malloc(slots * sizeof(Py_ssize_t));
    ms = PyMem_Malloc(slots * sizeof(framed));
    views = PyMem_Malloc(slots * sizeof(entry_view));
    seq = PyMem_Malloc((size_t)(channels ? channels : 1) * sizeof(unsigned long));
    if (rows == NULL || is_step == NULL || row_of == NULL || ms == NULL || seq == NULL || views == NULL) {
        PyErr_NoMemory();
        goto done;
    }
    for (Py_ssize_t c = 0; c < channels; c++) {
        seq[c] = PyLong_AsUnsignedLong(PyList_GET_ITEM(sequences, c));
        if (PyErr_Occurred()) goto done;
    }
    for (Py_ssize_t i = 0; i < n; i++) {
        entry_view *v = &views[i];
        if (queued == NULL) {
            if (read_entry(PyList_GET_ITEM(pending, i), v) < 0) goto done;
        } else {
            v->channel = cv_queue_channel(pending, &queued[i]);
            v->encode = queued[i].encode == Py_None ? NULL : queued[i].encode;
            v->item = queued[i].item;
            v->time = (unsigned long long)queued[i].time;
        }
        if (channel_index(v, channels, &ms[i].channel) < 0) goto done;
        ms[i].time = v->time;
        row_of[i] = -1;
        if (v->encode == NULL) {
            is_step[n_rows] = ms[i].channel == step_channel;
            rows[n_rows] = v->item;
            row_of[i] = n_rows++;
        }
    }
    t = cv_rows_prepare(rows, is_step, n_rows, name_of);
    if (t == NULL) goto done;
    static const char head[MESSAGE_HEAD] = {0};
    for (Py_ssize_t i = 0; i < n; i++) {
        Py_ssize_t at = out.size;
        if (cv_put(&out, head, MESSAGE_HEAD) < 0) goto done;
        int spliced = row_of[i] < 0 ? 0 : cv_rows_splice(t, row_of[i], &out);
        if (spliced < 0) goto done;
        if (spliced == 0) {
            PyObject *entry = entry_tuple(pending, i, &views[i]);
            PyObject *payload = entry == NULL ? NULL : PyObject_CallOneArg(fallback, entry);
            Py_XDECREF(entry);
            if (payload == NULL) goto done;
            int kept = PyBytes_CheckExact(payload) && cv_put(&out, PyBytes_AS_STRING(payload), PyBytes_GET_SIZE(payload)) == 0;
            if (!kept && PyErr_Occurred()) {
                Py_DECREF(payload);
                goto done;
            }
            if (!kept) { /* dropped: its Invalid, the first of the batch, goes back to the writer */
                if (failure == NULL) failure = payload;
                else Py_DECREF(payload);
                out.size = at;
                ms[i].channel = -1;
                continue;
            }
            Py_DECREF(payload);
        }
        Py_ssize_t c = ms[i].channel;
        unsigned char *h = (unsigned char *)out.data + at;
        h[0] = MESSAGE_OPCODE;
        put_le(h + 1, (uint64_t)(MESSAGE_FIXED + out.size - at - MESSAGE_HEAD), 8);
        put_le(h + 9, (uint64_t)c, 2);
        put_le(h + 11, seq[c], 4);
        put_le(h + 15, ms[i].time, 8);
        put_le(h + 23, ms[i].time, 8);
        seq[c] = (seq[c] + 1) & 0xFFFFFFFFul;
        ms[i].at = at;
        if (count == 0 || ms[i].time < first) first = ms[i].time;
        if (count == 0 || ms[i].time > last) last = ms[i].time;
        count++;
    }
    /* Everything encoded: now the caller's state, the chunk first (an index pair must never point
     * past it), then the sequences, then the index (which only an allocation can fail). */
    Py_ssize_t base = PyByteArray_GET_SIZE(chunk);
    if (PyByteArray_Resize(chunk, base + out.size) < 0) goto done;
    memcpy(PyByteArray_AS_STRING(chunk) + base, out.data, (size_t)out.size);
    for (Py_ssize_t c = 0; c < channels; c++) {
        PyObject *value = PyLong_FromUnsignedLong(seq[c]);
        if (value == NULL || PyList_SetItem(sequences, c, value) < 0) goto done; /* SetItem steals */
    }
    if (add_index(index, views, ms, n, base) < 0) goto done;
    result = Py_BuildValue("(nKKO)", count, first, last, failure == NULL ? Py_None : failure);
done:
    Py_XDECREF(failure);
    cv_rows_free(t);
    PyMem_Free(out.data);
    PyMem_Free(rows);
    PyMem_Free(is_step);
    PyMem_Free(row_of);
    PyMem_Free(ms);
    PyMem_Free(seq);
    PyMem_Free(views);
    if (queued != NULL) cv_queue_release(queued, n);
    return result;
}
