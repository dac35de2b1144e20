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
 *   gather(fd, other_fds, timeout_ms, count, buf) -> (ready_other_fds, wake_ups, hung_up)
 *       device mode's sleep over a byte stream (hostd.device.seriallink.SerialTransport.gather):
 *       poll() on fd and other_fds, the GIL released, until `count` frame delimiters (0x00)
 *       have arrived, another descriptor is readable or timeout_ms has passed; each wake-up by
 *       fd reads what arrived (non-blocking fd, only the bytes TIOCINQ counts: a read of an
 *       empty tty waits for the kernel's buffer work) onto the bytearray buf. hung_up: fd
 *       reported POLLHUP/POLLERR with nothing to read, TIOCINQ failed (EIO: hung up) or its
 *       read ended (0 bytes) or failed (not EAGAIN): the caller's next read says what happened.
 *       No REVISION change: fastlink looks the function up by name.
 *   deframe(buf, max_frame) -> (messages, bad_frames)
 *       protocol.Deframer's loop over its bytearray buf (serial framing: COBS(msg + CRC16 LE) +
 *       0x00): takes every complete frame off the front of buf, returns the valid messages (bytes)
 *       and how many frames were bad (COBS, too short, CRC); with no delimiter left and more than
 *       4 x max_frame bytes waiting, buf is cleared and one more bad frame counted (a resync).
 *       The same messages and counts as the reference (tests/test_device.py compares them);
 *       device mode's wake-up deframes a report pair here instead of in Python. Looked up by name.
 */
#define PY_SSIZE_T_CLEAN
#include <Python.h>
#include <errno.h>
#include <poll.h>
#include <sys/ioctl.h>
#include <stdint.h>
#include <string.h>
#include <time.h>
#include <unistd.h>
#include "fw_framing.h" /* fw_unframe: the firmware's framing (firmware/src/framing.c) */

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

static double now_ms(void) {
    struct timespec ts;
    clock_gettime(CLOCK_MONOTONIC, &ts);
    return ts.tv_sec * 1e3 + ts.tv_nsec * 1e-6;
}

#define GATHER_MAX_FDS 8

static PyObject *fl_gather(PyObject *self, PyObject *args) {
    int fd, timeout_ms, count;
    PyObject *others, *buf;
    if (!PyArg_ParseTuple(args, "iO!iiO!", &fd, &PyTuple_Type, &others, &timeout_ms, &count,
                          &PyByteArray_Type, &buf))
        return NULL;
    Py_ssize_t n_others = PyTuple_GET_SIZE(others);
    if (n_others > GATHER_MAX_FDS - 1) {
        PyErr_SetString(PyExc_ValueError, "gather: too many descriptors");
        return NULL;
    }
    struct pollfd pfd[GATHER_MAX_FDS];
    pfd[0].fd = fd;
    pfd[0].events = POLLIN;
    for (Py_ssize_t i = 0; i < n_others; i++) {
        long v = PyLong_AsLong(PyTuple_GET_ITEM(others, i));
        if (v == -1 && PyErr_Occurred())
            return NULL;
        pfd[i + 1].fd = (int)v;
        pfd[i + 1].events = POLLIN;
    }
    int nfds = (int)n_others + 1, runs = 0, hup = 0, frames = 0, ready_other = 0;
    double deadline = now_ms() + (timeout_ms > 0 ? timeout_ms : 0);
    unsigned char chunk[4096];
    for (;;) {
        int r, err = 0;
        Py_BEGIN_ALLOW_THREADS
        r = poll(pfd, (nfds_t)nfds, timeout_ms);
        if (r < 0)
            err = errno;
        Py_END_ALLOW_THREADS
        runs++;
        if (r < 0) {
            if (err != EINTR) {
                errno = err;
                return PyErr_SetFromErrno(PyExc_OSError);
            }
            if (PyErr_CheckSignals() < 0)
                return NULL;
            r = 0;
        }
        if (r > 0 && pfd[0].revents) {
            int first = 1;
            for (;;) { /* what arrived (one read, normally): only what TIOCINQ says is there, never
                        * a read of an empty tty, which waits for the kernel's buffer work */
                ssize_t got;
                int rerr = 0, avail = 0;
                if (ioctl(fd, TIOCINQ, &avail) < 0) {
                    hup = 1; /* hung up (EIO), or not a tty: the caller's read says which */
                    break;
                }
                if (avail <= 0 && !first) /* (the first: poll said readable; a descriptor that does
                                           * not count its bytes is read as before) */
                    break;
                if (avail <= 0 && (pfd[0].revents & (POLLHUP | POLLERR | POLLNVAL))) {
                    hup = 1;
                    break;
                }
                first = 0;
                const size_t want = avail > 0 && (size_t)avail < sizeof chunk ? (size_t)avail : sizeof chunk;
                Py_BEGIN_ALLOW_THREADS
                got = read(fd, chunk, want);
                if (got < 0)
                    rerr = errno;
                Py_END_ALLOW_THREADS
                if (got > 0) {
                    Py_ssize_t old = PyByteArray_GET_SIZE(buf);
                    if (PyByteArray_Resize(buf, old + got) < 0)
                        return NULL;
                    memcpy(PyByteArray_AS_STRING(buf) + old, chunk, (size_t)got);
                    if (got == (ssize_t)sizeof chunk)
                        continue;
                    break;
                }
                if (got < 0 && (rerr == EAGAIN || rerr == EWOULDBLOCK) &&
                    !(pfd[0].revents & (POLLHUP | POLLERR)))
                    break;
                hup = 1; /* the end, an error, or a hang-up with nothing left: the caller finds out */
                break;
            }
        }
        for (int i = 1; i < nfds; i++)
            if (pfd[i].revents)
                ready_other = 1;
        if (hup || ready_other || r == 0)
            break;
        /* count the delimiters gathered so far (frames of the messages waiting) */
        {
            Py_ssize_t len = PyByteArray_GET_SIZE(buf);
            const char *b = PyByteArray_AS_STRING(buf);
            int delims = 0;
            for (Py_ssize_t i = 0; i < len; i++)
                delims += b[i] == 0;
            frames = delims;
        }
        if (frames >= count)
            break;
        double left = deadline - now_ms();
        if (left <= 0)
            break;
        timeout_ms = (int)(left + 0.999);
    }
    PyObject *ready = PyList_New(0);
    if (!ready)
        return NULL;
    for (int i = 1; i < nfds; i++) {
        if (!pfd[i].revents)
            continue;
        PyObject *v = PyLong_FromLong(pfd[i].fd);
        if (!v || PyList_Append(ready, v) < 0) {
            Py_XDECREF(v);
            Py_DECREF(ready);
            return NULL;
        }
        Py_DECREF(v);
    }
    return Py_BuildValue("(Nii)", ready, runs, hup);
}

/* ------------------------------------------------------------------ serial framing (fw_framing.h) */

static PyObject *fl_deframe(PyObject *self, PyObject *args) {
    PyObject *buf;
    Py_ssize_t max_frame;
    if (!PyArg_ParseTuple(args, "O!n", &PyByteArray_Type, &buf, &max_frame))
        return NULL;
    PyObject *out = PyList_New(0);
    if (!out)
        return NULL;
    long bad = 0;
    unsigned char small[256], *raw = small, *big = NULL;
    Py_ssize_t len = PyByteArray_GET_SIZE(buf), at = 0;
    /* (nothing here runs Python code: buf cannot change under us) */
    const unsigned char *b = (const unsigned char *)PyByteArray_AS_STRING(buf);
    for (;;) {
        const unsigned char *z = at < len ? memchr(b + at, 0, (size_t)(len - at)) : NULL;
        if (!z)
            break;
        Py_ssize_t i = z - b, n = i - at;
        const unsigned char *body = b + at;
        at = i + 1;
        if (n == 0)
            continue;
        if (n > (Py_ssize_t)sizeof small) {
            unsigned char *nb = PyMem_Realloc(big, (size_t)n);
            if (!nb) {
                PyErr_NoMemory();
                goto fail;
            }
            raw = big = nb;
        } else
            raw = small;
        const int m = fw_unframe(body, (size_t)n, raw, (size_t)n); /* COBS never lengthens */
        if (m < 0) {
            bad++;
            continue;
        }
        PyObject *msg = PyBytes_FromStringAndSize((const char *)raw, m);
        if (!msg || PyList_Append(out, msg) < 0) {
            Py_XDECREF(msg);
            goto fail;
        }
        Py_DECREF(msg);
    }
    PyMem_Free(big);
    big = NULL;
    /* del buf[:at]; then, no delimiter in sight and too much waiting: resync */
    if (len - at > 4 * max_frame) {
        at = len;
        bad++;
    }
    if (at > 0) {
        memmove(PyByteArray_AS_STRING(buf), PyByteArray_AS_STRING(buf) + at, (size_t)(len - at));
        if (PyByteArray_Resize(buf, len - at) < 0)
            goto fail;
    }
    return Py_BuildValue("(Nl)", out, bad);
fail:
    PyMem_Free(big);
    Py_DECREF(out);
    return NULL;
}

static PyMethodDef methods[] = {
    {"deframe", fl_deframe, METH_VARARGS, "deframe(bytearray, max_frame) -> (messages, bad_frames)"},
    {"gather", fl_gather, METH_VARARGS,
     "gather(fd, other_fds, timeout_ms, count, buf) -> (ready_other_fds, wake_ups, hung_up)"},
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
