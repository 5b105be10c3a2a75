/* pmask.runtime.servo._core: the CPython binding of the native servo core (pmask_servo.h, core/).
 *
 * Thin on purpose: it converts probes exactly as the Python engine's float() does (PyNumber_Float; a
 * value that does not convert becomes NaN, a bad sample), calls pm_servo_step, and returns the same
 * objects the Python engine returns (tuples of floats, pmask.runtime.Status members).  The step runs
 * with the GIL held (it takes ~0.1-0.3 µs, less than releasing and taking the GIL back); the thread
 * mode's ticks never touch the GIL, and deformation and batch queries release it.  The one exception: a servo
 * made with a Python pair function (coupled contacts on a compressed artifact, pm_servo_create_paired) calls it,
 * taking the GIL on the servo's own thread, when a pair of contacts first lands on a pair of triangles.
 */
#define PY_SSIZE_T_CLEAN
#include <Python.h>

#include <math.h>
#include <string.h>

#include "pmask_servo.h"

#if PY_VERSION_HEX >= 0x030D0000
#define pm_py_finalizing Py_IsFinalizing
#else
#define pm_py_finalizing _Py_IsFinalizing
#endif

static PyObject *STATUS = NULL;   /* tuple of the 8 Status members, set by set_statuses */

static PyObject *status_object(int32_t s)
{
    if (STATUS && s >= 0 && s < PyTuple_GET_SIZE(STATUS)) {
        PyObject *o = PyTuple_GET_ITEM(STATUS, s);
        Py_INCREF(o);
        return o;
    }
    return PyLong_FromLong(s);
}

/* ------------------------------------------------------------------ probe conversion */
/* a coordinate: a real number that is not a truth value or text (the Python engine's tracking.coordinate) */
static int not_a_coordinate(PyObject *o)
{
    if (PyBool_Check(o) || PyUnicode_Check(o) || PyBytes_Check(o) || PyByteArray_Check(o)) return 1;
    const char *name = Py_TYPE(o)->tp_name;  /* numpy's bool scalar converts to 0.0 / 1.0 as Python's does */
    return strcmp(name, "numpy.bool") == 0 || strcmp(name, "numpy.bool_") == 0;
}

static double to_double(PyObject *o)
{
    if (PyFloat_CheckExact(o)) return PyFloat_AS_DOUBLE(o);
    if (not_a_coordinate(o)) return NAN;
    PyObject *f = PyNumber_Float(o);   /* what float(o) does: __float__, __index__ */
    if (!f) {
        PyErr_Clear();
        return NAN;
    }
    double v = PyFloat_AS_DOUBLE(f);
    Py_DECREF(f);
    return v;
}

static int is_double_format(const char *f)
{
    return f && (strcmp(f, "d") == 0 || strcmp(f, "<d") == 0 || strcmp(f, "=d") == 0 || strcmp(f, "@d") == 0);
}

/* an 8-byte signed integer buffer (numpy's int64: "q", or "l" on LP64) */
static int is_int64_format(const char *f, Py_ssize_t itemsize)
{
    if (!f || itemsize != 8) return 0;
    if (*f == '<' || *f == '=' || *f == '@') f++;
    return strcmp(f, "q") == 0 || strcmp(f, "l") == 0;
}

/* one probe sample -> out[3]; anything that is not three numbers gives NaN (a bad sample) */
static void sample_from(PyObject *o, double *out)
{
    out[0] = out[1] = out[2] = NAN;
    if (PyUnicode_Check(o) || PyBytes_Check(o) || PyByteArray_Check(o)) return;  /* text is not a point */
    if ((PyTuple_CheckExact(o) || PyList_CheckExact(o)) && PySequence_Fast_GET_SIZE(o) == 3) {
        PyObject **it = PySequence_Fast_ITEMS(o);
        for (int k = 0; k < 3; k++) out[k] = to_double(it[k]);
        return;
    }
    if (PyObject_CheckBuffer(o)) {
        Py_buffer v;
        if (PyObject_GetBuffer(o, &v, PyBUF_RECORDS_RO) == 0) {
            int ok = v.ndim == 1 && v.shape[0] == 3 && is_double_format(v.format) && v.itemsize == 8;
            if (ok) {
                for (int k = 0; k < 3; k++) memcpy(&out[k], (const char *)v.buf + k * v.strides[0], 8);
            }
            PyBuffer_Release(&v);
            if (ok) return;
        } else {
            PyErr_Clear();
        }
    }
    PyObject *seq = PySequence_Fast(o, "");
    if (!seq) {
        PyErr_Clear();
        return;
    }
    if (PySequence_Fast_GET_SIZE(seq) == 3) {
        PyObject **it = PySequence_Fast_ITEMS(seq);
        for (int k = 0; k < 3; k++) out[k] = to_double(it[k]);
    }
    Py_DECREF(seq);
}

/* n probe samples -> out[3n]; a wrong count makes every sample bad, as the Python engine does */
static void probes_from(PyObject *o, int32_t n, double *out)
{
    for (int32_t k = 0; k < 3 * n; k++) out[k] = NAN;
    if (PyObject_CheckBuffer(o) && !PyTuple_CheckExact(o) && !PyList_CheckExact(o)) {
        Py_buffer v;
        if (PyObject_GetBuffer(o, &v, PyBUF_RECORDS_RO) == 0) {
            int ok = v.ndim == 2 && v.shape[0] == n && v.shape[1] == 3 && is_double_format(v.format) && v.itemsize == 8;
            if (ok)
                for (int32_t l = 0; l < n; l++)
                    for (int k = 0; k < 3; k++)
                        memcpy(&out[3 * l + k], (const char *)v.buf + l * v.strides[0] + k * v.strides[1], 8);
            PyBuffer_Release(&v);
            if (ok) return;
        } else {
            PyErr_Clear();
        }
    }
    PyObject *seq = PySequence_Fast(o, "");
    if (!seq) {
        PyErr_Clear();
        return;
    }
    if (PySequence_Fast_GET_SIZE(seq) == n) {
        PyObject **it = PySequence_Fast_ITEMS(seq);
        for (int32_t l = 0; l < n; l++) sample_from(it[l], out + 3 * l);
    }
    Py_DECREF(seq);
}

static PyObject *triple(const double *v)
{
    PyObject *t = PyTuple_New(3);
    if (!t) return NULL;
    for (int k = 0; k < 3; k++) {
        PyObject *f = PyFloat_FromDouble(v[k]);
        if (!f) {
            Py_DECREF(t);
            return NULL;
        }
        PyTuple_SET_ITEM(t, k, f);
    }
    return t;
}

/* ------------------------------------------------------------------ Table */
typedef struct {
    PyObject_HEAD
    pm_table *table;
    Py_buffer *views;   /* Table(dict): the arrays the table points into, held until it is freed */
    Py_ssize_t nviews;
} TableObject;

static void release_views(TableObject *self)
{
    for (Py_ssize_t i = 0; i < self->nviews; i++) PyBuffer_Release(&self->views[i]);
    PyMem_Free(self->views);
    self->views = NULL;
    self->nviews = 0;
}

static void Table_dealloc(TableObject *self)
{
    pm_table_free(self->table);
    release_views(self);
    Py_TYPE(self)->tp_free((PyObject *)self);
}

/* Table({name: array}): the sections as C-contiguous 2-D float64/int64 buffers, or raw bytes (bytes, or a 1-D
 * uint8 array: "meta", a compressed Xi's 16-bit and float32 sections), borrowed (pm_table_from_sections) */
static int table_from_sections_dict(TableObject *self, PyObject *dict, char *err, size_t errlen)
{
    Py_ssize_t n = PyDict_Size(dict), pos = 0, i = 0;
    PyObject *key, *value;
    if (n > 4096) {
        PyErr_SetString(PyExc_ValueError, "too many sections");
        return -2;
    }
    self->views = PyMem_Calloc((size_t)(n ? n : 1), sizeof(Py_buffer));
    pm_section *secs = PyMem_Calloc((size_t)(n ? n : 1), sizeof(pm_section));
    if (!self->views || !secs) {
        PyMem_Free(secs);
        PyErr_NoMemory();
        return -2;
    }
    while (PyDict_Next(dict, &pos, &key, &value)) {
        const char *name = PyUnicode_Check(key) ? PyUnicode_AsUTF8(key) : NULL;
        if (!name) {
            PyMem_Free(secs);
            if (!PyErr_Occurred()) PyErr_SetString(PyExc_TypeError, "section names must be str");
            return -2;
        }
        Py_buffer *v = &self->views[i];
        int bytes = PyBytes_Check(value);
        if (PyObject_GetBuffer(value, v, bytes ? PyBUF_SIMPLE : (PyBUF_C_CONTIGUOUS | PyBUF_FORMAT))) {
            PyMem_Free(secs);
            return -2;
        }
        self->nviews = ++i;
        pm_section *s = &secs[i - 1];
        s->name = name;
        s->data = v->buf;
        if (bytes) {
            s->dtype = PM_SECTION_BYTES;
            s->rows = (int64_t)v->len;
            s->cols = 1;
            continue;
        }
        if (v->ndim == 1 && v->itemsize == 1 && v->format && !strcmp(v->format, "B")) {  /* uint8: raw bytes */
            s->dtype = PM_SECTION_BYTES;
            s->rows = (int64_t)v->len;
            s->cols = 1;
            continue;
        }
        int f64 = is_double_format(v->format) && v->itemsize == 8, i64 = is_int64_format(v->format, v->itemsize);
        if (v->ndim != 2 || !(f64 || i64)) {
            PyMem_Free(secs);
            PyErr_Format(PyExc_ValueError, "section '%s' must be a 2-D float64 or int64 array or 1-D uint8 bytes",
                         name);
            return -2;
        }
        s->dtype = f64 ? PM_SECTION_F64 : PM_SECTION_I64;
        s->rows = (int64_t)v->shape[0];
        s->cols = (int64_t)v->shape[1];
    }
    int rc;
    Py_BEGIN_ALLOW_THREADS
    rc = pm_table_from_sections(secs, (int32_t)n, &self->table, err, errlen);
    Py_END_ALLOW_THREADS
    PyMem_Free(secs);
    return rc;
}

static int table_from_dict(TableObject *self, PyObject *given, char *err, size_t errlen)
{
    PyObject *dict = PyDict_Copy(given);  /* its keys (the names) stay alive while the GIL is released */
    if (!dict) return -2;
    int rc = table_from_sections_dict(self, dict, err, errlen);
    Py_DECREF(dict);
    return rc;
}

static int Table_init(TableObject *self, PyObject *args, PyObject *kw)
{
    PyObject *src;
    if (!PyArg_ParseTuple(args, "O", &src)) return -1;
    char err[512] = "";
    int rc;
    if (self->table || self->views) {
        PyErr_SetString(PyExc_RuntimeError, "Table is already initialised");
        return -1;
    }
    if (PyDict_Check(src)) {
        rc = table_from_dict(self, src, err, sizeof err);
        if (rc == -2) {
            release_views(self);
            return -1;
        }
        if (rc) release_views(self);
    } else if (PyObject_CheckBuffer(src)) {
        Py_buffer v;
        if (PyObject_GetBuffer(src, &v, PyBUF_SIMPLE)) return -1;
        Py_BEGIN_ALLOW_THREADS
        rc = pm_table_from_memory(v.buf, (size_t)v.len, &self->table, err, sizeof err);
        Py_END_ALLOW_THREADS
        PyBuffer_Release(&v);
    } else {
        PyObject *path = NULL;
        if (!PyUnicode_FSConverter(src, &path)) return -1;
        const char *p = PyBytes_AS_STRING(path);
        Py_BEGIN_ALLOW_THREADS
        rc = pm_table_load(p, &self->table, err, sizeof err);
        Py_END_ALLOW_THREADS
        Py_DECREF(path);
    }
    if (rc) {
        PyErr_SetString(PyExc_ValueError, err);
        return -1;
    }
    return 0;
}

static PyObject *Table_counts(TableObject *self, PyObject *unused)
{
    return Py_BuildValue("LLi", (long long)pm_table_vertices(self->table), (long long)pm_table_triangles(self->table),
                         (int)pm_table_has_zeta(self->table));
}

static PyObject *Table_points(TableObject *self, PyObject *unused)
{
    return PyBytes_FromStringAndSize((const char *)pm_table_points(self->table),
                                     (Py_ssize_t)(24 * pm_table_vertices(self->table)));
}

static PyObject *Table_has_greens(TableObject *self, PyObject *unused)
{
    return PyBool_FromLong(pm_table_has_greens(self->table));
}

static PyObject *Table_pair_blocks(TableObject *self, PyObject *args)
{
    long long ta, tb;
    if (!PyArg_ParseTuple(args, "LL", &ta, &tb)) return NULL;
    double P[81];
    if (pm_table_pair_blocks(self->table, (int64_t)ta, (int64_t)tb, P)) {
        PyErr_SetString(PyExc_ValueError, "no coupling blocks: the table has neither a zeta table nor a compressed "
                        "Xi, or a triangle is out of range");
        return NULL;
    }
    PyObject *out = PyList_New(81);
    if (!out) return NULL;
    for (int k = 0; k < 81; k++) {
        PyObject *v = PyFloat_FromDouble(P[k]);
        if (!v) {
            Py_DECREF(out);
            return NULL;
        }
        PyList_SET_ITEM(out, k, v);
    }
    return out;
}

static PyObject *Table_meta(TableObject *self, PyObject *unused)
{
    return PyUnicode_FromString(pm_table_meta(self->table));
}

static PyObject *Table_nearest(TableObject *self, PyObject *arg)
{
    double p[3];
    sample_from(arg, p);
    if (!(isfinite(p[0]) && isfinite(p[1]) && isfinite(p[2]))) {
        PyErr_SetString(PyExc_ValueError, "the point must be 3 finite numbers");
        return NULL;
    }
    return PyLong_FromLongLong((long long)pm_table_nearest(self->table, p));
}

/* stiffness(triangles int64 (n,), barycentrics float64 (n, 3), out float64 (n, 9)): eq. 15 in a batch,
 * unchecked (the Python wrapper validates) */
static PyObject *Table_stiffness(TableObject *self, PyObject *args)
{
    Py_buffer t, b, o;
    if (!PyArg_ParseTuple(args, "y*y*w*", &t, &b, &o)) return NULL;
    Py_ssize_t n = t.len / 8;
    PyObject *res = NULL;
    if (b.len != n * 24 || o.len != n * 72) {
        PyErr_SetString(PyExc_ValueError, "stiffness: buffer sizes do not match");
    } else {
        Py_BEGIN_ALLOW_THREADS
        pm_table_stiffness(self->table, (int64_t)n, (const int64_t *)t.buf, (const double *)b.buf, (double *)o.buf);
        Py_END_ALLOW_THREADS
        res = Py_None;
        Py_INCREF(res);
    }
    PyBuffer_Release(&t);
    PyBuffer_Release(&b);
    PyBuffer_Release(&o);
    return res;
}

static PyObject *Table_display_deform(TableObject *self, PyObject *args)
{
    Py_buffer u, c, o;
    double radius;
    if (!PyArg_ParseTuple(args, "y*y*dw*", &u, &c, &radius, &o)) return NULL;
    PyObject *res = NULL;
    const int64_t nd = pm_display_vertices(self->table);
    if (u.len != pm_table_vertices(self->table) * 24 || c.len % 24 != 0 || c.len / 24 > INT32_MAX ||
        o.len != nd * 24) {
        PyErr_SetString(PyExc_ValueError, "display_deform: buffer sizes do not match");
    } else {
        Py_BEGIN_ALLOW_THREADS
        pm_display_deform(self->table, (const double *)u.buf, (int32_t)(c.len / 24), (const double *)c.buf, radius,
                          (double *)o.buf);
        Py_END_ALLOW_THREADS
        res = Py_None;
        Py_INCREF(res);
    }
    PyBuffer_Release(&u);
    PyBuffer_Release(&c);
    PyBuffer_Release(&o);
    return res;
}

static PyObject *Table_display_counts(TableObject *self, PyObject *unused)
{
    return Py_BuildValue("LL", (long long)pm_display_vertices(self->table),
                         (long long)pm_display_triangles(self->table));
}

static PyMethodDef Table_methods[] = {
    {"counts", (PyCFunction)Table_counts, METH_NOARGS, "(vertices, triangles, has_zeta)"},
    {"points", (PyCFunction)Table_points, METH_NOARGS, "the mesh's vertices at rest, as the contact surface has them"},
    {"pair_blocks", (PyCFunction)Table_pair_blocks, METH_VARARGS,
     "pair_blocks(ta, tb): the coupling blocks of two mesh triangles, 81 floats (pm_table_pair_blocks)"},
    {"has_greens", (PyCFunction)Table_has_greens, METH_NOARGS,
     "whether the table couples contacts itself: a zeta table, or a compressed Xi's sections (table 1.4)"},
    {"display_counts", (PyCFunction)Table_display_counts, METH_NOARGS, "(display vertices, display triangles)"},
    {"display_deform", (PyCFunction)Table_display_deform, METH_VARARGS,
     "the display surface deformed: (u bytes, contacts bytes, radius, out buffer)"},
    {"meta", (PyCFunction)Table_meta, METH_NOARGS, "the table's JSON metadata"},
    {"nearest", (PyCFunction)Table_nearest, METH_O, "the triangle nearest a point (bounding-volume hierarchy)"},
    {"stiffness", (PyCFunction)Table_stiffness, METH_VARARGS, "K(x) for a batch, into a buffer"},
    {NULL, NULL, 0, NULL}};

static PyTypeObject TableType = {
    PyVarObject_HEAD_INIT(NULL, 0).tp_name = "pmask.runtime.servo._core.Table",
    .tp_basicsize = sizeof(TableObject),
    .tp_flags = Py_TPFLAGS_DEFAULT,
    .tp_doc = "A runtime table in the native core: Table(path or bytes), or Table({name: array}) over arrays it "
               "holds (no copy).",
    .tp_new = PyType_GenericNew,
    .tp_init = (initproc)Table_init,
    .tp_dealloc = (destructor)Table_dealloc,
    .tp_methods = Table_methods,
};

/* ------------------------------------------------------------------ Servo */
typedef struct {
    PyObject_HEAD
    pm_servo *servo;
    PyObject *table;   /* keeps the table alive */
    PyObject *warn;    /* warn(kind, x, y, z): 'far' once, 'internal' when an internal error begins */
    PyObject *pairs;   /* pairs(ta, tb) -> 81 floats, or NULL (the table's ζ section, or no coupling) */
    int32_t n;
    int internal;
    double *probes, *forces;
    int32_t *status;
} ServoObject;

static void Servo_dealloc(ServoObject *self)
{
    if (self->servo) {
        Py_BEGIN_ALLOW_THREADS
        pm_servo_stop(self->servo);
        Py_END_ALLOW_THREADS
        pm_servo_free(self->servo);
    }
    Py_XDECREF(self->table);
    Py_XDECREF(self->warn);
    Py_XDECREF(self->pairs);
    PyMem_Free(self->probes);
    PyMem_Free(self->forces);
    PyMem_Free(self->status);
    Py_TYPE(self)->tp_free((PyObject *)self);
}

/* The pair function (pm_pair_fn) of a servo given a Python one: pairs(ta, tb) -> 81 numbers.  From a step called
 * from Python the GIL is held already, and an exception stays set for the step to raise; on the servo's own thread
 * the call takes the GIL, and an exception is printed as unraisable (that tick holds its force, PM_INTERNAL_ERROR,
 * and the next asks again). */
static int python_pairs(void *user, int64_t ta, int64_t tb, double *P)
{
    ServoObject *self = user;
    if (pm_py_finalizing()) return -1;  /* the interpreter is going: no Python to call */
    const int held = PyGILState_Check();
    PyGILState_STATE g = PyGILState_Ensure();
    int rc = -1;
    PyObject *r = PyObject_CallFunction(self->pairs, "LL", (long long)ta, (long long)tb);
    PyObject *seq = r ? PySequence_Fast(r, "pairs() must return 81 numbers") : NULL;
    if (seq && PySequence_Fast_GET_SIZE(seq) != 81)
        PyErr_Format(PyExc_ValueError, "pairs() must return 81 numbers, got %zd", PySequence_Fast_GET_SIZE(seq));
    else if (seq) {
        rc = 0;
        for (Py_ssize_t k = 0; k < 81 && rc == 0; k++) {
            P[k] = PyFloat_AsDouble(PySequence_Fast_GET_ITEM(seq, k));
            if (P[k] == -1.0 && PyErr_Occurred()) rc = -1;
        }
    }
    Py_XDECREF(seq);
    Py_XDECREF(r);
    if (rc && !held) PyErr_WriteUnraisable(self->pairs);
    PyGILState_Release(g);
    return rc;
}

/* Servo(table, n, (friction, dynamic_friction, damping, tool_radius, slip_length, rate, max_jump, decay,
 *        proxy_speed, reset_after, max_walk, passivity, coupled), warn[, pairs]) */
static int Servo_init(ServoObject *self, PyObject *args, PyObject *kw)
{
    PyObject *table, *warn, *pairs = Py_None;
    int n;
    pm_options o;
    int reset_after, max_walk, passivity, coupled;
    if (!PyArg_ParseTuple(args, "O!i(dddddddddiiii)O|O", &TableType, &table, &n, &o.friction, &o.dynamic_friction,
                          &o.damping, &o.tool_radius, &o.slip_length, &o.rate, &o.max_jump, &o.decay, &o.proxy_speed,
                          &reset_after, &max_walk, &passivity, &coupled, &warn, &pairs))
        return -1;
    if (self->servo) {
        PyErr_SetString(PyExc_RuntimeError, "Servo is already initialised");
        return -1;
    }
    if (pairs != Py_None && !PyCallable_Check(pairs)) {
        PyErr_SetString(PyExc_TypeError, "pairs must be callable or None");
        return -1;
    }
    if (pairs != Py_None) {  /* set before the servo exists: the core keeps a pointer to self */
        Py_INCREF(pairs);
        self->pairs = pairs;
    }
    o.reset_after = reset_after;
    o.max_walk = max_walk;
    o.passivity = passivity;
    o.coupled = coupled;
    char err[512] = "";
    if (pm_servo_create_paired(((TableObject *)table)->table, n, &o, self->pairs ? python_pairs : NULL, self,
                               &self->servo, err, sizeof err)) {
        PyErr_SetString(PyExc_ValueError, err);
        return -1;
    }
    self->n = n;
    self->probes = PyMem_Calloc(3 * (size_t)n, sizeof(double));
    self->forces = PyMem_Calloc(3 * (size_t)n, sizeof(double));
    self->status = PyMem_Calloc((size_t)n, sizeof(int32_t));
    if (!self->probes || !self->forces || !self->status) {
        PyErr_NoMemory();
        return -1;
    }
    Py_INCREF(table);
    self->table = table;
    Py_INCREF(warn);
    self->warn = warn;
    return 0;
}

static int after_step(ServoObject *self)
{
    double p[3];
    if (pm_servo_take_far_warning(self->servo, p)) {
        PyObject *r = PyObject_CallFunction(self->warn, "sddd", "far", p[0], p[1], p[2]);
        if (!r) return -1;
        Py_DECREF(r);
    }
    int internal = 0;
    for (int32_t l = 0; l < self->n; l++) internal |= self->status[l] == PM_INTERNAL_ERROR;
    if (internal && !self->internal) {
        PyObject *r = PyObject_CallFunction(self->warn, "sddd", "internal", 0.0, 0.0, 0.0);
        if (!r) return -1;
        Py_DECREF(r);
    }
    self->internal = internal;
    return 0;
}

static PyObject *results(ServoObject *self)
{
    PyObject *f = PyList_New(self->n), *s = PyList_New(self->n);
    if (!f || !s) goto fail;
    for (int32_t l = 0; l < self->n; l++) {
        PyObject *t = triple(self->forces + 3 * l), *st = status_object(self->status[l]);
        if (!t || !st) {
            Py_XDECREF(t);
            Py_XDECREF(st);
            goto fail;
        }
        PyList_SET_ITEM(f, l, t);
        PyList_SET_ITEM(s, l, st);
    }
    return Py_BuildValue("(NN)", f, s);
fail:
    Py_XDECREF(f);
    Py_XDECREF(s);
    return NULL;
}

static PyObject *Servo_step(ServoObject *self, PyObject *probes)
{
    probes_from(probes, self->n, self->probes);
    pm_servo_step(self->servo, self->probes, self->forces, self->status);
    if (PyErr_Occurred() || after_step(self)) return NULL;  /* the pair function's exception: our own bug */
    return results(self);
}

/* one instrument: step1(probe) -> (force, status) */
static PyObject *Servo_step1(ServoObject *self, PyObject *probe)
{
    sample_from(probe, self->probes);
    pm_servo_step(self->servo, self->probes, self->forces, self->status);
    if (PyErr_Occurred() || after_step(self)) return NULL;
    PyObject *f = triple(self->forces);
    if (!f) return NULL;
    return Py_BuildValue("(NN)", f, status_object(self->status[0]));
}

static PyObject *Servo_state(ServoObject *self, PyObject *arg)
{
    long k = PyLong_AsLong(arg);
    if (k == -1 && PyErr_Occurred()) return NULL;
    if (k < 0 || k >= self->n) {
        PyErr_SetString(PyExc_IndexError, "no such contact");
        return NULL;
    }
    pm_contact_state s;
    pm_servo_state(self->servo, (int32_t)k, &s);
    return Py_BuildValue("(L(ddd)NNNNOddON)", (long long)s.triangle, s.bary[0], s.bary[1], s.bary[2], triple(s.u_bar),
                         triple(s.force), triple(s.body_force), status_object(s.status),
                         s.in_contact ? Py_True : Py_False, s.depth, s.taper, s.sliding ? Py_True : Py_False,
                         triple(s.point));
}

static PyObject *Servo_reset(ServoObject *self, PyObject *unused)
{
    pm_servo_reset(self->servo);
    self->internal = 0;
    Py_RETURN_NONE;
}

static PyObject *Servo_deformation(ServoObject *self, PyObject *arg)
{
    Py_buffer o;
    if (PyObject_GetBuffer(arg, &o, PyBUF_WRITABLE | PyBUF_C_CONTIGUOUS)) return NULL;
    PyObject *res = NULL;
    /* the table's vertex count: the buffer must hold n_s x 3 doubles */
    TableObject *t = (TableObject *)self->table;
    if (o.len != 24 * (Py_ssize_t)pm_table_vertices(t->table)) {
        PyErr_SetString(PyExc_ValueError, "deformation: the output must hold n_vertices x 3 doubles");
    } else {
        int rc;
        Py_BEGIN_ALLOW_THREADS
        rc = pm_servo_deformation(self->servo, (double *)o.buf);
        Py_END_ALLOW_THREADS
        res = PyLong_FromLong(rc);
    }
    PyBuffer_Release(&o);
    return res;
}

static PyObject *Servo_start(ServoObject *self, PyObject *args)
{
    double rate, spin = PM_SPIN_DEFAULT;
    if (!PyArg_ParseTuple(args, "d|d", &rate, &spin)) return NULL;
    return PyLong_FromLong(pm_servo_start(self->servo, rate, spin, NULL));
}

static PyObject *Servo_stop(ServoObject *self, PyObject *unused)
{
    Py_BEGIN_ALLOW_THREADS
    pm_servo_stop(self->servo);
    Py_END_ALLOW_THREADS
    Py_RETURN_NONE;
}

static PyObject *Servo_running(ServoObject *self, PyObject *unused)
{
    return PyBool_FromLong(pm_servo_running(self->servo));
}

static PyObject *Servo_kernel(ServoObject *self, PyObject *unused)
{
    return PyUnicode_FromString(pm_servo_kernel(self->servo));
}

static PyObject *Servo_set_probes(ServoObject *self, PyObject *probes)
{
    probes_from(probes, self->n, self->probes);
    pm_servo_set_probes(self->servo, self->probes);
    Py_RETURN_NONE;
}

static PyObject *Servo_read(ServoObject *self, PyObject *unused)
{
    pm_tick_stats st;
    pm_servo_read(self->servo, self->forces, self->status, &st);
    if (after_step(self)) return NULL;
    PyObject *r = results(self);
    if (!r) return NULL;
    PyObject *out = Py_BuildValue("(OO(LLddL))", PyTuple_GET_ITEM(r, 0), PyTuple_GET_ITEM(r, 1), (long long)st.ticks,
                                  (long long)st.late, st.max_lateness, st.step_max, (long long)st.idle);
    Py_DECREF(r);
    return out;
}

static PyObject *Servo_start_exchange(ServoObject *self, PyObject *args)
{
    double rate, spin = PM_SPIN_DEFAULT;
    if (!PyArg_ParseTuple(args, "d|d", &rate, &spin)) return NULL;
    return PyLong_FromLong(pm_servo_start_exchange(self->servo, rate, spin));
}

/* exchange(probes, timeout) -> (forces, statuses): the tick that used these probes (the GIL released while
 * waiting); None when no tick answered in time */
static PyObject *Servo_exchange(ServoObject *self, PyObject *args)
{
    PyObject *probes;
    double timeout;
    if (!PyArg_ParseTuple(args, "Od", &probes, &timeout)) return NULL;
    /* its own buffers: other Python threads may step or read this servo while this one waits without the GIL */
    double *in = PyMem_Calloc(6 * (size_t)self->n, sizeof(double));
    int32_t *st = PyMem_Calloc((size_t)self->n, sizeof(int32_t));
    if (!in || !st) {
        PyMem_Free(in);
        PyMem_Free(st);
        return PyErr_NoMemory();
    }
    double *out = in + 3 * (size_t)self->n;
    probes_from(probes, self->n, in);
    int rc;
    Py_BEGIN_ALLOW_THREADS
    rc = pm_servo_exchange(self->servo, in, out, st, timeout);
    Py_END_ALLOW_THREADS
    if (rc == 0) {
        memcpy(self->forces, out, 3 * (size_t)self->n * sizeof(double));
        memcpy(self->status, st, (size_t)self->n * sizeof(int32_t));
    }
    PyMem_Free(in);
    PyMem_Free(st);
    if (rc == -2) {
        PyErr_SetString(PyExc_RuntimeError, "exchange() needs the servo thread started in exchange mode");
        return NULL;
    }
    if (rc != 0) Py_RETURN_NONE;
    if (after_step(self)) return NULL;
    return results(self);
}

static PyMethodDef Servo_methods[] = {
    {"step", (PyCFunction)Servo_step, METH_O, "one tick for n probes -> (forces, statuses)"},
    {"step1", (PyCFunction)Servo_step1, METH_O, "one tick for one probe -> (force, status)"},
    {"state", (PyCFunction)Servo_state, METH_O, "contact k after the last tick"},
    {"reset", (PyCFunction)Servo_reset, METH_NOARGS, "forget all contact state"},
    {"deformation", (PyCFunction)Servo_deformation, METH_O, "eq. 16 into a buffer (n_s x 3)"},
    {"start", (PyCFunction)Servo_start, METH_VARARGS, "start(rate[, spin]): the step on a thread of its own"},
    {"stop", (PyCFunction)Servo_stop, METH_NOARGS, "stop the thread"},
    {"running", (PyCFunction)Servo_running, METH_NOARGS, "whether the thread runs"},
    {"kernel", (PyCFunction)Servo_kernel, METH_NOARGS, "the coupled pairs' block-sum kernel: 'avx2' or 'baseline'"},
    {"set_probes", (PyCFunction)Servo_set_probes, METH_O, "the probes the thread uses from its next tick"},
    {"read", (PyCFunction)Servo_read, METH_NOARGS, "(forces, statuses, (ticks, late, max_lateness, step_max, idle))"},
    {"start_exchange", (PyCFunction)Servo_start_exchange, METH_VARARGS,
     "start_exchange(rate[, spin]): the thread on exchanged samples"},
    {"exchange", (PyCFunction)Servo_exchange, METH_VARARGS,
     "exchange(probes, timeout) -> (forces, statuses) of the tick that used them"},
    {NULL, NULL, 0, NULL}};

static PyTypeObject ServoType = {
    PyVarObject_HEAD_INIT(NULL, 0).tp_name = "pmask.runtime.servo._core.Servo",
    .tp_basicsize = sizeof(ServoObject),
    .tp_flags = Py_TPFLAGS_DEFAULT,
    .tp_doc = "Contact state for n instruments over a Table (see pmask.runtime.servo.NativeContacts).",
    .tp_new = PyType_GenericNew,
    .tp_init = (initproc)Servo_init,
    .tp_dealloc = (destructor)Servo_dealloc,
    .tp_methods = Servo_methods,
};

/* ------------------------------------------------------------------ module */
static PyObject *set_statuses(PyObject *mod, PyObject *arg)
{
    if (!PyTuple_Check(arg)) {
        PyErr_SetString(PyExc_TypeError, "set_statuses needs a tuple");
        return NULL;
    }
    Py_XDECREF(STATUS);
    Py_INCREF(arg);
    STATUS = arg;
    Py_RETURN_NONE;
}

static PyObject *zeta_rows(PyObject *mod, PyObject *args)
{
    Py_buffer x, c, ptr, idx, val, o;
    Py_ssize_t width;
    if (!PyArg_ParseTuple(args, "ny*y*y*y*y*w*", &width, &x, &c, &ptr, &idx, &val, &o)) return NULL;
    PyObject *res = NULL;
    char err[256] = "";
    if (width <= 0 || x.len != o.len || x.len % (8 * width) != 0 || c.len % 8 != 0 || ptr.len != c.len + 8 ||
        idx.len % 8 != 0 || val.len != idx.len) {
        PyErr_SetString(PyExc_ValueError, "zeta_rows: buffer sizes do not match");
    } else {
        int rc;
        Py_BEGIN_ALLOW_THREADS
        rc = pm_zeta_rows((int64_t)(x.len / (8 * width)), (int64_t)width, (const double *)x.buf, (int64_t)(c.len / 8),
                          (const int64_t *)c.buf, (const int64_t *)ptr.buf, (int64_t)(idx.len / 8),
                          (const int64_t *)idx.buf, (const double *)val.buf, (double *)o.buf, err, sizeof err);
        Py_END_ALLOW_THREADS
        if (rc) {
            PyErr_SetString(PyExc_ValueError, err);
        } else {
            res = Py_None;
            Py_INCREF(res);
        }
    }
    PyBuffer_Release(&x);
    PyBuffer_Release(&c);
    PyBuffer_Release(&ptr);
    PyBuffer_Release(&idx);
    PyBuffer_Release(&val);
    PyBuffer_Release(&o);
    return res;
}

static PyMethodDef module_methods[] = {
    {"set_statuses", set_statuses, METH_O, "the objects returned for each status value"},
    {"zeta_rows", zeta_rows, METH_VARARGS,
     "zeta_rows(width, xi_rows, centres, indptr, indices, values, out): the zeta table's rows (pm_zeta_rows)"},
    {NULL, NULL, 0, NULL}};

static struct PyModuleDef module = {PyModuleDef_HEAD_INIT, "_core", "The native servo core's binding.", -1,
                                    module_methods, NULL, NULL, NULL, NULL};

PyMODINIT_FUNC PyInit__core(void)
{
    if (PyType_Ready(&TableType) < 0 || PyType_Ready(&ServoType) < 0) return NULL;
    PyObject *m = PyModule_Create(&module);
    if (!m) return NULL;
    Py_INCREF(&TableType);
    Py_INCREF(&ServoType);
    if (PyModule_AddObject(m, "Table", (PyObject *)&TableType) ||
        PyModule_AddObject(m, "Servo", (PyObject *)&ServoType) ||
        PyModule_AddIntConstant(m, "TABLE_MAJOR", PM_TABLE_MAJOR) ||
        PyModule_AddIntConstant(m, "TABLE_MINOR", PM_TABLE_MINOR)) {
        Py_DECREF(m);
        return NULL;
    }
    return m;
}
