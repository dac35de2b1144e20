/* Compiled per-message work of the device link: decoding fixed-layout messages from the
 * device (STATUS every millisecond) and encoding SAMPLES messages to it.
 *
 * hostd/device/protocol.py (encode, decode) is the reference; hostd/device/fastlink.py picks
 * this module when it is built (and its REVISION matches), hands it the layouts read from
 * protocol.toml (so a layout change needs no change here), and falls back to the reference
 * for anything this module declines (it returns None: a short or padded-with-garbage message,
 * a value out of range), so the errors and their messages stay in one place.
 * tests/test_fastcycle.py checks that both give the same bytes and the same fields.
 * Integer and float32 fields only, little-endian, read byte by byte: the same on every CPU.
 *
 *   decode_fixed(msg, fmt, names) -> dict | None
 *       fmt: bytes of struct codes (B H I b h i f), one per name; the message must be at least
 *       as long as the layout and zero after it
 *   encode_samples(seq, codes) -> bytes | None
 *       SAMPLES = id:u8 flags:u8 seq:u16 count:u8 codes:i16[]; codes: an int16 buffer of at
 *       most max_samples items (set by init)
 *   init(samples_id, max_samples)
 */
#define PY_SSIZE_T_CLEAN
#include <Python.h>
#include <stdint.h>
#include <string.h>

#define REVISION 1 /* fastlink.C_REVISION must equal this */

static int samples_id = -1, max_samples = 0;

static uint32_t rd(const unsigned char *p, int n) {
    uint32_t v = 0;
    for (int i = n - 1; i >= 0; i--)
        v = (v << 8) | p[i];
    return v;
}

static PyObject *fl_init(PyObject *self, PyObject *args) {
    int sid, ms;
    if (!PyArg_ParseTuple(args, "ii", &sid, &ms))
        return NULL;
    if (sid < 0 || sid > 255 || ms < 0 || ms > 255) {
        PyErr_SetString(PyExc_ValueError, "init: id and max_samples must fit a byte");
        return NULL;
    }
    samples_id = sid;
    max_samples = ms;
    Py_RETURN_NONE;
}

static PyObject *fl_decode_fixed(PyObject *self, PyObject *args) {
    Py_buffer msg;
    const char *fmt;
    Py_ssize_t nfmt;
    PyObject *names;
    if (!PyArg_ParseTuple(args, "y*y#O!", &msg, &fmt, &nfmt, &PyTuple_Type, &names))
        return NULL;
    PyObject *out = NULL;
    if (PyTuple_GET_SIZE(names) != nfmt) {
        PyErr_SetString(PyExc_ValueError, "decode_fixed: one name per field");
        goto done;
    }
    Py_ssize_t size = 0;
    for (Py_ssize_t i = 0; i < nfmt; i++) {
        char c = fmt[i];
        if (c == 'B' || c == 'b')
            size += 1;
        else if (c == 'H' || c == 'h')
            size += 2;
        else if (c == 'I' || c == 'i' || c == 'f')
            size += 4;
        else {
            PyErr_Format(PyExc_ValueError, "decode_fixed: unsupported field code %c", c);
            goto done;
        }
    }
    const unsigned char *p = (const unsigned char *)msg.buf;
    if (msg.len < size) {
        out = Py_NewRef(Py_None);
        goto done;
    }
    for (Py_ssize_t i = size; i < msg.len; i++)
        if (p[i]) {
            out = Py_NewRef(Py_None);
            goto done;
        }
    out = _PyDict_NewPresized(nfmt);
    if (!out)
        goto done;
    Py_ssize_t off = 0;
    for (Py_ssize_t i = 0; i < nfmt; i++) {
        PyObject *v;
        uint32_t u;
        switch (fmt[i]) {
        case 'B': v = PyLong_FromUnsignedLong(p[off]); off += 1; break;
        case 'b': v = PyLong_FromLong((int8_t)p[off]); off += 1; break;
        case 'H': v = PyLong_FromUnsignedLong(rd(p + off, 2)); off += 2; break;
        case 'h': v = PyLong_FromLong((int16_t)rd(p + off, 2)); off += 2; break;
        case 'I': v = PyLong_FromUnsignedLong(rd(p + off, 4)); off += 4; break;
        case 'i': v = PyLong_FromLong((long)(int32_t)rd(p + off, 4)); off += 4; break;
        default: { /* 'f': IEEE single, widened exactly to double as struct.unpack does */
            float f;
            u = rd(p + off, 4);
            memcpy(&f, &u, 4);
            v = PyFloat_FromDouble((double)f);
            off += 4;
        }
        }
        if (!v || PyDict_SetItem(out, PyTuple_GET_ITEM(names, i), v) < 0) {
            Py_XDECREF(v);
            Py_CLEAR(out);
            goto done;
        }
        Py_DECREF(v);
    }
done:
    PyBuffer_Release(&msg);
    return out;
}

static PyObject *fl_encode_samples(PyObject *self, PyObject *args) {
    long seq;
    PyObject *o_codes;
    if (!PyArg_ParseTuple(args, "lO", &seq, &o_codes))
        return NULL;
    Py_buffer b;
    if (PyObject_GetBuffer(o_codes, &b, PyBUF_C_CONTIGUOUS | PyBUF_FORMAT) < 0)
        return NULL;
    PyObject *out = NULL;
    Py_ssize_t n = b.len / 2;
    if (b.itemsize != 2 || b.format == NULL || (strcmp(b.format, "h") && strcmp(b.format, "<h") &&
                                                strcmp(b.format, "=h"))) {
        PyErr_SetString(PyExc_TypeError, "encode_samples: an int16 buffer expected");
        goto done;
    }
    if (samples_id < 0 || seq < 0 || seq > 0xFFFF || n > max_samples) {
        out = Py_NewRef(Py_None); /* the reference says what is wrong */
        goto done;
    }
    unsigned char buf[5 + 2 * 255];
    const int16_t *c = (const int16_t *)b.buf;
    buf[0] = (unsigned char)samples_id;
    buf[1] = 0;
    buf[2] = (unsigned char)(seq & 0xFF);
    buf[3] = (unsigned char)(seq >> 8);
    buf[4] = (unsigned char)n;
    for (Py_ssize_t i = 0; i < n; i++) {
        uint16_t u = (uint16_t)c[i];
        buf[5 + 2 * i] = (unsigned char)(u & 0xFF);
        buf[6 + 2 * i] = (unsigned char)(u >> 8);
    }
    out = PyBytes_FromStringAndSize((const char *)buf, 5 + 2 * n);
done:
    PyBuffer_Release(&b);
    return out;
}

static PyMethodDef methods[] = {
    {"init", fl_init, METH_VARARGS, "init(samples_id, max_samples)"},
    {"decode_fixed", fl_decode_fixed, METH_VARARGS, "decode_fixed(msg, fmt, names) -> dict | None"},
    {"encode_samples", fl_encode_samples, METH_VARARGS, "encode_samples(seq, int16 codes) -> bytes | None"},
    {NULL, NULL, 0, NULL},
};

static struct PyModuleDef module = {
    PyModuleDef_HEAD_INIT, "_fastlink",
    "Compiled message decode/encode of the device link (see hostd/device/fastlink.py).", -1, methods,
    NULL, NULL, NULL, NULL,
};

PyMODINIT_FUNC PyInit__fastlink(void) {
    PyObject *m = PyModule_Create(&module);
    if (!m)
        return NULL;
    if (PyModule_AddIntConstant(m, "REVISION", REVISION) < 0) {
        Py_DECREF(m);
        return NULL;
    }
    return m;
}
