/* Device-side rendering (protocol v2); the design is described in include/fw_render.h.
 *
 * Uploads and parameters are validated before anything changes: a refused message (bad CRC,
 * N' out of range, a NaN or Inf, a chunk that is not the next one, a truncated sequence, an
 * unstable equalizer section ...) is answered with ACK(result != OK), counted in `refused`
 * and flagged REFUSED in the next STATUS, and leaves the output exactly as it was. */
#include <math.h>
#include <string.h>

#include "fw.h"
#include "hal.h"

#define XF_TICKS HP_RENDER_XFADE_TICKS
/* speed: half counts per edge-clock tick -> mm/s */
#define MM_S_PER_HALF ((float)(HP_UM_PER_COUNT_NM * 1e-6 / 2.0 * HP_RENDER_EDGE_CLOCK_HZ))
#define TWO_PI_F 6.28318530717958647692f
#define PI_F 3.14159265358979323846f

static uint16_t rd16(const uint8_t *p) { return (uint16_t)(p[0] | (p[1] << 8)); }
static uint32_t rd32(const uint8_t *p) {
    return (uint32_t)p[0] | ((uint32_t)p[1] << 8) | ((uint32_t)p[2] << 16) | ((uint32_t)p[3] << 24);
}
static float rdf(const uint8_t *p) {
    uint32_t u = rd32(p);
    float v;
    memcpy(&v, &u, sizeof v);
    return v;
}
static void wr16(uint8_t *p, uint16_t v) {
    p[0] = (uint8_t)v;
    p[1] = (uint8_t)(v >> 8);
}
static void wr32(uint8_t *p, uint32_t v) {
    for (int i = 0; i < 4; i++) p[i] = (uint8_t)(v >> (8 * i));
}
static bool zero_tail(const uint8_t *m, size_t from, size_t len) {
    for (size_t i = from; i < len; i++) {
        if (m[i] != 0) return false;
    }
    return true;
}

uint32_t fw_crc32(uint32_t crc, const uint8_t *p, size_t n) {
    crc = ~crc;
    for (size_t i = 0; i < n; i++) {
        crc ^= p[i];
        for (int b = 0; b < 8; b++) crc = (crc >> 1) ^ (0xEDB88320u & (0u - (crc & 1u)));
    }
    return ~crc;
}

static void reply(fw_t *f, uint8_t for_id, uint8_t slot, uint8_t result, uint16_t detail) {
    fw_render_t *r = &f->render;
    if (result != HP_RESULT_OK) {
        r->refused++;
        f->faults |= HP_FAULT_REFUSED;
    }
    uint8_t o[HP_ACK_SIZE];
    memset(o, 0, sizeof o);
    o[HP_ACK_OFF_ID] = HP_ID_ACK;
    o[HP_ACK_OFF_FOR_ID] = for_id;
    o[HP_ACK_OFF_SLOT] = slot;
    o[HP_ACK_OFF_RESULT] = result;
    wr16(o + HP_ACK_OFF_DETAIL, detail);
    wr16(o + HP_ACK_OFF_REFUSED, r->refused);
    hal_send(o, sizeof o);
}

void fw_render_init(fw_t *f) {
    fw_render_t *r = &f->render;
    memset(r, 0, sizeof *r);
    r->active = 0, r->next = 1, r->staging = 2;
    r->f_stop_hz = 400.0f; /* min(display band 400 Hz, 0.8 x Nyquist): the host's default */
    r->f_pass_hz = 0.8f * 400.0f;
    r->codes_per_um = (float)HP_LIMIT_CODE / 40.0f; /* +-40 um at the hard limit */
    r->host_lost_ms = HP_RENDER_DEFAULT_HOST_LOST_MS;
    fw_edges_init(&r->edges, f->quad.count);
    r->still_since_us = hal_time_us();
}

void fw_render_send_caps(const fw_t *f) {
    (void)f;
    uint8_t o[HP_CAPS_SIZE];
    memset(o, 0, sizeof o);
    o[HP_CAPS_OFF_ID] = HP_ID_CAPS;
    o[HP_CAPS_OFF_RENDER] = 1;
    wr16(o + HP_CAPS_OFF_MAX_COMPONENTS, HP_RENDER_MAX_COMPONENTS);
    o[HP_CAPS_OFF_MAX_SECTIONS] = HP_RENDER_MAX_SECTIONS;
    o[HP_CAPS_OFF_CHUNK_COEFFS] = HP_RENDER_CHUNK_COEFFS;
    wr32(o + HP_CAPS_OFF_EDGE_CLOCK_HZ, HP_RENDER_EDGE_CLOCK_HZ);
    wr16(o + HP_CAPS_OFF_XFADE_TICKS, HP_RENDER_XFADE_TICKS);
    hal_send(o, sizeof o);
}

/* ------------------------------------------------------------------ encoder */
/* edges the port gave without a time (fw_encoder_pins) are seen at time t */
static void track(fw_t *f, uint32_t t) { fw_edges_track(&f->render.edges, f->quad.count, t); }

/* ------------------------------------------------------------------ series */
static float phase_turns(const fw_texture_t *t, int64_t b0, float pf) {
    const uint64_t ph = (uint64_t)b0 * t->dphase_half; /* mod 2^64: whole turns drop out */
    const float hi = (float)(uint32_t)(ph >> 32) * 2.3283064365386963e-10f;
    float phi = hi + pf * t->turns_per_half + t->offset_turns;
    return phi - floorf(phi);
}

static float series(const fw_texture_t *t, float phi, float vabs, float f_pass, float f_stop) {
    const float th = TWO_PI_F * phi;
    const float wr = cosf(th), wi = sinf(th);
    const int n = t->n;
    int n_pass = n, n_end = n;
    const float f1 = vabs * t->hz_per_mm_s; /* Hz of component 1 at this speed */
    if (f1 > 0.0f) {
        const float kp = f_pass / f1, ks = f_stop / f1;
        if (kp < (float)n) n_pass = (int)kp;                      /* k <= kp: gain 1 */
        if (ks < (float)n + 1.0f) n_end = (int)ceilf(ks) - 1;     /* k < ks: in the band */
        if (n_pass > n_end) n_pass = n_end;
    }
    const float *c = t->c;
    float zr = wr, zi = wi, acc = 0.0f;
    int k = 1;
    for (; k <= n_pass; k++) {
        acc += c[k - 1] * zr;
        const float nr = zr * wr - zi * wi;
        zi = zr * wi + zi * wr;
        zr = nr;
    }
    if (k <= n_end) { /* raised-cosine fade: gain 0.5 (1 + cos(pi (f_k - f_pass) / (f_stop - f_pass))) */
        const float span = f_stop - f_pass;
        const float a0 = PI_F * ((float)k * f1 - f_pass) / span, b = PI_F * f1 / span;
        float gr = cosf(a0), gi = sinf(a0);
        const float br = cosf(b), bi = sinf(b);
        for (; k <= n_end; k++) {
            acc += c[k - 1] * (0.5f + 0.5f * gr) * zr;
            const float nr = zr * wr - zi * wi;
            zi = zr * wi + zi * wr;
            zr = nr;
            const float ng = gr * br - gi * bi;
            gi = gr * bi + gi * br;
            gr = ng;
        }
    }
    return acc;
}

static float equalize(fw_render_t *r, float x) {
    for (unsigned s = 0; s < r->n_eq; s++) {
        fw_biquad_t *q = &r->eq[s];
        const float y = q->b0 * x + q->z0;
        q->z0 = q->b1 * x - q->a1 * y + q->z1;
        q->z1 = q->b2 * x - q->a2 * y;
        if (fabsf(q->z0) < 1e-30f) q->z0 = 0.0f; /* no subnormal state (slow, and pointless) */
        if (fabsf(q->z1) < 1e-30f) q->z1 = 0.0f;
        x = y;
    }
    return x;
}

static void eq_reset(fw_render_t *r) {
    for (unsigned s = 0; s < HP_RENDER_MAX_SECTIONS; s++) r->eq[s].z0 = r->eq[s].z1 = 0.0f;
}

static void swap_u8(uint8_t *a, uint8_t *b) {
    uint8_t t = *a;
    *a = *b;
    *b = t;
}

void fw_render_halt(fw_t *f) {
    fw_render_t *r = &f->render;
    if (r->xfade) { /* the newest texture wins */
        swap_u8(&r->active, &r->next);
        r->xfade = 0;
    }
    r->on = false;
    r->env = r->env_target = 0.0f;
    r->host_lost = false;
}

int32_t fw_render_tick(fw_t *f) {
    fw_render_t *r = &f->render;
    const uint32_t now = (f->ticks - 1u) * (uint32_t)FW_EDGE_PER_TICK; /* this tick's instant */
    const uint32_t now_us = hal_time_us();
    track(f, now); /* edges the port gave without a time (fw_encoder_pins) */
    /* a lost host: keep rendering while the hand moves; fade out once it is also still */
    int64_t moved = r->edges.pos - r->still_anchor;
    if (moved > 2 || moved < -2) {
        r->still_anchor = r->edges.pos;
        r->still_since_us = now_us;
    }
    const bool lost = (uint32_t)(now_us - f->last_rx_us) > (uint32_t)r->host_lost_ms * 1000u;
    if (lost && !r->host_lost) r->host_lost_count++; /* a new episode */
    r->host_lost = lost;
    if (r->host_lost) {
        f->faults |= HP_FAULT_HOST_LOST;
        if ((uint32_t)(now_us - r->still_since_us) >= (uint32_t)HP_RENDER_STILL_MS * 1000u && r->env_target > 0.0f) {
            r->env_target = 0.0f;
            f->faults |= HP_FAULT_HOST_TIMEOUT;
        }
    }
    int64_t b0;
    float p, v;
    fw_edges_estimate(&r->edges, now, &b0, &p, &v);
    const float pf = p + v * r->delay_edge; /* felt position: ahead by the chain's delay */
    const float vabs = fabsf(v) * MM_S_PER_HALF;
    r->speed_mm_s = v * MM_S_PER_HALF;
    const fw_texture_t *ta = &r->tex[r->active];
    float h = series(ta, phase_turns(ta, b0, pf), vabs, r->f_pass_hz, r->f_stop_hz);
    if (r->xfade) {
        const fw_texture_t *tn = &r->tex[r->next];
        const float h2 = series(tn, phase_turns(tn, b0, pf), vabs, r->f_pass_hz, r->f_stop_hz);
        const float a = (float)r->xfade / (float)XF_TICKS;
        h = h + a * (h2 - h);
        if (++r->xfade > XF_TICKS) {
            swap_u8(&r->active, &r->next);
            r->xfade = 0;
        }
    }
    float y = equalize(r, h);
    if (r->env < r->env_target) {
        r->env = fminf(r->env + 1.0f / (float)HP_RAMP_TICKS, r->env_target);
    } else if (r->env > r->env_target) {
        r->env = fmaxf(r->env - 1.0f / (float)HP_RAMP_TICKS, r->env_target);
    }
    y *= r->env;
    if (r->env >= 1.0f) { /* the device's own account of what it rendered (RENDER_STATUS) */
        r->rendered_ticks++;
    } else {
        r->faded_ticks++;
    }
    if (f->ticks % HP_RENDER_STATUS_PERIOD_TICKS == 0) {
        uint8_t o[HP_RENDER_STATUS_SIZE];
        memset(o, 0, sizeof o);
        o[HP_RENDER_STATUS_OFF_ID] = HP_ID_RENDER_STATUS;
        o[HP_RENDER_STATUS_OFF_RENDER_STATE] = (uint8_t)(r->env_target == 0.0f ? HP_RSTATE_FADE_OUT
                                                         : r->xfade ? HP_RSTATE_CROSSFADE
                                                         : r->env < 1.0f ? HP_RSTATE_FADE_IN : HP_RSTATE_ON);
        o[HP_RENDER_STATUS_OFF_ACTIVE_SLOT] = r->tex[r->active].slot;
        o[HP_RENDER_STATUS_OFF_HOST_LOST] = r->host_lost;
        memcpy(o + HP_RENDER_STATUS_OFF_SPEED_MM_S, &r->speed_mm_s, 4); /* little-endian ports */
        wr16(o + HP_RENDER_STATUS_OFF_REFUSED, r->refused);
        wr16(o + HP_RENDER_STATUS_OFF_LOADS, r->loads);
        uint32_t silent_ms = (now_us - f->last_rx_us) / 1000u;
        wr16(o + HP_RENDER_STATUS_OFF_HOST_SILENT_MS, (uint16_t)(silent_ms > 0xFFFFu ? 0xFFFFu : silent_ms));
        wr16(o + HP_RENDER_STATUS_OFF_HOST_LOST_COUNT, r->host_lost_count);
        wr32(o + HP_RENDER_STATUS_OFF_DEVICE_TIME_US, now_us);
        wr32(o + HP_RENDER_STATUS_OFF_RENDERED_TICKS, r->rendered_ticks);
        wr32(o + HP_RENDER_STATUS_OFF_FADED_TICKS, r->faded_ticks);
        wr32(o + HP_RENDER_STATUS_OFF_IDLE_TICKS, f->idle_ticks);
        hal_send(o, sizeof o);
    }
    if (r->env == 0.0f && r->env_target == 0.0f) { /* faded out: idle */
        fw_render_halt(f);
        f->state = HP_STATE_IDLE;
    }
    const float code = y * r->codes_per_um;
    if (!isfinite(code)) { /* cannot happen with validated inputs; never reaches the DAC */
        eq_reset(r);
        r->last_um = 0.0f;
        return f->out;
    }
    r->last_um = y;
    return (int32_t)lrintf(fminf(fmaxf(code, -32768.0f), 32767.0f));
}

/* ------------------------------------------------------------------ messages */
static bool finite4(float a, float b, float c, float d) {
    return isfinite(a) && isfinite(b) && isfinite(c) && isfinite(d);
}

/* the phase step per half count, q / (4 L) turns, in 0.64 fixed point (bitwise long division) */
static uint64_t phase_step(uint32_t length_nm) {
    const uint64_t d = 4ull * length_nm;
    uint64_t rem = HP_UM_PER_COUNT_NM, q = 0;
    for (int i = 0; i < 64; i++) {
        rem <<= 1;
        q <<= 1;
        if (rem >= d) {
            rem -= d;
            q |= 1u;
        }
    }
    return q;
}

static void load_texture(fw_t *f, const uint8_t *m) {
    fw_render_t *r = &f->render;
    const uint8_t slot = m[HP_LOAD_TEXTURE_OFF_SLOT];
    const uint16_t ns = rd16(m + HP_LOAD_TEXTURE_OFF_N_SAMPLES), nc = rd16(m + HP_LOAD_TEXTURE_OFF_N_COEFFS);
    const uint32_t len_nm = rd32(m + HP_LOAD_TEXTURE_OFF_LENGTH_NM);
    const float scale = rdf(m + HP_LOAD_TEXTURE_OFF_SCALE);
    r->loading = false; /* a new header abandons any upload in progress */
    if (nc == 0 || nc > HP_RENDER_MAX_COMPONENTS || ns == 0 || len_nm < HP_UM_PER_COUNT_NM ||
        len_nm > HP_RENDER_MAX_LENGTH_NM) {
        reply(f, HP_ID_LOAD_TEXTURE, slot, HP_RESULT_TOO_LARGE, nc);
        return;
    }
    if (!isfinite(scale)) {
        reply(f, HP_ID_LOAD_TEXTURE, slot, HP_RESULT_NONFINITE, 0);
        return;
    }
    fw_texture_t *t = &r->tex[r->staging];
    t->valid = false;
    t->n = nc, t->n_samples = ns, t->length_nm = len_nm, t->slot = slot;
    r->loading = true;
    r->received = 0;
    r->crc = 0;
    r->crc_want = rd32(m + HP_LOAD_TEXTURE_OFF_CRC32);
    r->load_scale = scale;
}

static void load_chunk(fw_t *f, const uint8_t *m) {
    fw_render_t *r = &f->render;
    const uint8_t slot = m[HP_LOAD_CHUNK_OFF_SLOT], n = m[HP_LOAD_CHUNK_OFF_COUNT];
    const uint16_t first = rd16(m + HP_LOAD_CHUNK_OFF_FIRST);
    fw_texture_t *t = &r->tex[r->staging];
    if (!r->loading || slot != t->slot || first != r->received || (uint32_t)first + n > t->n) {
        reply(f, HP_ID_LOAD_CHUNK, slot, HP_RESULT_OUT_OF_ORDER, r->received);
        r->loading = false;
        return;
    }
    const uint8_t *p = m + HP_LOAD_CHUNK_SIZE;
    for (unsigned i = 0; i < n; i++) {
        if (!isfinite(rdf(p + 4 * i))) {
            reply(f, HP_ID_LOAD_CHUNK, slot, HP_RESULT_NONFINITE, (uint16_t)(first + i));
            r->loading = false;
            return;
        }
    }
    for (unsigned i = 0; i < n; i++) t->c[first + i] = rdf(p + 4 * i);
    r->crc = fw_crc32(r->crc, p, 4u * n);
    r->received = (uint16_t)(r->received + n);
}

static void load_end(fw_t *f, const uint8_t *m) {
    fw_render_t *r = &f->render;
    const uint8_t slot = m[HP_LOAD_END_OFF_SLOT];
    fw_texture_t *t = &r->tex[r->staging];
    if (!r->loading || slot != t->slot || r->received != t->n) {
        reply(f, HP_ID_LOAD_END, slot, HP_RESULT_TRUNCATED, r->received);
        r->loading = false;
        return;
    }
    if (r->crc != r->crc_want) {
        reply(f, HP_ID_LOAD_END, slot, HP_RESULT_BAD_CRC, r->received);
        r->loading = false;
        return;
    }
    if (r->on && r->xfade) { /* one swap at a time: the upload stays, LOAD_END may be resent */
        reply(f, HP_ID_LOAD_END, slot, HP_RESULT_BUSY, r->received);
        return;
    }
    for (unsigned i = 0; i < t->n; i++) {
        if (!isfinite(t->c[i] * r->load_scale)) {
            reply(f, HP_ID_LOAD_END, slot, HP_RESULT_NONFINITE, (uint16_t)i);
            r->loading = false;
            return;
        }
    }
    for (unsigned i = 0; i < t->n; i++) t->c[i] *= r->load_scale;
    t->dphase_half = phase_step(t->length_nm);
    t->turns_per_half = (float)((double)t->dphase_half * 5.42101086242752217e-20); /* x 2^-64 (load time only) */
    t->offset_turns = 0.25f / (float)t->n_samples;
    t->hz_per_mm_s = 1e6f / (2.0f * (float)t->length_nm);
    t->valid = true;
    r->loading = false;
    r->loads++;
    if (r->on) {
        swap_u8(&r->next, &r->staging);
        r->xfade = 1;
    } else {
        swap_u8(&r->active, &r->staging);
    }
    reply(f, HP_ID_LOAD_END, slot, HP_RESULT_OK, t->n);
}

static void set_eq(fw_t *f, const uint8_t *m) {
    fw_render_t *r = &f->render;
    const uint8_t idx = m[HP_SET_EQ_OFF_INDEX], ns = m[HP_SET_EQ_OFF_N_SECTIONS];
    const float b0 = rdf(m + HP_SET_EQ_OFF_B0), b1 = rdf(m + HP_SET_EQ_OFF_B1), b2 = rdf(m + HP_SET_EQ_OFF_B2);
    const float a1 = rdf(m + HP_SET_EQ_OFF_A1), a2 = rdf(m + HP_SET_EQ_OFF_A2);
    if (r->on) {
        reply(f, HP_ID_SET_EQ, idx, HP_RESULT_BUSY, 0);
        return;
    }
    if (ns == 0) { /* equalizer off */
        r->n_eq = 0;
        r->n_eq_staged = 0;
        reply(f, HP_ID_SET_EQ, idx, HP_RESULT_OK, 0);
        return;
    }
    if (!(finite4(b0, b1, b2, a1) && isfinite(a2))) {
        reply(f, HP_ID_SET_EQ, idx, HP_RESULT_NONFINITE, idx);
        r->n_eq_staged = 0;
        return;
    }
    /* stable: poles inside the unit circle (the stability triangle) */
    if (ns > HP_RENDER_MAX_SECTIONS || idx >= ns || !(fabsf(a2) < 1.0f && fabsf(a1) < 1.0f + a2)) {
        reply(f, HP_ID_SET_EQ, idx, HP_RESULT_BAD_PARAM, idx);
        r->n_eq_staged = 0;
        return;
    }
    if (idx == 0) {
        r->n_eq_staged = 0;
        r->n_eq_want = ns;
    }
    if (idx != r->n_eq_staged || ns != r->n_eq_want) {
        reply(f, HP_ID_SET_EQ, idx, HP_RESULT_OUT_OF_ORDER, r->n_eq_staged);
        r->n_eq_staged = 0;
        return;
    }
    r->eq_stage[idx] = (fw_biquad_t){b0, b1, b2, a1, a2, 0.0f, 0.0f};
    r->n_eq_staged++;
    if (r->n_eq_staged == ns) {
        memcpy(r->eq, r->eq_stage, sizeof r->eq);
        r->n_eq = ns;
        r->n_eq_staged = 0;
        reply(f, HP_ID_SET_EQ, idx, HP_RESULT_OK, ns);
    }
}

bool fw_render_on_message(fw_t *f, const uint8_t *m, size_t len) {
    fw_render_t *r = &f->render;
    size_t need;
    switch (m[0]) {
    case HP_ID_LOAD_TEXTURE: need = HP_LOAD_TEXTURE_SIZE; break;
    case HP_ID_LOAD_CHUNK:
        if (len < HP_LOAD_CHUNK_SIZE || m[HP_LOAD_CHUNK_OFF_COUNT] > HP_LOAD_CHUNK_MAX_COEFFS) {
            f->malformed++;
            return false;
        }
        need = HP_LOAD_CHUNK_SIZE + 4u * m[HP_LOAD_CHUNK_OFF_COUNT];
        break;
    case HP_ID_LOAD_END: need = HP_LOAD_END_SIZE; break;
    case HP_ID_SET_EQ: need = HP_SET_EQ_SIZE; break;
    case HP_ID_SET_BAND: need = HP_SET_BAND_SIZE; break;
    case HP_ID_SET_SCALE: need = HP_SET_SCALE_SIZE; break;
    case HP_ID_SET_DELAY: need = HP_SET_DELAY_SIZE; break;
    case HP_ID_START_RENDER: need = HP_START_RENDER_SIZE; break;
    case HP_ID_STOP_RENDER: need = HP_STOP_RENDER_SIZE; break;
    default:
        f->malformed++;
        return false;
    }
    if (len < need || !zero_tail(m, need, len)) {
        f->malformed++;
        return false;
    }
    switch (m[0]) {
    case HP_ID_LOAD_TEXTURE: load_texture(f, m); break;
    case HP_ID_LOAD_CHUNK: load_chunk(f, m); break;
    case HP_ID_LOAD_END: load_end(f, m); break;
    case HP_ID_SET_EQ: set_eq(f, m); break;
    case HP_ID_SET_BAND: {
        const float fs = rdf(m + HP_SET_BAND_OFF_F_STOP_HZ), fr = rdf(m + HP_SET_BAND_OFF_FADE_START);
        if (!(isfinite(fs) && isfinite(fr))) {
            reply(f, HP_ID_SET_BAND, 0, HP_RESULT_NONFINITE, 0);
        } else if (!(fs > 0.0f && fs <= 0.5f * (float)HP_SAMPLE_RATE_HZ && fr >= 0.0f && fr < 1.0f)) {
            reply(f, HP_ID_SET_BAND, 0, HP_RESULT_BAD_PARAM, 0);
        } else {
            r->f_stop_hz = fs;
            r->f_pass_hz = fr * fs;
            reply(f, HP_ID_SET_BAND, 0, HP_RESULT_OK, 0);
        }
        break;
    }
    case HP_ID_SET_SCALE: {
        const float s = rdf(m + HP_SET_SCALE_OFF_CODES_PER_UM);
        if (!isfinite(s)) {
            reply(f, HP_ID_SET_SCALE, 0, HP_RESULT_NONFINITE, 0);
        } else if (!(s > 0.0f && s <= 1e6f)) {
            reply(f, HP_ID_SET_SCALE, 0, HP_RESULT_BAD_PARAM, 0);
        } else {
            r->codes_per_um = s;
            reply(f, HP_ID_SET_SCALE, 0, HP_RESULT_OK, 0);
        }
        break;
    }
    case HP_ID_SET_DELAY: {
        const int16_t d = (int16_t)rd16(m + HP_SET_DELAY_OFF_DELAY_US);
        if (d > 20000 || d < -20000) {
            reply(f, HP_ID_SET_DELAY, 0, HP_RESULT_BAD_PARAM, 0);
        } else {
            r->delay_edge = (float)d * (float)(HP_RENDER_EDGE_CLOCK_HZ / 1000000);
            reply(f, HP_ID_SET_DELAY, 0, HP_RESULT_OK, 0);
        }
        break;
    }
    case HP_ID_START_RENDER: {
        if (!r->tex[r->active].valid) {
            reply(f, HP_ID_START_RENDER, 0, HP_RESULT_NO_TEXTURE, 0);
            break;
        }
        const uint16_t lost = rd16(m + HP_START_RENDER_OFF_HOST_LOST_MS);
        r->host_lost_ms = lost ? lost : HP_RENDER_DEFAULT_HOST_LOST_MS;
        if (!r->on) {
            eq_reset(r);
            r->env = 0.0f;
        }
        r->on = true;
        r->env_target = 1.0f;
        r->host_lost = false;
        fw_ring_clear(&f->ring);
        f->in_underrun = false;
        f->state = HP_STATE_RENDERING;
        reply(f, HP_ID_START_RENDER, r->tex[r->active].slot, HP_RESULT_OK, 0);
        break;
    }
    case HP_ID_STOP_RENDER:
        if (r->on) r->env_target = 0.0f; /* fade out, then idle */
        reply(f, HP_ID_STOP_RENDER, 0, HP_RESULT_OK, 0);
        break;
    default: break;
    }
    return true;
}
