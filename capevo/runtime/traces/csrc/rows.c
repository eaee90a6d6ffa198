/* RecordEncoder.rows (codec.py) in one C call.
 *
 * configure_rows(dumps, option, float32_array, exact_or_float32, outcomes, error_json, ndarray)
 * is called once at import with the codec's own helpers. encode_rows(rows, name_of) takes the same batch as
 * RecordEncoder.rows, a list of (is_step, row), and returns a list with, per row, its payload
 * (bytes) or None where the Python path must decide (a field of another type, a vector the
 * helpers reject, a value printed as null). Float text comes from one call of the codec's
 * orjson dumps over every vector of the batch, as in the Python version; this file only
 * classifies, de-duplicates and splices, which is what costs microseconds per row in Python.
 *
 * The Python version is the specification: for every input the two give the same bytes where
 * this one gives bytes (tests/runtime/traces/test_trace_rows.py).
 */
#include <stdint.h>
#include <string.h>

#include "traces.h"

static PyObject *g_dumps, *g_dumps_kwnames, *g_dumps_option, *g_float32_array, *g_exact_or_float32, *g_outcomes, *g_error_json;
static PyObject *s_eef_pos, *s_eef_force, *s_ndarray_type;

/* -- pointer -> vector index, one table per conversion rule ------------------------------------ */

typedef struct {
    PyObject *key;
    Py_ssize_t index;
} slot_entry;

typedef struct {
    slot_entry *entries;
    size_t mask;
} slot_table;

static int table_init(slot_table *t, Py_ssize_t expected) {
    size_t size = 64;
    while (size < (size_t)expected * 2) size <<= 1;
    t->entries = PyMem_Calloc(size, sizeof(slot_entry));
    t->mask = size - 1;
    return t->entries == NULL ? -1 : 0;
}

static slot_entry *table_find(slot_table *t, PyObject *key) {
    size_t h = ((uintptr_t)key >> 4) * 0x9E3779B97F4A7C15ull;
    for (size_t i = h & t->mask;; i = (i + 1) & t->mask)
        if (t->entries[i].key == key || t->entries[i].key == NULL) return &t->entries[i];
}

/* -- vector classification: what codec.float32_array / _exact_or_float32 return as they are -- */

static int is_float32_vector(PyObject *v) {
    if ((PyObject *)Py_TYPE(v) != s_ndarray_type) return 0;
    Py_buffer view;
    if (PyObject_GetBuffer(v, &view, PyBUF_FORMAT | PyBUF_C_CONTIGUOUS) < 0) {
        PyErr_Clear();
        return 0;
    }
    int ok = view.ndim == 1 && view.itemsize == 4 && view.format != NULL && strcmp(view.format, "f") == 0;
    PyBuffer_Release(&view);
    return ok;
}

static int is_float_tuple(PyObject *v) {
    if (!PyTuple_CheckExact(v)) return 0;
    for (Py_ssize_t i = 0, n = PyTuple_GET_SIZE(v); i < n; i++)
        if (!PyFloat_CheckExact(PyTuple_GET_ITEM(v, i))) return 0;
    return 1;
}

/* The exceptions the Python version turns into "take the record path". */
static int recoverable(void) {
    return PyErr_ExceptionMatches(PyExc_TypeError) || PyErr_ExceptionMatches(PyExc_ValueError) ||
           PyErr_ExceptionMatches(PyExc_OverflowError) || PyErr_ExceptionMatches(PyExc_AttributeError);
}

typedef struct {
    PyObject *vectors; /* list handed to dumps */
    PyObject *keys;    /* every vector the tables key by address, alive until the batch is done */
    slot_table observations, runtime;
} batch;

/* Index of v's text in the batch, converting it on first sight; -1 with an exception set. */
static Py_ssize_t vector_index(batch *b, PyObject *v, int observation) {
    slot_entry *e = table_find(observation ? &b->observations : &b->runtime, v);
    if (e->key != NULL) return e->index;
    PyObject *converted;
    if (observation ? is_float32_vector(v) : is_float_tuple(v)) {
        converted = Py_NewRef(v);
    } else {
        converted = PyObject_CallOneArg(observation ? g_float32_array : g_exact_or_float32, v);
        if (converted == NULL) return -1;
    }
    Py_ssize_t index = PyList_GET_SIZE(b->vectors);
    int failed = PyList_Append(b->vectors, converted);
    Py_DECREF(converted);
    if (failed) return -1;
    /* Entered only once converted: a vector that fails fails every row it is in. The key is an
     * address: hold the vector, or a freed one (an arm's property makes a new tuple per read)
     * could hand its address, and so its text, to the next. */
    if (PyList_Append(b->keys, v) < 0) return -1;
    e->key = v;
    e->index = index;
    return index;
}

static Py_ssize_t scalar_index(batch *b, PyObject *value) {
    PyObject *f = PyNumber_Float(value);
    if (f == NULL) return -1;
    PyObject *one = PyTuple_Pack(1, f);
    Py_DECREF(f);
    if (one == NULL) return -1;
    Py_ssize_t index = PyList_GET_SIZE(b->vectors);
    int failed = PyList_Append(b->vectors, one);
    Py_DECREF(one);
    return failed ? -1 : index;
}

/* -- plans: what each row's payload is made of ------------------------------------------------- */

enum { PLAN_RECORD_PATH = 0, PLAN_STEP = 1, PLAN_CALL = 2 };

typedef struct {
    int kind;
    long long episode, step, version;
    PyObject *name;       /* bytes, owned */
    PyObject *extra[2];   /* step: unused; call: outcome text (owned), error text (owned) */
    Py_ssize_t v[4];      /* step: obs, action, reward, next_obs; call: input, duration, output or -1 */
    char flags[3];        /* step: terminated, truncated, is_success */
    Py_ssize_t keys;      /* index of this row's first arm vector in the key list */
    Py_ssize_t n_keys;    /* 2 per arm */
} plan;

static void plan_clear(plan *p) {
    Py_CLEAR(p->name);
    Py_CLEAR(p->extra[0]);
    Py_CLEAR(p->extra[1]);
}

static int exact_int(PyObject *v, long long *out) {
    if (!PyLong_CheckExact(v)) return 0;
    int overflow = 0;
    *out = PyLong_AsLongLongAndOverflow(v, &overflow);
    if (overflow || (*out == -1 && PyErr_Occurred())) {
        PyErr_Clear();
        return 0;
    }
    return 1;
}

typedef struct {
    Py_ssize_t *items;
    Py_ssize_t size, capacity;
} index_list;

static int index_push(index_list *l, Py_ssize_t value) {
    if (l->size == l->capacity) {
        Py_ssize_t capacity = l->capacity ? l->capacity * 2 : 64;
        Py_ssize_t *items = PyMem_Realloc(l->items, (size_t)capacity * sizeof(Py_ssize_t));
        if (items == NULL) {
            PyErr_NoMemory();
            return -1;
        }
        l->items = items;
        l->capacity = capacity;
    }
    l->items[l->size++] = value;
    return 0;
}

/* Fill p from row; returns 1 planned, 0 record path (no exception), -1 error to propagate. */
static int plan_row(batch *b, plan *p, index_list *keys, int is_step, PyObject *row, PyObject *name_of,
                    PyObject **last_ecm, PyObject **last_name) {
    Py_ssize_t want = is_step ? 12 : 9;
    if (!PyTuple_CheckExact(row) || PyTuple_GET_SIZE(row) != want) return 0;
    PyObject *const *f = &PyTuple_GET_ITEM(row, 0);
    /* Beyond int64 the record path decides (orjson takes up to uint64, then refuses). */
    if (!exact_int(f[0], &p->episode) || !exact_int(f[1], &p->step) || !exact_int(f[3], &p->version)) return 0;
    if (!PyUnicode_CheckExact(f[2])) return 0;
    if (f[2] != *last_ecm) {
        PyObject *name = PyObject_CallOneArg(name_of, f[2]);
        if (name == NULL) return recoverable() ? (PyErr_Clear(), 0) : -1;
        if (!PyBytes_CheckExact(name)) {
            Py_DECREF(name);
            return 0;
        }
        Py_XSETREF(*last_name, name);
        *last_ecm = f[2];
    }
    p->name = Py_NewRef(*last_name);
    if (is_step) {
        Py_ssize_t o = vector_index(b, f[4], 1);
        Py_ssize_t a = o < 0 ? -1 : vector_index(b, f[5], 0);
        Py_ssize_t n = a < 0 ? -1 : vector_index(b, f[7], 1);
        Py_ssize_t r = n < 0 ? -1 : scalar_index(b, f[6]);
        if (r < 0) return recoverable() ? (PyErr_Clear(), 0) : -1;
        p->v[0] = o, p->v[1] = a, p->v[2] = r, p->v[3] = n;
        for (int k = 0; k < 3; k++) {
            int truth = PyObject_IsTrue(f[8 + k]);
            if (truth < 0) return recoverable() ? (PyErr_Clear(), 0) : -1;
            p->flags[k] = (char)truth;
        }
        PyObject *arms = PySequence_Fast(f[11], "arms");
        if (arms == NULL) return recoverable() ? (PyErr_Clear(), 0) : -1;
        p->keys = keys->size;
        int result = 1;
        for (Py_ssize_t i = 0, count = PySequence_Fast_GET_SIZE(arms); i < count && result == 1; i++) {
            PyObject *arm = PySequence_Fast_GET_ITEM(arms, i);
            for (int k = 0; k < 2 && result == 1; k++) {
                PyObject *vector = PyObject_GetAttr(arm, k == 0 ? s_eef_pos : s_eef_force);
                Py_ssize_t index = vector == NULL ? -1 : vector_index(b, vector, 0);
                Py_XDECREF(vector); /* vector_index holds it while the batch runs */
                if (index < 0 || index_push(keys, index) < 0) result = recoverable() ? (PyErr_Clear(), 0) : -1;
            }
        }
        Py_DECREF(arms);
        p->n_keys = keys->size - p->keys;
        if (result == 1) p->kind = PLAN_STEP;
        return result;
    }
    PyObject *outcome = PyDict_GetItemWithError(g_outcomes, f[7]);
    if (outcome == NULL) return PyErr_Occurred() ? (recoverable() ? (PyErr_Clear(), 0) : -1) : 0;
    p->extra[0] = Py_NewRef(outcome);
    if (f[8] == Py_None) {
        p->extra[1] = NULL;
    } else {
        p->extra[1] = PyObject_CallOneArg(g_error_json, f[8]);
        if (p->extra[1] == NULL) return recoverable() ? (PyErr_Clear(), 0) : -1;
        if (!PyBytes_CheckExact(p->extra[1])) return 0;
    }
    Py_ssize_t i = vector_index(b, f[4], 1), out = -1, d = -1;
    if (i >= 0 && f[5] != Py_None) out = vector_index(b, f[5], 0);
    if (i >= 0 && (f[5] == Py_None || out >= 0)) d = scalar_index(b, f[6]);
    if (d < 0) return recoverable() ? (PyErr_Clear(), 0) : -1;
    p->v[0] = i, p->v[1] = d, p->v[2] = out;
    p->kind = PLAN_CALL;
    return 1;
}

/* -- splicing ---------------------------------------------------------------------------------- */

typedef struct {
    char *data;
    Py_ssize_t size, capacity;
} buffer;

static int put(buffer *out, const char *data, Py_ssize_t n) {
    if (out->size + n > out->capacity) {
        Py_ssize_t capacity = out->capacity ? out->capacity : 4096;
        while (capacity < out->size + n) capacity *= 2;
        char *grown = PyMem_Realloc(out->data, (size_t)capacity);
        if (grown == NULL) {
            PyErr_NoMemory();
            return -1;
        }
        out->data = grown;
        out->capacity = capacity;
    }
    memcpy(out->data + out->size, data, (size_t)n);
    out->size += n;
    return 0;
}

#define PUT_LITERAL(out, s) put((out), (s), (Py_ssize_t)(sizeof(s) - 1))

static int put_int(buffer *out, long long v) {
    char digits[24];
    int n = snprintf(digits, sizeof digits, "%lld", v);
    return put(out, digits, n);
}

static int put_bytes(buffer *out, PyObject *bytes) {
    return put(out, PyBytes_AS_STRING(bytes), PyBytes_GET_SIZE(bytes));
}

typedef struct {
    const char *text;
    Py_ssize_t *start, *length;
} parts;

static int put_part(buffer *out, const parts *ps, Py_ssize_t i) {
    return put(out, ps->text + ps->start[i], ps->length[i]);
}

static int splice_step(buffer *out, const plan *p, const parts *ps, const Py_ssize_t *keys) {
    static const char *flags[2] = {"false", "true"};
    char name[48];
    if (PUT_LITERAL(out, "{\"episode\":") || put_int(out, p->episode) || PUT_LITERAL(out, ",\"step\":") ||
        put_int(out, p->step) || PUT_LITERAL(out, ",\"ecm\":") || put_bytes(out, p->name) ||
        PUT_LITERAL(out, ",\"version\":") || put_int(out, p->version) || PUT_LITERAL(out, ",\"obs\":[") ||
        put_part(out, ps, p->v[0]) || PUT_LITERAL(out, "],\"action\":[") || put_part(out, ps, p->v[1]) ||
        PUT_LITERAL(out, "],\"reward\":") || put_part(out, ps, p->v[2]) || PUT_LITERAL(out, ",\"next_obs\":[") ||
        put_part(out, ps, p->v[3]) || PUT_LITERAL(out, "],\"terminated\":") ||
        put(out, flags[(int)p->flags[0]], p->flags[0] ? 4 : 5) || PUT_LITERAL(out, ",\"truncated\":") ||
        put(out, flags[(int)p->flags[1]], p->flags[1] ? 4 : 5) || PUT_LITERAL(out, ",\"is_success\":") ||
        put(out, flags[(int)p->flags[2]], p->flags[2] ? 4 : 5) || PUT_LITERAL(out, ",\"key_state\":{"))
        return -1;
    for (Py_ssize_t k = 0; k < p->n_keys; k++) {
        int n = snprintf(name, sizeof name, "%s\"arm%zd_eef_%s\":[", k ? "," : "", k / 2, k % 2 ? "force" : "pos");
        if (put(out, name, n) || put_part(out, ps, keys[p->keys + k]) || PUT_LITERAL(out, "]")) return -1;
    }
    return PUT_LITERAL(out, "}}");
}

static int splice_call(buffer *out, const plan *p, const parts *ps) {
    if (PUT_LITERAL(out, "{\"episode\":") || put_int(out, p->episode) || PUT_LITERAL(out, ",\"step\":") ||
        put_int(out, p->step) || PUT_LITERAL(out, ",\"ecm\":") || put_bytes(out, p->name) ||
        PUT_LITERAL(out, ",\"version\":") || put_int(out, p->version) || PUT_LITERAL(out, ",\"input_state\":[") ||
        put_part(out, ps, p->v[0]) || PUT_LITERAL(out, "],\"output\":"))
        return -1;
    if (p->v[2] < 0 ? PUT_LITERAL(out, "null")
                    : (PUT_LITERAL(out, "[") || put_part(out, ps, p->v[2]) || PUT_LITERAL(out, "]")))
        return -1;
    if (PUT_LITERAL(out, ",\"duration_s\":") || put_part(out, ps, p->v[1]) || PUT_LITERAL(out, ",\"outcome\":") ||
        put_bytes(out, p->extra[0]) || PUT_LITERAL(out, ",\"error\":"))
        return -1;
    if (p->extra[1] == NULL ? PUT_LITERAL(out, "null") : put_bytes(out, p->extra[1])) return -1;
    return PUT_LITERAL(out, "}");
}

/* Cut dumps' "[[..],[..],...]" into the text inside each vector's brackets; -1 if it is not that. */
static int split_parts(const char *text, Py_ssize_t size, Py_ssize_t count, parts *ps) {
    Py_ssize_t at = 1;
    for (Py_ssize_t i = 0; i < count; i++) {
        if (at >= size || text[at] != '[') return -1;
        const char *close = memchr(text + at + 1, ']', (size_t)(size - at - 1));
        if (close == NULL) return -1;
        Py_ssize_t end = close - text;
        if (end + 1 >= size || text[end + 1] != (i + 1 < count ? ',' : ']')) return -1;
        ps->start[i] = at + 1;
        ps->length[i] = end - (at + 1);
        at = end + 2; /* past "]," or "]]" */
    }
    return (count == 0 ? size == 2 : at == size) ? 0 : -1;
}

static int part_has_null(const parts *ps, Py_ssize_t i) {
    /* Finite numbers print with digits, '-', '.', 'e' and '+' only: an 'n' is a null. */
    return memchr(ps->text + ps->start[i], 'n', (size_t)ps->length[i]) != NULL;
}

static int plan_has_null(const plan *p, const parts *ps, const char *null_parts, const Py_ssize_t *keys) {
    if (null_parts == NULL) return 0;
    int used = p->kind == PLAN_STEP ? 4 : (p->v[2] < 0 ? 2 : 3);
    for (int k = 0; k < used; k++)
        if (null_parts[p->v[k]]) return 1;
    if (p->kind == PLAN_STEP)
        for (Py_ssize_t k = 0; k < p->n_keys; k++)
            if (null_parts[keys[p->keys + k]]) return 1;
    (void)ps;
    return 0;
}

PyObject *cv_rows_encode(PyObject *self, PyObject *args) {
    (void)self;
    PyObject *rows, *name_of;
    if (!PyArg_ParseTuple(args, "O!O:encode_rows", &PyList_Type, &rows, &name_of)) return NULL;
    if (g_dumps == NULL) {
        PyErr_SetString(PyExc_RuntimeError, "_native.configure_rows() was not called");
        return NULL;
    }
    Py_ssize_t n_rows = PyList_GET_SIZE(rows);
    PyObject *result = NULL, *text = NULL, *last_ecm = NULL, *last_name = NULL;
    plan *plans = PyMem_Calloc((size_t)(n_rows ? n_rows : 1), sizeof(plan));
    index_list keys = {0};
    buffer out = {0};
    parts ps = {0};
    char *null_parts = NULL;
    batch b = {.vectors = PyList_New(0), .keys = PyList_New(0)};
    if (plans == NULL || b.vectors == NULL || b.keys == NULL || table_init(&b.observations, n_rows * 3) < 0 ||
        table_init(&b.runtime, n_rows * 5) < 0) {
        PyErr_NoMemory();
        goto done;
    }
    for (Py_ssize_t r = 0; r < n_rows; r++) {
        PyObject *item = PyList_GET_ITEM(rows, r);
        if (!PyTuple_CheckExact(item) || PyTuple_GET_SIZE(item) != 2) {
            PyErr_SetString(PyExc_TypeError, "encode takes a list of (is_step, row) pairs");
            goto done;
        }
        int is_step = PyObject_IsTrue(PyTuple_GET_ITEM(item, 0));
        if (is_step < 0) goto done;
        int planned = plan_row(&b, &plans[r], &keys, is_step, PyTuple_GET_ITEM(item, 1), name_of, &last_ecm,
                               &last_name);
        if (planned < 0) goto done;
        if (planned == 0) {
            plan_clear(&plans[r]);
            plans[r].kind = PLAN_RECORD_PATH;
        }
    }
    /* orjson matches its keyword by the interned name's address: call it as Python would. */
    PyObject *dumps_args[2] = {b.vectors, g_dumps_option};
    text = PyObject_Vectorcall(g_dumps, dumps_args, 1, g_dumps_kwnames);
    if (text == NULL) goto done;
    if (!PyBytes_CheckExact(text)) {
        PyErr_SetString(PyExc_TypeError, "dumps must return bytes");
        goto done;
    }
    Py_ssize_t n_vectors = PyList_GET_SIZE(b.vectors);
    ps.text = PyBytes_AS_STRING(text);
    ps.start = PyMem_Malloc((size_t)(n_vectors ? n_vectors : 1) * sizeof(Py_ssize_t));
    ps.length = PyMem_Malloc((size_t)(n_vectors ? n_vectors : 1) * sizeof(Py_ssize_t));
    if (ps.start == NULL || ps.length == NULL) {
        PyErr_NoMemory();
        goto done;
    }
    if (split_parts(ps.text, PyBytes_GET_SIZE(text), n_vectors, &ps) < 0) {
        PyErr_SetString(PyExc_RuntimeError, "dumps printed the vectors in an unexpected shape");
        goto done;
    }
    if (memchr(ps.text, 'n', (size_t)PyBytes_GET_SIZE(text)) != NULL) {
        null_parts = PyMem_Malloc((size_t)(n_vectors ? n_vectors : 1));
        if (null_parts == NULL) {
            PyErr_NoMemory();
            goto done;
        }
        for (Py_ssize_t i = 0; i < n_vectors; i++) null_parts[i] = (char)part_has_null(&ps, i);
    }
    result = PyList_New(n_rows);
    if (result == NULL) goto done;
    for (Py_ssize_t r = 0; r < n_rows; r++) {
        plan *p = &plans[r];
        PyObject *payload;
        if (p->kind == PLAN_RECORD_PATH || plan_has_null(p, &ps, null_parts, keys.items)) {
            payload = Py_NewRef(Py_None);
        } else {
            out.size = 0;
            if ((p->kind == PLAN_STEP ? splice_step(&out, p, &ps, keys.items) : splice_call(&out, p, &ps)) < 0) {
                Py_CLEAR(result);
                goto done;
            }
            payload = PyBytes_FromStringAndSize(out.data, out.size);
            if (payload == NULL) {
                Py_CLEAR(result);
                goto done;
            }
        }
        PyList_SET_ITEM(result, r, payload);
    }
done:
    if (plans != NULL)
        for (Py_ssize_t r = 0; r < n_rows; r++) plan_clear(&plans[r]);
    PyMem_Free(plans);
    PyMem_Free(keys.items);
    PyMem_Free(out.data);
    PyMem_Free(ps.start);
    PyMem_Free(ps.length);
    PyMem_Free(null_parts);
    PyMem_Free(b.observations.entries);
    PyMem_Free(b.runtime.entries);
    Py_XDECREF(b.vectors);
    Py_XDECREF(b.keys);
    Py_XDECREF(text);
    Py_XDECREF(last_name);
    return result;
}

PyObject *cv_rows_configure(PyObject *self, PyObject *args) {
    (void)self;
    PyObject *dumps, *option, *float32_array, *exact_or_float32, *outcomes, *error_json, *ndarray_type;
    if (!PyArg_ParseTuple(args, "OOOOO!OO:configure_rows", &dumps, &option, &float32_array, &exact_or_float32,
                          &PyDict_Type, &outcomes, &error_json, &ndarray_type))
        return NULL;
    PyObject *option_name = PyUnicode_InternFromString("option");
    PyObject *kwnames = option_name == NULL ? NULL : PyTuple_Pack(1, option_name);
    Py_XDECREF(option_name);
    if (kwnames == NULL) return NULL;
    Py_XSETREF(g_dumps_kwnames, kwnames);
    Py_XSETREF(g_dumps_option, Py_NewRef(option));
    Py_XSETREF(g_dumps, Py_NewRef(dumps));
    Py_XSETREF(g_float32_array, Py_NewRef(float32_array));
    Py_XSETREF(g_exact_or_float32, Py_NewRef(exact_or_float32));
    Py_XSETREF(g_outcomes, Py_NewRef(outcomes));
    Py_XSETREF(g_error_json, Py_NewRef(error_json));
    Py_XSETREF(s_ndarray_type, Py_NewRef(ndarray_type));
    Py_RETURN_NONE;
}

int cv_rows_init(void) {
    s_eef_pos = PyUnicode_InternFromString("eef_pos");
    s_eef_force = PyUnicode_InternFromString("eef_force");
    return s_eef_pos == NULL || s_eef_force == NULL ? -1 : 0;
}
