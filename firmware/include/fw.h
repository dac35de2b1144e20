/* hostd firmware core: protocol, ring buffer, 3 kHz playout, quadrature, safety.
 * C11, no dynamic memory, no registers (see hal.h). One fw_t per display. */
#ifndef HOSTD_FW_H
#define HOSTD_FW_H

#include <stdbool.h>
#include <stddef.h>
#include <stdint.h>

#include "hostd_proto.h"
#include "fw_render.h"

typedef struct {
    int16_t buf[HP_BUFFER_CAPACITY];
    uint16_t head; /* next to pop */
    uint16_t count;
} fw_ring_t;

void fw_ring_clear(fw_ring_t *r);
bool fw_ring_push(fw_ring_t *r, const int16_t *v, uint16_t n); /* all or nothing */
bool fw_ring_pop(fw_ring_t *r, int16_t *out);

typedef struct {
    uint8_t ab;      /* last A/B state, bit1 = A, bit0 = B */
    uint32_t count;  /* 32-bit, wraps */
    uint16_t errors; /* illegal transitions (both pins changed at once) */
    bool primed;
} fw_quad_t;

void fw_quad_init(fw_quad_t *q, uint8_t ab);
void fw_quad_update(fw_quad_t *q, uint8_t ab);

/* Serial framing: COBS(msg + CRC16/CCITT-FALSE LE) + 0x00 */
uint16_t fw_crc16(const uint8_t *p, size_t n);
/* Returns the frame length (delimiter included), 0 if out is too small. */
size_t fw_frame(const uint8_t *msg, size_t len, uint8_t *out, size_t cap);
/* Decodes one frame body (without the 0x00 delimiter); returns the message length or -1. */
int fw_unframe(const uint8_t *body, size_t len, uint8_t *out, size_t cap);

#define FW_FRAME_MAX (HP_REPORT_SIZE + 8)

typedef struct fw fw_t;

typedef struct {
    uint8_t buf[FW_FRAME_MAX];
    size_t len;
    bool overflow;
} fw_deframer_t;

struct fw {
    fw_ring_t ring;
    fw_quad_t quad;
    fw_deframer_t rx;
    uint8_t state;
    uint16_t faults;     /* sticky bits, cleared when a STATUS is sent */
    int16_t out;         /* last code written to the DAC */
    uint16_t limit_code; /* <= HP_LIMIT_CODE */
    uint16_t max_step_code;
    uint16_t timeout_ms;
    uint32_t ticks;
    uint32_t samples_played;
    uint32_t last_rx_us;
    uint16_t last_seq;
    uint16_t underruns;
    uint16_t malformed;
    bool in_underrun;
    bool played; /* the last tick's code came from the buffer (for logs and tests) */
    fw_render_t render; /* protocol v2: device-side rendering (render.c) */
};

void fw_init(fw_t *f, uint8_t encoder_ab);
/* One complete message from the host: parsed, validated, acted on or dropped and counted. */
void fw_on_message(fw_t *f, const uint8_t *msg, size_t len);
/* Raw serial bytes: deframed, each good frame handed to fw_on_message, bad ones counted. */
void fw_deframer_feed(fw_t *f, const uint8_t *bytes, size_t n);
void fw_encoder_pins(fw_t *f, uint8_t ab);
/* The 3 kHz playout tick: one DAC sample, safety, and a STATUS every HP_STATUS_PERIOD_TICKS. */
void fw_tick(fw_t *f);
/* Builders (also used by tests). Return the message length. */
size_t fw_build_status(const fw_t *f, uint8_t *out);
size_t fw_build_ident(const fw_t *f, uint8_t *out);

#endif
