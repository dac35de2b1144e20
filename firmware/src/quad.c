/* The encoder (include/fw_encoder.h): 4x quadrature decoding, Gray sequence forward
 * 00 -> 01 -> 11 -> 10 -> 00 (A = bit1), and the edge times the renderer measures from. */
#include <math.h>
#include <string.h>

#include "fw_encoder.h"

#define STALE_EDGE ((uint32_t)HP_RENDER_EDGE_CLOCK_HZ / 10u) /* 100 ms without an edge: at rest */

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

void fw_edges_init(fw_edges_t *e, uint32_t count) {
    memset(e, 0, sizeof *e);
    e->last_count = count;
}

void fw_edges_track(fw_edges_t *e, uint32_t count, uint32_t t) {
    int32_t d = (int32_t)(count - e->last_count);
    if (d == 0) return;
    e->last_count = count;
    e->pos += d;
    e->e_head = (uint8_t)((e->e_head + 1u) % FW_EDGE_RING);
    e->eb[e->e_head] = 2 * e->pos - (d > 0 ? 1 : -1); /* the boundary crossed, in half counts */
    e->et[e->e_head] = t;
    if (e->e_n < FW_EDGE_RING) e->e_n++;
}

void fw_edges_estimate(fw_edges_t *e, uint32_t now, int64_t *b0, float *p, float *v) {
    *v = 0.0f;
    *p = 0.0f;
    if (e->e_n == 0) {
        *b0 = 2 * e->pos;
        return;
    }
    const uint8_t h = e->e_head;
    *b0 = e->eb[h];
    const int64_t center = 2 * e->pos; /* the current count's cell centre */
    const float dir = center > *b0 ? 1.0f : -1.0f;
    const uint32_t since = now - e->et[h];
    if (since > STALE_EDGE && since < 0x80000000u) { /* at rest: the cell's centre */
        *p = dir;
        e->e_n = 1;
        return;
    }
    if (e->e_n >= 2) {
        const uint32_t t0 = e->et[h];
        unsigned k = 1;
        while (k + 1u < e->e_n && (uint32_t)(t0 - e->et[(h + FW_EDGE_RING - (k + 1u)) % FW_EDGE_RING]) <= FW_SPEED_WINDOW) {
            k++;
        }
        const unsigned i = (h + FW_EDGE_RING - k) % FW_EDGE_RING;
        const uint32_t dt = t0 - e->et[i];
        if (dt > 0 && dt < 0x80000000u) *v = (float)(*b0 - e->eb[i]) / (float)dt;
    }
    const float s = since < 0x80000000u ? (float)since : 0.0f; /* an edge stamped after the tick: 0 */
    if (fabsf(*v) * s > 2.0f) *v = (*v > 0.0f ? 2.0f : -2.0f) / s; /* < 1 count since the edge */
    float q = *v * s;
    /* stay inside the cell: between the boundary crossed and the next one ahead */
    if (dir > 0.0f) q = q < 0.0f ? 0.0f : (q > 2.0f ? 2.0f : q);
    else q = q > 0.0f ? 0.0f : (q < -2.0f ? -2.0f : q);
    *p = q;
}
