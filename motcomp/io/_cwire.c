/* The service's two hot wire operations in C: motcomp.io._cwire.
 *
 * pack_output(seq, t, src_seq, axes, positions, flags) -> bytes
 *     The output frame {"seq", "t", "src_seq", "pos": {axis: float}, "flags": [str]}, byte for
 *     byte what msgpack.Packer(use_bin_type=True).pack gives for the same dict with float
 *     positions (tests/test_wire.py checks it).
 *
 * parse_input(payload, index, lo, hi) -> (seq, t, pos) | None
 *     The common input frame only: a map of "seq" (int), "pos" (a non-empty map of known axis
 *     names to float32/float64 values within [lo, hi]) and optionally "t" (float or nil), no
 *     other key, nothing after the map; a finite t.  Anything else returns None and the caller runs the
 *     full validation, which names the problem (motcomp.io.wire.InputValidator).  A NaN fails
 *     the range check.  ``index`` maps axis name -> position in ``lo``/``hi``.
 */
#define PY_SSIZE_T_CLEAN
#include <Python.h>
#include <math.h>
#include <stdint.h>
#include <string.h>

/* ---- packing ------------------------------------------------------------------------------ */

typedef struct {
    char *buf;
    Py_ssize_t len, cap;
    char small[512];
} Out;

static int grow(Out *o, Py_ssize_t need) {
    if (o->len + need <= o->cap) return 0;
    Py_ssize_t cap = (o->cap + need) * 2;
    char *nb = PyMem_Malloc(cap);
    if (nb == NULL) {
        PyErr_NoMemory();
        return -1;
    }
    memcpy(nb, o->buf, o->len);
    if (o->buf != o->small) PyMem_Free(o->buf);
    o->buf = nb;
    o->cap = cap;
    return 0;
}

static int put(Out *o, const void *p, Py_ssize_t n) {
    if (grow(o, n) < 0) return -1;
    memcpy(o->buf + o->len, p, n);
    o->len += n;
    return 0;
}

static int put_be(Out *o, unsigned char tag, uint64_t x, int bytes) {
    unsigned char b[9];
    b[0] = tag;
    for (int j = 0; j < bytes; j++) b[1 + j] = (unsigned char)(x >> (8 * (bytes - 1 - j)));
    return put(o, b, 1 + bytes);
}

/* msgpack's smallest encoding of an integer, as msgpack-python chooses it */
static int put_int(Out *o, PyObject *obj) {
    int overflow = 0;
    long long x = PyLong_AsLongLongAndOverflow(obj, &overflow);
    if (x == -1 && PyErr_Occurred()) return -1;
    if (overflow > 0) {
        unsigned long long u = PyLong_AsUnsignedLongLong(obj);
        if (u == (unsigned long long)-1 && PyErr_Occurred()) return -1;
        return put_be(o, 0xcf, u, 8);
    }
    if (overflow < 0) {
        PyErr_SetString(PyExc_OverflowError, "integer below -2**63");
        return -1;
    }
    if (x >= 0) {
        if (x < 0x80) return put_be(o, (unsigned char)x, 0, 0);
        if (x <= 0xff) return put_be(o, 0xcc, (uint64_t)x, 1);
        if (x <= 0xffff) return put_be(o, 0xcd, (uint64_t)x, 2);
        if (x <= 0xffffffffLL) return put_be(o, 0xce, (uint64_t)x, 4);
        return put_be(o, 0xcf, (uint64_t)x, 8);
    }
    if (x >= -32) return put_be(o, (unsigned char)(0xe0 | (x + 32)), 0, 0);
    if (x >= -128) return put_be(o, 0xd0, (uint64_t)(uint8_t)(int8_t)x, 1);
    if (x >= -32768) return put_be(o, 0xd1, (uint64_t)(uint16_t)(int16_t)x, 2);
    if (x >= -2147483648LL) return put_be(o, 0xd2, (uint64_t)(uint32_t)(int32_t)x, 4);
    return put_be(o, 0xd3, (uint64_t)x, 8);
}

static int put_double(Out *o, double d) {
    uint64_t bits;
    memcpy(&bits, &d, 8);
    return put_be(o, 0xcb, bits, 8);
}

static int put_str(Out *o, PyObject *s) {
    Py_ssize_t n;
    const char *p = PyUnicode_AsUTF8AndSize(s, &n);
    if (p == NULL) return -1;
    int rc;
    if (n < 32) rc = put_be(o, (unsigned char)(0xa0 | n), 0, 0);
    else if (n <= 0xff) rc = put_be(o, 0xd9, (uint64_t)n, 1);
    else if (n <= 0xffff) rc = put_be(o, 0xda, (uint64_t)n, 2);
    else rc = put_be(o, 0xdb, (uint64_t)n, 4);
    return rc < 0 ? -1 : put(o, p, n);
}

static int put_container(Out *o, Py_ssize_t n, unsigned char fix, unsigned char t16,
                         unsigned char t32) {
    if (n < 16) return put_be(o, (unsigned char)(fix | n), 0, 0);
    if (n <= 0xffff) return put_be(o, t16, (uint64_t)n, 2);
    return put_be(o, t32, (uint64_t)n, 4);
}

static PyObject *pack_output(PyObject *mod, PyObject *const *args, Py_ssize_t nargs) {
    if (nargs != 6) {
        PyErr_SetString(PyExc_TypeError,
                        "pack_output(seq, t, src_seq, axes, positions, flags)");
        return NULL;
    }
    double t = PyFloat_AsDouble(args[1]);
    if (t == -1.0 && PyErr_Occurred()) return NULL;
    PyObject *axes = PySequence_Fast(args[3], "axes must be a sequence of str");
    if (axes == NULL) return NULL;
    PyObject *pos = PySequence_Fast(args[4], "positions must be a sequence of floats");
    if (pos == NULL) {
        Py_DECREF(axes);
        return NULL;
    }
    PyObject *flags = PySequence_Fast(args[5], "flags must be a sequence of str");
    if (flags == NULL) {
        Py_DECREF(axes);
        Py_DECREF(pos);
        return NULL;
    }
    Out o = {.len = 0, .cap = sizeof o.small};
    o.buf = o.small;
    PyObject *res = NULL;
    Py_ssize_t n = PySequence_Fast_GET_SIZE(axes), nf = PySequence_Fast_GET_SIZE(flags);
    if (PySequence_Fast_GET_SIZE(pos) != n) {
        PyErr_Format(PyExc_ValueError, "%zd positions for %zd axes",
                     PySequence_Fast_GET_SIZE(pos), n);
        goto done;
    }
    static const char k_seq[] = "\xa3seq", k_t[] = "\xa1t", k_src[] = "\xa7src_seq",
                      k_pos[] = "\xa3pos", k_flags[] = "\xa5" "flags";
    if (put_be(&o, 0x85, 0, 0) < 0 || put(&o, k_seq, 4) < 0 || put_int(&o, args[0]) < 0 ||
        put(&o, k_t, 2) < 0 || put_double(&o, t) < 0 || put(&o, k_src, 8) < 0 ||
        put_int(&o, args[2]) < 0 || put(&o, k_pos, 4) < 0 ||
        put_container(&o, n, 0x80, 0xde, 0xdf) < 0)
        goto done;
    for (Py_ssize_t i = 0; i < n; i++) {
        PyObject *name = PySequence_Fast_GET_ITEM(axes, i);
        if (!PyUnicode_Check(name)) {
            PyErr_SetString(PyExc_TypeError, "axis names must be str");
            goto done;
        }
        double x = PyFloat_AsDouble(PySequence_Fast_GET_ITEM(pos, i));
        if (x == -1.0 && PyErr_Occurred()) goto done;
        if (put_str(&o, name) < 0 || put_double(&o, x) < 0) goto done;
    }
    if (put(&o, k_flags, 6) < 0 || put_container(&o, nf, 0x90, 0xdc, 0xdd) < 0) goto done;
    for (Py_ssize_t i = 0; i < nf; i++) {
        PyObject *f = PySequence_Fast_GET_ITEM(flags, i);
        if (!PyUnicode_Check(f)) {
            PyErr_SetString(PyExc_TypeError, "flags must be str");
            goto done;
        }
        if (put_str(&o, f) < 0) goto done;
    }
    res = PyBytes_FromStringAndSize(o.buf, o.len);
done:
    if (o.buf != o.small) PyMem_Free(o.buf);
    Py_DECREF(axes);
    Py_DECREF(pos);
    Py_DECREF(flags);
    return res;
}

/* ---- parsing ------------------------------------------------------------------------------ */

typedef struct {
    const unsigned char *p, *end;
} In;

static int need(In *in, Py_ssize_t n) { return in->end - in->p >= n; }

static uint64_t be(const unsigned char *p, int n) {
    uint64_t x = 0;
    for (int j = 0; j < n; j++) x = (x << 8) | p[j];
    return x;
}

/* a map header: its size, or -1 */
static Py_ssize_t map_len(In *in) {
    if (!need(in, 1)) return -1;
    unsigned char c = *in->p;
    if ((c & 0xf0) == 0x80) {
        in->p++;
        return c & 0x0f;
    }
    if (c == 0xde && need(in, 3)) {
        in->p += 3;
        return (Py_ssize_t)be(in->p - 2, 2);
    }
    return -1;
}

/* a str: pointer and length, or NULL */
static const char *str(In *in, Py_ssize_t *n) {
    if (!need(in, 1)) return NULL;
    unsigned char c = *in->p;
    Py_ssize_t len, head;
    if ((c & 0xe0) == 0xa0) {
        len = c & 0x1f;
        head = 1;
    } else if (c == 0xd9 && need(in, 2)) {
        len = in->p[1];
        head = 2;
    } else {
        return NULL;
    }
    if (!need(in, head + len)) return NULL;
    const char *s = (const char *)in->p + head;
    in->p += head + len;
    *n = len;
    return s;
}

/* an integer as a Python int, or NULL without an error set */
static PyObject *integer(In *in) {
    if (!need(in, 1)) return NULL;
    unsigned char c = *in->p;
    if (c < 0x80) {
        in->p++;
        return PyLong_FromLong(c);
    }
    if (c >= 0xe0) {
        in->p++;
        return PyLong_FromLong((long)(signed char)c);
    }
    static const int size[] = {1, 2, 4, 8};
    if (c >= 0xcc && c <= 0xcf) {
        int n = size[c - 0xcc];
        if (!need(in, 1 + n)) return NULL;
        uint64_t x = be(in->p + 1, n);
        in->p += 1 + n;
        return PyLong_FromUnsignedLongLong(x);
    }
    if (c >= 0xd0 && c <= 0xd3) {
        int n = size[c - 0xd0];
        if (!need(in, 1 + n)) return NULL;
        uint64_t x = be(in->p + 1, n);
        in->p += 1 + n;
        int64_t v = n == 1 ? (int8_t)x : n == 2 ? (int16_t)x : n == 4 ? (int32_t)x : (int64_t)x;
        return PyLong_FromLongLong(v);
    }
    return NULL;
}

/* a float32/float64: 1 and the value, or 0 */
static int real(In *in, double *out) {
    if (need(in, 9) && *in->p == 0xcb) {
        uint64_t bits = be(in->p + 1, 8);
        memcpy(out, &bits, 8);
        in->p += 9;
        return 1;
    }
    if (need(in, 5) && *in->p == 0xca) {
        uint32_t bits = (uint32_t)be(in->p + 1, 4);
        float f;
        memcpy(&f, &bits, 4);
        *out = (double)f;
        in->p += 5;
        return 1;
    }
    return 0;
}

static PyObject *parse_input(PyObject *mod, PyObject *const *args, Py_ssize_t nargs) {
    if (nargs != 4 || !PyBytes_Check(args[0]) || !PyDict_Check(args[1])) {
        PyErr_SetString(PyExc_TypeError, "parse_input(payload: bytes, index: dict, lo, hi)");
        return NULL;
    }
    Py_buffer lo, hi;
    if (PyObject_GetBuffer(args[2], &lo, PyBUF_FORMAT | PyBUF_C_CONTIGUOUS) < 0) return NULL;
    if (PyObject_GetBuffer(args[3], &hi, PyBUF_FORMAT | PyBUF_C_CONTIGUOUS) < 0) {
        PyBuffer_Release(&lo);
        return NULL;
    }
    PyObject *seq = NULL, *t = NULL, *pos = NULL, *res = NULL;
    if (lo.itemsize != 8 || hi.itemsize != 8 || lo.len != hi.len || !lo.format ||
        strcmp(lo.format, "d") != 0 || !hi.format || strcmp(hi.format, "d") != 0) {
        PyErr_SetString(PyExc_TypeError, "lo and hi must be equal-length array('d')");
        goto done;
    }
    const double *lop = lo.buf, *hip = hi.buf;
    Py_ssize_t naxes = lo.len / 8;
    In in = {(const unsigned char *)PyBytes_AS_STRING(args[0]), NULL};
    in.end = in.p + PyBytes_GET_SIZE(args[0]);
    Py_ssize_t nkeys = map_len(&in);
    if (nkeys != 2 && nkeys != 3) goto reject;
    for (Py_ssize_t k = 0; k < nkeys; k++) {
        Py_ssize_t n;
        const char *key = str(&in, &n);
        if (key == NULL) goto reject;
        if (n == 3 && memcmp(key, "seq", 3) == 0 && seq == NULL) {
            if ((seq = integer(&in)) == NULL) goto reject;
        } else if (n == 1 && key[0] == 't' && t == NULL) {
            double x;
            if (need(&in, 1) && *in.p == 0xc0) {
                in.p++;
                t = Py_NewRef(Py_None);
            } else if (real(&in, &x) && isfinite(x)) {
                if ((t = PyFloat_FromDouble(x)) == NULL) goto reject;
            } else {
                goto reject;
            }
        } else if (n == 3 && memcmp(key, "pos", 3) == 0 && pos == NULL) {
            Py_ssize_t np = map_len(&in);
            if (np <= 0) goto reject;
            if ((pos = PyDict_New()) == NULL) goto reject;
            for (Py_ssize_t j = 0; j < np; j++) {
                Py_ssize_t an;
                const char *a = str(&in, &an);
                double x;
                if (a == NULL) goto reject;
                PyObject *name = PyUnicode_DecodeUTF8(a, an, NULL);
                if (name == NULL) goto reject;
                PyObject *idx = PyDict_GetItemWithError(args[1], name); /* borrowed */
                if (idx == NULL || !real(&in, &x)) {
                    Py_DECREF(name);
                    goto reject;
                }
                Py_ssize_t i = PyLong_AsSsize_t(idx);
                if (i < 0 || i >= naxes || !(lop[i] <= x && x <= hip[i])) {
                    Py_DECREF(name);
                    goto reject;
                }
                PyObject *val = PyFloat_FromDouble(x);
                int rc = val == NULL ? -1 : PyDict_SetItem(pos, name, val);
                Py_DECREF(name);
                Py_XDECREF(val);
                if (rc < 0) goto reject;
            }
        } else {
            goto reject;
        }
    }
    if (seq == NULL || pos == NULL || in.p != in.end) goto reject;
    res = PyTuple_Pack(3, seq, t ? t : Py_None, pos);
    goto done;
reject:
    PyErr_Clear();
    res = Py_NewRef(Py_None);
done:
    Py_XDECREF(seq);
    Py_XDECREF(t);
    Py_XDECREF(pos);
    PyBuffer_Release(&lo);
    PyBuffer_Release(&hi);
    return res;
}

static PyMethodDef methods[] = {
    {"pack_output", (PyCFunction)(void (*)(void))pack_output, METH_FASTCALL,
     "pack_output(seq, t, src_seq, axes, positions, flags) -> bytes: an output frame."},
    {"parse_input", (PyCFunction)(void (*)(void))parse_input, METH_FASTCALL,
     "parse_input(payload, index, lo, hi) -> (seq, t, pos) | None: the common input frame."},
    {NULL, NULL, 0, NULL}};

static struct PyModuleDef cwire_module = {
    PyModuleDef_HEAD_INIT, "_cwire", "The service's hot wire operations in C.", -1, methods};

PyMODINIT_FUNC PyInit__cwire(void) { return PyModule_Create(&cwire_module); }
