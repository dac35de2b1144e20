/* Compiled tail of the host renderer for the real-time path's small batches: equalizer
 * (second-order sections, transposed direct form II), output stage (soft-start envelope,
 * displacement limit, slew limit, non-finite guard) and DAC codes, in one call; and the
 * batch's series (clenshaw: hostd.render.series.clenshaw_py). The arithmetic is in
 * render_core.h, shared with hostd/device/_fastpump.c.
 *
 * hostd/render/equalizer.py (Equalizer.__call__, its scalar path for <= SMALL_BATCH samples)
 * and hostd/render/output.py (OutputStage.process, OutputStage.to_codes) are the reference;
 * hostd/render/fastrender.py picks this module when it is built (and its REVISION matches) and
 * tests/test_fastcycle.py checks that both give the same codes and the same state, sample for
 * sample, on random and recorded inputs.
 *
 * Sample-equal by construction: the same IEEE double operations in the same order as the
 * Python reference, one sample at a time (no reduction, no vectorization that could reorder
 * anything), and setup.py compiles this file with -ffp-contract=off so that no compiler fuses
 * a multiply and an add into an FMA (which rounds once instead of twice). rint() rounds half
 * to even in the default rounding mode, as numpy's rint does.
 *
 *   tail(sos, zi, x, codes, out) -> None
 *   out: the OutputStage, read and updated as its record (hs_output_t, hostd/device/cycle_state.h)
 *   sos: C-contiguous float64 (n_sections x 6: b0 b1 b2 a0 a1 a2), n_sections may be 0
 *   zi: writable C-contiguous float64 (n_sections x 2), updated in place
 *   x: C-contiguous float64 heights (µm), n <= 64; codes: writable int16 of the same length
 */
#define PY_SSIZE_T_CLEAN
#include <Python.h>
#include <math.h>
#include <stdint.h>
#include <string.h>

#include "render_core.h"

#define REVISION 3 /* fastrender.C_REVISION (and series._load_compiled) must equal this */
#define MAX_N RC_MAX_N

static int get_buf(PyObject *o, Py_buffer *b, int writable, Py_ssize_t itemsize, const char *what) {
    if (PyObject_GetBuffer(o, b, PyBUF_C_CONTIGUOUS | PyBUF_FORMAT | (writable ? PyBUF_WRITABLE : 0)) < 0)
        return -1;
    if (b->itemsize != itemsize) {
        PyErr_Format(PyExc_TypeError, "%s: items of %zd bytes expected", what, itemsize);
        PyBuffer_Release(b);
        return -1;
    }
    return 0;
}

static PyObject *fr_tail(PyObject *self, PyObject *args) {
    PyObject *o_sos, *o_zi, *o_x, *o_codes, *o_out;
    if (!PyArg_ParseTuple(args, "OOOOO", &o_sos, &o_zi, &o_x, &o_codes, &o_out))
        return NULL;
    Py_buffer sos, zi, x, codes, out;
    if (PyObject_GetBuffer(o_out, &out, PyBUF_WRITABLE) < 0)
        return NULL;
    if (out.len != sizeof(hs_output_t)) {
        PyBuffer_Release(&out);
        PyErr_SetString(PyExc_TypeError, "tail: an OutputStage (its hs_output_t record) expected");
        return NULL;
    }
    if (get_buf(o_sos, &sos, 0, 8, "sos") < 0) {
        PyBuffer_Release(&out);
        return NULL;
    }
    if (get_buf(o_zi, &zi, 1, 8, "zi") < 0) {
        PyBuffer_Release(&sos);
        PyBuffer_Release(&out);
        return NULL;
    }
    if (get_buf(o_x, &x, 0, 8, "x") < 0) {
        PyBuffer_Release(&sos);
        PyBuffer_Release(&zi);
        PyBuffer_Release(&out);
        return NULL;
    }
    if (get_buf(o_codes, &codes, 1, 2, "codes") < 0) {
        PyBuffer_Release(&sos);
        PyBuffer_Release(&zi);
        PyBuffer_Release(&x);
        PyBuffer_Release(&out);
        return NULL;
    }
    Py_ssize_t ns = sos.len / 48, n = x.len / 8;
    PyObject *ret = NULL;
    if (sos.len != ns * 48 || zi.len != ns * 16 || codes.len != n * 2 || n > MAX_N) {
        PyErr_SetString(PyExc_ValueError, "tail: sos (n x 6), zi (n x 2), x and codes (same length) expected");
        goto done;
    }
    rc_tail((const double *)sos.buf, ns, (double *)zi.buf, (const double *)x.buf, n, (int16_t *)codes.buf,
            (hs_output_t *)out.buf);
    ret = Py_NewRef(Py_None);
done:
    PyBuffer_Release(&out);
    PyBuffer_Release(&sos);
    PyBuffer_Release(&zi);
    PyBuffer_Release(&x);
    PyBuffer_Release(&codes);
    return ret;
}

static PyObject *fr_clenshaw(PyObject *self, PyObject *args) {
    PyObject *o_c, *o_th, *o_out;
    long k0;
    if (!PyArg_ParseTuple(args, "OOOl", &o_c, &o_th, &o_out, &k0))
        return NULL;
    Py_buffer c, th, out;
    if (get_buf(o_c, &c, 0, 8, "coeffs") < 0)
        return NULL;
    if (get_buf(o_th, &th, 0, 8, "theta") < 0) {
        PyBuffer_Release(&c);
        return NULL;
    }
    if (get_buf(o_out, &out, 1, 8, "out") < 0) {
        PyBuffer_Release(&c);
        PyBuffer_Release(&th);
        return NULL;
    }
    PyObject *ret = NULL;
    if (out.len != th.len || k0 < 1) {
        PyErr_SetString(PyExc_ValueError, "clenshaw: out as long as theta, k0 >= 1 expected");
    } else {
        rc_clenshaw((const double *)c.buf, c.len / 8, (const double *)th.buf, th.len / 8, (double *)out.buf, k0);
        ret = Py_NewRef(Py_None);
    }
    PyBuffer_Release(&c);
    PyBuffer_Release(&th);
    PyBuffer_Release(&out);
    return ret;
}

static PyMethodDef methods[] = {
    {"clenshaw", fr_clenshaw, METH_VARARGS,
     "clenshaw(coeffs, theta, out, k0): out[i] = sum_j coeffs[j] cos((k0 + j) theta[i]) (series.clenshaw_py)"},
    {"tail", fr_tail, METH_VARARGS,
     "tail(sos, zi, x, codes, last, env, target, lim, step, ramp, codes_per_um, limit_code)"
     " -> (last, env, nonfinite, clipped)"},
    {NULL, NULL, 0, NULL},
};

static struct PyModuleDef module = {
    PyModuleDef_HEAD_INIT, "_fastrender",
    "Compiled equalizer + output stage + codes for small batches (see hostd/render/fastrender.py).", -1,
    methods, NULL, NULL, NULL, NULL,
};

PyMODINIT_FUNC PyInit__fastrender(void) {
    PyObject *m = PyModule_Create(&module);
    if (!m)
        return NULL;
    if (PyModule_AddIntConstant(m, "REVISION", REVISION) < 0 || PyModule_AddIntConstant(m, "MAX_N", MAX_N) < 0) {
        Py_DECREF(m);
        return NULL;
    }
    return m;
}
