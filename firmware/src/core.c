/* The device core: message handling, playout tick and the safety stage.
 *
 * Safety holds whatever the host sends: every code written to the DAC satisfies
 *   |code| <= limit_code <= HP_LIMIT_CODE   and   |code - previous| <= max_step_code <= HP_MAX_STEP_CODE,
 * the output ramps to zero on underrun, on host timeout and on STOP, and a malformed
 * message is dropped and counted, never acted on. The hard limits (HP_LIMIT_CODE,
 * HP_MAX_STEP_CODE) always hold; a displacement limit that the host tightens below the present
 * output is reached at the slew limit, since a jump to it would break the slew limit. */
#include <string.h>

#include "fw.h"
#include "hal.h"

static uint16_t rd16(const uint8_t *p) { return (uint16_t)(p[0] | (p[1] << 8)); }
static void wr16(uint8_t *p, uint16_t v) {
    p[0] = (uint8_t)v;
    p[1] = (uint8_t)(v >> 8);
}
static void wr32(uint8_t *p, uint32_t v) {
    for (int i = 0; i < 4; i++) {
        p[i] = (uint8_t)(v >> (8 * i));
    }
}

void fw_init(fw_t *f, uint8_t encoder_ab) {
    memset(f, 0, sizeof *f);
    fw_ring_init(&f->ring);
    fw_quad_init(&f->quad, encoder_ab);
    f->state = HP_STATE_IDLE;
    f->limit_code = HP_LIMIT_CODE;
    f->max_step_code = HP_MAX_STEP_CODE;
    f->timeout_ms = HP_DEFAULT_TIMEOUT_MS;
    f->last_rx_us = hal_time_us();
    fw_render_init(f);
}

static bool zero_tail(const uint8_t *m, size_t from, size_t len) {
    for (size_t i = from; i < len; i++) {
        if (m[i] != 0) {
            return false;
        }
    }
    return true;
}

void fw_on_message(fw_t *f, const uint8_t *m, size_t len) {
    if (len == 0 || len > HP_REPORT_SIZE) {
        f->malformed++;
        return;
    }
    size_t need;
    switch (m[0]) {
    case HP_ID_SAMPLES:
        if (len < HP_SAMPLES_SIZE || m[HP_SAMPLES_OFF_COUNT] > HP_MAX_SAMPLES) {
            f->malformed++;
            return;
        }
        need = HP_SAMPLES_SIZE + 2u * m[HP_SAMPLES_OFF_COUNT];
        break;
    case HP_ID_START: need = HP_START_SIZE; break;
    case HP_ID_STOP: need = HP_STOP_SIZE; break;
    case HP_ID_SET_LIMITS: need = HP_SET_LIMITS_SIZE; break;
    case HP_ID_SET_TIMEOUT: need = HP_SET_TIMEOUT_SIZE; break;
    case HP_ID_IDENTIFY: need = HP_IDENTIFY_SIZE; break;
    default:
        if (fw_render_on_message(f, m, len)) { /* v2 render messages; counts its own malformed */
            f->last_rx_us = hal_time_us();
        }
        return;
    }
    if (len < need || !zero_tail(m, need, len)) {
        f->malformed++;
        return;
    }
    switch (m[0]) {
    case HP_ID_SAMPLES: {
        if (m[HP_SAMPLES_OFF_FLAGS] != 0) { /* no flags defined in version 1 */
            f->malformed++;
            return;
        }
        int16_t v[HP_MAX_SAMPLES];
        uint8_t n = m[HP_SAMPLES_OFF_COUNT];
        for (uint8_t i = 0; i < n; i++) {
            v[i] = (int16_t)rd16(m + HP_SAMPLES_SIZE + 2u * i);
        }
        if (!fw_ring_push(&f->ring, v, n)) {
            f->faults |= HP_FAULT_OVERFLOW;
        }
        f->last_seq = rd16(m + HP_SAMPLES_OFF_SEQ);
        break;
    }
    case HP_ID_START:
        fw_render_halt(f);
        f->state = HP_STATE_RUNNING;
        f->in_underrun = false;
        break;
    case HP_ID_STOP:
        if (f->state == HP_STATE_RUNNING || f->state == HP_STATE_RENDERING) {
            f->state = HP_STATE_RAMP_DOWN;
        }
        fw_render_halt(f);
        fw_ring_request_clear(&f->ring); /* producer side: the tick drops them */
        break;
    case HP_ID_SET_LIMITS: {
        uint16_t lim = rd16(m + HP_SET_LIMITS_OFF_LIMIT_CODE);
        uint16_t step = rd16(m + HP_SET_LIMITS_OFF_MAX_STEP_CODE);
        if (step == 0) {
            f->malformed++;
            return;
        }
        /* the host may only tighten the hard limits */
        f->limit_code = lim < HP_LIMIT_CODE ? lim : HP_LIMIT_CODE;
        f->max_step_code = step < HP_MAX_STEP_CODE ? step : HP_MAX_STEP_CODE;
        break;
    }
    case HP_ID_SET_TIMEOUT: {
        uint16_t t = rd16(m + HP_SET_TIMEOUT_OFF_TIMEOUT_MS);
        if (t == 0) {
            f->malformed++;
            return;
        }
        f->timeout_ms = t;
        break;
    }
    case HP_ID_IDENTIFY: {
        uint8_t out[HP_IDENT_SIZE];
        hal_send(out, fw_build_ident(f, out));
        fw_render_send_caps(f);
        break;
    }
    default:
        break;
    }
    f->last_rx_us = hal_time_us();
}

void fw_deframer_feed(fw_t *f, const uint8_t *bytes, size_t n) {
    fw_deframer_t *d = &f->rx;
    for (size_t i = 0; i < n; i++) {
        uint8_t b = bytes[i];
        if (b != 0) {
            if (d->len < sizeof d->buf) {
                d->buf[d->len++] = b;
            } else {
                d->overflow = true;
            }
            continue;
        }
        if (d->len > 0 || d->overflow) {
            uint8_t msg[HP_REPORT_SIZE + 2];
            int m = d->overflow ? -1 : fw_unframe(d->buf, d->len, msg, sizeof msg);
            if (m < 0 || m > HP_REPORT_SIZE) {
                f->malformed++;
            } else {
                fw_on_message(f, msg, (size_t)m);
            }
        }
        d->len = 0;
        d->overflow = false;
    }
}

static int32_t toward_zero(int32_t v) {
    const int32_t step = HP_LIMIT_CODE / HP_RAMP_TICKS > 0 ? HP_LIMIT_CODE / HP_RAMP_TICKS : 1;
    if (v > step) return v - step;
    if (v < -step) return v + step;
    return 0;
}

void fw_tick(fw_t *f) {
    f->ticks++;
    fw_ring_service(&f->ring);
    uint32_t now = hal_time_us();
    if (f->state == HP_STATE_RUNNING && (uint32_t)(now - f->last_rx_us) > (uint32_t)f->timeout_ms * 1000u) {
        f->state = HP_STATE_RAMP_DOWN;
        f->faults |= HP_FAULT_HOST_TIMEOUT;
        fw_ring_clear(&f->ring);
    }
    int32_t target = 0;
    f->played = false;
    if (f->state == HP_STATE_RUNNING) {
        int16_t s;
        if (fw_ring_pop(&f->ring, &s)) {
            target = s;
            f->in_underrun = false;
            f->samples_played++;
            f->played = true;
        } else {
            if (!f->in_underrun) {
                f->underruns++;
                f->in_underrun = true;
            }
            f->faults |= HP_FAULT_UNDERRUN;
            target = toward_zero(f->out);
        }
    } else if (f->state == HP_STATE_RENDERING) {
        target = fw_render_tick(f);
    } else if (f->state == HP_STATE_RAMP_DOWN) {
        target = toward_zero(f->out);
        f->idle_ticks++;
        if (target == 0) {
            f->state = HP_STATE_IDLE;
        }
    } else {
        target = toward_zero(f->out); /* idle: hold zero (slowly back to it if not there) */
        f->idle_ticks++;
    }
    /* safety stage: displacement limit, then slew limit */
    const int32_t lim = f->limit_code, step = f->max_step_code;
    if (target > lim) {
        target = lim;
        f->faults |= HP_FAULT_CLIPPED;
    } else if (target < -lim) {
        target = -lim;
        f->faults |= HP_FAULT_CLIPPED;
    }
    const int32_t d = target - (int32_t)f->out;
    if (d > step) {
        target = f->out + step;
        f->faults |= HP_FAULT_SLEWED;
    } else if (d < -step) {
        target = f->out - step;
        f->faults |= HP_FAULT_SLEWED;
    }
    f->out = (int16_t)target;
    hal_dac_write(f->out);
    /* while the device renders itself the host only supervises: a STATUS with each
     * RENDER_STATUS is enough, and lets the host sleep (docs/protocol.md) */
    const uint32_t period = f->state == HP_STATE_RENDERING ? HP_RENDER_STATUS_PERIOD_TICKS : HP_STATUS_PERIOD_TICKS;
    if (f->ticks % period == 0) {
        uint8_t msg[HP_STATUS_SIZE];
        hal_send(msg, fw_build_status(f, msg));
        f->faults &= (uint16_t)~rd16(msg + HP_STATUS_OFF_FAULT_FLAGS); /* atomic: keeps new bits */
    }
}

size_t fw_build_status(const fw_t *f, uint8_t *o) {
    memset(o, 0, HP_STATUS_SIZE);
    o[HP_STATUS_OFF_ID] = HP_ID_STATUS;
    o[HP_STATUS_OFF_STATE] = f->state;
    wr16(o + HP_STATUS_OFF_FAULT_FLAGS, f->faults);
    wr32(o + HP_STATUS_OFF_DEVICE_TIME_US, hal_time_us());
    wr32(o + HP_STATUS_OFF_ENCODER_COUNT, f->quad.count);
    wr32(o + HP_STATUS_OFF_SAMPLES_PLAYED, f->samples_played);
    wr16(o + HP_STATUS_OFF_BUFFER_FILL, fw_ring_fill(&f->ring));
    wr16(o + HP_STATUS_OFF_LAST_SEQ, f->last_seq);
    wr16(o + HP_STATUS_OFF_UNDERRUNS, f->underruns);
    wr16(o + HP_STATUS_OFF_MALFORMED, f->malformed);
    wr16(o + HP_STATUS_OFF_ENCODER_ERRORS, f->quad.errors);
    return HP_STATUS_SIZE;
}

size_t fw_build_ident(const fw_t *f, uint8_t *o) {
    memset(o, 0, HP_IDENT_SIZE);
    o[HP_IDENT_OFF_ID] = HP_ID_IDENT;
    wr16(o + HP_IDENT_OFF_PROTOCOL_VERSION, HP_VERSION);
    o[HP_IDENT_OFF_FW_MAJOR] = HP_FW_VERSION_MAJOR;
    o[HP_IDENT_OFF_FW_MINOR] = HP_FW_VERSION_MINOR;
    o[HP_IDENT_OFF_FW_PATCH] = HP_FW_VERSION_PATCH;
    o[HP_IDENT_OFF_DAC_BITS] = HP_DAC_BITS;
    wr32(o + HP_IDENT_OFF_SAMPLE_RATE_HZ, HP_SAMPLE_RATE_HZ);
    wr16(o + HP_IDENT_OFF_LIMIT_CODE, f->limit_code);
    wr16(o + HP_IDENT_OFF_MAX_STEP_CODE, f->max_step_code);
    wr16(o + HP_IDENT_OFF_BUFFER_CAPACITY, HP_BUFFER_CAPACITY);
    o[HP_IDENT_OFF_MAX_SAMPLES] = HP_MAX_SAMPLES;
    wr16(o + HP_IDENT_OFF_UM_PER_COUNT_NM, HP_UM_PER_COUNT_NM);
    return HP_IDENT_SIZE;
}
