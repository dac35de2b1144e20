/* Compiled implementation of the stream-v2 index coder: the adaptive binary range coder and
 * context model specified in docs/stream-format.md ("Entropy coder (exact)").
 *
 * hostd/codec/rangecoder.py holds the executable reference of the same spec and the pure-Python
 * fallback; it picks this module at import when it is built (and its REVISION matches) and
 * wraps it: argument checks and the StreamError messages live there, in one place. Both are
 * cross-tested on every golden vector and on random and hostile inputs (tests/test_rangecoder.py).
 *
 * Integer arithmetic only (uint32 range/code, uint64 low), no floating point, no
 * platform-dependent behaviour: the same bytes and indices on every CPU and compiler.
 *
 *   encode(q) -> bytes        q: a C-contiguous buffer of native int64 indices, |q| < 2^40
 *                             (checked by the caller)
 *   decode(payload, out) -> (status, n_sig)
 *                             out: a writable C-contiguous buffer of N' native int64, zeroed
 *                             by the caller; status 0 = decoded, ERR_* below = malformed.
 *                             Never reads past payload, never writes past out.
 */
#define PY_SSIZE_T_CLEAN
#include <Python.h>
#include <stdint.h>
#include <string.h>

#define REVISION 1          /* rangecoder.C_REVISION must equal this */
#define TOP (1u << 24)
#define N_CTX 5
#define N_EG 16
#define EG_MAX_PREFIX 40
#define MAX_ABS_INDEX ((((uint64_t)1) << 40) - 1)

#define ERR_TOO_LONG 1      /* an Exp-Golomb prefix longer than EG_MAX_PREFIX */
#define ERR_N_SIG 2         /* n_sig > N' */
#define ERR_RANGE 3         /* |q| > MAX_ABS_INDEX */

/* ------------------------------------------------------------------ decoder */

typedef struct {
    const uint8_t *buf;
    Py_ssize_t pos, len;
    uint32_t code, rng;
} Dec;

static inline uint32_t dec_byte(Dec *d) {
    return d->pos < d->len ? d->buf[d->pos++] : 0u;
}

static inline void dec_norm(Dec *d) {
    while (d->rng < TOP) {
        d->rng <<= 8;
        d->code = (d->code << 8) | dec_byte(d);
    }
}

static inline int dec_bit(Dec *d, uint16_t *pp) {
    uint32_t p = *pp;
    uint32_t bound = (d->rng >> 11) * p;
    int b;
    if (d->code < bound) {
        d->rng = bound;
        *pp = (uint16_t)(p + ((2048u - p) >> 4));
        b = 0;
    } else {
        d->code -= bound;
        d->rng -= bound;
        *pp = (uint16_t)(p - (p >> 4));
        b = 1;
    }
    dec_norm(d);
    return b;
}

static inline int dec_bypass(Dec *d) {
    int b = 0;
    d->rng >>= 1;
    if (d->code >= d->rng) {
        d->code -= d->rng;
        b = 1;
    }
    dec_norm(d);
    return b;
}

/* EG with adaptive prefix: *v1 = v + 1 */
static int dec_eg(Dec *d, uint16_t *probs, uint64_t *v1) {
    int n = 0, i;
    uint64_t v = 1;
    while (dec_bit(d, &probs[n < N_EG - 1 ? n : N_EG - 1])) {
        if (++n > EG_MAX_PREFIX)
            return ERR_TOO_LONG;
    }
    for (i = 0; i < n; i++)
        v = (v << 1) | (uint64_t)dec_bypass(d);
    *v1 = v;
    return 0;
}

static int decode_all(Dec *d, int64_t *out, uint64_t n_keep, uint64_t *n_sig_out) {
    uint16_t p_zero[N_CTX], p_gt1[N_CTX], p_sig[N_EG], p_mag[N_EG];
    uint64_t v1, n_sig, k, a, a1 = 0, a2 = 0;
    int i, err, ctx, neg;
    for (i = 0; i < N_CTX; i++) p_zero[i] = p_gt1[i] = 1024;
    for (i = 0; i < N_EG; i++) p_sig[i] = p_mag[i] = 1024;
    *n_sig_out = 0;
    if ((err = dec_eg(d, p_sig, &v1)))
        return err;
    n_sig = v1 - 1;
    *n_sig_out = n_sig;
    if (n_sig > n_keep)
        return ERR_N_SIG;
    for (k = 0; k < n_sig; k++) {
        ctx = (int)(a1 < 2 ? a1 : 2) + (int)(a2 < 2 ? a2 : 2);
        if (k != n_sig - 1 && !dec_bit(d, &p_zero[ctx])) {
            a2 = a1;
            a1 = 0;
            continue;
        }
        neg = dec_bypass(d);
        if (dec_bit(d, &p_gt1[ctx])) {
            if ((err = dec_eg(d, p_mag, &v1)))
                return err;
            a = 1 + v1;
            if (a > MAX_ABS_INDEX)
                return ERR_RANGE;
        } else {
            a = 1;
        }
        out[k] = neg ? -(int64_t)a : (int64_t)a;
        a2 = a1;
        a1 = a;
    }
    return 0;
}

static PyObject *rc_decode(PyObject *self, PyObject *args) {
    Py_buffer data, out;
    Dec d;
    int i, status;
    uint64_t n_sig = 0;
    (void)self;
    if (!PyArg_ParseTuple(args, "y*w*", &data, &out))
        return NULL;
    if (out.len % (Py_ssize_t)sizeof(int64_t) != 0) {
        PyBuffer_Release(&data);
        PyBuffer_Release(&out);
        PyErr_SetString(PyExc_ValueError, "out must hold int64 values");
        return NULL;
    }
    d.buf = (const uint8_t *)data.buf;
    d.len = data.len;
    d.code = 0;
    for (i = 0; i < 4; i++)
        d.code = (d.code << 8) | (i < d.len ? d.buf[i] : 0u);
    d.pos = 4;
    d.rng = 0xFFFFFFFFu;
    Py_BEGIN_ALLOW_THREADS
    status = decode_all(&d, (int64_t *)out.buf, (uint64_t)(out.len / (Py_ssize_t)sizeof(int64_t)),
                        &n_sig);
    Py_END_ALLOW_THREADS
    PyBuffer_Release(&data);
    PyBuffer_Release(&out);
    return Py_BuildValue("(iK)", status, (unsigned long long)n_sig);
}

/* ------------------------------------------------------------------ encoder */

typedef struct {
    uint64_t low, cache_size;
    uint32_t rng;
    uint8_t cache;
    uint8_t *out;
    size_t n, cap;
    int oom;
} Enc;

static inline void enc_put(Enc *e, uint8_t b) {
    if (e->n == e->cap) {
        size_t cap = e->cap ? 2 * e->cap : 256;
        uint8_t *p = (uint8_t *)PyMem_RawRealloc(e->out, cap);
        if (!p) {
            e->oom = 1;
            return;
        }
        e->out = p;
        e->cap = cap;
    }
    if (!e->oom)
        e->out[e->n++] = b;
}

static void enc_shift_low(Enc *e) {
    if (e->low < 0xFF000000u || e->low > 0xFFFFFFFFu) {
        uint8_t carry = (uint8_t)(e->low >> 32);
        uint8_t temp = e->cache;
        do {
            enc_put(e, (uint8_t)(temp + carry));
            temp = 0xFF;
        } while (--e->cache_size);
        e->cache = (uint8_t)(e->low >> 24);
    }
    e->cache_size++;
    e->low = (e->low & 0x00FFFFFFu) << 8;
}

static inline void enc_norm(Enc *e) {
    while (e->rng < TOP) {
        e->rng <<= 8;
        enc_shift_low(e);
    }
}

static inline void enc_bit(Enc *e, uint16_t *pp, int b) {
    uint32_t p = *pp;
    uint32_t bound = (e->rng >> 11) * p;
    if (b) {
        e->low += bound;
        e->rng -= bound;
        *pp = (uint16_t)(p - (p >> 4));
    } else {
        e->rng = bound;
        *pp = (uint16_t)(p + ((2048u - p) >> 4));
    }
    enc_norm(e);
}

static inline void enc_bypass(Enc *e, int b) {
    e->rng >>= 1;
    if (b)
        e->low += e->rng;
    enc_norm(e);
}

static void enc_eg(Enc *e, uint16_t *probs, uint64_t v) {
    uint64_t v1 = v + 1;
    int n = 0, i;
    while ((v1 >> (n + 1)) != 0)
        n++;                     /* n = bitlength(v1) - 1 */
    for (i = 0; i < n; i++)
        enc_bit(e, &probs[i < N_EG - 1 ? i : N_EG - 1], 1);
    enc_bit(e, &probs[n < N_EG - 1 ? n : N_EG - 1], 0);
    for (i = n - 1; i >= 0; i--)
        enc_bypass(e, (int)((v1 >> i) & 1));
}

static void encode_all(Enc *e, const int64_t *q, Py_ssize_t count) {
    uint16_t p_zero[N_CTX], p_gt1[N_CTX], p_sig[N_EG], p_mag[N_EG];
    Py_ssize_t k, n_sig = 0;
    uint64_t a, a1 = 0, a2 = 0, hi, v;
    int i, ctx, shift;
    for (i = 0; i < N_CTX; i++) p_zero[i] = p_gt1[i] = 1024;
    for (i = 0; i < N_EG; i++) p_sig[i] = p_mag[i] = 1024;
    for (k = 0; k < count; k++)
        if (q[k])
            n_sig = k + 1;
    enc_eg(e, p_sig, (uint64_t)n_sig);
    for (k = 0; k < n_sig; k++) {
        a = q[k] < 0 ? (uint64_t)0 - (uint64_t)q[k] : (uint64_t)q[k];
        ctx = (int)(a1 < 2 ? a1 : 2) + (int)(a2 < 2 ? a2 : 2);
        if (k != n_sig - 1)
            enc_bit(e, &p_zero[ctx], a != 0);
        if (a) {
            enc_bypass(e, q[k] < 0);
            enc_bit(e, &p_gt1[ctx], a > 1);
            if (a > 1)
                enc_eg(e, p_mag, a - 2);
        }
        a2 = a1;
        a1 = a;
    }
    /* the value in [low, low + range) with the most trailing zero bits, then flush */
    hi = e->low + e->rng - 1;
    for (shift = 32; shift >= 0; shift -= 8) {
        v = ((e->low + (((uint64_t)1) << shift) - 1) >> shift) << shift;
        if (v <= hi) {
            e->low = v;
            break;
        }
    }
    for (i = 0; i < 5; i++)
        enc_shift_low(e);
}

static PyObject *rc_encode(PyObject *self, PyObject *args) {
    Py_buffer q;
    Enc e;
    PyObject *res;
    size_t end;
    (void)self;
    if (!PyArg_ParseTuple(args, "y*", &q))
        return NULL;
    if (q.len % (Py_ssize_t)sizeof(int64_t) != 0) {
        PyBuffer_Release(&q);
        PyErr_SetString(PyExc_ValueError, "q must hold int64 values");
        return NULL;
    }
    memset(&e, 0, sizeof e);
    e.rng = 0xFFFFFFFFu;
    e.cache_size = 1;
    Py_BEGIN_ALLOW_THREADS
    encode_all(&e, (const int64_t *)q.buf, q.len / (Py_ssize_t)sizeof(int64_t));
    Py_END_ALLOW_THREADS
    PyBuffer_Release(&q);
    if (e.oom) {
        PyMem_RawFree(e.out);
        return PyErr_NoMemory();
    }
    if (e.n == 0 || e.out[0] != 0) {
        PyMem_RawFree(e.out);
        PyErr_SetString(PyExc_AssertionError, "range coder invariant broken: first byte not 0");
        return NULL;
    }
    end = e.n;
    while (end > 1 && e.out[end - 1] == 0)
        end--;
    res = PyBytes_FromStringAndSize((const char *)e.out + 1, (Py_ssize_t)(end - 1));
    PyMem_RawFree(e.out);
    return res;
}

/* ------------------------------------------------------------------ module */

static PyMethodDef methods[] = {
    {"encode", rc_encode, METH_VARARGS, "encode(q: int64 buffer) -> bytes (the index stream)"},
    {"decode", rc_decode, METH_VARARGS,
     "decode(payload: bytes, out: writable int64 buffer of N' zeros) -> (status, n_sig)"},
    {NULL, NULL, 0, NULL},
};

static struct PyModuleDef module = {
    PyModuleDef_HEAD_INIT, "_rangecoder",
    "Compiled stream-v2 index coder (see hostd/codec/rangecoder.py, the reference).", -1, methods,
    NULL, NULL, NULL, NULL,
};

PyMODINIT_FUNC PyInit__rangecoder(void) {
    PyObject *m = PyModule_Create(&module);
    if (!m)
        return NULL;
    if (PyModule_AddIntConstant(m, "REVISION", REVISION) < 0 ||
        PyModule_AddIntConstant(m, "ERR_TOO_LONG", ERR_TOO_LONG) < 0 ||
        PyModule_AddIntConstant(m, "ERR_N_SIG", ERR_N_SIG) < 0 ||
        PyModule_AddIntConstant(m, "ERR_RANGE", ERR_RANGE) < 0) {
        Py_DECREF(m);
        return NULL;
    }
    return m;
}
