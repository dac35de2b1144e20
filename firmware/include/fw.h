/* hostd firmware core: protocol, ring buffer, 3 kHz playout, quadrature, safety.
 * C11, no dynamic memory, no registers (see hal.h). One fw_t per display. */
#ifndef HOSTD_FW_H
#define HOSTD_FW_H

#include <stdatomic.h>
#include <stdbool.h>
#include <stddef.h>
#include <stdint.h>

#include "hostd_proto.h"
#include "fw_framing.h" /* fw_crc16, fw_frame, fw_unframe, FW_FRAME_MAX */
#include "fw_encoder.h"
#include "fw_render.h"

/* The sample queue between message handling (the producer: the USB interrupt on a chip) and
 * the 3 kHz tick (the consumer: a higher-priority timer interrupt). A single-producer /
 * single-consumer ring with no shared counter: `tail` is written only by the producer and
 * `head` only by the consumer; both run freely modulo 2^16 and index the buffer modulo its
 * capacity (a power of two dividing 2^16), so the fill is tail - head. The producer publishes
 * samples with a release store of `tail` after writing them; the consumer reads them after an
 * acquire load of `tail` and hands the slots back with a release store of `head`.
 * A clear asked for by the producer (STOP) must not write `head`: the producer publishes the
 * tail to drop up to (`clear_to`, then bumps `clear_req`), and the consumer moves `head` there
 * on its next pop or clear and acknowledges (`clear_ack`); fw_ring_fill counts from `clear_to`
 * meanwhile. Until then the producer still counts the dropped samples as queued (conservative:
 * it never overwrites a slot in use). The request counter is 16 bits: 65,536 STOPs within one
 * tick would be needed to lose one. */
typedef struct {
    int16_t buf[HP_BUFFER_CAPACITY];
    _Atomic uint16_t head;      /* consumer: next to pop */
    _Atomic uint16_t tail;      /* producer: next free slot */
    _Atomic uint16_t clear_to;  /* producer: drop everything before this tail */
    _Atomic uint16_t clear_req; /* producer: clears asked for (wraps) */
    _Atomic uint16_t clear_ack; /* consumer: clears applied (wraps) */
} fw_ring_t;

void fw_ring_init(fw_ring_t *r); /* before either side runs */
/* Consumer side (the tick). */
bool fw_ring_pop(fw_ring_t *r, int16_t *out);
void fw_ring_clear(fw_ring_t *r); /* drop everything queued */
/* Samples that will play (a pending clear applied); safe from either side. */
uint16_t fw_ring_fill(const fw_ring_t *r);
/* Producer side (message handling). */
bool fw_ring_push(fw_ring_t *r, const int16_t *v, uint16_t n); /* all or nothing */
void fw_ring_request_clear(fw_ring_t *r); /* drop what is queued now; applied by the consumer */
/* Consumer: apply a pending clear now (every tick, so that a STOP frees the buffer within one
 * tick even while the device is idle and pops nothing: the host re-primes right after STOP). */
void fw_ring_service(fw_ring_t *r);

typedef struct fw fw_t;

typedef struct {
    uint8_t buf[FW_FRAME_MAX];
    size_t len;
    bool overflow;
} fw_deframer_t;

/* Concurrency on a chip: fw_tick runs in a timer interrupt that pre-empts message handling
 * (fw_on_message in the USB interrupt), never the reverse. The samples travel through the
 * SPSC ring; the other fields both sides touch are _Atomic: `faults` is set by both and the
 * tick clears only the bits it reported; `state`, the limits, the timeout and `last_rx_us` are
 * written by message handling and read by the tick whole (each limit is safe on its own, so a
 * tick between the two stores of SET_LIMITS sees one new and one old limit, both in range). */
struct fw {
    fw_ring_t ring;
    fw_quad_t quad;
    fw_deframer_t rx;
    _Atomic uint8_t state;
    _Atomic uint16_t faults;     /* sticky bits, cleared when a STATUS reports them */
    int16_t out;                 /* last code written to the DAC */
    _Atomic uint16_t limit_code; /* <= HP_LIMIT_CODE */
    _Atomic uint16_t max_step_code;
    _Atomic uint16_t timeout_ms;
    uint32_t ticks;
    uint32_t samples_played;
    _Atomic uint32_t last_rx_us;
    uint16_t last_seq;
    uint16_t underruns;
    uint16_t malformed;
    uint32_t idle_ticks; /* ticks neither playing nor rendering (RENDER_STATUS) */
    bool in_underrun;
    bool played; /* the last tick's code came from the buffer (for logs and tests) */
    fw_render_t render; /* protocol v2: device-side rendering (render.c) */
};

void fw_init(fw_t *f, uint8_t encoder_ab);
/* One complete message from the host: parsed, validated, acted on or dropped and counted. */
void fw_on_message(fw_t *f, const uint8_t *msg, size_t len);
/* Raw serial bytes: deframed, each good frame handed to fw_on_message, bad ones counted. */
void fw_deframer_feed(fw_t *f, const uint8_t *bytes, size_t n);
/* The 3 kHz playout tick: one DAC sample, safety, and a STATUS every HP_STATUS_PERIOD_TICKS. */
void fw_tick(fw_t *f);
/* Builders (also used by tests). Return the message length. */
size_t fw_build_status(const fw_t *f, uint8_t *out);
size_t fw_build_ident(const fw_t *f, uint8_t *out);

#endif
