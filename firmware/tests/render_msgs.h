/* Builders of the device renderer's messages (protocol v2), zero-padded like HID reports and
 * handed to fw_on_message: shared by the C tests and the QEMU per-tick bench. */
#ifndef HOSTD_RENDER_MSGS_H
#define HOSTD_RENDER_MSGS_H

#include <math.h>
#include <string.h>

#include "fw.h"
#include "fw_render.h"

static inline void put16(uint8_t *p, uint16_t v) { p[0] = (uint8_t)v, p[1] = (uint8_t)(v >> 8); }
static inline void put32(uint8_t *p, uint32_t v) {
    for (int i = 0; i < 4; i++) p[i] = (uint8_t)(v >> (8 * i));
}
static inline void putf(uint8_t *p, float v) {
    uint32_t u;
    memcpy(&u, &v, 4);
    put32(p, u);
}
static inline void rm_msg(fw_t *f, const uint8_t *m, size_t n) {
    uint8_t r[HP_REPORT_SIZE] = {0};
    memcpy(r, m, n);
    fw_on_message(f, r, HP_REPORT_SIZE); /* zero-padded like a HID report */
}

enum { CORRUPT_NONE, CORRUPT_CRC, CORRUPT_NAN, CORRUPT_INF, CORRUPT_TRUNCATE, CORRUPT_SKIP };

/* Upload coefficients c[0..n) as slot `slot` (LOAD_TEXTURE, LOAD_CHUNKs, LOAD_END). */
static inline void rm_upload(fw_t *f, uint8_t slot, const float *c, uint16_t n, uint16_t ns, uint32_t len_nm,
                             int corrupt) {
    uint8_t m[HP_REPORT_SIZE] = {HP_ID_LOAD_TEXTURE, slot};
    uint32_t crc = fw_crc32(0, (const uint8_t *)c, 4u * n); /* little-endian */
    put16(m + HP_LOAD_TEXTURE_OFF_N_SAMPLES, ns);
    put16(m + HP_LOAD_TEXTURE_OFF_N_COEFFS, n);
    put32(m + HP_LOAD_TEXTURE_OFF_LENGTH_NM, len_nm);
    putf(m + HP_LOAD_TEXTURE_OFF_SCALE, 1.0f);
    put32(m + HP_LOAD_TEXTURE_OFF_CRC32, corrupt == CORRUPT_CRC ? crc ^ 1u : crc);
    rm_msg(f, m, HP_LOAD_TEXTURE_SIZE);
    const unsigned per = HP_LOAD_CHUNK_MAX_COEFFS;
    for (unsigned first = 0, j = 0; first < n; first += per, j++) {
        unsigned k = n - first < per ? n - first : per;
        if (corrupt == CORRUPT_TRUNCATE && first + k >= n) break;
        if (corrupt == CORRUPT_SKIP && j == 1) continue;
        uint8_t ch[HP_REPORT_SIZE] = {HP_ID_LOAD_CHUNK, slot};
        put16(ch + HP_LOAD_CHUNK_OFF_FIRST, (uint16_t)first);
        ch[HP_LOAD_CHUNK_OFF_COUNT] = (uint8_t)k;
        for (unsigned i = 0; i < k; i++) putf(ch + HP_LOAD_CHUNK_SIZE + 4 * i, c[first + i]);
        if (corrupt == CORRUPT_NAN && j == 2) putf(ch + HP_LOAD_CHUNK_SIZE, NAN);
        if (corrupt == CORRUPT_INF && j == 2) putf(ch + HP_LOAD_CHUNK_SIZE + 4, -INFINITY);
        rm_msg(f, ch, HP_LOAD_CHUNK_SIZE + 4 * k);
    }
    uint8_t e[2] = {HP_ID_LOAD_END, slot};
    rm_msg(f, e, 2);
}
static inline void rm_set_scale(fw_t *f, float s) {
    uint8_t m[5] = {HP_ID_SET_SCALE};
    putf(m + 1, s);
    rm_msg(f, m, 5);
}
static inline void rm_set_delay(fw_t *f, int16_t us) {
    uint8_t m[3] = {HP_ID_SET_DELAY};
    put16(m + 1, (uint16_t)us);
    rm_msg(f, m, 3);
}
static inline void rm_set_band(fw_t *f, float fstop, float fade) {
    uint8_t m[9] = {HP_ID_SET_BAND};
    putf(m + 1, fstop);
    putf(m + 5, fade);
    rm_msg(f, m, 9);
}
static inline void rm_set_eq(fw_t *f, uint8_t idx, uint8_t n, float b0, float b1, float b2, float a1, float a2) {
    uint8_t m[HP_SET_EQ_SIZE] = {HP_ID_SET_EQ, idx, n};
    putf(m + HP_SET_EQ_OFF_B0, b0), putf(m + HP_SET_EQ_OFF_B1, b1), putf(m + HP_SET_EQ_OFF_B2, b2);
    putf(m + HP_SET_EQ_OFF_A1, a1), putf(m + HP_SET_EQ_OFF_A2, a2);
    rm_msg(f, m, sizeof m);
}
static inline void rm_start_render(fw_t *f, uint16_t lost_ms) {
    uint8_t m[3] = {HP_ID_START_RENDER};
    put16(m + 1, lost_ms);
    rm_msg(f, m, 3);
}

#endif
