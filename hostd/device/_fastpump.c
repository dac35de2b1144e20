/* The host-rendering pump's steady-state cycle, compiled: hostd.device.pump.Pump.step (and the
 * loop of Pump.run) is the reference, hostd/device/fastpump.py the wrapper, tests/test_fastpump.py
 * the proof that both write the same bytes and leave the same state, cycle by cycle.
 *
 * Why: a cycle of the Python reference costs ~190 µs of CPU (a 1 kHz loop: ~19 % of a core);
 * this one costs the kernel's wake-up plus a few µs of arithmetic (docs/benchmarks.md).
 *
 * How it stays equal to the reference. The state is declared once, in
 * hostd/device/cycle_state.toml: each stage (pump and its stats, link and its stats, health,
 * renderer, position, motion, height, output stage) holds its fields in a record, a struct this
 * file reads and writes in place through the buffer protocol (hs_<kind>_t, cycle_state.h,
 * generated at build), the motion window and the unacknowledged messages included. What is not
 * a record (the latest STATUS dict, the weight caches and arrays, the transport's descriptor and buffers)
 * comes positionally from fastpump._parts and goes back through fastpump._put; no attribute is
 * read or written by name. A cycle is done here only while everything is ordinary: a serial
 * port with nothing queued or a hidraw node (mode), STATUS messages only (at most FRESH per
 * poll, no fault flag, counters that move forwards), a motion fit on evenly spaced readings whose
 * least-squares weights are cached, no glitch or re-lock, no open recovery episode, a speed
 * bucket whose weights are cached, no crossfade. Each STATUS is checked before anything is
 * changed; at the first thing that is not ordinary the cycle returns a hand-over, and
 * fastpump._hand does the rest the reference's way (`link._take` for the messages left, then
 * `pump.after_poll()`), so the rare paths (recovery, re-locks, new buckets, stalls) have one
 * implementation: the Python one.
 * The GIL is held throughout, the sleeps included: nothing else in the pump's process runs
 * Python meanwhile (it has no other Python thread), so nothing can change the state held here
 * behind its back; a signal ends the sleep and the run, and its handler runs at once.
 * The arithmetic is the reference's, operation by operation, in IEEE doubles, compiled with
 * -ffp-contract=off; Python's float semantics are spelled out where C differs (floored %, max()
 * and min() that keep the first of equals, round() half to even = rint()).
 *
 *   init(max_gap_us, ..., codes_from_bytes)   the cycle's constants (the protocol's: hostd_proto.h)
 *   step(parts, now_s, mode) -> (sent, hand, writes) | None    one pump.step(); now_s: the host
 *        clock (None: CLOCK_MONOTONIC); None: not ordinary (the reference's cycle)
 *   run(parts, start_s, k, duration_s, budget_s, fds, mode, top_done)
 *        -> (k, why, due_s, hand, c0, writes) | None
 *        Pump.run's iterations (deadline grid start_s + k x period) while they are ordinary, at
 *        most budget_s, waking early for none of them: returns at an iteration's top when the
 *        budget is spent, end_s passed, a descriptor of fds became readable (after the sleep to
 *        its deadline), a stall is due, a signal came, or a cycle needed the reference.
 */
#define PY_SSIZE_T_CLEAN
#include <Python.h>
#include <errno.h>
#include <math.h>
#include <poll.h>
#include <sys/ioctl.h>
#include <stdint.h>
#include <string.h>
#include <time.h>
#include <unistd.h>

#include "../render/render_core.h"
#include "fw_framing.h" /* the firmware's framing (firmware/src/framing.c) and protocol header */

#define STALL_MARGIN_CYCLES 2 /* pump.STALL_MARGIN_CYCLES */
#define REVISION 10 /* fastpump.C_REVISION must equal this */
#define FRESH 32   /* DeviceLink.FRESH */
/* the protocol's constants: hostd_proto.h, generated from protocol.toml (as is protocol.py) */
#define C_RATE HP_SAMPLE_RATE_HZ
#define C_MAX_SAMPLES HP_MAX_SAMPLES
#define MAX_MSGS 64
#define MAX_UNACKED ((long long)(sizeof ((hs_link_t *)0)->_un_seq / sizeof(int64_t)))
#define MAX_WIN 64
#define READ_SIZE 4096   /* SerialTransport.READ_SIZE */
#define MAX_PENDING 4096 /* SerialTransport.MAX_PENDING */
#define REST_BUCKET (-(1LL << 30))
#define MODE_SERIAL 0
#define MODE_HID 1
#define HS_COUNT(...) +1
#define HS_NREC (0 HS_RECORDS(HS_COUNT)) /* the records a cycle holds at most */

/* ------------------------------------------------------------------ constants (init) */
static int C_SMALL_BATCH = 32, C_CUBIC_MIN = 24; /* motion.CUBIC_MIN_READINGS (init) */
static long long C_MAX_GAP_US = 600000000LL;
static PyObject *codes_fn = NULL;   /* int16 bytes -> the codes array the reference renders (init) */


/* ------------------------------------------------------------------ the state */
#define STATUS_FIELD(name, off, size, kind) long long name;
typedef struct { /* a STATUS: its bytes and its fields (protocol.toml's layout, all unsigned) */
    unsigned char b[HP_STATUS_SIZE];
    HP_STATUS_FIELDS(STATUS_FIELD)
} status_t;
_Static_assert(HP_STATUS_SIZE == 26, "STATUS changed shape: take_status's wrap arithmetic is for this one");

typedef struct {
    /* objects: the caches borrowed (the parts outlive a call), the rest new references */
    PyObject *mcache, *wcache, *w; /* motion weight cache, height weight cache, current weights */
    PyObject *overflow;             /* messages of one poll beyond MAX_MSGS (a backlog), or NULL */
    Py_buffer wbuf, sosbuf, zibuf, ringbuf;
    int fd, mode; /* mode: MODE_SERIAL (COBS frames on a byte stream) or MODE_HID (a report per read/write) */
    int clock_live; /* the cycle's clock is CLOCK_MONOTONIC (not a test's now_s): read it again after the read */
    long long empty_reads;
    /* transport */
    unsigned char *dbuf;
    Py_ssize_t dlen, dcap;
    long long bad_frames;
    unsigned char pend[MAX_PENDING + 256];
    Py_ssize_t plen;
    /* the stages' records (hostd/device/cycle_state.toml), read and written in place */
    hs_pump_t *P;
    hs_pump_stats_t *PS;
    hs_link_t *L;
    hs_link_stats_t *LS;
    hs_health_t *H;
    hs_renderer_t *R;
    hs_position_t *Z;
    hs_motion_t *M;
    hs_height_t *E;
    /* link */
    status_t ls; /* the latest STATUS (link.stats.last_status, health._last) */
    int ls_new;  /* it came in this C run: its bytes go back (writes) */
    /* pump */
    PyObject *append; /* pump.sent_codes.append while it records, else None (borrowed) */
    /* motion: the least-squares rows in use */
    long long wkey_n, wkey_dt, wkey_order; /* the motion weights in mw (-1: none) */
    double mw[4][MAX_WIN];
    /* equalizer, output stage */
    Py_ssize_t ns;
    hs_output_t *o; /* the output stage's record (through the buffer protocol) */
    Py_buffer recbuf[HS_NREC];
    int nrec;
} S;

/* ------------------------------------------------------------------ records
 * A stage's state record (hostd/device/cycle_state.toml): the stage object holds its fields in
 * the struct and exposes it through the buffer protocol. NULL with TypeError: not a record. */
#define REC(s, obj, kind) ((hs_##kind##_t *)get_rec(s, obj, sizeof(hs_##kind##_t)))
static void *get_rec(S *s, PyObject *o, Py_ssize_t size) {
    Py_buffer *b = &s->recbuf[s->nrec];
    if (s->nrec >= HS_NREC) {
        PyErr_SetString(PyExc_SystemError, "more records than cycle_state.toml declares");
        return NULL;
    }
    if (PyObject_GetBuffer(o, b, PyBUF_WRITABLE) < 0)
        return NULL;
    s->nrec++;
    if (b->len != size) {
        PyErr_SetString(PyExc_TypeError, "a cycle_state record expected");
        return NULL;
    }
    return b->buf;
}

/* ------------------------------------------------------------------ load, writes */
static void release(S *s) { /* (a buffer not taken has obj NULL: PyBuffer_Release leaves it) */
    PyBuffer_Release(&s->wbuf);
    PyBuffer_Release(&s->sosbuf);
    PyBuffer_Release(&s->zibuf);
    PyBuffer_Release(&s->ringbuf);
    while (s->nrec > 0)
        PyBuffer_Release(&s->recbuf[--s->nrec]);
    Py_CLEAR(s->w);
    Py_CLEAR(s->overflow);
    PyMem_Free(s->dbuf);
    s->dbuf = NULL;
    s->dlen = s->dcap = 0;
}

static int set_weights(S *s, PyObject *w) { /* the height weights array in force (new ref taken) */
    Py_buffer b;
    if (PyObject_GetBuffer(w, &b, PyBUF_C_CONTIGUOUS | PyBUF_FORMAT) < 0)
        return -1;
    if (b.itemsize != 8 || !b.format || strcmp(b.format, "d") || b.ndim != 1) {
        PyBuffer_Release(&b);
        return 0; /* not float64: not ordinary */
    }
    PyBuffer_Release(&s->wbuf);
    s->wbuf = b;
    Py_INCREF(w);
    Py_XSETREF(s->w, w);
    return 1;
}

/* The parts of a cycle, in the order hostd/device/fastpump.py's _parts gives them: the stages
 * (each read as its record), then the objects that are not records (arrays, caches, the window,
 * the transport's descriptor and buffers). Nothing is looked up by name. */
enum {
    P_PUMP, P_PSTATS, P_LINK, P_LSTATS, P_HEALTH, P_RENDERER, P_POSITION, P_MOTION, P_HEIGHT, P_OUT,
    P_STEP_US, P_LAST_STATUS, P_MCACHE, P_W, P_WCACHE, P_SOS, P_ZI,
    P_APPEND, P_FD, P_EMPTY_READS, P_DBUF, P_BAD_FRAMES, P_N
};

/* 1: loaded and ordinary; 0: not ordinary (the reference does the cycle); -1: error */
static int load(S *s, PyObject *parts, int mode) {
    memset(s, 0, sizeof *s);
    s->mode = mode;
    s->wkey_n = -1;
    int r;
#define TRY(x)                                                                                            \
    do {                                                                                                  \
        if ((x) < 0)                                                                                      \
            goto fail;                                                                                    \
    } while (0)
#define NO(cond)                                                                                          \
    do {                                                                                                  \
        if (cond)                                                                                         \
            goto no;                                                                                      \
    } while (0)
#define PART(i) PyTuple_GET_ITEM(parts, i)
    if (!PyTuple_Check(parts) || PyTuple_GET_SIZE(parts) != P_N)
        return 0; /* (None: fastpump found the cycle not ordinary) */
    if (!(s->P = REC(s, PART(P_PUMP), pump)) || !(s->PS = REC(s, PART(P_PSTATS), pump_stats)) ||
        !(s->L = REC(s, PART(P_LINK), link)) || !(s->LS = REC(s, PART(P_LSTATS), link_stats)) ||
        !(s->H = REC(s, PART(P_HEALTH), health)) || !(s->R = REC(s, PART(P_RENDERER), renderer)) ||
        !(s->Z = REC(s, PART(P_POSITION), position)) || !(s->M = REC(s, PART(P_MOTION), motion)) ||
        !(s->E = REC(s, PART(P_HEIGHT), height)) || !(s->o = REC(s, PART(P_OUT), output)))
        goto fail;
    /* pump */
    NO(s->P->_guard_seq_set || s->P->_flags_seen != 0 || !s->P->_last_samples_played_set);
    PyObject *o;
    TRY(PyObject_GetBuffer(PART(P_STEP_US), &s->ringbuf, PyBUF_C_CONTIGUOUS | PyBUF_WRITABLE | PyBUF_FORMAT));
    NO(s->ringbuf.itemsize != 8 || strcmp(s->ringbuf.format, "d") || s->ringbuf.len < 8);
    /* link */
    NO(s->L->_fill_from_seq_set || !s->L->_last_us_set || !s->L->_offset_s_set);
    NO(s->L->_un_n < 0 || s->L->_un_n > MAX_UNACKED);
    /* the latest STATUS's fields (fastpump._parts: the link's and the health's, one dict) */
    o = PART(P_LAST_STATUS); /* its fields, in protocol.toml's order */
    NO(!PyTuple_Check(o) || PyTuple_GET_SIZE(o) != 0 HP_STATUS_FIELDS(HS_COUNT));
    Py_ssize_t fi = 0;
#define STATUS_GET(name, off, size, kind) s->ls.name = PyLong_AsLongLong(PyTuple_GET_ITEM(o, fi++));
    HP_STATUS_FIELDS(STATUS_GET)
    if (PyErr_Occurred())
        goto fail;
    /* transport */
    {
        long long fd = PyLong_AsLongLong(PART(P_FD));
        if (fd == -1 && PyErr_Occurred())
            goto fail;
        NO(fd < 0);
        s->fd = (int)fd;
    }
    if (mode == MODE_HID) { /* HidrawTransport: its count of empty reads */
        s->empty_reads = PyLong_AsLongLong(PART(P_EMPTY_READS));
    } else { /* SerialTransport, with nothing queued either way (fastpump checks): the deframer's */
        s->bad_frames = PyLong_AsLongLong(PART(P_BAD_FRAMES));
        o = PART(P_DBUF);
        NO(!PyByteArray_Check(o));
        s->dlen = PyByteArray_GET_SIZE(o);
        s->dcap = s->dlen + 2 * READ_SIZE;
        s->dbuf = PyMem_Malloc((size_t)s->dcap);
        if (!s->dbuf) {
            PyErr_NoMemory();
            goto fail;
        }
        memcpy(s->dbuf, PyByteArray_AS_STRING(o), (size_t)s->dlen);
    }
    if (PyErr_Occurred())
        goto fail;
    /* renderer, position, motion */
    NO(s->R->_xfade_left != 0 || !s->Z->_last_set);
    NO(s->Z->_total > (1LL << 52) || s->Z->_total < -(1LL << 52));
    NO(s->M->_window < 2 || s->M->_window > MAX_WIN || s->M->_order < 0 || s->M->_order > 3);
    NO(s->M->_n < 1 || s->M->_n > s->M->_window);
    s->append = PART(P_APPEND); /* (borrowed: the parts outlive the call) */
    s->mcache = PART(P_MCACHE);
    NO(!PyDict_Check(s->mcache));
    /* height: the series on float64 weights (checked by the wrapper: method, dtype) */
    NO(s->E->n <= 0);
    s->wcache = PART(P_WCACHE);
    NO(!PyDict_Check(s->wcache));
    r = set_weights(s, PART(P_W));
    TRY(r);
    NO(!r);
    /* equalizer and output stage (fastrender.tail's conditions) */
    o = PART(P_SOS);
    if (o != Py_None) {
        TRY(PyObject_GetBuffer(o, &s->sosbuf, PyBUF_C_CONTIGUOUS | PyBUF_FORMAT));
        NO(s->sosbuf.itemsize != 8 || strcmp(s->sosbuf.format, "d") || s->sosbuf.len % 48);
        s->ns = s->sosbuf.len / 48;
        o = PART(P_ZI);
        NO(o == Py_None);
        if (PyObject_GetBuffer(o, &s->zibuf, PyBUF_C_CONTIGUOUS | PyBUF_WRITABLE | PyBUF_FORMAT) < 0) {
            PyErr_Clear(); /* not writable or not contiguous: the reference copes */
            goto no;
        }
        NO(s->zibuf.itemsize != 8 || strcmp(s->zibuf.format, "d") || s->zibuf.len != s->ns * 16);
    } else
        s->ns = 0;
    NO(s->o->_limit_code < 0 || s->o->_limit_code > 32767);
    return 1;
no:
    if (PyErr_Occurred()) {
        if (!PyErr_ExceptionMatches(PyExc_TypeError) && !PyErr_ExceptionMatches(PyExc_OverflowError))
            goto fail;
        PyErr_Clear();
    }
    release(s);
    return 0;
fail:
    if (PyErr_ExceptionMatches(PyExc_TypeError) || PyErr_ExceptionMatches(PyExc_OverflowError)) {
        PyErr_Clear(); /* a value of an unusual type or size: not ordinary */
        release(s);
        return 0;
    }
    release(s);
    return -1;
#undef PART
}

/* What the cycle changed that is not a record, for fastpump.py to put back (its _put): the
 * latest STATUS's bytes (None: none came), the height weights in force, the transport's count
 * or buffers. NULL on error. Releases s. */
static PyObject *writes(S *s) {
    const char *st = s->ls_new ? (const char *)s->ls.b : NULL; /* (y#: NULL gives None) */
    const Py_ssize_t n = HP_STATUS_SIZE;
    PyObject *ret = PyErr_Occurred()        ? NULL
                    : s->mode == MODE_HID ? Py_BuildValue("(y#OL)", st, n, s->w, s->empty_reads)
                                          : Py_BuildValue("(y#OLy#y#)", st, n, s->w, s->bad_frames, (const char *)s->dbuf,
                                                          s->dlen, (const char *)s->pend, s->plen);
    release(s);
    return ret;
}

/* ------------------------------------------------------------------ serial framing (fw_framing.h) */

typedef struct {
    unsigned char b[2 * READ_SIZE]; /* a frame body is at most 4 x MAX_FRAME + one read long */
    Py_ssize_t n;
} msg_t;
static msg_t g_msgs[MAX_MSGS]; /* one poll's messages (the GIL is held throughout) */
static int16_t g_codes[RC_MAX_N]; /* a batch whose sending the reference finishes */

/* keep a message of one poll: in msgs while they hold, then in s->overflow (a backlog) */
static int keep_msg(S *s, msg_t *msgs, int *nm, const unsigned char *b, Py_ssize_t n) {
    if (*nm < MAX_MSGS) {
        if (b != msgs[*nm].b)
            memcpy(msgs[*nm].b, b, (size_t)n);
        msgs[*nm].n = n;
        (*nm)++;
        return 0;
    }
    if (!s->overflow && !(s->overflow = PyList_New(0)))
        return -1;
    PyObject *m = PyBytes_FromStringAndSize((const char *)b, n);
    int r = m ? PyList_Append(s->overflow, m) : -1;
    Py_XDECREF(m);
    return r;
}

/* Deframer.feed: append data, cut frames at zero bytes, keep what is valid */
static int deframe(S *s, const unsigned char *data, Py_ssize_t n, msg_t *msgs, int *nm) {
    if (s->dlen + n > s->dcap) {
        Py_ssize_t cap = (s->dlen + n) * 2;
        unsigned char *nb = PyMem_Realloc(s->dbuf, (size_t)cap);
        if (!nb) {
            PyErr_NoMemory();
            return -1;
        }
        s->dbuf = nb;
        s->dcap = cap;
    }
    memcpy(s->dbuf + s->dlen, data, (size_t)n);
    s->dlen += n;
    Py_ssize_t at = 0;
    static unsigned char spare[sizeof g_msgs[0].b];
    while (1) {
        unsigned char *z = memchr(s->dbuf + at, 0, (size_t)(s->dlen - at));
        if (!z) {
            memmove(s->dbuf, s->dbuf + at, (size_t)(s->dlen - at));
            s->dlen -= at;
            if (s->dlen > 4 * FW_FRAME_MAX) { /* no delimiter in sight: resync */
                s->dlen = 0;
                s->bad_frames++;
            }
            return 0;
        }
        Py_ssize_t i = z - s->dbuf, len = i - at;
        const unsigned char *body = s->dbuf + at;
        at = i + 1;
        if (len == 0)
            continue;
        unsigned char *raw = *nm < MAX_MSGS ? msgs[*nm].b : spare;
        const int m = fw_unframe(body, (size_t)len, raw, sizeof spare); /* COBS, length, CRC */
        if (m < 0)
            s->bad_frames++;
        else if (keep_msg(s, msgs, nm, raw, m) < 0)
            return -1;
    }
}

/* ------------------------------------------------------------------ python float semantics */
static double py_mod(double v, double w) { /* Python's float %: floored */
    double m = fmod(v, w);
    if (m != 0.0) {
        if ((w < 0) != (m < 0))
            m += w;
    } else
        m = copysign(0.0, w);
    return m;
}
static inline double py_max(double a, double b) { return b > a ? b : a; } /* max(a, b) */
static inline double py_min(double a, double b) { return b < a ? b : a; } /* min(a, b) */
static inline long long u32(long long v) { return v & 0xFFFFFFFFLL; }
static inline uint32_t le(const unsigned char *p, int n) { /* an unsigned little-endian field */
    uint32_t v = 0;
    while (n-- > 0)
        v = (v << 8) | p[n];
    return v;
}

static double clock_s(clockid_t clock) {
    struct timespec ts;
    clock_gettime(clock, &ts);
    return (double)ts.tv_sec + (double)ts.tv_nsec * 1e-9;
}
#define mono_now() clock_s(CLOCK_MONOTONIC)
#define thread_now() clock_s(CLOCK_THREAD_CPUTIME_ID)

/* ------------------------------------------------------------------ why cycles were handed over */
enum {
    H_LOAD, H_BACKLOG, H_MESSAGE, H_FAULT, H_RESET, H_GAP, H_GLITCH, H_IRREGULAR, H_FIT_UNCACHED, H_IMPLAUSIBLE,
    H_SUPERVISE, H_DECAY, H_BIG_BATCH, H_NEW_BUCKET, H_READ, H_WRITE, H_N
};
static const char *H_NAMES[H_N] = {"not_ordinary", "backlog", "message", "fault", "reset", "gap", "glitch",
                                   "irregular", "fit_uncached", "implausible", "supervise", "decay",
                                   "big_batch", "new_bucket", "read_error", "write_error"};
static long long hand_count[H_N];
static long long compiled_count; /* cycles done here from start to end */
#define HAND(why, code) (hand_count[why]++, (code))

/* ------------------------------------------------------------------ motion (MotionEstimator) */
static double predict_one(const S *s, double t) {
    const double m = s->M->_max_predict_s;
    const double dt = py_min(py_max(t - s->M->_t_ref, -m), m);
    return s->M->_c0 + dt * (s->M->_c1 + dt * (s->M->_c2 + dt * s->M->_c3));
}

/* the cached least-squares rows for (n, dt_us, order): 1 found, 0 not cached, -1 error */
static int motion_weights(S *s, long long n, long long dt_us, long long order) {
    if (s->wkey_n == n && s->wkey_dt == dt_us && s->wkey_order == order)
        return 1;
    PyObject *key = Py_BuildValue("(LLL)", n, dt_us, order);
    if (!key)
        return -1;
    PyObject *w = PyDict_GetItemWithError(s->mcache, key);
    Py_DECREF(key);
    if (!w)
        return PyErr_Occurred() ? -1 : 0;
    if (!PyTuple_Check(w) || PyTuple_GET_SIZE(w) < order + 1)
        return 0;
    for (long long j = 0; j <= order; j++) {
        PyObject *row = PyTuple_GET_ITEM(w, j);
        if (!PyList_Check(row) || PyList_GET_SIZE(row) != n)
            return 0;
        for (long long i = 0; i < n; i++) {
            PyObject *f = PyList_GET_ITEM(row, i);
            if (!PyFloat_Check(f))
                return 0;
            s->mw[j][i] = PyFloat_AS_DOUBLE(f);
        }
    }
    s->wkey_n = n;
    s->wkey_dt = dt_us;
    s->wkey_order = order;
    return 1;
}

static double dot(const double *w, const double *x, int n) { /* motion._dot */
    double acc = 0.0;
    for (int i = 0; i < n; i++)
        acc += w[i] * x[i];
    return acc;
}

/* ------------------------------------------------------------------ one STATUS */
/* 1 taken; 0 not ordinary (nothing changed); -1 error */
static int take_status(S *s, const msg_t *m, double now) {
    if (m->n < HP_STATUS_SIZE || m->b[0] != HP_ID_STATUS)
        return HAND(H_MESSAGE, 0);
    for (Py_ssize_t i = HP_STATUS_SIZE; i < m->n; i++)
        if (m->b[i] != 0)
            return HAND(H_MESSAGE, 0); /* not padding: the reference says what it is */
    status_t f;
    memcpy(f.b, m->b, HP_STATUS_SIZE);
#define STATUS_READ(name, off, size, kind) f.name = (long long)le(m->b + off, size);
    HP_STATUS_FIELDS(STATUS_READ)
    if (f.fault_flags != 0)
        return HAND(H_FAULT, 0); /* a fault: the reference records it and supervises */
    /* health.update's checks */
    const long long dt_us = u32(f.device_time_us - s->ls.device_time_us);
    const long long d_played = u32(f.samples_played - s->ls.samples_played);
    const long long d_under = (f.underruns - s->ls.underruns) & 0xFFFF;
    if (dt_us > C_MAX_GAP_US || d_played > dt_us * C_RATE / 1000000 + 3)
        return HAND(H_RESET, 0); /* a reset */
    /* link._status: the device's clock */
    long long time_hi = s->L->_time_hi;
    if (f.device_time_us < s->L->_last_us && s->L->_last_us - f.device_time_us > (1LL << 31))
        time_hi += 1LL << 32;
    const double device_time_s = (double)(time_hi + f.device_time_us) * 1e-6;
    /* position.update */
    const long long raw = f.encoder_count;
    long long d = u32(raw - s->Z->_last);
    if (d >= (1LL << 31))
        d -= 1LL << 32;
    const long long total = s->Z->_total + d;
    if (total > (1LL << 52) || total < -(1LL << 52))
        return HAND(H_RESET, 0);
    const double x_mm = (double)total * s->Z->um_per_count * 1e-3;
    /* motion.update, on a copy of its record (committed below, once nothing is handed over) */
    const double t_s = device_time_s;
    if (!isfinite(t_s) || !isfinite(x_mm))
        return HAND(H_GLITCH, 0);
    hs_motion_t mo;
    const int stale = t_s <= s->M->_tw[s->M->_n - 1];
    if (!stale) {
        mo = *s->M;
        double *mt = mo._tw, *mx = mo._xw;
        if (t_s - mt[mo._n - 1] > mo._max_gap_s)
            return HAND(H_GAP, 0); /* a gap: the fit restarts (reference) */
        if (mo._n >= mo._order + 2) {
            const double pred = predict_one(s, t_s);
            if (fabs(x_mm - pred) * 1000.0 > mo._glitch_um)
                return HAND(H_GLITCH, 0); /* a glitch or a real move (reference) */
        }
        mo._since_restart += 1;
        const long long dtu = (long long)rint((t_s - mt[mo._n - 1]) * 1e6); /* round() */
        mo._uniform = dtu == mo._dt_us ? mo._uniform + 1 : 1;
        mo._dt_us = dtu;
        if (mo._n == mo._window) {
            memmove(mt, mt + 1, sizeof(double) * (size_t)(mo._n - 1));
            memmove(mx, mx + 1, sizeof(double) * (size_t)(mo._n - 1));
            mo._n--;
        }
        mt[mo._n] = t_s;
        mx[mo._n] = x_mm;
        const int mn = (int)++mo._n;
        /* _fit */
        mo._t_ref = mt[mn - 1];
        long long order = mo._order < mn - 1 ? mo._order : mn - 1;
        if (mo._since_restart < 2 * (mo._order + 1) && order > 1)
            order = 1;
        if (order == 3 && mn < C_CUBIC_MIN)
            order = 2; /* a short window: motion.CUBIC_MIN_READINGS */
        if (order == 0) {
            mo._c0 = mx[mn - 1];
            mo._c1 = mo._c2 = mo._c3 = 0.0;
            mo._rest_x_set = 0;
        } else {
            if (mo._uniform < mn - 1)
                return HAND(H_IRREGULAR, 0); /* irregular spacing: solved afresh (reference) */
            int r = motion_weights(s, mn, mo._dt_us, order);
            if (r <= 0)
                return r < 0 ? -1 : HAND(H_FIT_UNCACHED, 0);
            mo._c0 = dot(s->mw[0], mx, mn);
            mo._c1 = dot(s->mw[1], mx, mn) * 1e3;
            mo._c2 = order >= 2 ? dot(s->mw[2], mx, mn) * 1e6 : 0.0;
            mo._c3 = order == 3 ? dot(s->mw[3], mx, mn) * 1e9 : 0.0;
            /* at rest: slow, and the readings within what that speed covers over the window
             * (max(x) - min(x) as Python's max and min: the first of equals) */
            double lo = mx[0], hi = mx[0];
            for (int i = 1; i < mn; i++) {
                if (mx[i] > hi)
                    hi = mx[i];
                if (mx[i] < lo)
                    lo = mx[i];
            }
            if (fabs(mo._c1) < mo._rest_speed_mm_s &&
                hi - lo <= mo._rest_speed_mm_s * (mt[mn - 1] - mt[0]) + mo._rest_hold_um * 1e-3) {
                double acc = 0.0;
                for (int i = 0; i < mn; i++)
                    acc += 1.0 * mx[i];
                const double mean = acc / (double)mn;
                if (!mo._rest_x_set || fabs(mean - mo._rest_x) * 1000.0 > mo._rest_hold_um) {
                    mo._rest_x = mean;
                    mo._rest_x_set = 1;
                }
                mo._c0 = mo._rest_x;
                mo._c1 = mo._c2 = mo._c3 = 0.0;
            } else
                mo._rest_x_set = 0;
        }
        if (fabs(mo._c1) > mo._max_speed_mm_s)
            return HAND(H_IMPLAUSIBLE, 0); /* implausible (reference) */
    }
    /* ---- commit. link._status */
    s->L->_time_hi = time_hi;
    s->L->_last_us = f.device_time_us;
    s->L->device_time_s = device_time_s;
    s->L->status_host_time = now;
    const double off = device_time_s - now;
    if (off < s->L->_offset_s - 30.0)
        s->L->_offset_s = off;
    else {
        const double decayed = s->L->_offset_s - 1e-3 * (now - s->L->_offset_host_t);
        s->L->_offset_s = py_max(off, decayed);
    }
    s->L->_offset_host_t = now;
    int drop = 0;
    while (drop < s->L->_un_n && ((f.last_seq - s->L->_un_seq[drop]) & 0xFFFF) < 0x8000)
        drop++;
    if (drop) { /* link._drop_unacked */
        memmove(s->L->_un_seq, s->L->_un_seq + drop, sizeof(int64_t) * (size_t)(s->L->_un_n - drop));
        memmove(s->L->_un_cnt, s->L->_un_cnt + drop, sizeof(int64_t) * (size_t)(s->L->_un_n - drop));
        s->L->_un_n -= drop;
    }
    s->LS->statuses++;
    /* health.update */
    s->H->state = f.state;
    s->H->_time_s += (double)dt_us * 1e-6;
    s->H->samples_played += d_played;
    s->H->underruns += d_under;
    if (s->H->_sel_active && !s->H->_sel_device) {
        if (!s->H->_sel_started && f.state == HP_STATE_RUNNING)
            s->H->_sel_started = 1;
        if (s->H->_sel_started) {
            s->H->_sel_due += (double)dt_us * 1e-6 * (double)C_RATE;
            s->H->_sel_played += d_played;
        }
    }
    /* pump._on_status */
    s->P->_flags_seen |= f.fault_flags;
    if (f.samples_played != s->P->_last_samples_played && f.state == HP_STATE_RUNNING) {
        s->P->_last_played_dev_s = device_time_s;
        s->P->_last_played_dev_s_set = 1;
    }
    if (s->P->_fill > s->P->_base_fill && f.state == HP_STATE_RUNNING && f.buffer_fill < s->P->_low_fill)
        s->P->_low_fill = f.buffer_fill; /* the evidence a raised target comes down on (no episode here) */
    s->P->_last_samples_played = f.samples_played;
    s->ls = f;
    s->ls_new = 1;
    /* renderer.on_encoder */
    s->Z->_last = raw;
    s->Z->_total = total;
    if (!stale)
        *s->M = mo;
    return 1;
}

/* ------------------------------------------------------------------ the cycle */
enum { DONE = 0, HAND_MSGS = 1, HAND_AFTER = 2, HAND_READERR = 3, HAND_SEND = 4 };

static double device_now(const S *s, double now) { return py_max(s->L->device_time_s, now + s->L->_offset_s); }

/* One SAMPLES message out, as link._send does it: 0 sent (serial: what the port did not take
 * waits in the pending bytes, as SerialTransport.send_raw keeps it), 1 not sent and nothing
 * changed (a write error; on HID also a busy or short write): the reference sends it. */
static int send_msg(S *s, const unsigned char *msg, Py_ssize_t ml) {
    if (s->mode == MODE_HID) { /* HidrawTransport.send: report id 0, the message padded */
        unsigned char rep[1 + HP_REPORT_SIZE];
        if (ml > HP_REPORT_SIZE)
            return 1;
        rep[0] = 0;
        memcpy(rep + 1, msg, (size_t)ml);
        memset(rep + 1 + ml, 0, (size_t)(HP_REPORT_SIZE - ml));
        ssize_t w = write(s->fd, rep, sizeof rep);
        return w == (ssize_t)sizeof rep ? 0 : 1;
    }
    unsigned char fr[2 * FW_FRAME_MAX], buf[MAX_PENDING + 256];
    const Py_ssize_t n = (Py_ssize_t)fw_frame(msg, (size_t)ml, fr, sizeof fr);
    if (n == 0)
        return 1;
    Py_ssize_t len = s->plen;
    memcpy(buf, s->pend, (size_t)len);
    memcpy(buf + len, fr, (size_t)n);
    len += n;
    ssize_t w = write(s->fd, buf, (size_t)len);
    if (w < 0) {
        if (errno != EAGAIN && errno != EWOULDBLOCK)
            return 1; /* (the pending bytes stay as they were) */
        w = 0;
    }
    if (len - w > MAX_PENDING)
        return 1; /* (cannot happen: a C cycle starts with nothing pending and sends two messages) */
    memcpy(s->pend, buf + w, (size_t)(len - w));
    s->plen = len - w;
    return 0;
}

/* One Pump.step, ordinary parts here. Returns DONE (*sent set), HAND_MSGS (messages from
 * *first on, then after_poll, are the reference's), HAND_AFTER (after_poll is), HAND_IOERR,
 * or -1 (error). */
static int cycle(S *s, double now, msg_t *msgs, int *nmsgs, int *first, int *more, long long *sent,
                 long long *ncodes) {
    *sent = 0;
    *nmsgs = 0;
    *first = 0;
    *more = 0;
    /* link.poll: transport.drain */
    unsigned char rb[READ_SIZE];
    int nm = 0;
    if (s->mode == MODE_HID) { /* Transport.drain: HidrawTransport.recv(0.0) until None */
        int empties = 0;
        while (1) {
            ssize_t r = read(s->fd, rb, READ_SIZE);
            if (r > 0) {
                if (keep_msg(s, msgs, &nm, rb, r) < 0)
                    return -1;
                empties = 0;
                continue;
            }
            if (r == 0) { /* a zero-length packet is not a report */
                s->empty_reads++;
                empties++;
            } else if (errno == EINTR)
                continue;
            else if (errno != EAGAIN && errno != EWOULDBLOCK)
                return HAND(H_READ, HAND_READERR);
            struct pollfd hp = {s->fd, POLLIN, 0};
            const int pr_ = poll(&hp, 1, 0);
            if (pr_ > 0 && (hp.revents & (POLLHUP | POLLERR | POLLNVAL)))
                return HAND(H_READ, HAND_READERR);
            if (pr_ <= 0 || empties > 64)
                break;
        }
    } else { /* SerialTransport.drain: only what the line discipline holds (TIOCINQ), never a read
              * of an empty tty (it waits for the kernel's buffer work: seriallink's header) */
        while (1) {
            int avail = 0;
            if (ioctl(s->fd, TIOCINQ, &avail) < 0) {
                if (errno == EINTR)
                    continue;
                return HAND(H_READ, HAND_READERR); /* hung up (EIO): the reference asks again and says so */
            }
            if (avail <= 0)
                break;
            ssize_t r = read(s->fd, rb, avail < READ_SIZE ? (size_t)avail : READ_SIZE);
            if (r < 0) {
                if (errno == EAGAIN || errno == EWOULDBLOCK)
                    break;
                if (errno == EINTR)
                    continue;
                return HAND(H_READ, HAND_READERR); /* the reference reads again and says what happened */
            }
            if (r == 0) /* bytes were there and the read ended: the other end hung up */
                return HAND(H_READ, HAND_READERR);
            if (deframe(s, rb, r, msgs, &nm) < 0)
                return -1;
            if (r < READ_SIZE)
                break;
        }
    }
    /* The reference's clock reads (link._status, fill_estimate, _decay: transport.now()) all
     * come after its read: a STATUS is stamped with a time at or after its arrival, so the
     * device-clock offset (the largest device time - arrival) stays a lower bound. The cycle's
     * start is not: a process held up between its wake-up and the read (measured: 10-30 ms on
     * a loaded machine) stamped the reports that arrived meanwhile early and raised the offset
     * by that much for seconds (it decays at 1 ms/s): device_now_s() ran ahead of the device,
     * the fill estimate fell short and the buffer held that much more (latency), stale()
     * misjudged. */
    if (s->clock_live)
        now = mono_now();
    *more = s->overflow != NULL;
    if (nm > FRESH || *more) { /* a backlog (the host stalled): stale statuses are the reference's */
        *nmsgs = nm;
        *first = 0;
        return HAND(H_BACKLOG, HAND_MSGS);
    }
    for (int i = 0; i < nm; i++) {
        int r = take_status(s, &msgs[i], now);
        if (r < 0)
            return -1;
        if (r == 0) {
            *nmsgs = nm;
            *first = i;
            return HAND_MSGS;
        }
    }
    /* after_poll: _supervise (ordinary: nothing to act on) */
    if (s->P->_flags_seen != 0 || s->H->underruns != s->P->_under_seen || s->ls.state != HP_STATE_RUNNING)
        return HAND(H_SUPERVISE, HAND_AFTER);
    /* _decay: at base, the quiet period starts now (committed below); a raised target after its
     * quiet period comes down by the reference's rule (Pump._decay), handed over when it is due */
    if (s->P->_fill > s->P->_base_fill && now - s->P->_last_decay >= s->P->_quiet_s)
        return HAND(H_DECAY, HAND_AFTER);
    /* fill_estimate, wanted */
    long long in_flight = 0;
    for (int i = 0; i < s->L->_un_n; i++)
        in_flight += s->L->_un_cnt[i];
    double dfill = (double)s->ls.buffer_fill;
    if (s->ls.state == HP_STATE_RUNNING)
        dfill -= (device_now(s, now) - s->L->device_time_s) * (double)C_RATE;
    dfill = py_max(0.0, dfill);
    const double fill = dfill + (double)in_flight;
    long long n = (long long)rint((double)s->L->target_fill - fill);
    if (n > 2 * C_MAX_SAMPLES)
        n = 2 * C_MAX_SAMPLES;
    if (n < 0)
        n = 0;
    double theta[RC_MAX_N], h[RC_MAX_N];
    int16_t codes[RC_MAX_N];
    int new_w = 0;
    if (n > 0) {
        if (n > C_SMALL_BATCH || s->L->_un_n + (n + C_MAX_SAMPLES - 1) / C_MAX_SAMPLES > MAX_UNACKED)
            return HAND(H_BIG_BATCH, HAND_AFTER); /* the reference's numpy path; or more in flight than held here */
        /* next_play_time_s */
        const double queued = s->L->device_time_s + (double)(s->ls.buffer_fill + in_flight + 1) / (double)C_RATE;
        const double t0 = py_max(queued, device_now(s, now) + (double)(in_flight + 1) / (double)C_RATE);
        /* plan: predict; heights: phase, weights of the speed's bucket, the series */
        const double m = s->M->_max_predict_s;
        /* Renderer.plan: the speed at the batch's middle instant (motion.velocity_at) */
        const double t_first = (t0 + 0.0 / (double)C_RATE) + s->R->latency_s;
        const double t_last = (t0 + (double)(n - 1) / (double)C_RATE) + s->R->latency_s;
        const double dtv = py_min(py_max(0.5 * (t_first + t_last) - s->M->_t_ref, -m), m);
        const double v = s->M->_c1 + dtv * (2.0 * s->M->_c2 + dtv * (3.0 * s->M->_c3));
        long long b;
        const double sp = fabs(v);
        if (sp < 1e-9 || sp <= s->E->_v_full_mm_s) /* HeightEvaluator._bucket: every gain 1 up to v_full */
            b = REST_BUCKET;
        else {
            const double q = floor(log(sp) / log1p(s->E->_speed_bucket));
            if (!(q > -4e18 && q < 4e18))
                return HAND(H_NEW_BUCKET, HAND_AFTER);
            b = (long long)q;
        }
        if (!s->E->_w_bucket_set || b != s->E->_w_bucket) {
            PyObject *key = PyLong_FromLongLong(b);
            if (!key)
                return -1;
            PyObject *w = PyDict_GetItemWithError(s->wcache, key);
            Py_DECREF(key);
            if (!w)
                return PyErr_Occurred() ? -1 : HAND(H_NEW_BUCKET, HAND_AFTER); /* its gains (reference) */
            int r = set_weights(s, w);
            if (r <= 0)
                return r < 0 ? -1 : HAND(H_NEW_BUCKET, HAND_AFTER);
            new_w = 1;
        }
        const double two_l = 2.0 * s->E->length_mm, dx = s->E->length_mm / (double)s->E->n, kph = M_PI / (double)s->E->n;
        for (long long i = 0; i < n; i++) {
            const double tp = t0 + (double)i / (double)C_RATE;
            const double t = tp + s->R->latency_s;
            const double dt = py_min(py_max(t - s->M->_t_ref, -m), m);
            const double x = s->M->_c0 + dt * (s->M->_c1 + dt * (s->M->_c2 + dt * s->M->_c3));
            theta[i] = (py_mod(x, two_l) / dx + 0.5) * kph;
        }
        rc_clenshaw((const double *)s->wbuf.buf, s->wbuf.len / 8, theta, n, h, 1);
        if (new_w) {
            s->E->_w_bucket = b;
            s->E->_w_bucket_set = 1;
        }
    }
    /* ---- commit the after-poll part */
    s->P->_flags_seen = 0;
    s->P->_under_seen = s->H->underruns;
    if (s->P->_fill <= s->P->_base_fill)
        s->P->_last_decay = now;
    if (n == 0)
        return DONE;
    if (fill < (double)s->R->_samples_per_batch)
        s->PS->late_batches++;
    rc_tail(s->sosbuf.obj ? (const double *)s->sosbuf.buf : NULL, s->ns, s->zibuf.obj ? (double *)s->zibuf.buf : NULL, h,
            n, codes, s->o);
    /* send_samples */
    long long done = 0;
    for (long long i = 0; i < n; i += C_MAX_SAMPLES) {
        const long long cnt = n - i < C_MAX_SAMPLES ? n - i : C_MAX_SAMPLES;
        const long long seq = (s->L->_seq + 1) & 0xFFFF;
        unsigned char msg[8 + 2 * 64];
        msg[0] = (unsigned char)HP_ID_SAMPLES;
        msg[1] = 0;
        msg[2] = (unsigned char)(seq & 0xFF);
        msg[3] = (unsigned char)(seq >> 8);
        msg[4] = (unsigned char)cnt;
        for (long long j = 0; j < cnt; j++) {
            const uint16_t c = (uint16_t)codes[i + j];
            msg[5 + 2 * j] = (unsigned char)(c & 0xFF);
            msg[6 + 2 * j] = (unsigned char)(c >> 8);
        }
        if (send_msg(s, msg, 5 + 2 * cnt)) {
            memcpy(g_codes, codes, sizeof(int16_t) * (size_t)n);
            *ncodes = n;
            *sent = done;
            return HAND(H_WRITE, HAND_SEND); /* the reference sends from this message on */
        }
        s->LS->messages_sent++;
        s->L->_seq = seq;
        s->L->_un_seq[s->L->_un_n] = seq;
        s->L->_un_cnt[s->L->_un_n] = cnt;
        s->L->_un_n++;
        s->LS->samples_sent += cnt;
        done += cnt;
    }
    if (s->append != Py_None) { /* Pump._send_codes: pump.sent_codes.append(codes[:sent]) when recording */
        PyObject *raw = PyBytes_FromStringAndSize((const char *)codes, (Py_ssize_t)(done * 2));
        PyObject *arr = raw ? PyObject_CallOneArg(codes_fn, raw) : NULL;
        Py_XDECREF(raw);
        PyObject *x = arr ? PyObject_CallOneArg(s->append, arr) : NULL;
        Py_XDECREF(arr);
        if (!x)
            return -1;
        Py_DECREF(x);
    }
    s->PS->samples += done;
    /* Pump._motion_stats */
    s->PS->relocks = s->P->_relocks_base + s->M->relocks;
    s->PS->implausible_speed = s->P->_implausible_base + s->M->implausible;
    *sent = done;
    return DONE;
}

/* ------------------------------------------------------------------ hand-over, step, run */

/* A cycle: DONE here (*sent: the samples sent), or handed over: the state is in the records (and,
 * from writes(), in what fastpump.py puts back) and *hand = (code, arg, extra) says where the
 * reference takes the cycle on (fastpump._hand): HAND_MSGS (link._take of extra's messages from
 * arg on, then after_poll), HAND_AFTER (after_poll), HAND_SEND (Pump._send_codes(extra, arg)),
 * HAND_READERR (the reference's cycle from the top). -1: error. */
static int do_cycle(S *s, double now, long long *sent, PyObject **hand) {
    msg_t *msgs = g_msgs;
    int nm, first, more;
    long long ncodes = 0;
    *hand = NULL;
    int r = cycle(s, now, msgs, &nm, &first, &more, sent, &ncodes);
    if (r == DONE) {
        compiled_count++;
        return DONE;
    }
    if (r < 0)
        return -1;
    PyObject *extra = NULL;
    long long arg = 0;
    if (r == HAND_MSGS) { /* link.poll's messages (then the rest of a backlog) */
        arg = first;
        extra = PyList_New(0);
        for (int i = 0; extra && i < nm; i++) {
            PyObject *m = PyBytes_FromStringAndSize((const char *)msgs[i].b, msgs[i].n);
            if (!m || PyList_Append(extra, m) < 0)
                Py_CLEAR(extra);
            Py_XDECREF(m);
        }
        if (extra && more && PyList_SetSlice(extra, nm, nm, s->overflow) < 0)
            Py_CLEAR(extra);
    } else if (r == HAND_SEND) { /* the batch, of which *sent went out */
        arg = *sent;
        PyObject *raw = PyBytes_FromStringAndSize((const char *)g_codes, (Py_ssize_t)(ncodes * 2));
        extra = raw ? PyObject_CallOneArg(codes_fn, raw) : NULL;
        Py_XDECREF(raw);
    } else
        extra = Py_NewRef(Py_None);
    if (!extra)
        return -1;
    *hand = Py_BuildValue("(iLN)", r, arg, extra);
    return *hand ? r : -1;
}

/* A cycle's state loaded from parts, or NULL with *res None (not ordinary: the reference's
 * cycle) or NULL (an error). */
static S *loaded(PyObject *parts, int mode, int clock_live, PyObject **res) {
    S *s = PyMem_Calloc(1, sizeof(S));
    const int r = s ? load(s, parts, mode) : (PyErr_NoMemory(), -1);
    if (r > 0) {
        s->clock_live = clock_live;
        return s;
    }
    if (r == 0)
        hand_count[H_LOAD]++;
    *res = r == 0 ? Py_NewRef(Py_None) : NULL;
    PyMem_Free(s);
    return NULL;
}

static PyObject *fp_step(PyObject *self, PyObject *args) {
    PyObject *parts, *o_now;
    int mode;
    if (!PyArg_ParseTuple(args, "OOi", &parts, &o_now, &mode))
        return NULL;
    double now;
    if (o_now == Py_None)
        now = mono_now();
    else {
        now = PyFloat_AsDouble(o_now);
        if (now == -1.0 && PyErr_Occurred())
            return NULL;
    }
    PyObject *res = NULL, *hand = NULL;
    S *s = loaded(parts, mode, o_now == Py_None, &res);
    if (!s)
        return res;
    long long sent = 0;
    const int r = do_cycle(s, now, &sent, &hand);
    PyObject *w = writes(s);
    if (r >= 0 && w)
        res = Py_BuildValue("(LOO)", sent, hand ? hand : Py_None, w);
    Py_XDECREF(hand);
    Py_XDECREF(w);
    PyMem_Free(s);
    return res;
}

/* sleep until `due` (CLOCK_MONOTONIC s) or until one of fds is readable (then on to due):
 * 0 slept to due, 1 a descriptor is ready (slept to due), 2 a signal came (not slept out) */
static int sleep_until(double due, struct pollfd *pfd, int nfd, int *fd_ready) {
    while (1) {
        const double left = due - mono_now();
        if (left <= 0)
            return *fd_ready;
        if (*fd_ready || nfd == 0) {
            struct timespec ts;
            double ip;
            const double fr = modf(due, &ip);
            ts.tv_sec = (time_t)ip;
            ts.tv_nsec = (long)(fr * 1e9);
            if (ts.tv_nsec >= 1000000000L)
                ts.tv_nsec = 999999999L;
            int e = clock_nanosleep(CLOCK_MONOTONIC, TIMER_ABSTIME, &ts, NULL);
            if (e == EINTR)
                return 2;
            return *fd_ready;
        }
        struct timespec ts;
        ts.tv_sec = (time_t)left;
        ts.tv_nsec = (long)((left - (double)ts.tv_sec) * 1e9);
        int r = ppoll(pfd, (nfds_t)nfd, &ts, NULL);
        if (r < 0) {
            if (errno == EINTR)
                return 2;
            return *fd_ready; /* a closed descriptor: the Python loop sees to it */
        }
        if (r > 0)
            *fd_ready = 1;
    }
}

static PyObject *fp_run(PyObject *self, PyObject *args) {
    PyObject *parts, *o_dur, *o_fds;
    double start, budget;
    long long k;
    int mode, top_done;
    if (!PyArg_ParseTuple(args, "OdLOdO!ip", &parts, &start, &k, &o_dur, &budget, &PyTuple_Type, &o_fds, &mode,
                          &top_done))
        return NULL;
    int has_dur = o_dur != Py_None;
    double duration = has_dur ? PyFloat_AsDouble(o_dur) : 0.0;
    if (has_dur && duration == -1.0 && PyErr_Occurred())
        return NULL;
    struct pollfd pfd[8];
    const int nfd = PyTuple_GET_SIZE(o_fds) < 8 ? (int)PyTuple_GET_SIZE(o_fds) : 8;
    for (int i = 0; i < nfd; i++)
        pfd[i] = (struct pollfd){(int)PyLong_AsLong(PyTuple_GET_ITEM(o_fds, i)), POLLIN, 0};
    if (PyErr_Occurred())
        return NULL;
    const char *why = "reference";
    double due_out = 0.0, c0 = 0.0;
    PyObject *ret = NULL, *hand = NULL;
    S *s = loaded(parts, mode, 1, &ret);
    if (!s)
        return ret;
    int r;
    const double t_run0 = mono_now();
    const long long lim_fill = HP_BUFFER_CAPACITY - C_MAX_SAMPLES;
    int skip_top = top_done && s->P->_last_cycle_start_set; /* the caller's loop did this iteration's top */
    while (1) {
        double now = mono_now();
        if (skip_top) {
            now = s->P->_last_cycle_start;
            skip_top = 0;
            goto cycle_now;
        }
        if (has_dur && now - start >= duration) {
            why = "end";
            break;
        }
        if (s->P->_last_cycle_start_set) {
            long long lf = s->P->_fill + s->P->_extra;
            if (lf > lim_fill)
                lf = lim_fill;
            /* Pump.run: a pause that left less than STALL_MARGIN_CYCLES cycles of the buffer */
            if (now - s->P->_last_cycle_start > (double)lf / (double)C_RATE - STALL_MARGIN_CYCLES * s->P->period_s) {
                why = "stall"; /* (Pump.run counts it) */
                break;
            }
        }
        if (now - t_run0 >= budget) {
            why = "budget";
            break;
        }
        s->P->_last_cycle_start = now;
        s->P->_last_cycle_start_set = 1;
    cycle_now:;
        c0 = thread_now();
        long long sent;
        r = do_cycle(s, now, &sent, &hand);
        if (r < 0)
            break;
        if (r != DONE) { /* handed over: fastpump finishes the cycle the reference's way, and ends it */
            why = "handed";
            break;
        }
        /* Pump._end_cycle */
        double *ring = (double *)s->ringbuf.buf;
        const Py_ssize_t rn = s->ringbuf.len / 8;
        ring[s->PS->cycles % rn] = (thread_now() - c0) * 1e6;
        s->PS->cycles++;
        k++;
        const double due = start + (double)k * s->P->period_s;
        now = mono_now();
        if (now > due) {
            const double late = (now - due) * 1e6;
            s->PS->max_late_us = py_max(s->PS->max_late_us, late);
            if (late > s->P->period_s * 0.5e6)
                s->PS->deadline_misses++;
            k = (long long)((now - start) / s->P->period_s);
            continue;
        }
        int fd_ready = 0;
        const int w = sleep_until(due, pfd, nfd, &fd_ready);
        if (w == 2) {
            why = "signal";
            due_out = due;
            break;
        }
        if (w == 1) {
            why = "wake";
            break;
        }
    }
    PyObject *w = writes(s);
    if (w && !PyErr_Occurred())
        ret = Py_BuildValue("(LsdOdO)", k, why, due_out, hand ? hand : Py_None, c0, w);
    Py_XDECREF(w);
    Py_XDECREF(hand);
    PyMem_Free(s);
    return ret;
}

static PyObject *fp_init(PyObject *self, PyObject *args) {
    PyObject *cf;
    if (!PyArg_ParseTuple(args, "LiiO", &C_MAX_GAP_US, &C_SMALL_BATCH, &C_CUBIC_MIN, &cf))
        return NULL;
    if (C_SMALL_BATCH > RC_MAX_N || C_CUBIC_MIN < 4) {
        PyErr_SetString(PyExc_ValueError, "init: constants out of range");
        return NULL;
    }
    Py_XSETREF(codes_fn, Py_NewRef(cf));
    Py_RETURN_NONE;
}

static PyObject *fp_handovers(PyObject *self, PyObject *noargs) {
    PyObject *d = Py_BuildValue("{sL}", "compiled", compiled_count);
    for (int i = 0; d && i < H_N; i++) {
        PyObject *v = PyLong_FromLongLong(hand_count[i]);
        if (!v || PyDict_SetItemString(d, H_NAMES[i], v) < 0)
            Py_CLEAR(d);
        Py_XDECREF(v);
    }
    return d;
}

static PyMethodDef methods[] = {
    {"handovers", fp_handovers, METH_NOARGS,
     "handovers() -> {cause: cycles handed to the reference, 'compiled': cycles done compiled}"},
    {"init", fp_init, METH_VARARGS,
     "init(max_gap_us, small_batch, cubic_min_readings, codes_from_bytes)"},
    {"step", fp_step, METH_VARARGS,
     "step(parts, now_s | None, mode) -> (sent, hand, writes) | None: pump.step() (fastpump.step)"},
    {"run", fp_run, METH_VARARGS,
     "run(parts, start_s, k, duration_s | None, budget_s, fds, mode, top_done) -> (k, why, due_s, hand, c0, "
     "writes) | None: Pump.run's ordinary iterations (fastpump.run)"},
    {NULL, NULL, 0, NULL},
};

static struct PyModuleDef module = {
    PyModuleDef_HEAD_INIT, "_fastpump", "The host-rendering pump's steady-state cycle (see hostd/device/fastpump.py).",
    -1, methods, NULL, NULL, NULL, NULL,
};

PyMODINIT_FUNC PyInit__fastpump(void) {
    PyObject *m = PyModule_Create(&module);
    if (!m)
        return NULL;
    if (PyModule_AddIntConstant(m, "REVISION", REVISION) < 0) {
        Py_DECREF(m);
        return NULL;
    }
    PyObject *sizes = PyDict_New(); /* RECORD_SIZES: kind -> sizeof(hs_<kind>_t), checked by fastpump.py */
#define SIZE(kind)                                                                                        \
    if (sizes) {                                                                                          \
        PyObject *v = PyLong_FromSize_t(sizeof(hs_##kind##_t));                                           \
        if (!v || PyDict_SetItemString(sizes, #kind, v) < 0)                                              \
            Py_CLEAR(sizes);                                                                              \
        Py_XDECREF(v);                                                                                    \
    }
    HS_RECORDS(SIZE)
#undef SIZE
    if (!sizes || PyModule_AddObject(m, "RECORD_SIZES", sizes) < 0) {
        Py_XDECREF(sizes);
        Py_DECREF(m);
        return NULL;
    }
    return m;
}
