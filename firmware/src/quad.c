/* 4x quadrature decoding. Gray sequence forward: 00 -> 01 -> 11 -> 10 -> 00 (A = bit1). */
#include "fw.h"

/* index (prev << 2) | cur: +1, -1, 0 (no change), 2 = illegal (both pins changed) */
static const int8_t STEP[16] = {0, 1, -1, 2, -1, 0, 2, 1, 1, 2, 0, -1, 2, -1, 1, 0};

void fw_quad_init(fw_quad_t *q, uint8_t ab) {
    q->ab = ab & 3u;
    q->count = 0;
    q->errors = 0;
    q->primed = true;
}

void fw_quad_update(fw_quad_t *q, uint8_t ab) {
    ab &= 3u;
    int8_t s = STEP[(q->ab << 2) | ab];
    if (s == 2) {
        q->errors++; /* a missed edge: direction unknown, count left alone */
    } else {
        q->count += (uint32_t)(int32_t)s; /* wraps modulo 2^32 */
    }
    q->ab = ab;
}
