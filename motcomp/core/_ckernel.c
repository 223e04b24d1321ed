/* The compensator's tick in C: motcomp.core._ckernel.
 *
 * One Stepper advances all axes of a Compensator by one sample.  It holds no state of its own:
 * it keeps writable views of the Compensator's state and parameter arrays (array.array
 * objects, allocated once and only ever changed in place, so the Python methods that reset,
 * reseed, reconfigure or inspect the compensator keep working on the same memory).
 *
 * The algorithm is the one documented in motcomp/core/compensator.py (Compensator._step_py)
 * and motcomp/core/saturation.py (limit_axis), written operation for operation in the same
 * order: with IEEE doubles and no contraction into fused multiply-adds (-ffp-contract=off,
 * set by setup.py) the results are bit-identical to the Python reference, which the tests
 * check.  x**3 is pow(x, 3.0), as CPython computes it.
 */
#define PY_SSIZE_T_CLEAN
#include <Python.h>
#include <math.h>
#include <stdint.h>

#define NONFINITE 8
#define POS 1
#define VEL 2
#define ACC 4
#define RECOVER 16
#define NLIM 24

enum {
    B_R, B_U, B_V, B_XC, B_XM, B_YLAST, B_DERIV, B_WPREV, B_RAW, B_FADE_OFF, B_FADE_PROG,
    B_INTEGRAL, B_DEV, B_TRACK, B_HIST_C, B_HIST_M, B_GAIN, B_MODEL, B_LIM, B_OFFS, B_BYPASS,
    NBUF
};

static const char *buf_names[NBUF] = {
    "r", "u", "v", "xc", "xm", "y_last", "deriv", "w_prev", "raw", "fade_offset",
    "fade_progress", "integral", "deviation", "track", "hist_c", "hist_m", "gain_p", "model_p",
    "lim", "offsets", "bypass"};

typedef struct {
    PyObject_HEAD
    Py_ssize_t n;
    int64_t mask;
    Py_ssize_t hist_len;
    int nviews;
    Py_buffer views[NBUF];
    double *d[NBUF - 2];
    int64_t *offs;
    signed char *bypass;
} Stepper;

static void Stepper_dealloc(Stepper *self) {
    for (int j = 0; j < self->nviews; j++) PyBuffer_Release(&self->views[j]);
    Py_TYPE(self)->tp_free((PyObject *)self);
}

/* Expected item format and length (in units of n, or n * hist_len for the histories). */
static int want(int j, char *fmt, Py_ssize_t *per) {
    switch (j) {
    case B_TRACK: *fmt = 'd'; *per = 3; return 0;
    case B_HIST_C: case B_HIST_M: *fmt = 'd'; *per = -1; return 0;
    case B_GAIN: *fmt = 'd'; *per = 6; return 0;
    case B_MODEL: *fmt = 'd'; *per = 3; return 0;
    case B_LIM: *fmt = 'd'; *per = NLIM; return 0;
    case B_OFFS: *fmt = 'q'; *per = 2; return 0;
    case B_BYPASS: *fmt = 'b'; *per = 1; return 0;
    default: *fmt = 'd'; *per = 1; return 0;
    }
}

static int Stepper_init(Stepper *self, PyObject *args, PyObject *kwds) {
    Py_ssize_t n, hist_len;
    PyObject *bufs;
    static char *kwlist[] = {"n", "hist_len", "buffers", NULL};
    if (!PyArg_ParseTupleAndKeywords(args, kwds, "nnO", kwlist, &n, &hist_len, &bufs))
        return -1;
    if (self->nviews) {
        PyErr_SetString(PyExc_RuntimeError, "Stepper is already initialised");
        return -1;
    }
    if (n <= 0 || hist_len <= 0 || (hist_len & (hist_len - 1)) != 0) {
        PyErr_Format(PyExc_ValueError, "Stepper needs n > 0 and a power-of-two hist_len, "
                     "got n=%zd, hist_len=%zd", n, hist_len);
        return -1;
    }
    PyObject *seq = PySequence_Fast(bufs, "buffers must be a sequence");
    if (seq == NULL) return -1;
    if (PySequence_Fast_GET_SIZE(seq) != NBUF) {
        PyErr_Format(PyExc_ValueError, "Stepper needs %d buffers, got %zd", NBUF,
                     PySequence_Fast_GET_SIZE(seq));
        Py_DECREF(seq);
        return -1;
    }
    for (int j = 0; j < NBUF; j++) {
        Py_buffer *view = &self->views[j];
        if (PyObject_GetBuffer(PySequence_Fast_GET_ITEM(seq, j), view,
                               PyBUF_WRITABLE | PyBUF_FORMAT | PyBUF_C_CONTIGUOUS) < 0) {
            Py_DECREF(seq);
            return -1;
        }
        self->nviews = j + 1;
        char fmt;
        Py_ssize_t per;
        want(j, &fmt, &per);
        Py_ssize_t items = per < 0 ? n * hist_len : n * per;
        const char *f = view->format ? view->format : "B";
        if (f[0] == '@' || f[0] == '=') f++;
        Py_ssize_t size = fmt == 'd' ? 8 : fmt == 'q' ? 8 : 1;
        if (f[0] != fmt || f[1] != '\0' || view->itemsize != size || view->len != items * size) {
            PyErr_Format(PyExc_ValueError, "buffer %s: want %zd items of format '%c', got "
                         "%zd bytes of format '%s'", buf_names[j], items, fmt, view->len, f);
            Py_DECREF(seq);
            return -1;
        }
        if (j < NBUF - 2) self->d[j] = (double *)view->buf;
    }
    Py_DECREF(seq);
    self->offs = (int64_t *)self->views[B_OFFS].buf;
    self->bypass = (signed char *)self->views[B_BYPASS].buf;
    self->n = n;
    self->hist_len = hist_len;
    self->mask = (int64_t)hist_len - 1;
    return 0;
}

/* saturation.limit_axis, operation for operation. */
static inline double limit_axis(double target, double u0, double v0, double *trk,
                                const double *c, double *v_out, int *fl_out) {
    const double h = c[0], inv_h = c[1], p_min = c[2], p_max = c[3], v_max = c[4], ah = c[5],
                 ah2 = c[6], two_a = c[7], inv_two_a = c[8], ahc = c[9], ahc2 = c[10],
                 two_ac = c[11];
    const double *f = c + 12, *g = c + 21;
    if (!isfinite(target)) target = u0;
    if (target > p_max) target = p_max;
    else if (target < p_min) target = p_min;
    double sp = trk[0], sv = trk[1], sa = trk[2];
    double nsp = f[0] * sp + f[1] * sv + f[2] * sa + g[0] * target;
    double nsv = f[3] * sp + f[4] * sv + f[5] * sa + g[1] * target;
    double nsa = f[6] * sp + f[7] * sv + f[8] * sa + g[2] * target;
    trk[0] = nsp;
    trk[1] = nsv;
    trk[2] = nsa;
    sv = nsv;
    double vel = (target - u0) * inv_h;
    if (v0 - ah <= vel && vel <= v0 + ah && -v_max <= vel && vel <= v_max && p_min <= u0 &&
        u0 <= p_max &&
        (vel > 0.0 ? vel * (h + vel * inv_two_a) <= p_max - u0
                   : -vel * (h - vel * inv_two_a) <= u0 - p_min)) {
        *v_out = vel;
        *fl_out = 0;
        return target; /* feasible: passes through bit-exactly */
    }
    int fl = RECOVER;
    double v_t = (-v_max <= sv && sv <= v_max) ? sv : (sv > 0.0 ? v_max : -v_max);
    double gap = target - v_t * h - u0;
    if (gap >= 0.0) vel = v_t + sqrt(ahc2 + two_ac * gap) - ahc;
    else vel = v_t + ahc - sqrt(ahc2 - two_ac * gap);
    if (vel > 0.0) {
        double room = p_max - u0;
        if (vel * (h + vel * inv_two_a) > room) {
            vel = sqrt(ah2 + two_a * (room > 0.0 ? room : 0.0)) - ah;
            fl |= POS;
        }
        if (vel > v_max) {
            vel = v_max;
            fl |= VEL;
        }
    } else if (vel < 0.0) {
        double room = u0 - p_min;
        if (-vel * (h - vel * inv_two_a) > room) {
            vel = ah - sqrt(ah2 + two_a * (room > 0.0 ? room : 0.0));
            fl |= POS;
        }
        if (vel < -v_max) {
            vel = -v_max;
            fl |= VEL;
        }
    }
    if (u0 > p_max || u0 < p_min) fl |= POS;
    if (vel > v0 + ah) {
        vel = v0 + ah;
        fl |= ACC;
    } else if (vel < v0 - ah) {
        vel = v0 - ah;
        fl |= ACC;
    }
    double u = u0 + vel * h;
    if (u > p_max && u0 <= p_max) u = p_max;
    else if (u < p_min && u0 >= p_min) u = p_min;
    *v_out = (u - u0) * inv_h;
    *fl_out = fl;
    return u;
}

static PyObject *Stepper_step(Stepper *self, PyObject *const *args, Py_ssize_t nargs) {
    if (nargs != 3) {
        PyErr_SetString(PyExc_TypeError, "step(reference, k, fade_step)");
        return NULL;
    }
    const Py_ssize_t n = self->n;
    PyObject *seq = PySequence_Fast(args[0], "reference must be a sequence of floats");
    if (seq == NULL) return NULL;
    if (PySequence_Fast_GET_SIZE(seq) != n) {
        PyErr_Format(PyExc_ValueError, "reference has %zd values for %zd axes",
                     PySequence_Fast_GET_SIZE(seq), n);
        Py_DECREF(seq);
        return NULL;
    }
    int64_t k = PyLong_AsLongLong(args[1]);
    double fade_step = PyFloat_AsDouble(args[2]);
    if (PyErr_Occurred()) {
        Py_DECREF(seq);
        return NULL;
    }
    double ref[64];
    double *refp = n <= 64 ? ref : PyMem_Malloc(sizeof(double) * n);
    if (refp == NULL) {
        Py_DECREF(seq);
        return PyErr_NoMemory();
    }
    PyObject **items = PySequence_Fast_ITEMS(seq);
    for (Py_ssize_t i = 0; i < n; i++) {
        PyObject *x = items[i];
        refp[i] = PyFloat_CheckExact(x) ? PyFloat_AS_DOUBLE(x) : PyFloat_AsDouble(x);
        if (refp[i] == -1.0 && PyErr_Occurred()) {
            if (refp != ref) PyMem_Free(refp);
            Py_DECREF(seq);
            return NULL;
        }
    }
    Py_DECREF(seq);
    PyObject *out = PyList_New(n), *flags = PyList_New(n);
    if (out == NULL || flags == NULL) {
        Py_XDECREF(out);
        Py_XDECREF(flags);
        if (refp != ref) PyMem_Free(refp);
        return NULL;
    }
    double *rr = self->d[B_R], *us = self->d[B_U], *vs = self->d[B_V], *xcs = self->d[B_XC],
           *xms = self->d[B_XM], *ys = self->d[B_YLAST], *ds = self->d[B_DERIV],
           *wps = self->d[B_WPREV], *raws = self->d[B_RAW], *foff = self->d[B_FADE_OFF],
           *fprog = self->d[B_FADE_PROG], *ints = self->d[B_INTEGRAL], *dev = self->d[B_DEV],
           *trk = self->d[B_TRACK], *hcs = self->d[B_HIST_C], *hms = self->d[B_HIST_M],
           *gain = self->d[B_GAIN], *model = self->d[B_MODEL], *lim = self->d[B_LIM];
    const int64_t mask = self->mask, L = self->hist_len;
    for (Py_ssize_t i = 0; i < n; i++) {
        const double *gp = gain + 6 * i, *mp = model + 3 * i;
        const double kp = gp[0], kih = gp[1], ad = gp[2], bd = gp[3], b = gp[4], c = gp[5];
        const double phi = mp[0], g0 = mp[1], g1 = mp[2];
        double r = refp[i];
        int fl;
        if (isfinite(r)) {
            rr[i] = r;
            fl = 0;
        } else {
            r = rr[i];
            fl = NONFINITE;
        }
        double y = xcs[i]; /* y_m + y_aw = M v */
        ys[i] = y;
        double w = c * r - y;
        double d = ad * ds[i] + bd * (w - wps[i]);
        ds[i] = d;
        wps[i] = w;
        double v = kp * (b * r - y) + ints[i] + d; /* error = reference - model_output */
        double target;
        if (self->bypass[i]) {
            double progress = fprog[i];
            if (progress < 1.0) {
                target = r + foff[i] * (1.0 - pow(progress, 3.0) *
                                                  (10.0 - 15.0 * progress + 6.0 * progress * progress));
                double next = progress + fade_step;
                fprog[i] = 1.0 < next ? 1.0 : next;
            } else {
                target = r;
            }
        } else {
            target = v;
        }
        double vel;
        int sat;
        double u = limit_axis(target, us[i], vs[i], trk + 3 * i, lim + NLIM * i, &vel, &sat);
        vs[i] = vel;
        us[i] = u;
        dev[i] = u - target;
        if (self->bypass[i]) {
            ints[i] += u - v;
            v = u;
        }
        raws[i] = v;
        ints[i] += kih * (r - y);
        const int64_t slot = k & mask, slot0 = (k + self->offs[2 * i]) & mask,
                      slot1 = (k + self->offs[2 * i + 1]) & mask;
        double *hc = hcs + L * i, *hm = hms + L * i;
        hc[slot] = v;
        xcs[i] = phi * y + g0 * hc[slot0] + g1 * hc[slot1];
        hm[slot] = u;
        xms[i] = phi * xms[i] + g0 * hm[slot0] + g1 * hm[slot1];
        PyObject *uo = PyFloat_FromDouble(u), *fo = PyLong_FromLong(fl | sat);
        if (uo == NULL || fo == NULL) {
            Py_XDECREF(uo);
            Py_XDECREF(fo);
            Py_DECREF(out);
            Py_DECREF(flags);
            if (refp != ref) PyMem_Free(refp);
            return NULL;
        }
        PyList_SET_ITEM(out, i, uo);
        PyList_SET_ITEM(flags, i, fo);
    }
    if (refp != ref) PyMem_Free(refp);
    PyObject *res = PyTuple_New(2);
    if (res == NULL) {
        Py_DECREF(out);
        Py_DECREF(flags);
        return NULL;
    }
    PyTuple_SET_ITEM(res, 0, out);
    PyTuple_SET_ITEM(res, 1, flags);
    return res;
}

static PyMethodDef Stepper_methods[] = {
    {"step", (PyCFunction)(void (*)(void))Stepper_step, METH_FASTCALL,
     "step(reference, k, fade_step) -> (commands, flags): one sample of every axis."},
    {NULL, NULL, 0, NULL}};

static PyTypeObject StepperType = {
    PyVarObject_HEAD_INIT(NULL, 0)
    .tp_name = "motcomp.core._ckernel.Stepper",
    .tp_basicsize = sizeof(Stepper),
    .tp_dealloc = (destructor)Stepper_dealloc,
    .tp_flags = Py_TPFLAGS_DEFAULT,
    .tp_doc = "Stepper(n, hist_len, buffers): the compensator's tick over shared arrays.",
    .tp_methods = Stepper_methods,
    .tp_init = (initproc)Stepper_init,
    .tp_new = PyType_GenericNew,
};

static struct PyModuleDef ckernel_module = {
    PyModuleDef_HEAD_INIT, "_ckernel",
    "The compensator's tick in C (see motcomp.core.compensator).", -1, NULL};

PyMODINIT_FUNC PyInit__ckernel(void) {
    if (PyType_Ready(&StepperType) < 0) return NULL;
    PyObject *m = PyModule_Create(&ckernel_module);
    if (m == NULL) return NULL;
    Py_INCREF(&StepperType);
    if (PyModule_AddObject(m, "Stepper", (PyObject *)&StepperType) < 0) {
        Py_DECREF(&StepperType);
        Py_DECREF(m);
        return NULL;
    }
    if (PyModule_AddStringConstant(m, "BUFFERS", "r u v xc xm y_last deriv w_prev raw "
                                   "fade_offset fade_progress integral deviation track hist_c "
                                   "hist_m gain_p model_p lim offsets bypass") < 0) {
        Py_DECREF(m);
        return NULL;
    }
    return m;
}
