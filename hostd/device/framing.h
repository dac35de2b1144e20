/* The serial link's framing, decoded (COBS(message + CRC-16 LE) + 0x00, docs/protocol.md), for
 * the compiled modules that take frames off a byte stream: _fastpump.c (the host-rendering
 * cycle) and _fastlink.c (device mode's deframing). Reference: hostd.device.protocol.Deframer
 * (cobs.decode, binascii.crc_hqx). Include after Python.h (Py_ssize_t). */
#ifndef HOSTD_FRAMING_H
#define HOSTD_FRAMING_H

#include <stdint.h>
#include <string.h>

/* CRC-16/CCITT-FALSE = binascii.crc_hqx(p, 0xFFFF) */
static inline uint16_t crc16(const unsigned char *p, Py_ssize_t n) {
    uint16_t c = 0xFFFF;
    for (Py_ssize_t i = 0; i < n; i++) {
        c ^= (uint16_t)(p[i] << 8);
        for (int b = 0; b < 8; b++)
            c = (c & 0x8000) ? (uint16_t)((c << 1) ^ 0x1021) : (uint16_t)(c << 1);
    }
    return c;
}

/* cobs.decode of one frame body of n > 0 bytes (the delimiter cut it: no zero byte in it); out
 * holds n bytes (COBS never lengthens); returns the length or -1 (cobs.DecodeError) */
static inline Py_ssize_t cobs_decode(const unsigned char *in, Py_ssize_t n, unsigned char *out) {
    Py_ssize_t i = 0, k = 0;
    while (1) {
        unsigned len = in[i];
        if (len == 0)
            return -1;
        i++;
        Py_ssize_t end = i + len - 1;
        if (end > n)
            return -1;
        memcpy(out + k, in + i, (size_t)(end - i));
        k += end - i;
        i = end;
        if (i < n) {
            if (len < 0xFF)
                out[k++] = 0;
        } else
            break;
    }
    return k;
}

#endif
