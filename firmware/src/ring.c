#include "fw.h"

#include <string.h>

void fw_ring_clear(fw_ring_t *r) {
    r->head = 0;
    r->count = 0;
}

bool fw_ring_push(fw_ring_t *r, const int16_t *v, uint16_t n) {
    if ((uint32_t)r->count + n > HP_BUFFER_CAPACITY) {
        return false;
    }
    for (uint16_t i = 0; i < n; i++) {
        r->buf[(r->head + r->count + i) % HP_BUFFER_CAPACITY] = v[i];
    }
    r->count = (uint16_t)(r->count + n);
    return true;
}

bool fw_ring_pop(fw_ring_t *r, int16_t *out) {
    if (r->count == 0) {
        return false;
    }
    *out = r->buf[r->head];
    r->head = (uint16_t)((r->head + 1) % HP_BUFFER_CAPACITY);
    r->count--;
    return true;
}
