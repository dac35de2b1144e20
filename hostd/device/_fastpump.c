/* The host-rendering pump's steady-state cycle, compiled: hostd.device.pump.Pump.step (and the
 * loop of Pump.run) is the reference, hostd/device/fastpump.py the wrapper, tests/test_fastpump.py
 * the proof that both write the same bytes and leave the same state, cycle by cycle.
 *
 * Why: a cycle of the Python reference costs ~190 µs of CPU (a 1 kHz loop: ~19 % of a core);
 * this one costs the kernel's wake-up plus a few µs of arithmetic (docs/benchmarks.md).
 *
 * How it stays equal to the reference. The state lives in the Python objects (pump, link,
 * health, renderer, motion, position, height, equalizer, output stage, transport); `load` reads
 * it into a C struct, `store` writes it back. A cycle is done here only while everything is
 * ordinary: a serial port with nothing queued or a hidraw node (mode), STATUS messages only (at most FRESH per
 * poll, no fault flag, counters that move forwards), a motion fit on evenly spaced readings whose
 * least-squares weights are cached, no glitch or re-lock, no open recovery episode, a speed
 * bucket whose weights are cached, no crossfade. Each STATUS is checked before anything is
 * changed; at the first thing that is not ordinary the state is stored and the reference does
 * the rest of the cycle (`link._take` for the messages left, then `pump.after_poll()`), so the
 * rare paths (recovery, re-locks, new buckets, stalls) have one implementation: the Python one.
 * The GIL is held throughout, the sleeps included: nothing else in the pump's process runs
 * Python meanwhile (it has no other Python thread), so nothing can change the state held here
 * behind its back; a signal ends the sleep and the run, and its handler runs at once.
 * The arithmetic is the reference's, operation by operation, in IEEE doubles, compiled with
 * -ffp-contract=off; Python's float semantics are spelled out where C differs (floored %, max()
 * and min() that keep the first of equals, round() half to even = rint()).
 *
 *   init(consts, DeviceBusy, decode, codes_from_bytes)   the protocol's ids, sizes, constants
 *   step(pump, now_s, mode) -> int           one pump.step(); now_s: the host clock (None: CLOCK_MONOTONIC)
 *   run(pump, start_s, k, duration_s, budget_s, fds, mode, top_done) -> (k, why, due_s)
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
#include "framing.h" /* crc16, cobs_decode */

#define STALL_MARGIN_CYCLES 2 /* pump.STALL_MARGIN_CYCLES */
#define REVISION 7 /* fastpump.C_REVISION must equal this */
#define FRESH 32   /* DeviceLink.FRESH */
#define MAX_MSGS 64
#define MAX_UNACKED 64
#define MAX_WIN 64
#define READ_SIZE 4096   /* SerialTransport.READ_SIZE */
#define MAX_PENDING 4096 /* SerialTransport.MAX_PENDING */
#define STATUS_LEN 26
#define REST_BUCKET (-(1LL << 30))
#define MODE_SERIAL 0
#define MODE_HID 1
#define REPORT_SIZE 64 /* protocol.REPORT_SIZE (checked at init) */
#define HS_COUNT(kind) +1
#define HS_NREC (0 HS_RECORDS(HS_COUNT)) /* the records a cycle holds at most */

/* ------------------------------------------------------------------ constants (init) */
static int C_STATUS_ID = -1, C_SAMPLES_ID = -1, C_MAX_SAMPLES = 0, C_RUNNING = 1, C_SMALL_BATCH = 32,
           C_CUBIC_MIN = 24; /* motion.CUBIC_MIN_READINGS (init) */
static long long C_RATE = 3000, C_CAP = 0, C_MAX_FRAME = 0, C_MAX_GAP_US = 600000000LL;
static PyObject *decode_fn = NULL; /* hostd.device.fastlink.decode: builds last_status dicts */
static PyObject *DeviceBusy = NULL; /* hostd.errors.DeviceBusy (init) */
static PyObject *codes_fn = NULL;   /* int16 bytes -> the codes array the reference renders (init) */


/* interned attribute names */
#define NAMES(X)                                                                                          \
    X(renderer) X(record) X(_episode) X(_guard_seq) X(_flags_seen) X(_last_samples_played)                \
    X(_last_played_dev_s) X(_under_seen) X(_fill) X(_last_decay) X(_extra) X(jitter) X(base_fill)         \
    X(_low_fill) X(quiet_s)                                                                               \
    X(stats) X(cycles) X(late_batches) X(samples) X(deadline_misses) X(max_late_us)      \
    X(step_us) X(relocks) X(implausible_speed) X(_motion_base)             \
    X(_last_cycle_start) X(period_s) X(link) X(health) X(t) X(target_fill) X(_seq) X(_unacked)            \
    X(_time_hi) X(_last_us) X(device_time_s) X(status_host_time) X(_offset_s) X(_offset_host_t)           \
    X(_fill_from_seq) X(statuses) X(messages_sent) X(samples_sent) X(last_status) X(_last) X(state)        \
    X(underruns) X(samples_played) X(_time_s) X(_sel_active) X(_sel_device) X(_sel_due) X(_sel_played)    \
    X(_sel_started) X(motion) X(position) X(height) X(eq) X(out) X(latency_s) X(_xfade_left) X(cfg)        \
    X(samples_per_batch) X(_total) X(um_per_count) X(_t) X(_x) X(_c0) X(_c1) X(_c2) X(_c3) X(_t_ref) \
    X(_rest_x) X(_dt_us) X(_uniform) X(_cache) X(implausible) X(_outliers) X(_since_restart) X(window)    \
    X(order)                                                                                              \
    X(glitch_um) X(rest_speed_mm_s) X(rest_hold_um) X(max_predict_s) X(max_gap_s) X(max_speed_mm_s)       \
    X(n) X(length_mm) X(band) X(speed_bucket) X(_v_full_mm_s) X(_w_bucket) X(_w) X(_w_cache) X(sos)     \
    X(zi)                                                                                                 \
    X(ser) X(fd) X(deframer) X(_buf) X(bad_frames) X(_queue) X(_pending)          \
    X(_vmin) X(after_poll) X(_take) X(clear) X(extend) X(step) X(empty_reads)
#define DECL(name) static PyObject *N_##name;
NAMES(DECL)
#undef DECL

/* ------------------------------------------------------------------ the state */
typedef struct {
    unsigned char b[STATUS_LEN];
    int state;
    long long flags, us, enc, played, fill, last_seq, under;
} status_t;

typedef struct {
    /* objects (new references) */
    PyObject *pump, *link, *t, *health, *r, *motion, *pos, *height, *eq, *out, *pstats, *lstats, *deframer;
    PyObject *mcache, *wcache, *w; /* motion weight cache, height weight cache, current weights */
    PyObject *overflow;             /* messages of one poll beyond MAX_MSGS (a backlog), or NULL */
    Py_buffer wbuf, sosbuf, zibuf, ringbuf;
    int have_w, have_sos, have_zi, have_ring;
    int fd, mode; /* mode: MODE_SERIAL (COBS frames on a byte stream) or MODE_HID (a report per read/write) */
    int clock_live; /* the cycle's clock is CLOCK_MONOTONIC (not a test's now_s): read it again after the read */
    long long empty_reads;
    /* transport */
    unsigned char *dbuf;
    Py_ssize_t dlen, dcap;
    long long bad_frames;
    unsigned char pend[MAX_PENDING + 256];
    Py_ssize_t plen;
    /* link */
    long long seq, time_hi, last_us, statuses, messages_sent, samples_sent, target_fill;
    int n_un;
    long long un_seq[MAX_UNACKED], un_cnt[MAX_UNACKED];
    double device_time_s, status_host_time, offset_s, offset_host_t;
    status_t ls; /* the latest STATUS (link.stats.last_status, health._last) */
    int ls_new;  /* it came in this C run: its dict is built at store */
    /* health */
    long long h_underruns, h_played;
    int h_state;
    double h_time_s, sel_due;
    int sel_active, sel_device, sel_started;
    long long sel_played;
    /* pump */
    long long flags_seen, last_sp, under_seen, fill, extra, base_fill, cycles, late_batches, samples;
    long long deadline_misses, motion_base0, motion_base1;
    int has_last_played, has_last_cycle, sent_any, record;
    double last_played_dev_s, last_decay, max_late_us, period_s, last_cycle_start;
    long long low_fill; /* the device's lowest reported fill while the target is raised (Pump._low_fill) */
    double quiet_s;     /* JitterConfig.quiet_s */
    /* renderer */
    double latency_s;
    long long spb;
    /* position */
    long long pos_last, pos_total;
    double um_per_count;
    /* motion */
    int win, order;
    double glitch_um, rest_speed, rest_hold, max_predict, max_gap, max_speed;
    double mt[MAX_WIN], mx[MAX_WIN];
    int mn;
    double c0, c1, c2, c3, t_ref, rest_x;
    int has_rest;
    long long dt_us, uniform, since_restart, m_relocks, m_implausible;
    long long wkey_n, wkey_dt, wkey_order; /* the motion weights in mw (-1: none) */
    double mw[4][MAX_WIN];
    /* height */
    long long hn, w_bucket;
    int has_wb;
    double length_mm, speed_bucket, v_full;
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
    if (s->nrec >= HS_NREC || PyObject_GetBuffer(o, b, PyBUF_WRITABLE) < 0)
        return NULL;
    s->nrec++;
    if (b->len != size) {
        PyErr_SetString(PyExc_TypeError, "a cycle_state record expected");
        return NULL;
    }
    return b->buf;
}

/* ------------------------------------------------------------------ attribute helpers */
static int get_obj(PyObject *o, PyObject *name, PyObject **dst) {
    *dst = PyObject_GetAttr(o, name);
    return *dst ? 0 : -1;
}
static int get_d(PyObject *o, PyObject *name, double *dst) {
    PyObject *v = PyObject_GetAttr(o, name);
    if (!v)
        return -1;
    *dst = PyFloat_AsDouble(v);
    Py_DECREF(v);
    return (*dst == -1.0 && PyErr_Occurred()) ? -1 : 0;
}
static int get_ll(PyObject *o, PyObject *name, long long *dst) {
    PyObject *v = PyObject_GetAttr(o, name);
    if (!v)
        return -1;
    if (!PyLong_Check(v)) { /* bool is an int; anything else is not ordinary */
        Py_DECREF(v);
        PyErr_SetString(PyExc_TypeError, "an int expected");
        return -1;
    }
    *dst = PyLong_AsLongLong(v);
    Py_DECREF(v);
    return (*dst == -1 && PyErr_Occurred()) ? -1 : 0;
}
/* an attribute that may be None: *has = 0 for None */
static int get_opt_d(PyObject *o, PyObject *name, double *dst, int *has) {
    PyObject *v = PyObject_GetAttr(o, name);
    if (!v)
        return -1;
    *has = v != Py_None;
    if (*has)
        *dst = PyFloat_AsDouble(v);
    Py_DECREF(v);
    return (*has && *dst == -1.0 && PyErr_Occurred()) ? -1 : 0;
}
static int get_opt_ll(PyObject *o, PyObject *name, long long *dst, int *has) {
    PyObject *v = PyObject_GetAttr(o, name);
    if (!v)
        return -1;
    *has = v != Py_None;
    if (*has) {
        if (!PyLong_Check(v)) {
            Py_DECREF(v);
            PyErr_SetString(PyExc_TypeError, "an int expected");
            return -1;
        }
        *dst = PyLong_AsLongLong(v);
    }
    Py_DECREF(v);
    return (*has && *dst == -1 && PyErr_Occurred()) ? -1 : 0;
}
static int is_none(PyObject *o, PyObject *name) { /* 1 None, 0 not, -1 error */
    PyObject *v = PyObject_GetAttr(o, name);
    if (!v)
        return -1;
    int r = v == Py_None;
    Py_DECREF(v);
    return r;
}
static int set_obj(PyObject *o, PyObject *name, PyObject *v) { /* steals v */
    if (!v)
        return -1;
    int r = PyObject_SetAttr(o, name, v);
    Py_DECREF(v);
    return r;
}
#define SET_D(o, name, v) set_obj(o, N_##name, PyFloat_FromDouble(v))
#define SET_LL(o, name, v) set_obj(o, N_##name, PyLong_FromLongLong(v))
#define SET_B(o, name, v) set_obj(o, N_##name, PyBool_FromLong(v))

/* ------------------------------------------------------------------ load / store */
static void release(S *s) {
    if (s->have_w)
        PyBuffer_Release(&s->wbuf);
    if (s->have_sos)
        PyBuffer_Release(&s->sosbuf);
    if (s->have_zi)
        PyBuffer_Release(&s->zibuf);
    if (s->have_ring)
        PyBuffer_Release(&s->ringbuf);
    s->have_w = s->have_sos = s->have_zi = s->have_ring = 0;
    while (s->nrec > 0)
        PyBuffer_Release(&s->recbuf[--s->nrec]);
    Py_CLEAR(s->pump);
    Py_CLEAR(s->link);
    Py_CLEAR(s->t);
    Py_CLEAR(s->health);
    Py_CLEAR(s->r);
    Py_CLEAR(s->motion);
    Py_CLEAR(s->pos);
    Py_CLEAR(s->height);
    Py_CLEAR(s->eq);
    Py_CLEAR(s->out);
    Py_CLEAR(s->pstats);
    Py_CLEAR(s->lstats);
    Py_CLEAR(s->deframer);
    Py_CLEAR(s->mcache);
    Py_CLEAR(s->wcache);
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
    if (s->have_w)
        PyBuffer_Release(&s->wbuf);
    s->wbuf = b;
    s->have_w = 1;
    Py_INCREF(w);
    Py_XSETREF(s->w, w);
    return 1;
}

static int read_status_fields(PyObject *d, status_t *st) { /* from a last_status dict */
    static const char *keys[] = {"state", "fault_flags", "device_time_us", "encoder_count", "samples_played",
                                 "buffer_fill", "last_seq", "underruns"};
    long long v[8];
    for (int i = 0; i < 8; i++) {
        PyObject *x = PyDict_GetItemString(d, keys[i]);
        if (!x || !PyLong_Check(x))
            return 0;
        v[i] = PyLong_AsLongLong(x);
        if (v[i] == -1 && PyErr_Occurred())
            return -1;
    }
    st->state = (int)v[0];
    st->flags = v[1];
    st->us = v[2];
    st->enc = v[3];
    st->played = v[4];
    st->fill = v[5];
    st->last_seq = v[6];
    st->under = v[7];
    return 1;
}

static int load_deque(PyObject *dq, double *dst, int max, int *n) {
    PyObject *it = PyObject_GetIter(dq);
    if (!it)
        return -1;
    PyObject *x;
    int k = 0;
    while ((x = PyIter_Next(it))) {
        if (k >= max || !PyFloat_Check(x)) {
            Py_DECREF(x);
            Py_DECREF(it);
            return 0;
        }
        dst[k++] = PyFloat_AS_DOUBLE(x);
        Py_DECREF(x);
    }
    Py_DECREF(it);
    if (PyErr_Occurred())
        return -1;
    *n = k;
    return 1;
}

/* 1: loaded and ordinary; 0: not ordinary (the reference does the cycle); -1: error */
static int load(S *s, PyObject *pump, int mode) {
    memset(s, 0, sizeof *s);
    s->mode = mode;
    s->wkey_n = -1;
    Py_INCREF(pump);
    s->pump = pump;
    long long ll;
    int has, r;
    PyObject *o = NULL;
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
    /* pump */
    TRY(get_obj(pump, N_renderer, &s->r));
    NO(s->r == Py_None);
    TRY(get_obj(pump, N_record, &o));
    r = PyObject_IsTrue(o);
    Py_CLEAR(o);
    TRY(r);
    s->record = r; /* (the demo's summary: pump.sent_codes gets each batch sent) */
    TRY(r = is_none(pump, N__episode));
    NO(!r);
    TRY(r = is_none(pump, N__guard_seq));
    NO(!r);
    TRY(get_ll(pump, N__flags_seen, &s->flags_seen));
    NO(s->flags_seen != 0);
    TRY(get_opt_ll(pump, N__last_samples_played, &s->last_sp, &has));
    NO(!has);
    TRY(get_opt_d(pump, N__last_played_dev_s, &s->last_played_dev_s, &s->has_last_played));
    TRY(get_ll(pump, N__under_seen, &s->under_seen));
    TRY(get_ll(pump, N__fill, &s->fill));
    TRY(get_d(pump, N__last_decay, &s->last_decay));
    TRY(get_ll(pump, N__low_fill, &s->low_fill));
    TRY(get_ll(pump, N__extra, &s->extra));
    TRY(get_d(pump, N_period_s, &s->period_s));
    TRY(get_opt_d(pump, N__last_cycle_start, &s->last_cycle_start, &s->has_last_cycle));
    TRY(get_obj(pump, N_jitter, &o));
    r = get_ll(o, N_base_fill, &s->base_fill) < 0 || get_d(o, N_quiet_s, &s->quiet_s) < 0;
    Py_CLEAR(o);
    if (r)
        goto fail;
    TRY(get_obj(pump, N__motion_base, &o));
    if (!PyTuple_Check(o) || PyTuple_GET_SIZE(o) != 2) {
        Py_CLEAR(o);
        goto no;
    }
    s->motion_base0 = PyLong_AsLongLong(PyTuple_GET_ITEM(o, 0));
    s->motion_base1 = PyLong_AsLongLong(PyTuple_GET_ITEM(o, 1));
    Py_CLEAR(o);
    if (PyErr_Occurred())
        goto fail;
    TRY(get_obj(pump, N_stats, &s->pstats));
    TRY(get_ll(s->pstats, N_cycles, &s->cycles));
    TRY(get_ll(s->pstats, N_late_batches, &s->late_batches));
    TRY(get_ll(s->pstats, N_samples, &s->samples));
    TRY(get_ll(s->pstats, N_deadline_misses, &s->deadline_misses));
    TRY(get_d(s->pstats, N_max_late_us, &s->max_late_us));
    TRY(get_obj(s->pstats, N_step_us, &o));
    if (PyObject_GetBuffer(o, &s->ringbuf, PyBUF_C_CONTIGUOUS | PyBUF_WRITABLE | PyBUF_FORMAT) < 0) {
        Py_CLEAR(o);
        goto fail;
    }
    Py_CLEAR(o);
    s->have_ring = 1;
    NO(s->ringbuf.itemsize != 8 || strcmp(s->ringbuf.format, "d") || s->ringbuf.len < 8);
    TRY(get_obj(pump, N_health, &s->health));
    /* link */
    TRY(get_obj(pump, N_link, &s->link));
    TRY(r = is_none(s->link, N__fill_from_seq));
    NO(!r);
    TRY(get_ll(s->link, N_target_fill, &s->target_fill));
    TRY(get_ll(s->link, N__seq, &s->seq));
    TRY(get_ll(s->link, N__time_hi, &s->time_hi));
    TRY(get_opt_ll(s->link, N__last_us, &s->last_us, &has));
    NO(!has);
    TRY(get_d(s->link, N_device_time_s, &s->device_time_s));
    TRY(get_d(s->link, N_status_host_time, &s->status_host_time));
    TRY(get_opt_d(s->link, N__offset_s, &s->offset_s, &has));
    NO(!has);
    TRY(get_d(s->link, N__offset_host_t, &s->offset_host_t));
    TRY(get_obj(s->link, N__unacked, &o));
    {
        PyObject *it = PyObject_GetIter(o), *x;
        Py_CLEAR(o);
        if (!it)
            goto fail;
        while ((x = PyIter_Next(it))) {
            int ok = PyTuple_Check(x) && PyTuple_GET_SIZE(x) == 2 && s->n_un < MAX_UNACKED;
            if (ok) {
                s->un_seq[s->n_un] = PyLong_AsLongLong(PyTuple_GET_ITEM(x, 0));
                s->un_cnt[s->n_un] = PyLong_AsLongLong(PyTuple_GET_ITEM(x, 1));
                s->n_un++;
            }
            Py_DECREF(x);
            if (!ok) {
                Py_DECREF(it);
                goto no;
            }
        }
        Py_DECREF(it);
        if (PyErr_Occurred())
            goto fail;
    }
    TRY(get_obj(s->link, N_stats, &s->lstats));
    TRY(get_ll(s->lstats, N_statuses, &s->statuses));
    TRY(get_ll(s->lstats, N_messages_sent, &s->messages_sent));
    TRY(get_ll(s->lstats, N_samples_sent, &s->samples_sent));
    TRY(get_obj(s->lstats, N_last_status, &o));
    r = PyDict_Check(o) ? read_status_fields(o, &s->ls) : 0;
    Py_CLEAR(o);
    TRY(r);
    NO(!r);
    /* health: its last STATUS is the link's (the same dict) */
    TRY(get_obj(s->health, N__last, &o));
    {
        PyObject *ls = PyObject_GetAttr(s->lstats, N_last_status);
        if (!ls) {
            Py_CLEAR(o);
            goto fail;
        }
        r = o == ls;
        Py_DECREF(ls);
        Py_CLEAR(o);
        NO(!r);
    }
    TRY(get_ll(s->health, N_underruns, &s->h_underruns));
    TRY(get_ll(s->health, N_samples_played, &s->h_played));
    TRY(get_ll(s->health, N_state, &ll));
    s->h_state = (int)ll;
    TRY(get_d(s->health, N__time_s, &s->h_time_s));
    TRY(get_d(s->health, N__sel_due, &s->sel_due));
    TRY(get_ll(s->health, N__sel_played, &s->sel_played));
    TRY(get_ll(s->health, N__sel_active, &ll));
    s->sel_active = ll != 0;
    TRY(get_ll(s->health, N__sel_device, &ll));
    s->sel_device = ll != 0;
    TRY(get_ll(s->health, N__sel_started, &ll));
    s->sel_started = ll != 0;
    /* transport */
    TRY(get_obj(s->link, N_t, &s->t));
    if (mode == MODE_HID) { /* HidrawTransport: its descriptor, its count of empty reads */
        TRY(get_ll(s->t, N_fd, &ll));
        NO(ll < 0);
        s->fd = (int)ll;
        TRY(get_ll(s->t, N_empty_reads, &s->empty_reads));
    } else { /* SerialTransport, with nothing queued either way */
        TRY(get_obj(s->t, N__queue, &o));
        r = PyList_Check(o) && PyList_GET_SIZE(o) == 0;
        Py_CLEAR(o);
        NO(!r);
        TRY(get_obj(s->t, N__pending, &o));
        r = PyBytes_Check(o) && PyBytes_GET_SIZE(o) == 0;
        Py_CLEAR(o);
        NO(!r);
        TRY(get_ll(s->t, N__vmin, &ll));
        NO(ll != 0);
        TRY(get_obj(s->t, N_ser, &o));
        r = get_ll(o, N_fd, &ll);
        Py_CLEAR(o);
        TRY(r);
        s->fd = (int)ll;
        TRY(get_obj(s->t, N_deframer, &s->deframer));
        TRY(get_ll(s->deframer, N_bad_frames, &s->bad_frames));
        TRY(get_obj(s->deframer, N__buf, &o));
        if (!PyByteArray_Check(o)) {
            Py_CLEAR(o);
            goto no;
        }
        s->dlen = PyByteArray_GET_SIZE(o);
        s->dcap = s->dlen + 2 * READ_SIZE;
        s->dbuf = PyMem_Malloc((size_t)s->dcap);
        if (!s->dbuf) {
            Py_CLEAR(o);
            PyErr_NoMemory();
            goto fail;
        }
        memcpy(s->dbuf, PyByteArray_AS_STRING(o), (size_t)s->dlen);
        Py_CLEAR(o);
    }
    /* renderer */
    TRY(get_ll(s->r, N__xfade_left, &ll));
    NO(ll != 0);
    TRY(get_d(s->r, N_latency_s, &s->latency_s));
    TRY(get_obj(s->r, N_cfg, &o));
    r = get_ll(o, N_samples_per_batch, &s->spb);
    Py_CLEAR(o);
    TRY(r);
    TRY(get_obj(s->r, N_position, &s->pos));
    TRY(get_opt_ll(s->pos, N__last, &s->pos_last, &has));
    NO(!has);
    TRY(get_ll(s->pos, N__total, &s->pos_total));
    NO(s->pos_total > (1LL << 52) || s->pos_total < -(1LL << 52));
    TRY(get_d(s->pos, N_um_per_count, &s->um_per_count));
    TRY(get_obj(s->r, N_motion, &s->motion));
    TRY(get_obj(s->motion, N_cfg, &o));
    {
        long long w, ord;
        r = get_ll(o, N_window, &w) < 0 || get_ll(o, N_order, &ord) < 0 || get_d(o, N_glitch_um, &s->glitch_um) < 0 ||
            get_d(o, N_rest_speed_mm_s, &s->rest_speed) < 0 || get_d(o, N_rest_hold_um, &s->rest_hold) < 0 ||
            get_d(o, N_max_predict_s, &s->max_predict) < 0 || get_d(o, N_max_gap_s, &s->max_gap) < 0 ||
            get_d(o, N_max_speed_mm_s, &s->max_speed) < 0;
        Py_CLEAR(o);
        if (r)
            goto fail;
        NO(w < 2 || w > MAX_WIN || ord < 0 || ord > 3);
        s->win = (int)w;
        s->order = (int)ord;
    }
    TRY(get_obj(s->motion, N__outliers, &o));
    r = PyList_Check(o) && PyList_GET_SIZE(o) == 0;
    Py_CLEAR(o);
    NO(!r);
    {
        int nt = 0, nx = 0;
        TRY(get_obj(s->motion, N__t, &o));
        r = load_deque(o, s->mt, s->win, &nt);
        Py_CLEAR(o);
        TRY(r);
        NO(!r);
        TRY(get_obj(s->motion, N__x, &o));
        r = load_deque(o, s->mx, s->win, &nx);
        Py_CLEAR(o);
        TRY(r);
        NO(!r || nt != nx || nt == 0);
        s->mn = nt;
    }
    TRY(get_d(s->motion, N__c0, &s->c0));
    TRY(get_d(s->motion, N__c1, &s->c1));
    TRY(get_d(s->motion, N__c2, &s->c2));
    TRY(get_d(s->motion, N__c3, &s->c3));
    TRY(get_d(s->motion, N__t_ref, &s->t_ref));
    TRY(get_opt_d(s->motion, N__rest_x, &s->rest_x, &s->has_rest));
    TRY(get_ll(s->motion, N__dt_us, &s->dt_us));
    TRY(get_ll(s->motion, N__uniform, &s->uniform));
    TRY(get_ll(s->motion, N__since_restart, &s->since_restart));
    TRY(get_ll(s->motion, N_relocks, &s->m_relocks));
    TRY(get_ll(s->motion, N_implausible, &s->m_implausible));
    TRY(get_obj(s->motion, N__cache, &s->mcache));
    NO(!PyDict_Check(s->mcache));
    /* height: the series on float64 weights (checked by the wrapper: method, dtype) */
    TRY(get_obj(s->r, N_height, &s->height));
    TRY(get_ll(s->height, N_n, &s->hn));
    NO(s->hn <= 0);
    TRY(get_d(s->height, N_length_mm, &s->length_mm));
    TRY(get_d(s->height, N__v_full_mm_s, &s->v_full));
    TRY(get_obj(s->height, N_band, &o));
    r = get_d(o, N_speed_bucket, &s->speed_bucket);
    Py_CLEAR(o);
    TRY(r);
    TRY(get_opt_ll(s->height, N__w_bucket, &s->w_bucket, &s->has_wb));
    TRY(get_obj(s->height, N__w_cache, &s->wcache));
    NO(!PyDict_Check(s->wcache));
    TRY(get_obj(s->height, N__w, &o));
    r = set_weights(s, o);
    Py_CLEAR(o);
    TRY(r);
    NO(!r);
    /* equalizer and output stage (fastrender.tail's conditions) */
    TRY(get_obj(s->r, N_eq, &s->eq));
    TRY(get_obj(s->eq, N_sos, &o));
    if (o != Py_None) {
        r = PyObject_GetBuffer(o, &s->sosbuf, PyBUF_C_CONTIGUOUS | PyBUF_FORMAT);
        Py_CLEAR(o);
        TRY(r);
        s->have_sos = 1;
        NO(s->sosbuf.itemsize != 8 || strcmp(s->sosbuf.format, "d") || s->sosbuf.len % 48);
        s->ns = s->sosbuf.len / 48;
        TRY(get_obj(s->eq, N_zi, &o));
        if (o == Py_None) {
            Py_CLEAR(o);
            goto no;
        }
        r = PyObject_GetBuffer(o, &s->zibuf, PyBUF_C_CONTIGUOUS | PyBUF_WRITABLE | PyBUF_FORMAT);
        Py_CLEAR(o);
        if (r < 0) {
            PyErr_Clear(); /* not writable or not contiguous: the reference copes */
            goto no;
        }
        s->have_zi = 1;
        NO(s->zibuf.itemsize != 8 || strcmp(s->zibuf.format, "d") || s->zibuf.len != s->ns * 16);
    } else {
        Py_CLEAR(o);
        s->ns = 0;
    }
    TRY(get_obj(s->r, N_out, &s->out));
    if (!(s->o = REC(s, s->out, output)))
        goto fail;
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
}

static int store_deque(PyObject *owner, PyObject *name, const double *v, int n) {
    PyObject *dq = PyObject_GetAttr(owner, name);
    if (!dq)
        return -1;
    PyObject *lst = PyList_New(n);
    if (!lst) {
        Py_DECREF(dq);
        return -1;
    }
    for (int i = 0; i < n; i++) {
        PyObject *f = PyFloat_FromDouble(v[i]);
        if (!f) {
            Py_DECREF(lst);
            Py_DECREF(dq);
            return -1;
        }
        PyList_SET_ITEM(lst, i, f);
    }
    PyObject *r1 = PyObject_CallMethodNoArgs(dq, N_clear);
    PyObject *r2 = r1 ? PyObject_CallMethodOneArg(dq, N_extend, lst) : NULL;
    Py_XDECREF(r1);
    Py_XDECREF(r2);
    Py_DECREF(lst);
    Py_DECREF(dq);
    return r2 ? 0 : -1;
}

/* write the state back into the Python objects and release them */
static int store(S *s) {
    int e = 0;
    PyObject *o;
    /* transport */
    if (s->mode == MODE_HID)
        e |= SET_LL(s->t, empty_reads, s->empty_reads);
    else {
        o = PyByteArray_FromStringAndSize((const char *)s->dbuf, s->dlen);
        e |= set_obj(s->deframer, N__buf, o);
        e |= SET_LL(s->deframer, bad_frames, s->bad_frames);
        e |= set_obj(s->t, N__pending, PyBytes_FromStringAndSize((const char *)s->pend, s->plen));
    }
    /* link */
    e |= SET_LL(s->link, _seq, s->seq);
    e |= SET_LL(s->link, _time_hi, s->time_hi);
    e |= SET_LL(s->link, _last_us, s->last_us);
    e |= SET_D(s->link, device_time_s, s->device_time_s);
    e |= SET_D(s->link, status_host_time, s->status_host_time);
    e |= SET_D(s->link, _offset_s, s->offset_s);
    e |= SET_D(s->link, _offset_host_t, s->offset_host_t);
    o = PyObject_GetAttr(s->link, N__unacked);
    if (o) {
        PyObject *lst = PyList_New(s->n_un);
        for (int i = 0; lst && i < s->n_un; i++)
            PyList_SET_ITEM(lst, i, Py_BuildValue("(LL)", s->un_seq[i], s->un_cnt[i]));
        PyObject *r1 = lst ? PyObject_CallMethodNoArgs(o, N_clear) : NULL;
        PyObject *r2 = r1 ? PyObject_CallMethodOneArg(o, N_extend, lst) : NULL;
        e |= r2 ? 0 : -1;
        Py_XDECREF(r1);
        Py_XDECREF(r2);
        Py_XDECREF(lst);
        Py_DECREF(o);
    } else
        e = -1;
    e |= SET_LL(s->lstats, statuses, s->statuses);
    e |= SET_LL(s->lstats, messages_sent, s->messages_sent);
    e |= SET_LL(s->lstats, samples_sent, s->samples_sent);
    if (s->ls_new) { /* the latest STATUS as the reference decodes it: one dict for link and health */
        PyObject *msg = PyBytes_FromStringAndSize((const char *)s->ls.b, STATUS_LEN);
        PyObject *res = msg ? PyObject_CallOneArg(decode_fn, msg) : NULL;
        Py_XDECREF(msg);
        if (res && PyTuple_Check(res) && PyTuple_GET_SIZE(res) == 2) {
            PyObject *d = PyTuple_GET_ITEM(res, 1);
            e |= PyObject_SetAttr(s->lstats, N_last_status, d);
            e |= PyObject_SetAttr(s->health, N__last, d);
        } else
            e = -1;
        Py_XDECREF(res);
    }
    /* health */
    e |= SET_LL(s->health, underruns, s->h_underruns);
    e |= SET_LL(s->health, samples_played, s->h_played);
    e |= SET_LL(s->health, state, s->h_state);
    e |= SET_D(s->health, _time_s, s->h_time_s);
    e |= SET_D(s->health, _sel_due, s->sel_due);
    e |= SET_LL(s->health, _sel_played, s->sel_played);
    e |= SET_B(s->health, _sel_started, s->sel_started);
    /* pump */
    e |= SET_LL(s->pump, _flags_seen, s->flags_seen);
    e |= SET_LL(s->pump, _last_samples_played, s->last_sp);
    if (s->has_last_played)
        e |= SET_D(s->pump, _last_played_dev_s, s->last_played_dev_s);
    e |= SET_LL(s->pump, _under_seen, s->under_seen);
    e |= SET_D(s->pump, _last_decay, s->last_decay);
    e |= SET_LL(s->pump, _low_fill, s->low_fill);
    if (s->has_last_cycle)
        e |= SET_D(s->pump, _last_cycle_start, s->last_cycle_start);
    e |= SET_LL(s->pstats, cycles, s->cycles);
    e |= SET_LL(s->pstats, late_batches, s->late_batches);
    e |= SET_LL(s->pstats, samples, s->samples);
    e |= SET_LL(s->pstats, deadline_misses, s->deadline_misses);
    e |= SET_D(s->pstats, max_late_us, s->max_late_us);
    if (s->sent_any) { /* after_poll sets these after a send */
        e |= SET_LL(s->pstats, relocks, s->motion_base0 + s->m_relocks);
        e |= SET_LL(s->pstats, implausible_speed, s->motion_base1 + s->m_implausible);
    }
    /* position, motion */
    e |= SET_LL(s->pos, _last, s->pos_last);
    e |= SET_LL(s->pos, _total, s->pos_total);
    e |= store_deque(s->motion, N__t, s->mt, s->mn);
    e |= store_deque(s->motion, N__x, s->mx, s->mn);
    e |= SET_D(s->motion, _c0, s->c0);
    e |= SET_D(s->motion, _c1, s->c1);
    e |= SET_D(s->motion, _c2, s->c2);
    e |= SET_D(s->motion, _c3, s->c3);
    e |= SET_D(s->motion, _t_ref, s->t_ref);
    if (s->has_rest)
        e |= SET_D(s->motion, _rest_x, s->rest_x);
    else
        e |= PyObject_SetAttr(s->motion, N__rest_x, Py_None);
    e |= SET_LL(s->motion, _dt_us, s->dt_us);
    e |= SET_LL(s->motion, _uniform, s->uniform);
    e |= SET_LL(s->motion, _since_restart, s->since_restart);
    /* height: the bucket in force and its weights */
    if (s->has_wb)
        e |= SET_LL(s->height, _w_bucket, s->w_bucket);
    e |= PyObject_SetAttr(s->height, N__w, s->w);
    release(s);
    return e ? -1 : 0;
}

/* ------------------------------------------------------------------ serial framing
 * (decoding: framing.h, shared by both compiled modules) */

static Py_ssize_t cobs_encode(const unsigned char *in, Py_ssize_t n, unsigned char *out) {
    Py_ssize_t code_at = 0, k = 1;
    unsigned char code = 1;
    for (Py_ssize_t i = 0; i < n; i++) {
        if (in[i] == 0) {
            out[code_at] = code;
            code_at = k++;
            code = 1;
        } else {
            out[k++] = in[i];
            if (++code == 0xFF) {
                out[code_at] = code;
                code_at = k++;
                code = 1;
            }
        }
    }
    out[code_at] = code;
    return k;
}

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
            if (s->dlen > 4 * C_MAX_FRAME) { /* no delimiter in sight: resync */
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
        /* COBS never lengthens: the body's length suffices */
        unsigned char *raw = *nm < MAX_MSGS ? msgs[*nm].b : spare;
        Py_ssize_t m = len <= (Py_ssize_t)sizeof msgs[0].b ? cobs_decode(body, len, raw) : -1;
        if (m < 3) {
            s->bad_frames++;
            continue;
        }
        if (crc16(raw, m - 2) != (uint16_t)(raw[m - 2] | (raw[m - 1] << 8))) {
            s->bad_frames++;
            continue;
        }
        if (keep_msg(s, msgs, nm, raw, m - 2) < 0)
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

static double mono_now(void) {
    struct timespec ts;
    clock_gettime(CLOCK_MONOTONIC, &ts);
    return (double)ts.tv_sec + (double)ts.tv_nsec * 1e-9;
}
static double thread_now(void) {
    struct timespec ts;
    clock_gettime(CLOCK_THREAD_CPUTIME_ID, &ts);
    return (double)ts.tv_sec + (double)ts.tv_nsec * 1e-9;
}

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
    const double m = s->max_predict;
    const double dt = py_min(py_max(t - s->t_ref, -m), m);
    return s->c0 + dt * (s->c1 + dt * (s->c2 + dt * s->c3));
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
    if (m->n < STATUS_LEN || m->b[0] != C_STATUS_ID)
        return HAND(H_MESSAGE, 0);
    for (Py_ssize_t i = STATUS_LEN; i < m->n; i++)
        if (m->b[i] != 0)
            return HAND(H_MESSAGE, 0); /* not padding: the reference says what it is */
    const unsigned char *p = m->b;
    status_t f;
    memcpy(f.b, p, STATUS_LEN);
    f.state = p[1];
    f.flags = p[2] | (p[3] << 8);
    f.us = (long long)((uint32_t)p[4] | ((uint32_t)p[5] << 8) | ((uint32_t)p[6] << 16) | ((uint32_t)p[7] << 24));
    f.enc = (long long)((uint32_t)p[8] | ((uint32_t)p[9] << 8) | ((uint32_t)p[10] << 16) | ((uint32_t)p[11] << 24));
    f.played = (long long)((uint32_t)p[12] | ((uint32_t)p[13] << 8) | ((uint32_t)p[14] << 16) |
                           ((uint32_t)p[15] << 24));
    f.fill = p[16] | (p[17] << 8);
    f.last_seq = p[18] | (p[19] << 8);
    f.under = p[20] | (p[21] << 8);
    if (f.flags != 0)
        return HAND(H_FAULT, 0); /* a fault: the reference records it and supervises */
    /* health.update's checks */
    const long long dt_us = u32(f.us - s->ls.us);
    const long long d_played = u32(f.played - s->ls.played);
    const long long d_under = (f.under - s->ls.under) & 0xFFFF;
    if (dt_us > C_MAX_GAP_US || d_played > dt_us * C_RATE / 1000000 + 3)
        return HAND(H_RESET, 0); /* a reset */
    /* link._status: the device's clock */
    long long time_hi = s->time_hi;
    if (f.us < s->last_us && s->last_us - f.us > (1LL << 31))
        time_hi += 1LL << 32;
    const double device_time_s = (double)(time_hi + f.us) * 1e-6;
    /* position.update */
    const long long raw = f.enc;
    long long d = u32(raw - s->pos_last);
    if (d >= (1LL << 31))
        d -= 1LL << 32;
    const long long total = s->pos_total + d;
    if (total > (1LL << 52) || total < -(1LL << 52))
        return HAND(H_RESET, 0);
    const double x_mm = (double)total * s->um_per_count * 1e-3;
    /* motion.update, on a copy of the window */
    const double t_s = device_time_s;
    if (!isfinite(t_s) || !isfinite(x_mm))
        return HAND(H_GLITCH, 0);
    double mt[MAX_WIN], mx[MAX_WIN];
    int mn = s->mn;
    long long since = s->since_restart, mdt = s->dt_us, uni = s->uniform;
    double c0 = s->c0, c1 = s->c1, c2 = s->c2, c3 = s->c3, t_ref = s->t_ref, rest_x = s->rest_x;
    int has_rest = s->has_rest;
    const int stale = t_s <= s->mt[s->mn - 1];
    if (!stale) {
        if (t_s - s->mt[s->mn - 1] > s->max_gap)
            return HAND(H_GAP, 0); /* a gap: the fit restarts (reference) */
        if (mn >= s->order + 2) {
            const double pred = predict_one(s, t_s);
            if (fabs(x_mm - pred) * 1000.0 > s->glitch_um)
                return HAND(H_GLITCH, 0); /* a glitch or a real move (reference) */
        }
        memcpy(mt, s->mt, sizeof(double) * (size_t)mn);
        memcpy(mx, s->mx, sizeof(double) * (size_t)mn);
        since += 1;
        const long long dtu = (long long)rint((t_s - mt[mn - 1]) * 1e6); /* round() */
        uni = dtu == mdt ? uni + 1 : 1;
        mdt = dtu;
        if (mn == s->win) {
            memmove(mt, mt + 1, sizeof(double) * (size_t)(mn - 1));
            memmove(mx, mx + 1, sizeof(double) * (size_t)(mn - 1));
            mn--;
        }
        mt[mn] = t_s;
        mx[mn] = x_mm;
        mn++;
        /* _fit */
        t_ref = mt[mn - 1];
        long long order = s->order < mn - 1 ? s->order : mn - 1;
        if (since < 2 * (s->order + 1) && order > 1)
            order = 1;
        if (order == 3 && mn < C_CUBIC_MIN)
            order = 2; /* a short window: motion.CUBIC_MIN_READINGS */
        if (order == 0) {
            c0 = mx[mn - 1];
            c1 = c2 = c3 = 0.0;
            has_rest = 0;
        } else {
            if (uni < mn - 1)
                return HAND(H_IRREGULAR, 0); /* irregular spacing: solved afresh (reference) */
            int r = motion_weights(s, mn, mdt, order);
            if (r <= 0)
                return r < 0 ? -1 : HAND(H_FIT_UNCACHED, 0);
            c0 = dot(s->mw[0], mx, mn);
            c1 = dot(s->mw[1], mx, mn) * 1e3;
            c2 = order >= 2 ? dot(s->mw[2], mx, mn) * 1e6 : 0.0;
            c3 = order == 3 ? dot(s->mw[3], mx, mn) * 1e9 : 0.0;
            /* at rest: slow, and the readings within what that speed covers over the window
             * (max(x) - min(x) as Python's max and min: the first of equals) */
            double lo = mx[0], hi = mx[0];
            for (int i = 1; i < mn; i++) {
                if (mx[i] > hi)
                    hi = mx[i];
                if (mx[i] < lo)
                    lo = mx[i];
            }
            if (fabs(c1) < s->rest_speed && hi - lo <= s->rest_speed * (mt[mn - 1] - mt[0]) + s->rest_hold * 1e-3) {
                double acc = 0.0;
                for (int i = 0; i < mn; i++)
                    acc += 1.0 * mx[i];
                const double mean = acc / (double)mn;
                if (!has_rest || fabs(mean - rest_x) * 1000.0 > s->rest_hold) {
                    rest_x = mean;
                    has_rest = 1;
                }
                c0 = rest_x;
                c1 = c2 = c3 = 0.0;
            } else
                has_rest = 0;
        }
        if (fabs(c1) > s->max_speed)
            return HAND(H_IMPLAUSIBLE, 0); /* implausible (reference) */
    }
    /* ---- commit. link._status */
    s->time_hi = time_hi;
    s->last_us = f.us;
    s->device_time_s = device_time_s;
    s->status_host_time = now;
    const double off = device_time_s - now;
    if (off < s->offset_s - 30.0)
        s->offset_s = off;
    else {
        const double decayed = s->offset_s - 1e-3 * (now - s->offset_host_t);
        s->offset_s = py_max(off, decayed);
    }
    s->offset_host_t = now;
    int drop = 0;
    while (drop < s->n_un && ((f.last_seq - s->un_seq[drop]) & 0xFFFF) < 0x8000)
        drop++;
    if (drop) {
        memmove(s->un_seq, s->un_seq + drop, sizeof(long long) * (size_t)(s->n_un - drop));
        memmove(s->un_cnt, s->un_cnt + drop, sizeof(long long) * (size_t)(s->n_un - drop));
        s->n_un -= drop;
    }
    s->statuses++;
    /* health.update */
    s->h_state = f.state;
    s->h_time_s += (double)dt_us * 1e-6;
    s->h_played += d_played;
    s->h_underruns += d_under;
    if (s->sel_active && !s->sel_device) {
        if (!s->sel_started && f.state == C_RUNNING)
            s->sel_started = 1;
        if (s->sel_started) {
            s->sel_due += (double)dt_us * 1e-6 * (double)C_RATE;
            s->sel_played += d_played;
        }
    }
    /* pump._on_status */
    s->flags_seen |= f.flags;
    if (f.played != s->last_sp && f.state == C_RUNNING) {
        s->last_played_dev_s = device_time_s;
        s->has_last_played = 1;
    }
    if (s->fill > s->base_fill && f.state == C_RUNNING && f.fill < s->low_fill)
        s->low_fill = f.fill; /* the evidence a raised target comes down on (no episode here) */
    s->last_sp = f.played;
    s->ls = f;
    s->ls_new = 1;
    /* renderer.on_encoder */
    s->pos_last = raw;
    s->pos_total = total;
    if (!stale) {
        memcpy(s->mt, mt, sizeof(double) * (size_t)mn);
        memcpy(s->mx, mx, sizeof(double) * (size_t)mn);
        s->mn = mn;
        s->since_restart = since;
        s->dt_us = mdt;
        s->uniform = uni;
        s->c0 = c0;
        s->c1 = c1;
        s->c2 = c2;
        s->c3 = c3;
        s->t_ref = t_ref;
        s->rest_x = rest_x;
        s->has_rest = has_rest;
    }
    return 1;
}

/* ------------------------------------------------------------------ the cycle */
enum { DONE = 0, HAND_MSGS = 1, HAND_AFTER = 2, HAND_READERR = 3, HAND_SEND = 4 };

static double device_now(const S *s, double now) { return py_max(s->device_time_s, now + s->offset_s); }

/* One SAMPLES message out, as link._send does it: 0 sent (serial: what the port did not take
 * waits in the pending bytes, as SerialTransport.send_raw keeps it), 1 not sent and nothing
 * changed (a write error; on HID also a busy or short write): the reference sends it. */
static int send_msg(S *s, const unsigned char *msg, Py_ssize_t ml) {
    if (s->mode == MODE_HID) { /* HidrawTransport.send: report id 0, the message padded */
        unsigned char rep[1 + REPORT_SIZE];
        if (ml > REPORT_SIZE)
            return 1;
        rep[0] = 0;
        memcpy(rep + 1, msg, (size_t)ml);
        memset(rep + 1 + ml, 0, (size_t)(REPORT_SIZE - ml));
        ssize_t w = write(s->fd, rep, sizeof rep);
        return w == (ssize_t)sizeof rep ? 0 : 1;
    }
    unsigned char fr[2 * (REPORT_SIZE + 8)], buf[MAX_PENDING + 256];
    unsigned char framed[REPORT_SIZE + 8];
    if (ml + 2 > (Py_ssize_t)sizeof framed)
        return 1;
    memcpy(framed, msg, (size_t)ml);
    const uint16_t crc = crc16(msg, ml);
    framed[ml] = (unsigned char)(crc & 0xFF);
    framed[ml + 1] = (unsigned char)(crc >> 8);
    Py_ssize_t n = cobs_encode(framed, ml + 2, fr);
    fr[n++] = 0;
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
    if (s->flags_seen != 0 || s->h_underruns != s->under_seen || s->ls.state != C_RUNNING)
        return HAND(H_SUPERVISE, HAND_AFTER);
    /* _decay: at base, the quiet period starts now (committed below); a raised target after its
     * quiet period comes down by the reference's rule (Pump._decay), handed over when it is due */
    if (s->fill > s->base_fill && now - s->last_decay >= s->quiet_s)
        return HAND(H_DECAY, HAND_AFTER);
    /* fill_estimate, wanted */
    long long in_flight = 0;
    for (int i = 0; i < s->n_un; i++)
        in_flight += s->un_cnt[i];
    double dfill = (double)s->ls.fill;
    if (s->ls.state == C_RUNNING)
        dfill -= (device_now(s, now) - s->device_time_s) * (double)C_RATE;
    dfill = py_max(0.0, dfill);
    const double fill = dfill + (double)in_flight;
    long long n = (long long)rint((double)s->target_fill - fill);
    if (n > 2 * C_MAX_SAMPLES)
        n = 2 * C_MAX_SAMPLES;
    if (n < 0)
        n = 0;
    double theta[RC_MAX_N], h[RC_MAX_N];
    int16_t codes[RC_MAX_N];
    int new_w = 0;
    if (n > 0) {
        if (n > C_SMALL_BATCH || s->n_un + (n + C_MAX_SAMPLES - 1) / C_MAX_SAMPLES > MAX_UNACKED)
            return HAND(H_BIG_BATCH, HAND_AFTER); /* the reference's numpy path; or more in flight than held here */
        /* next_play_time_s */
        const double queued = s->device_time_s + (double)(s->ls.fill + in_flight + 1) / (double)C_RATE;
        const double t0 = py_max(queued, device_now(s, now) + (double)(in_flight + 1) / (double)C_RATE);
        /* plan: predict; heights: phase, weights of the speed's bucket, the series */
        const double m = s->max_predict;
        /* Renderer.plan: the speed at the batch's middle instant (motion.velocity_at) */
        const double t_first = (t0 + 0.0 / (double)C_RATE) + s->latency_s;
        const double t_last = (t0 + (double)(n - 1) / (double)C_RATE) + s->latency_s;
        const double dtv = py_min(py_max(0.5 * (t_first + t_last) - s->t_ref, -m), m);
        const double v = s->c1 + dtv * (2.0 * s->c2 + dtv * (3.0 * s->c3));
        long long b;
        const double sp = fabs(v);
        if (sp < 1e-9 || sp <= s->v_full) /* HeightEvaluator._bucket: every gain 1 up to v_full */
            b = REST_BUCKET;
        else {
            const double q = floor(log(sp) / log1p(s->speed_bucket));
            if (!(q > -4e18 && q < 4e18))
                return HAND(H_NEW_BUCKET, HAND_AFTER);
            b = (long long)q;
        }
        if (!s->has_wb || b != s->w_bucket) {
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
        const double two_l = 2.0 * s->length_mm, dx = s->length_mm / (double)s->hn, kph = M_PI / (double)s->hn;
        for (long long i = 0; i < n; i++) {
            const double tp = t0 + (double)i / (double)C_RATE;
            const double t = tp + s->latency_s;
            const double dt = py_min(py_max(t - s->t_ref, -m), m);
            const double x = s->c0 + dt * (s->c1 + dt * (s->c2 + dt * s->c3));
            theta[i] = (py_mod(x, two_l) / dx + 0.5) * kph;
        }
        rc_clenshaw((const double *)s->wbuf.buf, s->wbuf.len / 8, theta, n, h, 1);
        if (new_w) {
            s->w_bucket = b;
            s->has_wb = 1;
        }
    }
    /* ---- commit the after-poll part */
    s->flags_seen = 0;
    s->under_seen = s->h_underruns;
    if (s->fill <= s->base_fill)
        s->last_decay = now;
    if (n == 0)
        return DONE;
    if (fill < (double)s->spb)
        s->late_batches++;
    rc_tail(s->have_sos ? (const double *)s->sosbuf.buf : NULL, s->ns, s->have_zi ? (double *)s->zibuf.buf : NULL, h,
            n, codes, s->o);
    /* send_samples */
    long long done = 0;
    for (long long i = 0; i < n; i += C_MAX_SAMPLES) {
        const long long cnt = n - i < C_MAX_SAMPLES ? n - i : C_MAX_SAMPLES;
        const long long seq = (s->seq + 1) & 0xFFFF;
        unsigned char msg[8 + 2 * 64];
        msg[0] = (unsigned char)C_SAMPLES_ID;
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
        s->messages_sent++;
        s->seq = seq;
        s->un_seq[s->n_un] = seq;
        s->un_cnt[s->n_un] = cnt;
        s->n_un++;
        s->samples_sent += cnt;
        done += cnt;
    }
    if (s->record) { /* Pump._send_codes: pump.sent_codes.append(codes[:sent]) */
        PyObject *raw = PyBytes_FromStringAndSize((const char *)codes, (Py_ssize_t)(done * 2));
        PyObject *arr = raw ? PyObject_CallOneArg(codes_fn, raw) : NULL;
        Py_XDECREF(raw);
        PyObject *lst = arr ? PyObject_GetAttrString(s->pump, "sent_codes") : NULL;
        int r = lst ? PyList_Append(lst, arr) : -1;
        Py_XDECREF(lst);
        Py_XDECREF(arr);
        if (r < 0)
            return -1;
    }
    s->samples += done;
    s->sent_any = 1;
    *sent = done;
    return DONE;
}

/* ------------------------------------------------------------------ hand-over, step, run */

/* A cycle: here while ordinary, else stored and finished by the reference. Returns the samples
 * sent (a new int), NULL on error. *loaded: whether s is still loaded afterwards. */
static PyObject *do_cycle(S *s, double now, int *loaded) {
    msg_t *msgs = g_msgs;
    int nm, first, more;
    long long sent, ncodes = 0;
    int r = cycle(s, now, msgs, &nm, &first, &more, &sent, &ncodes);
    if (r == DONE) {
        compiled_count++;
        return PyLong_FromLongLong(sent);
    }
    *loaded = 0;
    if (r < 0) {
        release(s);
        return NULL;
    }
    PyObject *pump = s->pump, *link = s->link, *t = s->t, *overflow = s->overflow;
    Py_INCREF(pump);
    Py_INCREF(link);
    Py_INCREF(t);
    Py_XINCREF(overflow);
    PyObject *res = NULL;
    if (store(s) < 0)
        goto out;
    if (r == HAND_MSGS) { /* link.poll's loop over the messages, from `first` on */
        PyObject *all = PyList_New(0);
        if (!all)
            goto out;
        for (int i = 0; i < nm; i++) {
            PyObject *m = PyBytes_FromStringAndSize((const char *)msgs[i].b, msgs[i].n);
            if (!m || PyList_Append(all, m) < 0) {
                Py_XDECREF(m);
                Py_DECREF(all);
                goto out;
            }
            Py_DECREF(m);
        }
        if (more) { /* the rest of the backlog */
            PyObject *x = PyObject_CallMethodOneArg(all, N_extend, overflow);
            if (!x) {
                Py_DECREF(all);
                goto out;
            }
            Py_DECREF(x);
        }
        const Py_ssize_t total = PyList_GET_SIZE(all), stale = total - FRESH;
        for (Py_ssize_t i = first; i < total; i++) {
            PyObject *x = PyObject_CallMethodObjArgs(link, N__take, PyList_GET_ITEM(all, i),
                                                     i >= stale ? Py_True : Py_False, NULL);
            if (!x) {
                Py_DECREF(all);
                goto out;
            }
            Py_DECREF(x);
        }
        Py_DECREF(all);
        res = PyObject_CallMethodNoArgs(pump, N_after_poll);
    } else if (r == HAND_AFTER) {
        res = PyObject_CallMethodNoArgs(pump, N_after_poll);
    } else if (r == HAND_SEND) { /* Pump._send_codes from the message that did not go out */
        PyObject *raw = PyBytes_FromStringAndSize((const char *)g_codes, (Py_ssize_t)(ncodes * 2));
        PyObject *codes = raw ? PyObject_CallOneArg(codes_fn, raw) : NULL;
        Py_XDECREF(raw);
        if (codes) {
            res = PyObject_CallMethod(pump, "_send_codes", "OL", codes, sent);
            Py_DECREF(codes);
            PyObject *x = res ? PyObject_CallMethod(pump, "_motion_stats", NULL) : NULL;
            if (!x)
                Py_CLEAR(res);
            Py_XDECREF(x);
        }
    } else { /* a read failed: the reference's cycle, from the top (it reads again) */
        res = PyObject_CallMethodNoArgs(pump, N_step);
    }
out:
    Py_DECREF(pump);
    Py_DECREF(link);
    Py_DECREF(t);
    Py_XDECREF(overflow);
    return res;
}

static PyObject *fp_step(PyObject *self, PyObject *args) {
    PyObject *pump, *o_now;
    int mode;
    if (!PyArg_ParseTuple(args, "OOi", &pump, &o_now, &mode))
        return NULL;
    double now;
    if (o_now == Py_None)
        now = mono_now();
    else {
        now = PyFloat_AsDouble(o_now);
        if (now == -1.0 && PyErr_Occurred())
            return NULL;
    }
    S *s = PyMem_Calloc(1, sizeof(S));
    if (!s)
        return PyErr_NoMemory();
    PyObject *res = NULL;
    int r = load(s, pump, mode);
    s->clock_live = o_now == Py_None;
    if (r < 0)
        goto done;
    if (r == 0) {
        hand_count[H_LOAD]++;
        res = PyObject_CallMethodNoArgs(pump, N_step);
        goto done;
    }
    int loaded = 1;
    res = do_cycle(s, now, &loaded);
    if (loaded) {
        if (store(s) < 0)
            Py_CLEAR(res);
    }
done:
    PyMem_Free(s);
    return res;
}

static int add_dropped(PyObject *pump) { /* pump.stats.io_dropped += 1 */
    PyObject *st = PyObject_GetAttrString(pump, "stats");
    if (!st)
        return -1;
    PyObject *v = PyObject_GetAttrString(st, "io_dropped");
    PyObject *one = PyLong_FromLong(1);
    PyObject *nv = v && one ? PyNumber_Add(v, one) : NULL;
    int r = nv ? PyObject_SetAttrString(st, "io_dropped", nv) : -1;
    Py_XDECREF(nv);
    Py_XDECREF(one);
    Py_XDECREF(v);
    Py_DECREF(st);
    return r;
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
    PyObject *pump, *o_dur, *o_fds;
    double start, budget;
    long long k;
    int mode, top_done;
    if (!PyArg_ParseTuple(args, "OdLOdOip", &pump, &start, &k, &o_dur, &budget, &o_fds, &mode, &top_done))
        return NULL;
    int has_dur = o_dur != Py_None;
    double duration = has_dur ? PyFloat_AsDouble(o_dur) : 0.0;
    if (has_dur && duration == -1.0 && PyErr_Occurred())
        return NULL;
    struct pollfd pfd[8];
    int nfd = 0;
    PyObject *seq = PySequence_Fast(o_fds, "fds: a sequence of descriptors");
    if (!seq)
        return NULL;
    for (Py_ssize_t i = 0; i < PySequence_Fast_GET_SIZE(seq) && nfd < 8; i++) {
        long fd = PyLong_AsLong(PySequence_Fast_GET_ITEM(seq, i));
        if (fd == -1 && PyErr_Occurred()) {
            Py_DECREF(seq);
            return NULL;
        }
        pfd[nfd].fd = (int)fd;
        pfd[nfd].events = POLLIN;
        pfd[nfd].revents = 0;
        nfd++;
    }
    Py_DECREF(seq);
    S *s = PyMem_Calloc(1, sizeof(S));
    if (!s)
        return PyErr_NoMemory();
    const char *why = "reference";
    double due_out = 0.0;
    PyObject *ret = NULL;
    int r = load(s, pump, mode);
    s->clock_live = 1;
    if (r < 0)
        goto done;
    if (r == 0) {
        hand_count[H_LOAD]++;
        goto out;
    }
    int loaded = 1;
    const double t_run0 = mono_now();
    const long long lim_fill = C_CAP - C_MAX_SAMPLES;
    int skip_top = top_done && s->has_last_cycle; /* the caller's loop did this iteration's top */
    while (1) {
        double now = mono_now();
        if (skip_top) {
            now = s->last_cycle_start;
            skip_top = 0;
            goto cycle_now;
        }
        if (has_dur && now - start >= duration) {
            why = "end";
            break;
        }
        if (s->has_last_cycle) {
            long long lf = s->fill + s->extra;
            if (lf > lim_fill)
                lf = lim_fill;
            /* Pump.run: a pause that left less than STALL_MARGIN_CYCLES cycles of the buffer */
            if (now - s->last_cycle_start > (double)lf / (double)C_RATE - STALL_MARGIN_CYCLES * s->period_s) {
                why = "stall"; /* (Pump.run counts it) */
                break;
            }
        }
        if (now - t_run0 >= budget) {
            why = "budget";
            break;
        }
        s->last_cycle_start = now;
        s->has_last_cycle = 1;
    cycle_now:;
        const double c0 = thread_now();
        PyObject *res = do_cycle(s, now, &loaded);
        if (!loaded) { /* handed over: the reference finished the cycle; Pump.run's tail ends it */
            if (!res) {
                if (!DeviceBusy || !PyErr_ExceptionMatches(DeviceBusy))
                    goto done;
                PyErr_Clear();
                if (add_dropped(pump) < 0)
                    goto done;
            }
            Py_XDECREF(res);
            PyObject *tail = PyObject_CallMethod(pump, "_end_cycle", "ddL", c0, start, k);
            if (!tail)
                goto done;
            if (!PyArg_ParseTuple(tail, "Ld", &k, &due_out)) {
                Py_DECREF(tail);
                goto done;
            }
            Py_DECREF(tail);
            why = "handed";
            goto out;
        }
        if (!res) /* (no memory for the count) */
            break;
        Py_DECREF(res);
        /* Pump._end_cycle */
        double *ring = (double *)s->ringbuf.buf;
        const Py_ssize_t rn = s->ringbuf.len / 8;
        ring[s->cycles % rn] = (thread_now() - c0) * 1e6;
        s->cycles++;
        k++;
        const double due = start + (double)k * s->period_s;
        now = mono_now();
        if (now > due) {
            const double late = (now - due) * 1e6;
            s->max_late_us = py_max(s->max_late_us, late);
            if (late > s->period_s * 0.5e6)
                s->deadline_misses++;
            k = (long long)((now - start) / s->period_s);
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
    if (PyErr_Occurred()) {
        store(s);
        goto done;
    }
    if (store(s) < 0)
        goto done;
out:
    ret = Py_BuildValue("(Lsd)", k, why, due_out);
done:
    if (s->pump)
        release(s);
    PyMem_Free(s);
    return ret;
}

static PyObject *fp_init(PyObject *self, PyObject *args) {
    PyObject *d, *busy, *dec, *cf;
    if (!PyArg_ParseTuple(args, "O!OOO", &PyDict_Type, &d, &busy, &dec, &cf))
        return NULL;
    struct {
        const char *key;
        long long *dst;
    } ll[] = {{"rate", &C_RATE}, {"buffer_capacity", &C_CAP}, {"max_frame", &C_MAX_FRAME}, {"max_gap_us", &C_MAX_GAP_US}};
    for (size_t i = 0; i < sizeof ll / sizeof ll[0]; i++) {
        PyObject *v = PyDict_GetItemString(d, ll[i].key);
        if (!v) {
            PyErr_Format(PyExc_KeyError, "init: %s", ll[i].key);
            return NULL;
        }
        *ll[i].dst = PyLong_AsLongLong(v);
    }
    struct {
        const char *key;
        int *dst;
    } ii[] = {{"status_id", &C_STATUS_ID}, {"samples_id", &C_SAMPLES_ID}, {"max_samples", &C_MAX_SAMPLES},
              {"running", &C_RUNNING}, {"small_batch", &C_SMALL_BATCH},
              {"cubic_min_readings", &C_CUBIC_MIN}};
    for (size_t i = 0; i < sizeof ii / sizeof ii[0]; i++) {
        PyObject *v = PyDict_GetItemString(d, ii[i].key);
        if (!v) {
            PyErr_Format(PyExc_KeyError, "init: %s", ii[i].key);
            return NULL;
        }
        *ii[i].dst = (int)PyLong_AsLong(v);
    }
    if (PyErr_Occurred())
        return NULL;
    PyObject *rs = PyDict_GetItemString(d, "report_size");
    if (!rs || PyLong_AsLong(rs) != REPORT_SIZE) {
        PyErr_SetString(PyExc_ValueError, "init: a report of 64 bytes expected");
        return NULL;
    }
    if (C_MAX_SAMPLES < 1 || 5 + 2 * C_MAX_SAMPLES > REPORT_SIZE || C_SMALL_BATCH > RC_MAX_N || C_RATE <= 0 ||
        C_CUBIC_MIN < 4) {
        PyErr_SetString(PyExc_ValueError, "init: constants out of range");
        return NULL;
    }
    Py_INCREF(busy);
    Py_XSETREF(DeviceBusy, busy);
    Py_INCREF(dec);
    Py_XSETREF(decode_fn, dec);
    Py_INCREF(cf);
    Py_XSETREF(codes_fn, cf);
    Py_RETURN_NONE;
}

static PyObject *fp_handovers(PyObject *self, PyObject *noargs) {
    PyObject *d = PyDict_New();
    PyObject *c = d ? PyLong_FromLongLong(compiled_count) : NULL;
    if (!c || PyDict_SetItemString(d, "compiled", c) < 0) {
        Py_XDECREF(c);
        Py_XDECREF(d);
        return NULL;
    }
    Py_DECREF(c);
    for (int i = 0; d && i < H_N; i++) {
        PyObject *v = PyLong_FromLongLong(hand_count[i]);
        if (!v || PyDict_SetItemString(d, H_NAMES[i], v) < 0) {
            Py_XDECREF(v);
            Py_CLEAR(d);
            break;
        }
        Py_DECREF(v);
    }
    return d;
}

static PyMethodDef methods[] = {
    {"handovers", fp_handovers, METH_NOARGS,
     "handovers() -> {cause: cycles handed to the reference, 'compiled': cycles done compiled}"},
    {"init", fp_init, METH_VARARGS, "init(consts, DeviceBusy, decode, codes_from_bytes)"},
    {"step", fp_step, METH_VARARGS, "step(pump, now_s | None, mode) -> samples sent: pump.step()"},
    {"run", fp_run, METH_VARARGS,
     "run(pump, start_s, k, duration_s | None, budget_s, fds, mode, top_done) -> (k, why, due_s): Pump.run's "
     "ordinary iterations (top_done: the caller began the first one: stall check, _last_cycle_start)"},
    {NULL, NULL, 0, NULL},
};

static struct PyModuleDef module = {
    PyModuleDef_HEAD_INIT, "_fastpump", "The host-rendering pump's steady-state cycle (see hostd/device/fastpump.py).",
    -1, methods, NULL, NULL, NULL, NULL,
};

PyMODINIT_FUNC PyInit__fastpump(void) {
#define INTERN(name)                                                                                      \
    if (!(N_##name = PyUnicode_InternFromString(#name)))                                                  \
        return NULL;
    NAMES(INTERN)
#undef INTERN
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
