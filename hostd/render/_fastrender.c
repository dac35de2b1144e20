/* Compiled tail of the host renderer for the real-time path's small batches: equalizer
 * (second-order sections, transposed direct form II), output stage (soft-start envelope,
 * displacement limit, slew limit, non-finite guard) and DAC codes, in one call.
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
 *   tail(sos, zi, x, codes, last, env, target, lim, step, ramp, codes_per_um, limit_code)
 *       -> (last, env, nonfinite, clipped)
 *   sos: C-contiguous float64 (n_sections x 6: b0 b1 b2 a0 a1 a2), n_sections may be 0
 *   zi: writable C-contiguous float64 (n_sections x 2), updated in place
 *   x: C-contiguous float64 heights (µm), n <= 64; codes: writable int16 of the same length
 */
#define PY_SSIZE_T_CLEAN
#include <Python.h>
#include <math.h>
#include <stdint.h>
#include <string.h>

#define REVISION 1 /* fastrender.C_REVISION must equal this */
#define MAX_N 64 /* the real-time batches are <= equalizer.SMALL_BATCH samples */
#define DENORMAL_GUARD 1e-30 /* equalizer.DENORMAL_GUARD */

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
    PyObject *o_sos, *o_zi, *o_x, *o_codes;
    double last, env, target, lim, step, ramp, cpu;
    long lc;
    if (!PyArg_ParseTuple(args, "OOOOdddddddl", &o_sos, &o_zi, &o_x, &o_codes, &last, &env, &target, &lim,
                          &step, &ramp, &cpu, &lc))
        return NULL;
    Py_buffer sos, zi, x, codes;
    if (get_buf(o_sos, &sos, 0, 8, "sos") < 0)
        return NULL;
    if (get_buf(o_zi, &zi, 1, 8, "zi") < 0) {
        PyBuffer_Release(&sos);
        return NULL;
    }
    if (get_buf(o_x, &x, 0, 8, "x") < 0) {
        PyBuffer_Release(&sos);
        PyBuffer_Release(&zi);
        return NULL;
    }
    if (get_buf(o_codes, &codes, 1, 2, "codes") < 0) {
        PyBuffer_Release(&sos);
        PyBuffer_Release(&zi);
        PyBuffer_Release(&x);
        return NULL;
    }
    Py_ssize_t ns = sos.len / 48, n = x.len / 8;
    PyObject *ret = NULL;
    if (sos.len != ns * 48 || zi.len != ns * 16 || codes.len != n * 2 || n > MAX_N) {
        PyErr_SetString(PyExc_ValueError, "tail: sos (n x 6), zi (n x 2), x and codes (same length) expected");
        goto done;
    }
    const double *s = (const double *)sos.buf;
    double *z = (double *)zi.buf;
    double ys[MAX_N];
    memcpy(ys, x.buf, (size_t)n * sizeof(double));
    for (Py_ssize_t k = 0; k < ns; k++) {
        const double b0 = s[6 * k], b1 = s[6 * k + 1], b2 = s[6 * k + 2], a1 = s[6 * k + 4], a2 = s[6 * k + 5];
        double z0 = z[2 * k], z1 = z[2 * k + 1];
        for (Py_ssize_t i = 0; i < n; i++) {
            const double v = ys[i];
            const double y = b0 * v + z0;
            z0 = b1 * v - a1 * y + z1;
            z1 = b2 * v - a2 * y;
            ys[i] = y;
        }
        z[2 * k] = fabs(z0) >= DENORMAL_GUARD ? z0 : 0.0;
        z[2 * k + 1] = fabs(z1) >= DENORMAL_GUARD ? z1 : 0.0;
    }
    long nonfinite = 0, clipped = 0;
    int16_t *out = (int16_t *)codes.buf;
    const double lcd = (double)lc;
    for (Py_ssize_t i = 0; i < n; i++) {
        double v = ys[i];
        if (!isfinite(v)) {
            nonfinite++;
            v = last;
        }
        if (env != target) {
            if (target > env) {
                const double e = env + ramp;
                env = (1.0 < e) ? 1.0 : e; /* Python's min(e, 1.0) */
            } else {
                const double e = env - ramp;
                env = (0.0 > e) ? 0.0 : e; /* Python's max(e, 0.0) */
            }
        }
        v *= env;
        if (v > lim || v < -lim) {
            clipped++;
            v = v > 0 ? lim : -lim;
        }
        const double d = v - last;
        if (d > step)
            v = last + step;
        else if (d < -step)
            v = last - step;
        last = v;
        double c = rint(v * cpu); /* OutputStage.to_codes: rint, clip, astype */
        if (c < -lcd)
            c = -lcd;
        else if (c > lcd)
            c = lcd;
        out[i] = (int16_t)c;
    }
    ret = Py_BuildValue("ddll", last, env, nonfinite, clipped);
done:
    PyBuffer_Release(&sos);
    PyBuffer_Release(&zi);
    PyBuffer_Release(&x);
    PyBuffer_Release(&codes);
    return ret;
}

static PyMethodDef methods[] = {
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
