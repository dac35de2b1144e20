#include "fw_framing.h"

uint16_t fw_crc16(const uint8_t *p, size_t n) {
    uint16_t crc = 0xFFFF;
    for (size_t i = 0; i < n; i++) {
        crc ^= (uint16_t)((uint16_t)p[i] << 8);
        for (int b = 0; b < 8; b++) {
            uint32_t c = (uint32_t)crc << 1;
            crc = (uint16_t)((crc & 0x8000u) ? (c ^ 0x1021u) : c);
        }
    }
    return crc;
}

size_t fw_frame(const uint8_t *msg, size_t len, uint8_t *out, size_t cap) {
    uint8_t raw[HP_REPORT_SIZE + 2];
    if (len > HP_REPORT_SIZE) {
        return 0;
    }
    for (size_t i = 0; i < len; i++) {
        raw[i] = msg[i];
    }
    uint16_t crc = fw_crc16(msg, len);
    raw[len] = (uint8_t)(crc & 0xFF);
    raw[len + 1] = (uint8_t)(crc >> 8);
    size_t n = len + 2;
    /* COBS: worst case n + n/254 + 1 bytes, plus the delimiter */
    if (cap < n + n / 254 + 2) {
        return 0;
    }
    size_t code_at = 0, o = 1;
    uint8_t code = 1;
    for (size_t i = 0; i < n; i++) {
        if (raw[i] == 0) {
            out[code_at] = code;
            code_at = o++;
            code = 1;
        } else {
            out[o++] = raw[i];
            if (++code == 0xFF) {
                out[code_at] = code;
                code_at = o++;
                code = 1;
            }
        }
    }
    out[code_at] = code;
    out[o++] = 0;
    return o;
}

int fw_unframe(const uint8_t *body, size_t len, uint8_t *out, size_t cap) {
    size_t o = 0, i = 0;
    while (i < len) {
        uint8_t code = body[i++];
        if (code == 0) {
            return -1;
        }
        for (uint8_t k = 1; k < code; k++) {
            if (i >= len || body[i] == 0 || o >= cap) {
                return -1;
            }
            out[o++] = body[i++];
        }
        if (code != 0xFF && i < len) {
            if (o >= cap) {
                return -1;
            }
            out[o++] = 0;
        }
    }
    if (o < 3) {
        return -1;
    }
    uint16_t crc = (uint16_t)(out[o - 2] | (out[o - 1] << 8));
    if (fw_crc16(out, o - 2) != crc) {
        return -1;
    }
    return (int)(o - 2);
}
