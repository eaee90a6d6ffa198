/* frame_messages: McapFileWriter.add_message (mcapfile.py) for a batch, in one C call.
 *
 * frame_messages(chunk, index, messages, limit) appends to the bytearray ``chunk`` one MCAP
 * Message record per (channel id, log time, sequence, payload) of ``messages``, from the first,
 * with publish time = log time, and appends (log time, offset of the record in the chunk) to
 * ``index[channel id]`` (a new list for a new channel). It stops after the message with which the
 * chunk reaches ``limit`` bytes, so the caller finishes the chunk where add_message would, and
 * returns (messages framed, smallest log time, largest log time) of what it framed.
 */
#include <stdint.h>
#include <string.h>

#include "traces.h"

#define MESSAGE_OPCODE 0x05
#define MESSAGE_HEAD 31  /* opcode u8, record length u64, channel u16, sequence u32, two times u64 */
#define MESSAGE_FIXED 22 /* the record length counts what follows it: head minus 9, plus the payload */

static void put_le(unsigned char *at, uint64_t value, int bytes) {
    for (int i = 0; i < bytes; i++) at[i] = (unsigned char)(value >> (8 * i));
}

typedef struct {
    unsigned long channel, sequence;
    unsigned long long time;
    PyObject *payload;
} message;

static int read_message(PyObject *item, message *m) {
    if (!PyTuple_CheckExact(item) || PyTuple_GET_SIZE(item) != 4 || !PyBytes_CheckExact(PyTuple_GET_ITEM(item, 3))) {
        PyErr_SetString(PyExc_TypeError, "a message is (channel id, log time, sequence, payload bytes)");
        return -1;
    }
    m->channel = PyLong_AsUnsignedLong(PyTuple_GET_ITEM(item, 0));
    m->time = PyLong_AsUnsignedLongLong(PyTuple_GET_ITEM(item, 1));
    m->sequence = PyLong_AsUnsignedLong(PyTuple_GET_ITEM(item, 2));
    if (PyErr_Occurred()) return -1;
    if (m->channel > 0xFFFF || m->sequence > 0xFFFFFFFFul) {
        PyErr_SetString(PyExc_OverflowError, "channel id or sequence out of range");
        return -1;
    }
    m->payload = PyTuple_GET_ITEM(item, 3);
    return 0;
}

PyObject *cv_frame_messages(PyObject *self, PyObject *args) {
    (void)self;
    PyObject *chunk, *index, *messages;
    Py_ssize_t limit;
    if (!PyArg_ParseTuple(args, "O!O!O!n:frame_messages", &PyByteArray_Type, &chunk, &PyDict_Type, &index,
                          &PyList_Type, &messages, &limit))
        return NULL;
    Py_ssize_t n = PyList_GET_SIZE(messages), start = PyByteArray_GET_SIZE(chunk), size = start, count = 0;
    unsigned long long first = 0, last = 0;
    message m;
    /* First pass: how many messages fit before the chunk reaches the limit, and their size. */
    while (count < n) {
        if (read_message(PyList_GET_ITEM(messages, count), &m) < 0) return NULL;
        size += MESSAGE_HEAD + PyBytes_GET_SIZE(m.payload);
        count++;
        if (size >= limit) break;
    }
    if (PyByteArray_Resize(chunk, size) < 0) return NULL;
    unsigned char *out = (unsigned char *)PyByteArray_AS_STRING(chunk);
    Py_ssize_t at = start;
    for (Py_ssize_t i = 0; i < count; i++) {
        read_message(PyList_GET_ITEM(messages, i), &m); /* checked in the first pass */
        Py_ssize_t length = PyBytes_GET_SIZE(m.payload);
        unsigned char *head = out + at;
        head[0] = MESSAGE_OPCODE;
        put_le(head + 1, (uint64_t)(MESSAGE_FIXED + length), 8);
        put_le(head + 9, m.channel, 2);
        put_le(head + 11, m.sequence, 4);
        put_le(head + 15, m.time, 8);
        put_le(head + 23, m.time, 8);
        memcpy(head + MESSAGE_HEAD, PyBytes_AS_STRING(m.payload), (size_t)length);
        PyObject *key = PyTuple_GET_ITEM(PyList_GET_ITEM(messages, i), 0);
        PyObject *entries = PyDict_GetItemWithError(index, key);
        if (entries == NULL) {
            if (PyErr_Occurred()) return NULL;
            entries = PyList_New(0);
            if (entries == NULL) return NULL;
            int failed = PyDict_SetItem(index, key, entries);
            Py_DECREF(entries); /* the dict holds it */
            if (failed) return NULL;
        }
        PyObject *entry = Py_BuildValue("(KK)", m.time, (unsigned long long)at);
        if (entry == NULL) return NULL;
        int failed = PyList_Append(entries, entry);
        Py_DECREF(entry);
        if (failed) return NULL;
        if (i == 0 || m.time < first) first = m.time;
        if (i == 0 || m.time > last) last = m.time;
        at += MESSAGE_HEAD + length;
    }
    return Py_BuildValue("(nKK)", count, first, last);
}
