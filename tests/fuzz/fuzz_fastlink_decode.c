/* libFuzzer (clang -fsanitize=fuzzer,address,undefined) on the compiled decoder of fixed-layout
 * device messages (hostd/device/_fastlink.c: decode_fixed), built into this harness with its whole
 * source, differential against a plain reference written here after hostd/device/protocol.py's
 * decode (struct.unpack '<' of the layout; the message at least as long as the layout and zero
 * after it, else declined). The layout (field codes B H I b h i f, up to 16) comes from the input,
 * then the message bytes. Build and run: tests/fuzz/run_fuzzers.sh.
 */
#include "../../hostd/device/_fastlink.c"

#include <math.h>
#include <stdlib.h>

static const char CODES[] = "BHIbhif";

static double ref_field(char c, const unsigned char *p) {
    uint32_t u = 0;
    int n = (c == 'B' || c == 'b') ? 1 : (c == 'H' || c == 'h') ? 2 : 4;
    for (int i = 0; i < n; i++)
        u |= (uint32_t)p[i] << (8 * i);
    switch (c) {
    case 'B': case 'H': case 'I': return (double)u;
    case 'b': return (double)(int8_t)u;
    case 'h': return (double)(int16_t)u;
    case 'i': return (double)(int32_t)u;
    default: {
        float f;
        memcpy(&f, &u, 4);
        return (double)f;
    }
    }
}

int LLVMFuzzerInitialize(int *argc, char ***argv) {
    (void)argc;
    (void)argv;
    Py_InitializeEx(0);
    return 0;
}

int LLVMFuzzerTestOneInput(const uint8_t *data, size_t size) {
    if (size < 1)
        return 0;
    int nf = data[0] % 17;
    if (size < 1 + (size_t)nf)
        return 0;
    char fmt[17];
    size_t need = 0;
    for (int i = 0; i < nf; i++) {
        fmt[i] = CODES[data[1 + i] % 7];
        need += (fmt[i] == 'B' || fmt[i] == 'b') ? 1 : (fmt[i] == 'H' || fmt[i] == 'h') ? 2 : 4;
    }
    const unsigned char *msg = data + 1 + nf;
    size_t mlen = size - 1 - nf;
    PyObject *names = PyTuple_New(nf);
    for (int i = 0; i < nf; i++)
        PyTuple_SET_ITEM(names, i, PyUnicode_FromFormat("f%d", i));
    PyObject *args = Py_BuildValue("(y#y#O)", (const char *)msg, (Py_ssize_t)mlen, fmt, (Py_ssize_t)nf, names);
    PyObject *out = fl_decode_fixed(NULL, args);
    if (!out)
        abort(); /* a valid layout never raises */
    int declines = mlen < need;
    for (size_t i = need; !declines && i < mlen; i++)
        declines = msg[i] != 0;
    if (declines != (out == Py_None))
        abort();
    if (!declines) {
        if (PyDict_GET_SIZE(out) != nf)
            abort();
        size_t off = 0;
        for (int i = 0; i < nf; i++) {
            PyObject *v = PyDict_GetItem(out, PyTuple_GET_ITEM(names, i));
            double want = ref_field(fmt[i], msg + off);
            double got = PyFloat_Check(v) ? PyFloat_AS_DOUBLE(v) : PyLong_AsDouble(v);
            if (!(got == want || (isnan(got) && isnan(want))) || PyFloat_Check(v) != (fmt[i] == 'f'))
                abort();
            off += (fmt[i] == 'B' || fmt[i] == 'b') ? 1 : (fmt[i] == 'H' || fmt[i] == 'h') ? 2 : 4;
        }
    }
    Py_DECREF(out);
    Py_DECREF(args);
    Py_DECREF(names);
    return 0;
}
