/* libFuzzer (clang -fsanitize=fuzzer,address,undefined) on the serial deframer of the compiled
 * host-rendering cycle (hostd/device/_fastpump.c: deframe, keep_msg; the firmware's fw_unframe), built
 * into this harness with its whole source, differential against a plain reference written here
 * after hostd/device/protocol.py's Deframer (cobs.decode, CRC-16/CCITT-FALSE, resync when more
 * than 4 x MAX_FRAME bytes hold no delimiter). The input is cut into reads of at most READ_SIZE
 * bytes (as SerialTransport reads them); every read, both give the same messages in the same
 * order and the same bad-frame count. Build and run: tests/fuzz/run_fuzzers.sh.
 */
#include "../../hostd/device/_fastpump.c"

#include <stdio.h>
#include <stdlib.h>

#define REF_MAX_FRAME (64 + 8) /* protocol.Deframer.MAX_FRAME = REPORT_SIZE + 8 */

static unsigned char ref_buf[8 * READ_SIZE];
static size_t ref_len;
static long long ref_bad;

/* the textbook COBS decoder (cobs-python's semantics): -1 on a zero code or a block past the end */
static long ref_cobs(const unsigned char *in, size_t n, unsigned char *out) {
    size_t i = 0, k = 0;
    while (i < n) {
        unsigned code = in[i++];
        if (code == 0)
            return -1;
        for (unsigned j = 1; j < code; j++) {
            if (i >= n)
                return -1;
            out[k++] = in[i++];
        }
        if (code < 0xFF && i < n)
            out[k++] = 0;
    }
    return (long)k;
}

static uint16_t ref_crc(const unsigned char *p, size_t n) { /* table-free, bit-reflected-free form */
    uint32_t c = 0xFFFF;
    for (size_t i = 0; i < n; i++)
        for (int b = 7; b >= 0; b--) {
            uint32_t bit = ((p[i] >> b) & 1) ^ ((c >> 15) & 1);
            c = ((c << 1) & 0xFFFF) ^ (bit ? 0x1021 : 0);
        }
    return (uint16_t)c;
}

typedef struct {
    unsigned char b[2 * READ_SIZE];
    size_t n;
} ref_msg;
static ref_msg ref_out[4 * READ_SIZE];

static int ref_feed(const unsigned char *d, size_t n) {
    int nm = 0;
    memcpy(ref_buf + ref_len, d, n);
    ref_len += n;
    while (1) {
        unsigned char *z = memchr(ref_buf, 0, ref_len);
        if (!z) {
            if (ref_len > 4 * REF_MAX_FRAME) {
                ref_len = 0;
                ref_bad++;
            }
            return nm;
        }
        size_t len = (size_t)(z - ref_buf);
        static unsigned char raw[8 * READ_SIZE];
        long m = len ? ref_cobs(ref_buf, len, raw) : 0;
        memmove(ref_buf, z + 1, ref_len - len - 1);
        ref_len -= len + 1;
        if (len == 0)
            continue;
        if (m < 3 || ref_crc(raw, (size_t)m - 2) != (uint16_t)(raw[m - 2] | (raw[m - 1] << 8))) {
            ref_bad++;
            continue;
        }
        memcpy(ref_out[nm].b, raw, (size_t)m - 2);
        ref_out[nm].n = (size_t)m - 2;
        nm++;
    }
}

int LLVMFuzzerInitialize(int *argc, char ***argv) {
    (void)argc;
    (void)argv;
    Py_InitializeEx(0);
    _Static_assert(FW_FRAME_MAX == REF_MAX_FRAME, "the reference's MAX_FRAME");
    return 0;
}

int LLVMFuzzerTestOneInput(const uint8_t *data, size_t size) {
    static S s; /* only the deframer's fields are used */
    PyMem_Free(s.dbuf);
    Py_CLEAR(s.overflow);
    memset(&s, 0, sizeof s);
    s.dcap = 2 * READ_SIZE; /* as load() sets it up from the reference's empty buffer */
    s.dbuf = PyMem_Malloc((size_t)s.dcap);
    ref_len = 0;
    ref_bad = 0;
    size_t at = 0;
    while (at < size) {
        /* a read: its length from two input bytes, at most READ_SIZE */
        size_t n = 1;
        if (at + 2 <= size) {
            n = ((size_t)data[at] | ((size_t)data[at + 1] << 8)) % READ_SIZE + 1;
            at += 2;
        }
        if (n > size - at)
            n = size - at;
        if (n == 0) /* a read of 0 bytes is no data (the cycle never feeds it) */
            break;
        int nm = 0;
        if (deframe(&s, data + at, (Py_ssize_t)n, g_msgs, &nm) < 0)
            abort();
        int rm = ref_feed(data + at, n);
        at += n;
        Py_ssize_t extra = s.overflow ? PyList_GET_SIZE(s.overflow) : 0;
        if (nm + extra != rm || s.bad_frames != ref_bad) {
            fprintf(stderr, "divergence: compiled %d+%zd messages, %lld bad; reference %d, %lld bad\n", nm,
                    (ssize_t)extra, s.bad_frames, rm, ref_bad);
            abort();
        }
        for (int i = 0; i < rm; i++) {
            const unsigned char *b;
            Py_ssize_t bn;
            if (i < nm) {
                b = g_msgs[i].b;
                bn = g_msgs[i].n;
            } else {
                PyObject *o = PyList_GET_ITEM(s.overflow, i - nm);
                b = (const unsigned char *)PyBytes_AS_STRING(o);
                bn = PyBytes_GET_SIZE(o);
            }
            if ((size_t)bn != ref_out[i].n || memcmp(b, ref_out[i].b, (size_t)bn) != 0) {
                fprintf(stderr, "divergence: message %d differs\n", i);
                abort();
            }
        }
        Py_CLEAR(s.overflow);
    }
    return 0;
}
