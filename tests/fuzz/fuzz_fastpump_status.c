/* libFuzzer (clang -fsanitize=fuzzer,address,undefined) on the compiled host-rendering cycle's
 * reading of the device's STATUS reports (hostd/device/_fastpump.c: take_status: the fields,
 * the fault, reset, gap and glitch checks, the device clock's unwrapping, the encoder's position,
 * the motion window and its fit, the flow control's acknowledgements, the health counters),
 * built into this harness with its whole source. The input is a sequence of reports: each of
 * 8 input bytes either steps the previous report as a display would (1 ms on, the encoder a few
 * counts, a sample played, an acknowledgement) with fuzzer-chosen deviations (faults, clock
 * leaps and wraps, counter jumps, encoder jumps, other ids, garbage after the layout), or is the
 * display's next report cut or lengthened to 20..35 bytes and XORed with the next input bytes. take_status's state carries from report to report
 * as in a run of the cycle (a report it hands to the reference leaves it as it was).
 *
 * Checked after every report: no sanitizer report; a message that is not a STATUS of at least 26
 * bytes with zeros after them is handed over and changes nothing; an accepted one's fields are
 * those of a plain little-endian reading, and the state stays within its bounds (the motion
 * window within 1..win readings, finite fit coefficients, a speed at most max_speed, the
 * unacknowledged batches within their array). The motion fit's weights come from a cache
 * filled here for 1 ms spacing (the cycle's Python side fills it the same way).
 * Build and run: tests/fuzz/run_fuzzers.sh.
 */
#include "../../hostd/device/_fastpump.c"

#include <stdio.h>
#include <stdlib.h>

#define WIN 32
#define STATUS_ID HP_ID_STATUS

static PyObject *g_mcache;

int LLVMFuzzerInitialize(int *argc, char ***argv) {
    (void)argc;
    (void)argv;
    Py_InitializeEx(0);
    C_CUBIC_MIN = 24;
    g_mcache = PyDict_New();
    for (long long n = 2; n <= WIN; n++)
        for (long long order = 1; order <= 3; order++) {
            PyObject *rows = PyTuple_New(order + 1);
            for (long long j = 0; j <= order; j++) {
                PyObject *row = PyList_New(n);
                for (long long i = 0; i < n; i++) /* finite weights; their values do not matter here */
                    PyList_SET_ITEM(row, i, PyFloat_FromDouble((double)(i + 1 - j) / (double)(n * n)));
                PyTuple_SET_ITEM(rows, j, row);
            }
            PyObject *key = Py_BuildValue("(LLL)", n, 1000LL, order);
            PyDict_SetItem(g_mcache, key, rows);
            Py_DECREF(key);
            Py_DECREF(rows);
        }
    return 0;
}

static void put16(unsigned char *p, long long v) {
    p[0] = (unsigned char)(v & 0xFF);
    p[1] = (unsigned char)((v >> 8) & 0xFF);
}

static void put32(unsigned char *p, long long v) {
    for (int i = 0; i < 4; i++)
        p[i] = (unsigned char)((v >> (8 * i)) & 0xFF);
}

static long long get(const unsigned char *p, int n) {
    long long v = 0;
    for (int i = n - 1; i >= 0; i--)
        v = (v << 8) | p[i];
    return v;
}

static void check(int ok, const char *what) {
    if (!ok) {
        fprintf(stderr, "take_status: %s\n", what);
        abort();
    }
}

int LLVMFuzzerTestOneInput(const uint8_t *data, size_t size) {
    static S s;
    static hs_pump_t P;
    static hs_pump_stats_t PS;
    static hs_link_t L;
    static hs_link_stats_t LS;
    static hs_health_t H;
    static hs_position_t Z;
    static hs_motion_t M;
    memset(&s, 0, sizeof s);
    memset(&P, 0, sizeof P);
    memset(&PS, 0, sizeof PS);
    memset(&L, 0, sizeof L);
    memset(&LS, 0, sizeof LS);
    memset(&H, 0, sizeof H);
    memset(&Z, 0, sizeof Z);
    memset(&M, 0, sizeof M);
    s.P = &P, s.PS = &PS, s.L = &L, s.LS = &LS, s.H = &H, s.Z = &Z, s.M = &M; /* the stages' records */
    s.mcache = g_mcache;
    M._window = WIN;
    M._order = 3;
    M._glitch_um = 20.0;
    M._rest_speed_mm_s = 0.5;
    M._rest_hold_um = 2.0;
    M._max_predict_s = 0.02;
    M._max_gap_s = 0.05;
    M._max_speed_mm_s = 2000.0;
    Z.um_per_count = 0.4;
    M._n = 1; /* the reference's window starts with a reading (motion.update after a restart) */
    s.wkey_n = s.wkey_dt = s.wkey_order = -1;
    P._fill = 12;
    P._base_fill = 12;
    P._low_fill = 1 << 30;
    memset(hand_count, 0, sizeof hand_count);
    /* the display's counters, stepped as it would */
    long long us = 0, enc = 0, played = 0, seq = 0, under = 0; /* as the last report (s.ls) says */
    double now = 100.0;
    msg_t m;
    size_t at = 0;
    while (at < size) {
        const uint8_t op = data[at++];
        if ((op & 0x0F) == 0x0F) { /* the display's next report, 20 + (op >> 4) bytes long, XOR the input */
            us += 1000;
            played += 1;
            memset(m.b, 0, sizeof m.b);
            m.b[0] = STATUS_ID;
            m.b[1] = 1;
            put32(m.b + 4, us);
            put32(m.b + 8, enc);
            put32(m.b + 12, played);
            put16(m.b + 18, seq);
            put16(m.b + 20, under);
            m.n = 20 + (op >> 4);
            for (Py_ssize_t i = 0; i < m.n && at < size; i++)
                m.b[i] ^= data[at++];
        } else {
            unsigned char d[7] = {0};
            size_t n = size - at < 7 ? size - at : 7;
            memcpy(d, data + at, n);
            at += n;
            us += (op & 1) ? (long long)get(d, 4) : 1000; /* a leap, a wrap, or 1 ms */
            enc += (op & 2) ? (long long)(int32_t)get(d, 4) : (int8_t)d[4];
            played += (op & 4) ? (long long)get(d + 2, 4) : (d[5] & 1);
            under += (op & 8) ? d[6] : 0;
            seq += d[5] >> 4;
            memset(m.b, 0, sizeof m.b);
            m.b[0] = (op & 0x30) == 0x30 ? d[6] : STATUS_ID; /* now and then another id */
            m.b[1] = (unsigned char)(d[6] % 4);              /* idle, running, ramping down, rendering */
            put16(m.b + 2, (op & 0xC0) == 0xC0 ? d[5] : 0);  /* fault flags */
            put32(m.b + 4, us);
            put32(m.b + 8, enc);
            put32(m.b + 12, played);
            put16(m.b + 16, d[4]);
            put16(m.b + 18, seq);
            put16(m.b + 20, under);
            m.n = HP_STATUS_SIZE + ((op & 0x40) && (op & 0x80) == 0 ? (d[3] & 7) : 0);
            if ((op & 0xF0) == 0x70 && m.n > HP_STATUS_SIZE)
                m.b[m.n - 1] = 1; /* garbage after the layout */
        }
        now += 1e-3;
        const long long statuses = LS.statuses;
        const int r = take_status(&s, &m, now);
        check(r == 0 || r == 1, "an error (a Python exception)");
        int padded = 0;
        for (Py_ssize_t i = HP_STATUS_SIZE; i < m.n; i++)
            padded |= m.b[i] != 0;
        if (m.n < HP_STATUS_SIZE || m.b[0] != STATUS_ID || padded)
            check(r == 0 && LS.statuses == statuses, "a message that is not a STATUS was taken");
        if (r == 1) {
            const unsigned char *p = m.b;
            check(s.ls.state == p[1] && s.ls.fault_flags == get(p + 2, 2) && s.ls.device_time_us == get(p + 4, 4) &&
                      s.ls.encoder_count == get(p + 8, 4) && s.ls.samples_played == get(p + 12, 4) &&
                      s.ls.buffer_fill == get(p + 16, 2) && s.ls.last_seq == get(p + 18, 2) &&
                      s.ls.underruns == get(p + 20, 2),
                  "the fields differ from a little-endian reading");
            check(LS.statuses == statuses + 1, "an accepted report not counted");
        }
        check(M._n >= 1 && M._n <= M._window, "the motion window out of 1..win");
        check(isfinite(M._c0) && isfinite(M._c1) && isfinite(M._c2) && isfinite(M._c3), "a fit that is not finite");
        check(fabs(M._c1) <= M._max_speed_mm_s, "a speed past max_speed");
        check(L._un_n >= 0 && L._un_n <= MAX_UNACKED, "the unacknowledged batches out of their array");
        check(isfinite(L.device_time_s), "a device time that is not finite");
    }
    return 0;
}
