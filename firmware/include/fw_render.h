/* Device-side rendering (protocol v2): the firmware evaluates the texture at its own encoder.
 *
 * Per 3 kHz tick, in float32 (a Cortex-M4F's FPU), no dynamic memory:
 *   position   the quadrature count plus sub-count interpolation from edge times: an edge
 *              into count c moving +1 happens on the boundary c - 1/2 (c + 1/2 moving -1), so
 *              the position at the last edge is exact; since then the hand moved v * dt,
 *              kept inside the current count's cell (no further edge was seen);
 *   speed      from edge times: boundary positions over the edges of the last 1 ms (at least
 *              the previous edge), bounded by "less than one count since the last edge";
 *   delay      the position is extrapolated by the actuator chain's delay (SET_DELAY);
 *   series     h = sum_k g_k(v) C'_k cos(k phi), phi = pi x / L + pi / (2N), by a rotation
 *              recurrence z_{k+1} = z_k e^{i phi} (4 mul + 2 add per component, plus 1 mul +
 *              1 add to accumulate); components in the band limit's raised-cosine fade also
 *              rotate their gain's phasor (6 more flops + 2 for the gain); components above
 *              f_stop are skipped. The phase of the integer position is exact in 0.64 fixed
 *              point (64-bit), so a hand far from the origin loses no precision;
 *   crossfade  a texture committed while rendering replaces the old one over xfade_ticks;
 *   equalizer  up to max_sections biquads (transposed direct form II);
 *   envelope   fade in on START_RENDER, fade out on STOP_RENDER and on a lost host;
 * then the core's safety stage (limits, slew) as for streamed samples.
 *
 * A lost host in device mode: the host is lost when it has sent no valid message for
 * host_lost_ms (START_RENDER's field, default HP_RENDER_DEFAULT_HOST_LOST_MS; the v1 50 ms
 * stream timeout does not apply while rendering). A lost host does NOT stop the texture while
 * the hand moves (STATUS flags HOST_LOST): the device fades out only once the encoder has
 * also been still (within +-2 counts) for HP_RENDER_STILL_MS, then goes idle (flag
 * HOST_TIMEOUT). A message from the host before that clears the lost state. */
#ifndef HOSTD_FW_RENDER_H
#define HOSTD_FW_RENDER_H

#include <stdbool.h>
#include <stddef.h>
#include <stdint.h>

#include "fw_encoder.h"
#include "hostd_proto.h"

typedef struct {
    float c[HP_RENDER_MAX_COMPONENTS]; /* C'_k x scale, µm */
    uint16_t n;                        /* N' */
    uint16_t n_samples;                /* N */
    uint32_t length_nm;                /* L */
    uint64_t dphase_half;              /* turns per half count, 0.64 fixed point */
    float turns_per_half;              /* the same as a float (for the sub-count part) */
    float offset_turns;                /* 1 / (4N): the series' half-sample phase */
    float hz_per_mm_s;                 /* f_1 per |v|: 1 / (2L) in 1/mm */
    uint8_t slot;
    bool valid;
} fw_texture_t;

typedef struct {
    float b0, b1, b2, a1, a2, z0, z1;
} fw_biquad_t;

typedef struct {
    fw_texture_t tex[3]; /* active, incoming (crossfade) and staging (upload) */
    uint8_t active, next, staging;
    /* upload in progress */
    bool loading;
    uint16_t received;
    uint32_t crc, crc_want;
    float load_scale;
    /* parameters */
    fw_biquad_t eq[HP_RENDER_MAX_SECTIONS];
    uint8_t n_eq;
    fw_biquad_t eq_stage[HP_RENDER_MAX_SECTIONS];
    uint8_t n_eq_staged, n_eq_want;
    float f_stop_hz, f_pass_hz;
    float codes_per_um;
    float delay_edge; /* chain delay in edge-clock units */
    uint16_t host_lost_ms;
    /* state */
    bool on;          /* rendering */
    float env, env_target;
    uint16_t xfade;   /* 0 = no crossfade, else ticks into it */
    bool host_lost;
    /* encoder */
    fw_edges_t edges;
    int64_t still_anchor;
    uint32_t still_since_us;
    /* reported */
    float speed_mm_s;
    float last_um;    /* the equalized, enveloped displacement of the last tick */
    uint16_t refused, loads;
    uint16_t host_lost_count; /* episodes of a lost host while rendering (wraps) */
    uint32_t rendered_ticks;  /* ticks rendering the texture at full gain (wraps) */
    uint32_t faded_ticks;     /* ticks rendering below full gain: fading in or out (wraps) */
} fw_render_t;

struct fw;

void fw_render_init(struct fw *f);
/* A render message (ids 0x20..0x2f). Returns true when it was well formed (acted on or
 * refused with a NAK), false when it was malformed (dropped and counted). */
bool fw_render_on_message(struct fw *f, const uint8_t *m, size_t len);
/* The rendered target code of this tick (before the core's safety stage). */
int32_t fw_render_tick(struct fw *f);
/* Rendering ends at once (v1 START or STOP while rendering: the core's ramps take over). */
void fw_render_halt(struct fw *f);
/* After IDENT: the render capabilities. */
void fw_render_send_caps(const struct fw *f);
/* CRC-32 (IEEE 802.3, reflected 0xEDB88320, as zlib): crc = fw_crc32(crc, p, n), start at 0. */
uint32_t fw_crc32(uint32_t crc, const uint8_t *p, size_t n);

#endif
