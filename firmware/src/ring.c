/* Single-producer / single-consumer sample queue (see fw_ring_t in fw.h for who owns what).
 * C11 atomics: on a Cortex-M4 the acquire/release accesses compile to plain 16-bit loads and
 * stores with a DMB, so the samples written before a release store of `tail` are visible to
 * the tick that sees that `tail`, and a slot is reused only after the tick released it. */
#include "fw.h"

_Static_assert((HP_BUFFER_CAPACITY & (HP_BUFFER_CAPACITY - 1)) == 0 && HP_BUFFER_CAPACITY <= 32768,
               "the ring's free-running 16-bit indices need a power-of-two capacity <= 2^15");

#define MASK (HP_BUFFER_CAPACITY - 1u)

void fw_ring_init(fw_ring_t *r) {
    atomic_init(&r->head, 0);
    atomic_init(&r->tail, 0);
    atomic_init(&r->clear_to, 0);
    atomic_init(&r->clear_req, 0);
    atomic_init(&r->clear_ack, 0);
}

/* Consumer: apply a clear the producer asked for. clear_to is a tail the producer had
 * published before the request, so head only moves forward to it. */
static uint16_t consumer_head(fw_ring_t *r) {
    uint16_t head = atomic_load_explicit(&r->head, memory_order_relaxed);
    uint16_t req = atomic_load_explicit(&r->clear_req, memory_order_acquire);
    if (req != atomic_load_explicit(&r->clear_ack, memory_order_relaxed)) {
        uint16_t to = atomic_load_explicit(&r->clear_to, memory_order_relaxed);
        uint16_t tail = atomic_load_explicit(&r->tail, memory_order_acquire);
        /* forward only: a clear_to rewritten by a second request after `req` was read may be
         * one this side already applied and played past */
        if ((uint16_t)(to - head) <= (uint16_t)(tail - head)) {
            head = to;
            atomic_store_explicit(&r->head, head, memory_order_release);
        }
        atomic_store_explicit(&r->clear_ack, req, memory_order_release);
    }
    return head;
}

bool fw_ring_pop(fw_ring_t *r, int16_t *out) {
    uint16_t head = consumer_head(r);
    uint16_t tail = atomic_load_explicit(&r->tail, memory_order_acquire);
    if (tail == head) {
        return false;
    }
    *out = r->buf[head & MASK];
    atomic_store_explicit(&r->head, (uint16_t)(head + 1u), memory_order_release);
    return true;
}

void fw_ring_service(fw_ring_t *r) { (void)consumer_head(r); }

void fw_ring_clear(fw_ring_t *r) {
    (void)consumer_head(r);
    uint16_t tail = atomic_load_explicit(&r->tail, memory_order_acquire);
    atomic_store_explicit(&r->head, tail, memory_order_release);
}

uint16_t fw_ring_fill(const fw_ring_t *r) {
    uint16_t head = atomic_load_explicit(&r->head, memory_order_acquire);
    uint16_t ack = atomic_load_explicit(&r->clear_ack, memory_order_acquire);
    if (atomic_load_explicit(&r->clear_req, memory_order_acquire) != ack) {
        head = atomic_load_explicit(&r->clear_to, memory_order_relaxed);
    }
    uint16_t tail = atomic_load_explicit(&r->tail, memory_order_acquire);
    return (uint16_t)(tail - head);
}

bool fw_ring_push(fw_ring_t *r, const int16_t *v, uint16_t n) {
    uint16_t tail = atomic_load_explicit(&r->tail, memory_order_relaxed);
    uint16_t head = atomic_load_explicit(&r->head, memory_order_acquire);
    if ((uint32_t)(uint16_t)(tail - head) + n > HP_BUFFER_CAPACITY) {
        return false;
    }
    for (uint16_t i = 0; i < n; i++) {
        r->buf[(uint16_t)(tail + i) & MASK] = v[i];
    }
    atomic_store_explicit(&r->tail, (uint16_t)(tail + n), memory_order_release);
    return true;
}

void fw_ring_request_clear(fw_ring_t *r) {
    uint16_t tail = atomic_load_explicit(&r->tail, memory_order_relaxed);
    atomic_store_explicit(&r->clear_to, tail, memory_order_relaxed);
    atomic_fetch_add_explicit(&r->clear_req, 1u, memory_order_release);
}
