/* The encoder: 4x quadrature decoding, and the edge times the device renderer measures the
 * hand's position and speed from (src/quad.c). Its own header, so that the core (fw.h: STATUS
 * reports the count and the illegal transitions) and the renderer (fw_render.h) both depend on
 * it and neither reaches into the other's state for it. No dependency on fw.h (struct fw is
 * only named). */
#ifndef HOSTD_FW_ENCODER_H
#define HOSTD_FW_ENCODER_H

#include <stdbool.h>
#include <stdint.h>

#include "hostd_proto.h"

typedef struct {
    uint8_t ab;      /* last A/B state, bit1 = A, bit0 = B */
    uint32_t count;  /* 32-bit, wraps */
    uint16_t errors; /* illegal transitions (both pins changed at once) */
    bool primed;
} fw_quad_t;

void fw_quad_init(fw_quad_t *q, uint8_t ab);
void fw_quad_update(fw_quad_t *q, uint8_t ab);

#define FW_EDGE_PER_TICK (HP_RENDER_EDGE_CLOCK_HZ / HP_SAMPLE_RATE_HZ) /* 4000 */
#define FW_EDGE_RING 64u
#define FW_SPEED_WINDOW (HP_RENDER_EDGE_CLOCK_HZ / 1000) /* 1 ms of edge clock */

/* The latest edges with their times: the boundary each crossed (an edge into count c moving
 * +1 happens on c - 1/2, moving -1 on c + 1/2), in half counts, and its edge-clock time. */
typedef struct {
    int64_t pos;        /* unwrapped count */
    uint32_t last_count; /* the quadrature count already taken in */
    int64_t eb[FW_EDGE_RING];
    uint32_t et[FW_EDGE_RING];
    uint8_t e_head; /* newest edge */
    uint8_t e_n;    /* edges stored */
} fw_edges_t;

void fw_edges_init(fw_edges_t *e, uint32_t count);
/* Take in the quadrature count reached at edge-clock time t (the edges since the last call). */
void fw_edges_track(fw_edges_t *e, uint32_t count, uint32_t t);
/* Position at edge-clock time now: the boundary b0 (half counts) of the last edge plus p half
 * counts (kept inside the current cell), and the speed v in half counts per edge-clock tick:
 * boundary positions over the edges of the last 1 ms (at least the previous edge), bounded by
 * "less than one count since the last edge"; after 100 ms without an edge the hand rests in
 * the cell's centre. */
void fw_edges_estimate(fw_edges_t *e, uint32_t now, int64_t *b0, float *p, float *v);

/* The port's entry points (src/encoder.c): they take the whole device state (struct fw, fw.h),
 * so that neither the core nor the renderer calls the other for the encoder.
 * fw_encoder_pins: the A/B pin state on every pin change (or polled fast); an illegal
 * transition sets HP_FAULT_ENCODER. Edges given this way are seen by the renderer at the next
 * tick's time. fw_encoder_edge: the same with the edge's capture time (edge clock,
 * HP_RENDER_EDGE_CLOCK_HZ; tick k of fw_tick, counting from 1, is at (k - 1) * FW_EDGE_PER_TICK). */
struct fw;
void fw_encoder_pins(struct fw *f, uint8_t ab);
void fw_encoder_edge(struct fw *f, uint8_t ab, uint32_t t_edge);

#endif
