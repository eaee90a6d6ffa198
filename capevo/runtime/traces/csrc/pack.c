/* pack_float32: the episode loop's ECM input for its invocation row, in one C call.
 *
 * pack_float32(obs, keys) returns the float32 values of obs[k] for each k of ``keys`` that obs
 * has, in order, each array flattened in C order, as one bytes object: what
 * np.concatenate([obs[k] for k in keys if k in obs], axis=None) holds, immutable, without a numpy
 * call between two robosuite steps. Where obs is not a dict, keys not a tuple or a value not a
 * C-contiguous native float32 buffer, it returns fallback(obs, keys) instead, the function
 * configure_pack(fallback) gave (rows.py: numpy's concatenation), or None before that.
 */
#include <string.h>

#include "traces.h"

#define MAX_PARTS 64

static PyObject *g_fallback;

PyObject *cv_configure_pack(PyObject *self, PyObject *fallback) {
    (void)self;
    Py_XSETREF(g_fallback, Py_NewRef(fallback));
    Py_RETURN_NONE;
}

static PyObject *fall_back(PyObject *obs, PyObject *keys) {
    if (g_fallback == NULL) Py_RETURN_NONE;
    return PyObject_CallFunctionObjArgs(g_fallback, obs, keys, NULL);
}

PyObject *cv_pack_float32(PyObject *self, PyObject *const *args, Py_ssize_t nargs) {
    (void)self;
    if (nargs != 2) {
        PyErr_SetString(PyExc_TypeError, "pack_float32(obs, keys) takes 2 arguments");
        return NULL;
    }
    PyObject *obs = args[0], *keys = args[1];
    if (!PyDict_CheckExact(obs) || !PyTuple_CheckExact(keys) || PyTuple_GET_SIZE(keys) > MAX_PARTS)
        return fall_back(obs, keys);
    Py_ssize_t n = PyTuple_GET_SIZE(keys), parts = 0, total = 0;
    Py_buffer views[MAX_PARTS];
    PyObject *result = NULL;
    for (Py_ssize_t i = 0; i < n; i++) {
        PyObject *value = PyDict_GetItemWithError(obs, PyTuple_GET_ITEM(keys, i));
        if (value == NULL) {
            if (PyErr_Occurred()) goto done;
            continue; /* a key the observation lacks is left out, as the Python version does */
        }
        if (PyObject_GetBuffer(value, &views[parts], PyBUF_FORMAT | PyBUF_C_CONTIGUOUS) < 0) {
            PyErr_Clear();
            goto other;
        }
        parts++;
        Py_buffer *v = &views[parts - 1];
        if (v->itemsize != 4 || v->format == NULL || strcmp(v->format, "f") != 0) goto other;
        total += v->len;
    }
    result = PyBytes_FromStringAndSize(NULL, total);
    if (result != NULL) {
        char *at = PyBytes_AS_STRING(result);
        for (Py_ssize_t i = 0; i < parts; i++) {
            memcpy(at, views[i].buf, (size_t)views[i].len);
            at += views[i].len;
        }
    }
done:
    for (Py_ssize_t i = 0; i < parts; i++) PyBuffer_Release(&views[i]);
    return result;
other:
    for (Py_ssize_t i = 0; i < parts; i++) PyBuffer_Release(&views[i]);
    return fall_back(obs, keys);
}
