/* capevo.runtime.governance._fused: R(a, Φ) for a whole Φ in one call.
 *
 * Program(specs, dim, n_arms, rot, labels) is built once per governor (see fused.py). Calling it
 * as program(arms, action, enforce=True) returns
 *   True                          allow: no check intervened;
 *   None                          fall back: run the Python checks for this call (an input the
 *                                 kernel does not take exactly: not a flat sequence of exact
 *                                 floats of the right length, a non-finite value, a state field
 *                                 of another type, or a check's rare path);
 *   (governed, records, indices)  interventions: ``governed`` the last record's result (None
 *                                 for ⊥), ``records`` the Intervention records exactly as the
 *                                 Python governor builds them (``enforced`` = enforce), ``indices``
 *                                 the index in Φ of each record's check (for the counters).
 * It never raises for bad input (that is the Python path's job) and never touches the counters.
 */
#define PY_SSIZE_T_CLEAN
#include <Python.h>
#include <string.h>

#include "kernel.h"

double cv_shrink = 1.0 - 1e-9;

typedef struct {
    const char *kind;
    cv_check_fn fn;
} cv_kind;

static const cv_kind KINDS[] = {
    {"workspace_box", cv_check_workspace_box},
    {"contact_force", cv_check_contact_force},
    {"velocity_cap", cv_check_velocity_cap},
    {"forbidden_zone", cv_check_forbidden_zone},
    {"workspace_guard", cv_check_workspace_guard},
    {"force_ramp", cv_check_force_ramp},
    {"contact_approach", cv_check_contact_approach},
    {"surface_approach", cv_check_surface_approach},
    {"obstacle_approach", cv_check_obstacle_approach},
    {"arm_separation", cv_check_arm_separation},
    {"reach_limit", cv_check_reach_limit},
};
#define N_KINDS ((int)(sizeof(KINDS) / sizeof(KINDS[0])))

typedef struct {
    cv_check_fn fn;
    cv_spec spec;
    double *f;
    long *i;
    PyObject *reasons; /* tuple of str */
} cv_compiled;

typedef struct {
    PyObject_HEAD
    vectorcallfunc vectorcall;
    PyObject *labels; /* tuple of str: each check's label, as interventions carry it */
    int dim;
    int n_arms;
    int n_checks;
    cv_compiled *checks;
    int n_rot;
    int rot_offset[CV_MAX_ARMS];
    double rot[CV_MAX_ARMS][9];
} Program;

static PyObject *s_eef_pos, *s_eef_force, *s_eef_rot, *s_near, *s_join_sep;

/* records.Intervention and the setters of its slots, given once by set_record_type(): records
 * are built here the way records.new_intervention builds them, without the frozen __setattr__. */
static PyTypeObject *record_type;
static PyObject *record_fields[5]; /* constraint, original, result, reason, enforced */

static PyObject *new_record(PyObject *constraint, PyObject *original, PyObject *result, PyObject *reason,
                            PyObject *enforced) {
    PyObject *values[5] = {constraint, original, result, reason, enforced};
    PyObject *obj = record_type->tp_alloc(record_type, 0);
    if (obj == NULL) return NULL;
    for (int k = 0; k < 5; k++)
        if (Py_TYPE(record_fields[k])->tp_descr_set(record_fields[k], obj, values[k]) < 0) {
            Py_DECREF(obj);
            return NULL;
        }
    return obj;
}

/* ---- reading inputs ---------------------------------------------------------------------- */

/* ``n`` exact floats from a tuple of exactly n; 0 on anything else. */
static int read_floats(PyObject *t, double *out, Py_ssize_t n) {
    if (!PyTuple_CheckExact(t) || PyTuple_GET_SIZE(t) != n) return 0;
    for (Py_ssize_t k = 0; k < n; k++) {
        PyObject *v = PyTuple_GET_ITEM(t, k);
        if (!PyFloat_CheckExact(v)) return 0;
        out[k] = PyFloat_AS_DOUBLE(v);
    }
    return 1;
}

/* getattr(obj, name) without raising (and paying for) AttributeError: 1 found (*out a new
 * reference), 0 missing, -1 another error (set). */
static int optional_attr(PyObject *obj, PyObject *name, PyObject **out) {
#if PY_VERSION_HEX >= 0x030D0000
    return PyObject_GetOptionalAttr(obj, name, out);
#else
    return _PyObject_LookupAttr(obj, name, out);
#endif
}

/* Fill one cv_arm from an ArmState / ArmPose / ArmScene; ``near_buf`` holds CV_MAX_NEAR * 8.
 * Returns 1, 0 (fall back) or -1 (a Python error is set). */
static int read_arm(PyObject *arm, cv_arm *out, double *near_buf) {
    PyObject *v;
    int ok;
    v = PyObject_GetAttr(arm, s_eef_pos);
    if (v == NULL) { PyErr_Clear(); return 0; }
    ok = read_floats(v, out->pos, 3);
    Py_DECREF(v);
    if (!ok) return 0;
    v = PyObject_GetAttr(arm, s_eef_force);
    if (v == NULL) { PyErr_Clear(); return 0; }
    ok = read_floats(v, out->force, 3);
    Py_DECREF(v);
    if (!ok) return 0;
    /* rotation_of(): eef_rot, or None when the state has none. */
    int found = optional_attr(arm, s_eef_rot, &v);
    if (found < 0) { PyErr_Clear(); return 0; }
    out->has_rot = found && v != Py_None;
    ok = out->has_rot ? read_floats(v, out->rot, 9) : 1;
    Py_XDECREF(v);
    if (!ok) return 0;
    out->n_near = 0;
    out->near = near_buf;
    /* near_of(): getattr(arm, "near", ()). */
    found = optional_attr(arm, s_near, &v);
    if (found < 0) { PyErr_Clear(); return 0; }
    if (!found) return 1;
    if (!PyTuple_CheckExact(v) || PyTuple_GET_SIZE(v) > CV_MAX_NEAR) { Py_DECREF(v); return 0; }
    Py_ssize_t n = PyTuple_GET_SIZE(v);
    for (Py_ssize_t p = 0; p < n; p++) {
        PyObject *pair = PyTuple_GET_ITEM(v, p);
        if (!PyTuple_CheckExact(pair) || PyTuple_GET_SIZE(pair) != 8) { Py_DECREF(v); return 0; }
        double *row = near_buf + 8 * p;
        for (int k = 0; k < 7; k++) {
            PyObject *x = PyTuple_GET_ITEM(pair, k);
            if (!PyFloat_CheckExact(x)) { Py_DECREF(v); return 0; }
            row[k] = PyFloat_AS_DOUBLE(x);
        }
        PyObject *owner = PyTuple_GET_ITEM(pair, 7);
        if (!PyLong_CheckExact(owner)) { Py_DECREF(v); return 0; }
        long o = PyLong_AsLong(owner);
        if (o == -1 && PyErr_Occurred()) { PyErr_Clear(); Py_DECREF(v); return 0; }
        if (o < -1000 || o > 1000) { Py_DECREF(v); return 0; }
        row[7] = (double)o;
    }
    out->n_near = (int)n;
    Py_DECREF(v);
    return 1;
}

/* The action as ``dim`` finite doubles: a list or tuple of exact floats, or a C-contiguous 1-D
 * float64 buffer (a numpy array, which the Python path turns into floats with tolist()). */
static int read_action(PyObject *action, double *a, int dim) {
    if (PyList_CheckExact(action) || PyTuple_CheckExact(action)) {
        Py_ssize_t n = PySequence_Fast_GET_SIZE(action);
        if (n != dim) return 0;
        PyObject **items = PySequence_Fast_ITEMS(action);
        for (Py_ssize_t k = 0; k < n; k++) {
            if (!PyFloat_CheckExact(items[k])) return 0;
            a[k] = PyFloat_AS_DOUBLE(items[k]);
        }
    } else if (PyObject_CheckBuffer(action)) {
        Py_buffer view;
        if (PyObject_GetBuffer(action, &view, PyBUF_C_CONTIGUOUS | PyBUF_FORMAT) != 0) {
            PyErr_Clear();
            return 0;
        }
        /* float64 as is, float32 widened exactly (what tolist() gives); anything else is Python's. */
        int is_d = view.format != NULL && strcmp(view.format, "d") == 0 && view.itemsize == (Py_ssize_t)sizeof(double);
        int is_f = view.format != NULL && strcmp(view.format, "f") == 0 && view.itemsize == (Py_ssize_t)sizeof(float);
        int ok = view.ndim == 1 && view.shape != NULL && view.shape[0] == dim && (is_d || is_f);
        if (ok && is_d) memcpy(a, view.buf, sizeof(double) * (size_t)dim);
        if (ok && is_f)
            for (int k = 0; k < dim; k++) a[k] = (double)((const float *)view.buf)[k];
        PyBuffer_Release(&view);
        if (!ok) return 0;
    } else {
        return 0;
    }
    for (int k = 0; k < dim; k++)
        if (!isfinite(a[k])) return 0;
    return 1;
}

/* governor._rotate, the same operations in the same order. */
static void rotate(const Program *p, const double *in, double *out, int to_world) {
    memcpy(out, in, sizeof(double) * (size_t)p->dim);
    for (int j = 0; j < p->n_rot; j++) {
        int o = p->rot_offset[j];
        const double *r = p->rot[j];
        double x = in[o], y = in[o + 1], z = in[o + 2];
        if (to_world) {
            out[o] = r[0] * x + r[1] * y + r[2] * z;
            out[o + 1] = r[3] * x + r[4] * y + r[5] * z;
            out[o + 2] = r[6] * x + r[7] * y + r[8] * z;
        } else {
            out[o] = r[0] * x + r[3] * y + r[6] * z;
            out[o + 1] = r[1] * x + r[4] * y + r[7] * z;
            out[o + 2] = r[2] * x + r[5] * y + r[8] * z;
        }
    }
}

static PyObject *float_tuple(const double *v, int n) {
    PyObject *t = PyTuple_New(n);
    if (t == NULL) return NULL;
    for (int k = 0; k < n; k++) {
        PyObject *x = PyFloat_FromDouble(v[k]);
        if (x == NULL) { Py_DECREF(t); return NULL; }
        PyTuple_SET_ITEM(t, k, x);
    }
    return t;
}

/* The action-frame tuple of a world-frame action. */
static PyObject *action_tuple(const Program *p, const double *world) {
    if (p->n_rot == 0) return float_tuple(world, p->dim);
    double local[CV_MAX_DIM];
    rotate(p, world, local, 0);
    return float_tuple(local, p->dim);
}

static PyObject *reason_of(const cv_compiled *c, const cv_reasons *r) {
    if (r->n == 1) {
        PyObject *s = PyTuple_GET_ITEM(c->reasons, r->idx[0]);
        Py_INCREF(s);
        return s;
    }
    PyObject *parts = PyTuple_New(r->n);
    if (parts == NULL) return NULL;
    for (int k = 0; k < r->n; k++) {
        PyObject *s = PyTuple_GET_ITEM(c->reasons, r->idx[k]);
        Py_INCREF(s);
        PyTuple_SET_ITEM(parts, k, s);
    }
    PyObject *joined = PyUnicode_Join(s_join_sep, parts);
    Py_DECREF(parts);
    return joined;
}

/* ---- the call ---------------------------------------------------------------------------- */

static PyObject *program_run(Program *p, PyObject *arms, PyObject *action, PyObject *enforced) {
    cv_state s;
    double near_bufs[CV_MAX_ARMS][CV_MAX_NEAR * 8];
    double input[CV_MAX_DIM], bufs[2][CV_MAX_DIM];

    if (!read_action(action, input, p->dim)) Py_RETURN_NONE;
    if (!PyTuple_CheckExact(arms) || PyTuple_GET_SIZE(arms) != p->n_arms) Py_RETURN_NONE;
    s.n_arms = p->n_arms;
    s.dim = p->dim;
    for (int j = 0; j < p->n_arms; j++) {
        int ok = read_arm(PyTuple_GET_ITEM(arms, j), &s.arms[j], near_bufs[j]);
        if (ok < 0) return NULL;
        if (ok == 0) Py_RETURN_NONE;
    }
    double *cur = bufs[0], *out = bufs[1];
    if (p->n_rot) rotate(p, input, cur, 1);
    else memcpy(cur, input, sizeof(double) * (size_t)p->dim);

    /* Interventions are rare: remember them as (check, verdict, reasons, a′) and build Python
     * objects only once the whole pass is known not to fall back. */
    int hit_check[64], hit_verdict[64];
    cv_reasons hit_reasons[64];
    double hit_result[64][CV_MAX_DIM];
    double first[CV_MAX_DIM];
    int n_hits = 0;
    memcpy(first, cur, sizeof(double) * (size_t)p->dim);
    for (int c = 0; c < p->n_checks; c++) {
        cv_compiled *ck = &p->checks[c];
        cv_reasons r;
        r.n = 0;
        memcpy(out, cur, sizeof(double) * (size_t)p->dim);
        int v = ck->fn(&ck->spec, &s, cur, out, &r);
        if (v == CV_ALLOW) continue;
        if (v != CV_MODIFY && v != CV_REJECT) Py_RETURN_NONE;
        if (r.n < 1 || r.n > CV_MAX_REASONS || n_hits >= 64) Py_RETURN_NONE;
        for (int k = 0; k < r.n; k++)
            if (r.idx[k] < 0 || r.idx[k] >= ck->spec.n_reasons) Py_RETURN_NONE;
        hit_check[n_hits] = c;
        hit_verdict[n_hits] = v;
        hit_reasons[n_hits] = r;
        if (v == CV_MODIFY) memcpy(hit_result[n_hits], out, sizeof(double) * (size_t)p->dim);
        n_hits++;
        if (v == CV_REJECT) break;
        double *t = cur; cur = out; out = t;
    }
    if (n_hits == 0) Py_RETURN_TRUE;

    /* As Governor._intervene records them: each record's original is the previous result. */
    PyObject *original = action_tuple(p, first);
    PyObject *records = PyTuple_New(n_hits);
    PyObject *indices = PyTuple_New(n_hits);
    if (original == NULL || records == NULL || indices == NULL) goto fail;
    for (int h = 0; h < n_hits; h++) {
        cv_compiled *ck = &p->checks[hit_check[h]];
        PyObject *result, *reason, *index, *record;
        if (hit_verdict[h] == CV_MODIFY) {
            result = action_tuple(p, hit_result[h]);
        } else {
            result = Py_None;
            Py_INCREF(result);
        }
        reason = reason_of(ck, &hit_reasons[h]);
        index = PyLong_FromLong(hit_check[h]);
        if (result == NULL || reason == NULL || index == NULL) {
            Py_XDECREF(result); Py_XDECREF(reason); Py_XDECREF(index);
            goto fail;
        }
        record = new_record(PyTuple_GET_ITEM(p->labels, hit_check[h]), original, result, reason, enforced);
        Py_DECREF(reason);
        if (record == NULL) { Py_DECREF(result); Py_DECREF(index); goto fail; }
        PyTuple_SET_ITEM(records, h, record);
        PyTuple_SET_ITEM(indices, h, index);
        Py_DECREF(original);
        original = result; /* the next record's original; after the loop, the governed action */
    }
    PyObject *ret = PyTuple_Pack(3, original, records, indices);
    Py_DECREF(original);
    Py_DECREF(records);
    Py_DECREF(indices);
    return ret;
fail:
    Py_XDECREF(original);
    Py_XDECREF(records);
    Py_XDECREF(indices);
    return NULL;
}

static PyObject *program_vectorcall(PyObject *self, PyObject *const *args, size_t nargsf, PyObject *kwnames) {
    Py_ssize_t n = PyVectorcall_NARGS(nargsf);
    /* ``enforce`` goes into the records as given, as the Python governor stores it. */
    if (n < 2 || n > 3 || (kwnames != NULL && PyTuple_GET_SIZE(kwnames) != 0)) {
        PyErr_SetString(PyExc_TypeError, "program(arms, action, enforce=True) takes positional arguments only");
        return NULL;
    }
    if (record_type == NULL) {
        PyErr_SetString(PyExc_RuntimeError, "set_record_type() was not called");
        return NULL;
    }
    return program_run((Program *)self, args[0], args[1], n == 3 ? args[2] : Py_True);
}

/* ---- construction ------------------------------------------------------------------------ */

static void program_free_checks(Program *p) {
    if (p->checks == NULL) return;
    for (int c = 0; c < p->n_checks; c++) {
        PyMem_Free(p->checks[c].f);
        PyMem_Free(p->checks[c].i);
        Py_XDECREF(p->checks[c].reasons);
    }
    PyMem_Free(p->checks);
    p->checks = NULL;
}

static void program_dealloc(Program *p) {
    program_free_checks(p);
    Py_XDECREF(p->labels);
    Py_TYPE(p)->tp_free((PyObject *)p);
}

static int fill_check(cv_compiled *c, PyObject *spec) {
    const char *kind;
    PyObject *floats, *ints, *reasons;
    if (!PyArg_ParseTuple(spec, "sO!O!O!", &kind, &PyTuple_Type, &floats, &PyTuple_Type, &ints, &PyTuple_Type,
                          &reasons))
        return -1;
    c->fn = NULL;
    for (int k = 0; k < N_KINDS; k++)
        if (strcmp(KINDS[k].kind, kind) == 0) c->fn = KINDS[k].fn;
    if (c->fn == NULL) {
        PyErr_Format(PyExc_ValueError, "no kernel check for constraint kind %s", kind);
        return -1;
    }
    Py_ssize_t nf = PyTuple_GET_SIZE(floats), ni = PyTuple_GET_SIZE(ints), nr = PyTuple_GET_SIZE(reasons);
    c->f = PyMem_Malloc(sizeof(double) * (size_t)(nf + 1));
    c->i = PyMem_Malloc(sizeof(long) * (size_t)(ni + 1));
    if (c->f == NULL || c->i == NULL) { PyErr_NoMemory(); return -1; }
    for (Py_ssize_t k = 0; k < nf; k++) {
        PyObject *x = PyTuple_GET_ITEM(floats, k);
        if (!PyFloat_CheckExact(x)) {
            PyErr_Format(PyExc_TypeError, "%s: float parameter %zd is not a float", kind, k);
            return -1;
        }
        c->f[k] = PyFloat_AS_DOUBLE(x);
    }
    for (Py_ssize_t k = 0; k < ni; k++) {
        long v = PyLong_AsLong(PyTuple_GET_ITEM(ints, k));
        if (v == -1 && PyErr_Occurred()) return -1;
        c->i[k] = v;
    }
    for (Py_ssize_t k = 0; k < nr; k++)
        if (!PyUnicode_CheckExact(PyTuple_GET_ITEM(reasons, k))) {
            PyErr_Format(PyExc_TypeError, "%s: reason %zd is not a str", kind, k);
            return -1;
        }
    Py_INCREF(reasons);
    c->reasons = reasons;
    c->spec.f = c->f;
    c->spec.nf = (int)nf;
    c->spec.i = c->i;
    c->spec.ni = (int)ni;
    c->spec.n_reasons = (int)nr;
    return 0;
}

static PyObject *program_new(PyTypeObject *type, PyObject *args, PyObject *kwds) {
    static char *kwlist[] = {"specs", "dim", "n_arms", "rot", "labels", NULL};
    PyObject *specs, *rot, *labels;
    int dim, n_arms;
    if (!PyArg_ParseTupleAndKeywords(args, kwds, "O!iiO!O!", kwlist, &PyTuple_Type, &specs, &dim, &n_arms,
                                     &PyTuple_Type, &rot, &PyTuple_Type, &labels))
        return NULL;
    if (PyTuple_GET_SIZE(labels) != PyTuple_GET_SIZE(specs)) {
        PyErr_SetString(PyExc_ValueError, "Program: one label per spec");
        return NULL;
    }
    if (dim < 1 || dim > CV_MAX_DIM || n_arms < 1 || n_arms > CV_MAX_ARMS || PyTuple_GET_SIZE(specs) > 64 ||
        PyTuple_GET_SIZE(rot) > CV_MAX_ARMS) {
        PyErr_SetString(PyExc_ValueError, "Program: dim, arms, checks or frames out of the kernel's range");
        return NULL;
    }
    Program *p = (Program *)type->tp_alloc(type, 0);
    if (p == NULL) return NULL;
    p->vectorcall = program_vectorcall;
    Py_INCREF(labels);
    p->labels = labels;
    p->dim = dim;
    p->n_arms = n_arms;
    p->n_checks = (int)PyTuple_GET_SIZE(specs);
    p->checks = PyMem_Calloc((size_t)p->n_checks + 1, sizeof(cv_compiled));
    if (p->checks == NULL) { Py_DECREF(p); return PyErr_NoMemory(); }
    for (int c = 0; c < p->n_checks; c++)
        if (fill_check(&p->checks[c], PyTuple_GET_ITEM(specs, c)) < 0) { Py_DECREF(p); return NULL; }
    p->n_rot = (int)PyTuple_GET_SIZE(rot);
    for (int j = 0; j < p->n_rot; j++) {
        PyObject *r9;
        int off;
        if (!PyArg_ParseTuple(PyTuple_GET_ITEM(rot, j), "iO!", &off, &PyTuple_Type, &r9) ||
            !read_floats(r9, p->rot[j], 9) || off < 0 || off + 3 > dim) {
            if (!PyErr_Occurred()) PyErr_SetString(PyExc_ValueError, "Program: bad frame");
            Py_DECREF(p);
            return NULL;
        }
        p->rot_offset[j] = off;
    }
    return (PyObject *)p;
}

static PyTypeObject ProgramType = {
    PyVarObject_HEAD_INIT(NULL, 0).tp_name = "capevo.runtime.governance._fused.Program",
    .tp_basicsize = sizeof(Program),
    .tp_dealloc = (destructor)program_dealloc,
    .tp_vectorcall_offset = offsetof(Program, vectorcall),
    .tp_call = PyVectorcall_Call,
    .tp_flags = Py_TPFLAGS_DEFAULT | Py_TPFLAGS_HAVE_VECTORCALL,
    .tp_doc = "A Φ compiled for one action layout: program(arms, action, enforce) -> True | None | "
              "(governed, records, check indices).",
    .tp_new = program_new,
};

static PyObject *kinds(PyObject *self, PyObject *unused) {
    PyObject *t = PyTuple_New(N_KINDS);
    if (t == NULL) return NULL;
    for (int k = 0; k < N_KINDS; k++) {
        PyObject *s = PyUnicode_FromString(KINDS[k].kind);
        if (s == NULL) { Py_DECREF(t); return NULL; }
        PyTuple_SET_ITEM(t, k, s);
    }
    return t;
}

static PyObject *set_shrink(PyObject *self, PyObject *arg) {
    double v = PyFloat_AsDouble(arg);
    if (v == -1.0 && PyErr_Occurred()) return NULL;
    cv_shrink = v;
    Py_RETURN_NONE;
}

static PyObject *set_record_type(PyObject *self, PyObject *cls) {
    static const char *names[5] = {"constraint", "original", "result", "reason", "enforced"};
    if (!PyType_Check(cls)) {
        PyErr_SetString(PyExc_TypeError, "set_record_type takes the Intervention class");
        return NULL;
    }
    PyObject *fields[5];
    for (int k = 0; k < 5; k++) {
        /* The slot's member descriptor from the class's own dict (the class attribute lookup would
         * find the same object; its __set__ writes the slot directly). */
        fields[k] = PyDict_GetItemString(((PyTypeObject *)cls)->tp_dict, names[k]);
        if (fields[k] == NULL || Py_TYPE(fields[k])->tp_descr_set == NULL) {
            PyErr_Format(PyExc_TypeError, "record type has no slot %s", names[k]);
            return NULL;
        }
    }
    for (int k = 0; k < 5; k++) {
        Py_INCREF(fields[k]);
        Py_XSETREF(record_fields[k], fields[k]);
    }
    Py_INCREF(cls);
    Py_XSETREF(record_type, (PyTypeObject *)cls);
    Py_RETURN_NONE;
}

static PyMethodDef methods[] = {
    {"set_record_type", set_record_type, METH_O, "Set records.Intervention (called once at import)."},
    {"kinds", kinds, METH_NOARGS, "The constraint kinds the kernel has a check for."},
    {"set_shrink", set_shrink, METH_O, "Set cap.SHRINK (called once at import)."},
    {NULL, NULL, 0, NULL},
};

static struct PyModuleDef moduledef = {
    PyModuleDef_HEAD_INIT, "_fused", "The fused governance kernel (see capevo.runtime.governance.fused).", -1,
    methods,
};

PyMODINIT_FUNC PyInit__fused(void) {
    if (PyType_Ready(&ProgramType) < 0) return NULL;
    s_eef_pos = PyUnicode_InternFromString("eef_pos");
    s_eef_force = PyUnicode_InternFromString("eef_force");
    s_eef_rot = PyUnicode_InternFromString("eef_rot");
    s_near = PyUnicode_InternFromString("near");
    s_join_sep = PyUnicode_InternFromString("; ");
    if (!s_eef_pos || !s_eef_force || !s_eef_rot || !s_near || !s_join_sep) return NULL;
    PyObject *m = PyModule_Create(&moduledef);
    if (m == NULL) return NULL;
    Py_INCREF(&ProgramType);
    if (PyModule_AddObject(m, "Program", (PyObject *)&ProgramType) < 0) {
        Py_DECREF(&ProgramType);
        Py_DECREF(m);
        return NULL;
    }
    return m;
}
