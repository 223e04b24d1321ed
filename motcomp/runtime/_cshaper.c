/* The reference shaper's two per-tick loops in C: motcomp.runtime._cshaper.
 *
 * They work on the shaper's own per-axis Python lists (floats), operation for operation as
 * ReferenceShaper.on_input and ReferenceShaper._live_now do in motcomp/runtime/shaper.py, so
 * the results are bit-identical (tests/test_shaper_kernel.py checks it).
 *
 * update_axes(pos, index, driven, t, fresh_allowed, stale_after_s,
 *             live, t_frame, slope, period) -> None
 * live_now(t_now, age, late, max_extrapolation_s, live, slope, t_frame, period) -> list
 */
#define PY_SSIZE_T_CLEAN
#include <Python.h>

static int item(PyObject *list, Py_ssize_t i, double *out) {
    PyObject *x = PyList_GET_ITEM(list, i);
    if (PyFloat_CheckExact(x)) {
        *out = PyFloat_AS_DOUBLE(x);
        return 0;
    }
    *out = PyFloat_AsDouble(x);
    return (*out == -1.0 && PyErr_Occurred()) ? -1 : 0;
}

static int set(PyObject *list, Py_ssize_t i, double x) {
    PyObject *f = PyFloat_FromDouble(x);
    if (f == NULL) return -1;
    PyObject *old = PyList_GET_ITEM(list, i);
    PyList_SET_ITEM(list, i, f);
    Py_DECREF(old);
    return 0;
}

static int lists(PyObject *const *lst, int count, Py_ssize_t n) {
    for (int j = 0; j < count; j++) {
        if (!PyList_CheckExact(lst[j]) || PyList_GET_SIZE(lst[j]) != n) {
            PyErr_Format(PyExc_TypeError, "per-axis state must be lists of %zd floats", n);
            return -1;
        }
    }
    return 0;
}

static PyObject *update_axes(PyObject *mod, PyObject *const *args, Py_ssize_t nargs) {
    if (nargs != 10) {
        PyErr_SetString(PyExc_TypeError,
                        "update_axes(pos, index, driven, t, fresh_allowed, stale_after_s, "
                        "live, t_frame, slope, period)");
        return NULL;
    }
    PyObject *pos = args[0], *index = args[1], *driven = args[2];
    if (!PyDict_Check(pos) || !PyDict_Check(index) || !PyList_CheckExact(driven)) {
        PyErr_SetString(PyExc_TypeError, "pos and index must be dicts, driven a list");
        return NULL;
    }
    Py_ssize_t n = PyList_GET_SIZE(driven);
    PyObject *live = args[6], *t_frame = args[7], *slope = args[8], *period = args[9];
    if (lists(args + 6, 4, n) < 0) return NULL;
    double t = PyFloat_AsDouble(args[3]);
    int fresh_allowed = PyObject_IsTrue(args[4]);
    double stale_after = PyFloat_AsDouble(args[5]);
    if (PyErr_Occurred() || fresh_allowed < 0) return NULL;
    Py_ssize_t it = 0;
    PyObject *axis, *value;
    while (PyDict_Next(pos, &it, &axis, &value)) {
        PyObject *idx = PyDict_GetItemWithError(index, axis);
        if (idx == NULL) {
            if (!PyErr_Occurred()) PyErr_SetObject(PyExc_KeyError, axis);
            return NULL;
        }
        Py_ssize_t i = PyLong_AsSsize_t(idx);
        if (i == -1 && PyErr_Occurred()) return NULL;
        if (i < 0 || i >= n) {
            PyErr_Format(PyExc_IndexError, "axis index %zd out of range", i);
            return NULL;
        }
        int drv = PyObject_IsTrue(PyList_GET_ITEM(driven, i));
        if (drv < 0) return NULL;
        if (!drv) continue;
        double v = PyFloat_AsDouble(value);
        double tf, lv;
        if ((v == -1.0 && PyErr_Occurred()) || item(t_frame, i, &tf) < 0 ||
            item(live, i, &lv) < 0)
            return NULL;
        double dt = t - tf;
        int fresh = fresh_allowed && 0.0 < dt && dt <= stale_after;
        if (set(slope, i, fresh ? (v - lv) / dt : 0.0) < 0) return NULL;
        if (fresh) {
            double p;
            if (item(period, i, &p) < 0) return NULL;
            p = p == 0.0 ? dt : p + 0.05 * (dt - p);
            if (set(period, i, p) < 0) return NULL;
        }
        if (set(live, i, v) < 0 || set(t_frame, i, t) < 0) return NULL;
    }
    Py_RETURN_NONE;
}

static PyObject *live_now(PyObject *mod, PyObject *const *args, Py_ssize_t nargs) {
    if (nargs != 8) {
        PyErr_SetString(PyExc_TypeError, "live_now(t_now, age, late, max_extrapolation_s, "
                                         "live, slope, t_frame, period)");
        return NULL;
    }
    double x4[4];  /* t_now, age, late, max_extrapolation_s */
    for (int j = 0; j < 4; j++) {
        x4[j] = PyFloat_AsDouble(args[j]);
        if (x4[j] == -1.0 && PyErr_Occurred()) return NULL;
    }
    double t_now = x4[0], age = x4[1], late = x4[2], max_ext = x4[3];
    if (!PyList_CheckExact(args[4])) {
        PyErr_SetString(PyExc_TypeError, "live must be a list");
        return NULL;
    }
    Py_ssize_t n = PyList_GET_SIZE(args[4]);
    if (lists(args + 4, 4, n) < 0) return NULL;
    PyObject *out = PyList_New(n);
    if (out == NULL) return NULL;
    for (Py_ssize_t i = 0; i < n; i++) {
        double v, s, tf, p;
        if (item(args[4], i, &v) < 0 || item(args[5], i, &s) < 0 ||
            item(args[6], i, &tf) < 0 || item(args[7], i, &p) < 0) {
            Py_DECREF(out);
            return NULL;
        }
        double tau = t_now - tf;
        double c = 1.5 * p; /* the transit jitter allowed for */
        /* min(max(max_ext, c) if late <= c else c + c, age + c) */
        double hi = late <= c ? (max_ext >= c ? max_ext : c) : c + c;
        double b = age + c;
        b = hi <= b ? hi : b;
        double x = (0.0 < tau && tau < b) ? tau : (tau >= b ? b : 0.0);
        PyObject *f = PyFloat_FromDouble(v + s * x);
        if (f == NULL) {
            Py_DECREF(out);
            return NULL;
        }
        PyList_SET_ITEM(out, i, f);
    }
    return out;
}

static PyMethodDef methods[] = {
    {"update_axes", (PyCFunction)(void (*)(void))update_axes, METH_FASTCALL,
     "The per-axis part of ReferenceShaper.on_input."},
    {"live_now", (PyCFunction)(void (*)(void))live_now, METH_FASTCALL,
     "ReferenceShaper._live_now with linear reconstruction: the extrapolated live values."},
    {NULL, NULL, 0, NULL}};

static struct PyModuleDef cshaper_module = {
    PyModuleDef_HEAD_INIT, "_cshaper", "The reference shaper's per-tick loops in C.", -1,
    methods};

PyMODINIT_FUNC PyInit__cshaper(void) { return PyModule_Create(&cshaper_module); }
