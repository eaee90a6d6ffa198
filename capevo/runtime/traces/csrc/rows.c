/* RecordEncoder.rows (codec.py) in one C call.
 *
 * configure_rows(dumps, option, float32_array, exact_or_float32, outcomes, error_json, ndarray,
 * float32, probes) is called once at import with the codec's own helpers (and returns whether
 * numpy's array head reads as expected). encode_rows(rows, name_of) takes the same batch as
 * RecordEncoder.rows, a list of (is_step, row), and returns a list with, per row, its payload
 * (bytes) or None where the Python path must decide (a field of another type, a vector the
 * helpers reject, a value printed as null). Float text comes from one call of the codec's
 * orjson dumps over every vector (and scalar) of the batch, as in the Python version; this file
 * only classifies, de-duplicates and splices, which is what costs microseconds per row in Python.
 * An invocation's input selected from the observation (input_index) is cut from the
 * observation's text, element by element. cv_rows_prepare and cv_rows_splice (traces.h) are the
 * same work for frame.c, which splices into the MCAP chunk instead of into bytes per row.
 *
 * The Python version is the specification: for every input the two give the same bytes where
 * this one gives bytes (tests/runtime/traces/test_trace_rows.py).
 */
#include <stdint.h>
#include <string.h>

#include "traces.h"

static PyObject *g_dumps, *g_dumps_kwnames, *g_dumps_option, *g_float32_array, *g_exact_or_float32, *g_outcomes, *g_error_json;
static PyObject *s_eef_pos, *s_eef_force, *s_ndarray_type, *s_float32;

/* The head of numpy's array struct (PyArrayObject_fields, numpy/ndarraytypes.h; the same in numpy
 * 1.x and 2.x), read without building against numpy's headers. configure_rows checks it on probe
 * arrays and falls back to the buffer protocol if they disagree: a buffer request was a fifth of
 * a T6 batch's classifying, cold (numpy builds and caches a format per fresh array). */
typedef struct {
    PyObject_HEAD
    char *data;
    int nd;
    Py_ssize_t *dimensions, *strides;
    PyObject *base, *descr;
    int flags;
} array_head;
#define ARRAY_C_CONTIGUOUS 0x0001 /* NPY_ARRAY_C_CONTIGUOUS */
static int g_array_head_ok;

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
    if (g_array_head_ok) {
        const array_head *a = (const array_head *)v;
        /* numpy's float32 descriptor is a singleton; another (byte-swapped, say) asks the buffer */
        if (a->descr == s_float32) return a->nd == 1 && (a->flags & ARRAY_C_CONTIGUOUS);
    }
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

/* An input_index read once per batch (an ECM's activation hands the same tuple to each of its
 * calls): its positions, or valid 0 where one is not an int the record path would take. */
typedef struct {
    PyObject *index; /* owned */
    long long *at;
    Py_ssize_t n;
    int valid;
} selection;

typedef struct {
    PyObject *vectors; /* list handed to dumps */
    PyObject *keys;    /* every vector the tables key by address, alive until the batch is done */
    slot_table observations, runtime;
    selection *selections;
    Py_ssize_t n_selections, selections_capacity;
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

/* A scalar goes into the list as the float itself (no tuple: one container less per row, and
 * dumps prints it bare, which split_parts reads). */
static Py_ssize_t scalar_index(batch *b, PyObject *value) {
    PyObject *f = PyNumber_Float(value);
    if (f == NULL) return -1;
    Py_ssize_t index = PyList_GET_SIZE(b->vectors);
    int failed = PyList_Append(b->vectors, f);
    Py_DECREF(f);
    return failed ? -1 : index;
}

/* -- plans: what each row's payload is made of ------------------------------------------------- */

enum { PLAN_RECORD_PATH = 0, PLAN_STEP = 1, PLAN_CALL = 2 };

typedef struct {
    int kind;
    long long episode, step, version;
    PyObject *name;       /* bytes, owned */
    PyObject *extra[2];   /* step: unused; call: outcome text (owned), error text (owned) */
    Py_ssize_t selection; /* call: its input_index in the batch's selections, or -1 (the input is v[0]) */
    Py_ssize_t v[4];      /* step: obs, action, reward, next_obs; call: input, duration, output or -1 */
    char flags[3];        /* step: terminated, truncated, is_success */
    Py_ssize_t keys;      /* index of this row's first arm vector in the key list */
    Py_ssize_t n_keys;    /* 2 per arm */
} plan;

static void plan_clear(plan *p) {
    p->selection = -1;
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

/* The batch's selection for the tuple index (read on first sight), or -1 with an exception set. */
static Py_ssize_t selection_of(batch *b, PyObject *index) {
    for (Py_ssize_t s = b->n_selections - 1; s >= 0; s--) /* the latest activation's, most often */
        if (b->selections[s].index == index) return s;
    if (b->n_selections == b->selections_capacity) {
        Py_ssize_t capacity = b->selections_capacity ? b->selections_capacity * 2 : 8;
        selection *grown = PyMem_Realloc(b->selections, (size_t)capacity * sizeof(selection));
        if (grown == NULL) return PyErr_NoMemory(), -1;
        b->selections = grown;
        b->selections_capacity = capacity;
    }
    Py_ssize_t n = PyTuple_GET_SIZE(index);
    long long *at = PyMem_Malloc((size_t)(n ? n : 1) * sizeof(long long));
    if (at == NULL) return PyErr_NoMemory(), -1;
    int valid = 1;
    for (Py_ssize_t k = 0; k < n && valid; k++) valid = exact_int(PyTuple_GET_ITEM(index, k), &at[k]) && at[k] >= 0;
    b->selections[b->n_selections] = (selection){Py_NewRef(index), at, n, valid};
    return b->n_selections++;
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
    Py_ssize_t want = is_step ? 12 : 10;
    p->selection = -1;
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
    /* call: input, input_index, output, duration, outcome, error */
    PyObject *outcome = PyDict_GetItemWithError(g_outcomes, f[8]);
    if (outcome == NULL) return PyErr_Occurred() ? (recoverable() ? (PyErr_Clear(), 0) : -1) : 0;
    p->extra[0] = Py_NewRef(outcome);
    if (f[9] == Py_None) {
        p->extra[1] = NULL;
    } else {
        p->extra[1] = PyObject_CallOneArg(g_error_json, f[9]);
        if (p->extra[1] == NULL) return recoverable() ? (PyErr_Clear(), 0) : -1;
        if (!PyBytes_CheckExact(p->extra[1])) return 0;
    }
    Py_ssize_t i = vector_index(b, f[4], 1), out = -1, d = -1;
    if (i >= 0 && f[5] != Py_None) {
        /* A selection from the observation: only from the loop's own arrays (printed as they are,
         * which the step's row found already: no second buffer request), by a tuple. */
        if (!PyTuple_CheckExact(f[5]) || PyList_GET_ITEM(b->vectors, i) != f[4]) return 0;
        p->selection = selection_of(b, f[5]);
        if (p->selection < 0) return -1;
    }
    if (i >= 0 && f[6] != Py_None) out = vector_index(b, f[6], 0);
    if (i >= 0 && (f[6] == Py_None || out >= 0)) d = scalar_index(b, f[7]);
    if (d < 0) return recoverable() ? (PyErr_Clear(), 0) : -1;
    p->v[0] = i, p->v[1] = d, p->v[2] = out;
    p->kind = PLAN_CALL;
    return 1;
}

/* -- splicing ---------------------------------------------------------------------------------- */

int cv_put_growing(cv_buffer *out, const char *data, Py_ssize_t n) {
    Py_ssize_t capacity = out->capacity ? out->capacity : 4096;
    while (capacity < out->size + n) capacity *= 2;
    char *grown = PyMem_Realloc(out->data, (size_t)capacity);
    if (grown == NULL) {
        PyErr_NoMemory();
        return -1;
    }
    out->data = grown;
    out->capacity = capacity;
    memcpy(out->data + out->size, data, (size_t)n);
    out->size += n;
    return 0;
}

#define put cv_put
#define PUT_LITERAL(out, s) put((out), (s), (Py_ssize_t)(sizeof(s) - 1))

/* %lld by hand: snprintf's format parsing was a tenth of a batch's splice (perf). */
static int put_int(cv_buffer *out, long long v) {
    char digits[24];
    char *end = digits + sizeof digits, *at = end;
    unsigned long long u = v < 0 ? 0ull - (unsigned long long)v : (unsigned long long)v;
    do {
        *--at = (char)('0' + u % 10);
        u /= 10;
    } while (u);
    if (v < 0) *--at = '-';
    return put(out, at, end - at);
}

static int put_bytes(cv_buffer *out, PyObject *bytes) {
    return put(out, PyBytes_AS_STRING(bytes), PyBytes_GET_SIZE(bytes));
}

typedef struct {
    const char *text;
    Py_ssize_t *start, *length;
} parts;

static int put_part(cv_buffer *out, const parts *ps, Py_ssize_t i) {
    return put(out, ps->text + ps->start[i], ps->length[i]);
}

static int splice_step(cv_buffer *out, const plan *p, const parts *ps, const Py_ssize_t *keys) {
    static const char *flags[2] = {"false", "true"};
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
        if ((k && PUT_LITERAL(out, ",")) || PUT_LITERAL(out, "\"arm") || put_int(out, k / 2) ||
            (k % 2 ? PUT_LITERAL(out, "_eef_force\":[") : PUT_LITERAL(out, "_eef_pos\":[")) ||
            put_part(out, ps, keys[p->keys + k]) || PUT_LITERAL(out, "]"))
            return -1;
    }
    return PUT_LITERAL(out, "}}");
}

static int select_text(const batch *b, const plan *p, const parts *ps, cv_buffer *out);

/* 1 spliced, 0 the record path decides (a selection it cannot cut), -1 error. */
static int splice_call(cv_buffer *out, const plan *p, const parts *ps, const batch *b) {
    if (PUT_LITERAL(out, "{\"episode\":") || put_int(out, p->episode) || PUT_LITERAL(out, ",\"step\":") ||
        put_int(out, p->step) || PUT_LITERAL(out, ",\"ecm\":") || put_bytes(out, p->name) ||
        PUT_LITERAL(out, ",\"version\":") || put_int(out, p->version) || PUT_LITERAL(out, ",\"input_state\":["))
        return -1;
    int selected = p->selection < 0 ? (put_part(out, ps, p->v[0]) ? -1 : 1) : select_text(b, p, ps, out);
    if (selected <= 0) return selected;
    if (PUT_LITERAL(out, "],\"output\":")) return -1;
    if (p->v[2] < 0 ? PUT_LITERAL(out, "null")
                    : (PUT_LITERAL(out, "[") || put_part(out, ps, p->v[2]) || PUT_LITERAL(out, "]")))
        return -1;
    if (PUT_LITERAL(out, ",\"duration_s\":") || put_part(out, ps, p->v[1]) || PUT_LITERAL(out, ",\"outcome\":") ||
        put_bytes(out, p->extra[0]) || PUT_LITERAL(out, ",\"error\":"))
        return -1;
    if (p->extra[1] == NULL ? PUT_LITERAL(out, "null") : put_bytes(out, p->extra[1])) return -1;
    return PUT_LITERAL(out, "}") ? -1 : 1;
}

/* Cut dumps' "[[..],1.5,[..],...]" into each element's text: inside a vector's brackets, or the
 * bare number of a scalar; -1 if it is not that. */
static int split_parts(const char *text, Py_ssize_t size, Py_ssize_t count, parts *ps) {
    Py_ssize_t at = 1;
    for (Py_ssize_t i = 0; i < count; i++) {
        if (at >= size) return -1;
        Py_ssize_t start, end, next;
        if (text[at] == '[') {
            const char *close = memchr(text + at + 1, ']', (size_t)(size - at - 1));
            if (close == NULL) return -1;
            start = at + 1;
            end = close - text;
            next = end + 1;
        } else {
            start = at;
            end = at;
            while (end < size && text[end] != ',' && text[end] != ']' && text[end] != '[') end++;
            if (end == start) return -1;
            next = end;
        }
        if (next >= size || text[next] != (i + 1 < count ? ',' : ']')) return -1;
        ps->start[i] = start;
        ps->length[i] = end - start;
        at = next + 1; /* past the ',' or the closing ']' */
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
    for (int k = p->selection >= 0; k < used; k++)
        if (null_parts[p->v[k]]) return 1;
    if (p->kind == PLAN_STEP)
        for (Py_ssize_t k = 0; k < p->n_keys; k++)
            if (null_parts[keys[p->keys + k]]) return 1;
    (void)ps;
    return 0;
}

/* -- a batch's texts: planned rows, the vectors' text, split ------------------------------------ */

struct cv_rows {
    Py_ssize_t n_rows;
    plan *plans;
    index_list keys;
    batch b;
    PyObject *text;   /* dumps' bytes */
    parts ps;
    char *null_parts; /* per vector: its text holds a null (NULL: none does) */
};

void cv_rows_free(cv_rows *t) {
    if (t == NULL) return;
    if (t->plans != NULL)
        for (Py_ssize_t r = 0; r < t->n_rows; r++) plan_clear(&t->plans[r]);
    PyMem_Free(t->plans);
    PyMem_Free(t->keys.items);
    PyMem_Free(t->ps.start);
    PyMem_Free(t->ps.length);
    PyMem_Free(t->null_parts);
    for (Py_ssize_t s = 0; s < t->b.n_selections; s++) {
        Py_DECREF(t->b.selections[s].index);
        PyMem_Free(t->b.selections[s].at);
    }
    PyMem_Free(t->b.selections);
    PyMem_Free(t->b.observations.entries);
    PyMem_Free(t->b.runtime.entries);
    Py_XDECREF(t->b.vectors);
    Py_XDECREF(t->b.keys);
    Py_XDECREF(t->text);
    PyMem_Free(t);
}

cv_rows *cv_rows_prepare(PyObject *const *rows, const char *is_step, Py_ssize_t n_rows, PyObject *name_of) {
    if (g_dumps == NULL) {
        PyErr_SetString(PyExc_RuntimeError, "_native.configure_rows() was not called");
        return NULL;
    }
    cv_rows *t = PyMem_Calloc(1, sizeof(cv_rows));
    if (t == NULL) return (cv_rows *)PyErr_NoMemory();
    PyObject *last_ecm = NULL, *last_name = NULL;
    t->n_rows = n_rows;
    t->plans = PyMem_Calloc((size_t)(n_rows ? n_rows : 1), sizeof(plan));
    t->b.vectors = PyList_New(0);
    t->b.keys = PyList_New(0);
    if (t->plans == NULL || t->b.vectors == NULL || t->b.keys == NULL ||
        table_init(&t->b.observations, n_rows * 3) < 0 || table_init(&t->b.runtime, n_rows * 5) < 0) {
        if (!PyErr_Occurred()) PyErr_NoMemory();
        goto failed;
    }
    for (Py_ssize_t r = 0; r < n_rows; r++) {
        int planned = plan_row(&t->b, &t->plans[r], &t->keys, is_step[r], rows[r], name_of, &last_ecm, &last_name);
        if (planned < 0) goto failed;
        if (planned == 0) {
            plan_clear(&t->plans[r]);
            t->plans[r].kind = PLAN_RECORD_PATH;
        }
    }
    Py_CLEAR(last_name);
    /* orjson matches its keyword by the interned name's address: call it as Python would. */
    PyObject *dumps_args[2] = {t->b.vectors, g_dumps_option};
    t->text = PyObject_Vectorcall(g_dumps, dumps_args, 1, g_dumps_kwnames);
    if (t->text == NULL) goto failed;
    if (!PyBytes_CheckExact(t->text)) {
        PyErr_SetString(PyExc_TypeError, "dumps must return bytes");
        goto failed;
    }
    Py_ssize_t n_vectors = PyList_GET_SIZE(t->b.vectors), size = PyBytes_GET_SIZE(t->text);
    t->ps.text = PyBytes_AS_STRING(t->text);
    t->ps.start = PyMem_Malloc((size_t)(n_vectors ? n_vectors : 1) * sizeof(Py_ssize_t));
    t->ps.length = PyMem_Malloc((size_t)(n_vectors ? n_vectors : 1) * sizeof(Py_ssize_t));
    if (t->ps.start == NULL || t->ps.length == NULL) {
        PyErr_NoMemory();
        goto failed;
    }
    if (split_parts(t->ps.text, size, n_vectors, &t->ps) < 0) {
        PyErr_SetString(PyExc_RuntimeError, "dumps printed the vectors in an unexpected shape");
        goto failed;
    }
    if (memchr(t->ps.text, 'n', (size_t)size) != NULL) {
        t->null_parts = PyMem_Malloc((size_t)(n_vectors ? n_vectors : 1));
        if (t->null_parts == NULL) {
            PyErr_NoMemory();
            goto failed;
        }
        for (Py_ssize_t i = 0; i < n_vectors; i++) t->null_parts[i] = (char)part_has_null(&t->ps, i);
    }
    return t;
failed:
    Py_XDECREF(last_name);
    cv_rows_free(t);
    return NULL;
}

/* Where each element of a vector's text begins: starts[e] for element e of n, starts[n] = length + 1
 * (element e spans starts[e] .. starts[e + 1] - 2, its comma excluded); returns n, or -1 when there
 * are more than cap elements. The commas are found eight bytes at a time: a byte-at-a-time scan of
 * the observation's text was most of an invocation's splice (about 1.7 µs, cold). */
static Py_ssize_t element_starts(const char *text, Py_ssize_t length, Py_ssize_t *starts, Py_ssize_t cap) {
    Py_ssize_t n = 0, k = 0;
    if (length == 0) return 0;
    starts[n++] = 0;
#if defined(__BYTE_ORDER__) && __BYTE_ORDER__ == __ORDER_LITTLE_ENDIAN__ /* byte i of a word is text[k + i] */
    const uint64_t low7 = 0x7F7F7F7F7F7F7F7Full, commas = 0x0101010101010101ull * ',';
    for (; k + 8 <= length; k += 8) {
        uint64_t word;
        memcpy(&word, text + k, 8);
        uint64_t x = word ^ commas; /* zero where a comma is */
        /* Bit 7 of each zero byte, exactly: the (x - 1s) & ~x form borrows across bytes and
         * flags the '-' that follows a comma. */
        uint64_t zeros = ~(((x & low7) + low7) | x | low7);
        for (; zeros; zeros &= zeros - 1) {
            if (n >= cap) return -1;
            starts[n++] = k + (__builtin_ctzll(zeros) >> 3) + 1;
        }
    }
#endif
    for (; k < length; k++) {
        if (text[k] != ',') continue;
        if (n >= cap) return -1;
        starts[n++] = k + 1;
    }
    starts[n] = length + 1;
    return n;
}

/* The text of a selection's values: the elements of vector v[0]'s text at the selection's positions,
 * comma-separated, appended to out. 1 done; 0 the record path decides (a position that is not an
 * int in the vector, or a null among the values); -1 error. */
static int select_text(const batch *b, const plan *p, const parts *ps, cv_buffer *out) {
    const selection *s = &b->selections[p->selection];
    if (!s->valid) return 0;
    const char *text = ps->text + ps->start[p->v[0]];
    Py_ssize_t length = ps->length[p->v[0]];
    Py_ssize_t local[256], *starts = local, cap = 255;
    Py_ssize_t n = element_starts(text, length, starts, cap);
    if (n < 0) { /* a long vector: count, then the exact size */
        cap = 1;
        for (Py_ssize_t k = 0; k < length; k++) cap += text[k] == ',';
        starts = PyMem_Malloc((size_t)(cap + 1) * sizeof(Py_ssize_t));
        if (starts == NULL) return PyErr_NoMemory(), -1;
        n = element_starts(text, length, starts, cap);
    }
    Py_ssize_t mark = out->size;
    int result = 1;
    for (Py_ssize_t k = 0; k < s->n && result == 1; k++) {
        long long e = s->at[k];
        if (e >= n) result = 0;
        else if ((k && PUT_LITERAL(out, ",")) || put(out, text + starts[e], starts[e + 1] - 1 - starts[e])) result = -1;
    }
    if (starts != local) PyMem_Free(starts);
    if (result == 1 && memchr(out->data + mark, 'n', (size_t)(out->size - mark)) != NULL) result = 0;
    return result;
}

int cv_rows_splice(const cv_rows *t, Py_ssize_t r, cv_buffer *out) {
    const plan *p = &t->plans[r];
    if (p->kind == PLAN_RECORD_PATH || plan_has_null(p, &t->ps, t->null_parts, t->keys.items)) return 0;
    if (p->kind == PLAN_STEP) return splice_step(out, p, &t->ps, t->keys.items) ? -1 : 1;
    Py_ssize_t mark = out->size;
    int result = splice_call(out, p, &t->ps, &t->b);
    if (result == 0) out->size = mark; /* nothing of a row the record path prints */
    return result;
}

PyObject *cv_rows_encode(PyObject *self, PyObject *args) {
    (void)self;
    PyObject *rows, *name_of;
    if (!PyArg_ParseTuple(args, "O!O:encode_rows", &PyList_Type, &rows, &name_of)) return NULL;
    Py_ssize_t n_rows = PyList_GET_SIZE(rows);
    PyObject *result = NULL, **row = PyMem_Malloc((size_t)(n_rows ? n_rows : 1) * sizeof(PyObject *));
    char *is_step = PyMem_Malloc((size_t)(n_rows ? n_rows : 1));
    cv_rows *t = NULL;
    cv_buffer out = {0};
    if (row == NULL || is_step == NULL) {
        PyErr_NoMemory();
        goto done;
    }
    for (Py_ssize_t r = 0; r < n_rows; r++) {
        PyObject *item = PyList_GET_ITEM(rows, r);
        if (!PyTuple_CheckExact(item) || PyTuple_GET_SIZE(item) != 2) {
            PyErr_SetString(PyExc_TypeError, "encode takes a list of (is_step, row) pairs");
            goto done;
        }
        int truth = PyObject_IsTrue(PyTuple_GET_ITEM(item, 0));
        if (truth < 0) goto done;
        is_step[r] = (char)truth;
        row[r] = PyTuple_GET_ITEM(item, 1);
    }
    t = cv_rows_prepare(row, is_step, n_rows, name_of);
    if (t == NULL) goto done;
    result = PyList_New(n_rows);
    if (result == NULL) goto done;
    for (Py_ssize_t r = 0; r < n_rows; r++) {
        out.size = 0;
        int spliced = cv_rows_splice(t, r, &out);
        PyObject *payload = spliced < 0 ? NULL : spliced ? PyBytes_FromStringAndSize(out.data, out.size) : Py_NewRef(Py_None);
        if (payload == NULL) {
            Py_CLEAR(result);
            goto done;
        }
        PyList_SET_ITEM(result, r, payload);
    }
done:
    cv_rows_free(t);
    PyMem_Free(out.data);
    PyMem_Free(row);
    PyMem_Free(is_step);
    return result;
}

PyObject *cv_rows_configure(PyObject *self, PyObject *args) {
    (void)self;
    PyObject *dumps, *option, *float32_array, *exact_or_float32, *outcomes, *error_json, *ndarray_type, *float32,
        *probes;
    if (!PyArg_ParseTuple(args, "OOOOO!OOOO!:configure_rows", &dumps, &option, &float32_array, &exact_or_float32,
                          &PyDict_Type, &outcomes, &error_json, &ndarray_type, &float32, &PyList_Type, &probes))
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
    Py_XSETREF(s_float32, Py_NewRef(float32));
    /* Each probe classified by the buffer protocol, then by the array head: they must agree, and
     * the head must name the data and length the buffer does. */
    Py_ssize_t n_probes = PyList_GET_SIZE(probes);
    int agree = n_probes > 0;
    g_array_head_ok = 0; /* on every way out that does not reach the end */
    for (Py_ssize_t i = 0; i < n_probes && agree; i++) {
        PyObject *probe = PyList_GET_ITEM(probes, i);
        if ((PyObject *)Py_TYPE(probe) != s_ndarray_type) return PyErr_Format(PyExc_TypeError, "probes are arrays");
        g_array_head_ok = 0;
        int by_buffer = is_float32_vector(probe);
        g_array_head_ok = 1;
        agree = is_float32_vector(probe) == by_buffer;
        g_array_head_ok = 0;
        const array_head *a = (const array_head *)probe;
        if (agree && a->nd == 1) {
            Py_buffer view;
            if (PyObject_GetBuffer(probe, &view, PyBUF_STRIDES) < 0) return NULL;
            agree = view.buf == a->data && view.shape[0] == a->dimensions[0] && view.strides[0] == a->strides[0];
            PyBuffer_Release(&view);
        }
    }
    g_array_head_ok = agree;
    return PyBool_FromLong(agree);
}

int cv_rows_init(void) {
    s_eef_pos = PyUnicode_InternFromString("eef_pos");
    s_eef_force = PyUnicode_InternFromString("eef_force");
    return s_eef_pos == NULL || s_eef_force == NULL ? -1 : 0;
}
