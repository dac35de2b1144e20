/* Tests of device-side rendering (render.c), with a fake HAL: accuracy against the exact
 * series at the true position (sub-count interpolation, delay), refused uploads that leave the
 * output unchanged, a click-free texture swap, a lost host, parameters, and random bytes. */
#include <math.h>
#include <stdint.h>
#include <stdlib.h>
#include <string.h>

#include "check.h"
#include "fw.h"
#include "hal.h"
#include "render_msgs.h"

int g_checks, g_failures;

/* ---- fake HAL ---- */
static uint32_t fake_us;
static int16_t last_dac;
static uint8_t sent[256][80];
static size_t sent_n;
uint32_t hal_time_us(void) { return fake_us; }
void hal_dac_write(int16_t code) { last_dac = code; }
void hal_send(const uint8_t *msg, size_t len) {
    memcpy(sent[sent_n & 255], msg, len < 80 ? len : 80);
    sent_n++;
}

static const uint8_t GRAY[4] = {0, 1, 3, 2};
#define Q_MM (HP_UM_PER_COUNT_NM * 1e-6) /* mm per count */
#define PI_D 3.14159265358979323846

/* A device with its simulated hand at constant speed: edges at their exact crossing times. */
typedef struct {
    fw_t f;
    double x0_mm, v_mm_s;
    int64_t count;
} rig_t;

static double hand_mm(const rig_t *g, double t) { return g->x0_mm + g->v_mm_s * t; }

static void rig_init(rig_t *g, double x0, double v) {
    memset(g, 0, sizeof *g);
    fake_us = 0;
    g->x0_mm = x0, g->v_mm_s = v;
    g->count = llround(x0 / Q_MM);
    fw_init(&g->f, GRAY[(uint64_t)g->count & 3u]);
    g->f.quad.count = (uint32_t)g->count;
    g->f.render.edges.pos = g->count;
    g->f.render.edges.last_count = g->f.quad.count;
}

/* one tick: edges up to its instant, then fw_tick; returns the DAC code */
static int16_t rig_tick(rig_t *g) {
    const uint32_t k = g->f.ticks; /* this tick is at k / 3000 s */
    const double t = k / (double)HP_SAMPLE_RATE_HZ;
    const int64_t want = llround(hand_mm(g, t) / Q_MM);
    while (g->count != want) {
        const int d = want > g->count ? 1 : -1;
        const double xb = ((double)g->count + 0.5 * d) * Q_MM; /* boundary to the next count */
        const double te = (xb - g->x0_mm) / g->v_mm_s;
        g->count += d;
        fw_encoder_edge(&g->f, GRAY[(uint64_t)g->count & 3u], (uint32_t)llround(te * HP_RENDER_EDGE_CLOCK_HZ));
    }
    fake_us = (uint32_t)((uint64_t)k * 1000000u / HP_SAMPLE_RATE_HZ);
    fw_tick(&g->f);
    return last_dac;
}

/* ---- message builders (tests/render_msgs.h), each returning the ACK's result ---- */
static const uint8_t *last_ack(void) {
    for (size_t i = sent_n; i-- > 0 && i + 256 > sent_n;) {
        if (sent[i & 255][0] == HP_ID_ACK) return sent[i & 255];
    }
    return NULL;
}
static int last_result(void) {
    const uint8_t *a = last_ack();
    return a ? a[HP_ACK_OFF_RESULT] : -1;
}
static int upload(fw_t *f, uint8_t slot, const float *c, uint16_t n, uint16_t ns, uint32_t len_nm, int corrupt) {
    rm_upload(f, slot, c, n, ns, len_nm, corrupt);
    return last_result();
}
static int set_scale(fw_t *f, float s) { return rm_set_scale(f, s), last_result(); }
static int set_delay(fw_t *f, int16_t us) { return rm_set_delay(f, us), last_result(); }
static int set_band(fw_t *f, float fstop, float fade) { return rm_set_band(f, fstop, fade), last_result(); }
static int set_eq(fw_t *f, uint8_t idx, uint8_t n, float b0, float b1, float b2, float a1, float a2) {
    return rm_set_eq(f, idx, n, b0, b1, b2, a1, a2), last_result();
}
static int start_render(fw_t *f, uint16_t lost_ms) { return rm_start_render(f, lost_ms), last_result(); }

/* a texture of one component k (amplitude a_um) among n */
static float tex1[HP_RENDER_MAX_COMPONENTS], tex2[HP_RENDER_MAX_COMPONENTS];
static void one_component(float *c, uint16_t n, int k, float a_um) {
    memset(c, 0, sizeof(float) * HP_RENDER_MAX_COMPONENTS);
    (void)n;
    c[k - 1] = a_um;
}
#define LEN_NM 10000000u /* 10 mm */
#define NS 1000

static double exact_um(int k, float a, double x_mm) {
    return a * cos(k * (PI_D * x_mm / (LEN_NM * 1e-6) + PI_D / (2.0 * NS)));
}

static void test_accuracy_sub_count_and_delay(void) {
    static rig_t g;
    const int k = 400; /* 100 Hz at 5 mm/s; half a count of position error = 10 codes */
    for (int delay_us = 0; delay_us <= 1000; delay_us += 1000) {
        rig_init(&g, 3.0, 5.0);
        one_component(tex1, 400, k, 1.0f);
        CHECK_EQ(upload(&g.f, 1, tex1, 400, NS, LEN_NM, CORRUPT_NONE), HP_RESULT_OK);
        CHECK_EQ(set_scale(&g.f, 409.6f), HP_RESULT_OK);
        CHECK_EQ(set_delay(&g.f, (int16_t)delay_us), HP_RESULT_OK);
        CHECK_EQ(start_render(&g.f, 0), HP_RESULT_OK);
        CHECK_EQ(g.f.state, HP_STATE_RENDERING);
        int worst = 0;
        for (int i = 0; i < 3000; i++) {
            int16_t code = rig_tick(&g);
            double t = (g.f.ticks - 1) / 3000.0 + delay_us * 1e-6;
            if (i > HP_RAMP_TICKS + 10) {
                int want = (int)lrint(409.6 * exact_um(k, 1.0f, hand_mm(&g, t)));
                if (abs(code - want) > worst) worst = abs(code - want);
            }
            if (i % 7 == 0) { /* the host keeps talking */
                uint8_t id = HP_ID_IDENTIFY;
                rm_msg(&g.f, &id, 1);
            }
        }
        CHECK(worst <= 1); /* float32 and the edge clock: within 1 code (cell centre alone: 10) */
        printf("render accuracy: worst %d codes at delay %d us\n", worst, delay_us);
        if (worst > 1) fprintf(stderr, "accuracy: worst %d codes (delay %d us)\n", worst, delay_us);
        CHECK_EQ(g.f.render.refused, 0);
    }
}

/* Two identical devices; B also receives corrupt uploads: every one refused and counted,
 * and B's output stays identical to A's, code for code. */
static void test_corrupt_uploads_are_refused_and_change_nothing(void) {
    static rig_t a, b;
    rig_init(&a, 1.0, 30.0);
    rig_init(&b, 1.0, 30.0);
    one_component(tex1, 300, 37, 2.0f);
    for (int i = 0; i < 300; i++) tex2[i] = (float)((i * 7919) % 13) * 0.01f;
    fw_t *fs[2] = {&a.f, &b.f};
    for (int j = 0; j < 2; j++) {
        CHECK_EQ(upload(fs[j], 1, tex1, 300, NS, LEN_NM, CORRUPT_NONE), HP_RESULT_OK);
        CHECK_EQ(start_render(fs[j], 60000), HP_RESULT_OK);
    }
    static const struct { int corrupt; int result; } cases[] = {
        {CORRUPT_CRC, HP_RESULT_BAD_CRC},      {CORRUPT_NAN, HP_RESULT_TRUNCATED},
        {CORRUPT_INF, HP_RESULT_TRUNCATED},    {CORRUPT_TRUNCATE, HP_RESULT_TRUNCATED},
        {CORRUPT_SKIP, HP_RESULT_TRUNCATED},
    };
    int diffs = 0;
    uint16_t refused = 0;
    for (int i = 0; i < 2400; i++) {
        if (i >= 300 && i % 300 == 0 && (i / 300 - 1) < 5) {
            int c = i / 300 - 1;
            size_t n0 = sent_n;
            CHECK_EQ(upload(&b.f, 2, tex2, 300, NS, LEN_NM, cases[c].corrupt), cases[c].result);
            /* NaN/Inf and a skipped chunk are refused at the chunk, then LOAD_END as truncated */
            /* a bad chunk is refused, so is every chunk after it (not the next one), then LOAD_END */
            const int chunks = (300 + HP_LOAD_CHUNK_MAX_COEFFS - 1) / HP_LOAD_CHUNK_MAX_COEFFS;
            uint16_t want = (uint16_t)(cases[c].corrupt == CORRUPT_CRC || cases[c].corrupt == CORRUPT_TRUNCATE ? 1 : chunks - 2 + 1);
            CHECK_EQ(b.f.render.refused - refused, want);
            refused = b.f.render.refused;
            int nonfinite = 0;
            for (size_t s = n0; s < sent_n; s++) {
                if (sent[s & 255][0] == HP_ID_ACK && sent[s & 255][HP_ACK_OFF_RESULT] == HP_RESULT_NONFINITE) nonfinite++;
            }
            CHECK_EQ(nonfinite, cases[c].corrupt == CORRUPT_NAN || cases[c].corrupt == CORRUPT_INF);
        }
        if (i == 1800) { /* N' too large, a scale of Inf, then START without a texture elsewhere */
            uint8_t m[HP_LOAD_TEXTURE_SIZE] = {HP_ID_LOAD_TEXTURE, 3};
            put16(m + HP_LOAD_TEXTURE_OFF_N_SAMPLES, NS);
            put16(m + HP_LOAD_TEXTURE_OFF_N_COEFFS, HP_RENDER_MAX_COMPONENTS + 1);
            put32(m + HP_LOAD_TEXTURE_OFF_LENGTH_NM, LEN_NM);
            rm_msg(&b.f, m, sizeof m);
            CHECK_EQ(last_result(), HP_RESULT_TOO_LARGE);
            put16(m + HP_LOAD_TEXTURE_OFF_N_COEFFS, 10);
            putf(m + HP_LOAD_TEXTURE_OFF_SCALE, INFINITY);
            rm_msg(&b.f, m, sizeof m);
            CHECK_EQ(last_result(), HP_RESULT_NONFINITE);
            CHECK_EQ(set_scale(&b.f, NAN), HP_RESULT_NONFINITE);
            CHECK_EQ(set_scale(&b.f, -1.0f), HP_RESULT_BAD_PARAM);
            CHECK_EQ(set_band(&b.f, 2000.0f, 0.8f), HP_RESULT_BAD_PARAM);
            CHECK_EQ(set_band(&b.f, 400.0f, 1.0f), HP_RESULT_BAD_PARAM);
            CHECK_EQ(set_delay(&b.f, 30000), HP_RESULT_BAD_PARAM);
            CHECK_EQ(set_eq(&b.f, 0, 1, 1, 0, 0, 0, 0), HP_RESULT_BUSY); /* not while rendering */
        }
        if (rig_tick(&a) != rig_tick(&b)) diffs++;
    }
    CHECK_EQ(diffs, 0);
    CHECK_EQ(b.f.render.refused, 1 + 21 + 21 + 1 + 21 + 8);
    CHECK_EQ(b.f.render.loads, 1);
    CHECK_EQ(b.f.state, HP_STATE_RENDERING);
    static fw_t fresh;
    fw_init(&fresh, 0);
    CHECK_EQ(start_render(&fresh, 0), HP_RESULT_NO_TEXTURE);
    CHECK_EQ(fresh.state, HP_STATE_IDLE);
}

/* A swap while rendering crossfades: with a slew limit far below a jump between the two
 * textures, it never engages; afterwards the output is the new texture's, code for code. */
static void test_texture_swap_without_a_click(void) {
    static rig_t a, b;
    rig_init(&a, 2.0, 40.0);
    rig_init(&b, 2.0, 40.0);
    one_component(tex1, 200, 20, 5.0f);  /* 80 Hz, ±5 µm */
    one_component(tex2, 200, 23, -5.0f); /* in antiphase nearby: a hard cut would jump ~4000 codes */
    CHECK_EQ(upload(&a.f, 1, tex1, 200, NS, LEN_NM, CORRUPT_NONE), HP_RESULT_OK);
    CHECK_EQ(upload(&b.f, 2, tex2, 200, NS, LEN_NM, CORRUPT_NONE), HP_RESULT_OK);
    CHECK_EQ(start_render(&a.f, 0), HP_RESULT_OK);
    CHECK_EQ(start_render(&b.f, 0), HP_RESULT_OK);
    uint8_t lim[5] = {HP_ID_SET_LIMITS, 0xFF, 0x3F, 0, 0};
    put16(lim + 3, 400); /* 1 µm per tick: steady rendering needs ~260 */
    rm_msg(&a.f, lim, 5);
    rm_msg(&b.f, lim, 5);
    int slewed = 0, max_step = 0, same_after = 0;
    int16_t prev = 0;
    for (int i = 0; i < 1500; i++) {
        if (i == 600) CHECK_EQ(upload(&a.f, 2, tex2, 200, NS, LEN_NM, CORRUPT_NONE), HP_RESULT_OK);
        if (i == 650) CHECK_EQ(upload(&a.f, 3, tex1, 200, NS, LEN_NM, CORRUPT_NONE), HP_RESULT_BUSY);
        if (i % 10 == 0) { /* the host is alive */
            uint8_t id = HP_ID_IDENTIFY;
            rm_msg(&a.f, &id, 1), rm_msg(&b.f, &id, 1);
        }
        int16_t ca = rig_tick(&a), cb = rig_tick(&b);
        if (a.f.faults & HP_FAULT_SLEWED) slewed++;
        if (i > 0 && abs(ca - prev) > max_step) max_step = abs(ca - prev);
        prev = ca;
        if (i > 600 + HP_RENDER_XFADE_TICKS + 2) same_after += (ca == cb);
    }
    CHECK_EQ(slewed, 0);
    CHECK(max_step < 400);
    CHECK_EQ(same_after, 1500 - (600 + HP_RENDER_XFADE_TICKS + 3));
    CHECK_EQ(a.f.render.tex[a.f.render.active].slot, 2);
}

/* A silent host does not stop a rendering device while the hand moves; once the hand has
 * also been still for HP_RENDER_STILL_MS, the device fades out and goes idle. */
static void test_lost_host_keeps_rendering_while_the_hand_moves(void) {
    static rig_t g;
    rig_init(&g, 0.0, 20.0);
    one_component(tex1, 100, 10, 3.0f);
    CHECK_EQ(upload(&g.f, 1, tex1, 100, NS, LEN_NM, CORRUPT_NONE), HP_RESULT_OK);
    CHECK_EQ(start_render(&g.f, 200), HP_RESULT_OK); /* host lost after 200 ms */
    int lost_seen = 0, nonzero_late = 0;
    for (int i = 0; i < 3 * 3000; i++) { /* 3 s of host silence, hand moving */
        int16_t c = rig_tick(&g);
        if (g.f.render.host_lost) lost_seen++;
        if (i > 2 * 3000 && c != 0) nonzero_late++;
    }
    CHECK_EQ(g.f.state, HP_STATE_RENDERING);
    CHECK(lost_seen > 2 * 3000);
    CHECK(nonzero_late > 2500);
    g.v_mm_s = 0.0; /* the hand stops where it is */
    g.x0_mm = (double)g.count * Q_MM;
    int ticks = 0;
    while (g.f.state == HP_STATE_RENDERING && ticks < 10000) rig_tick(&g), ticks++;
    CHECK(ticks >= HP_RENDER_STILL_MS * 3 && ticks <= HP_RENDER_STILL_MS * 3 + HP_RAMP_TICKS + 5);
    CHECK_EQ(g.f.state, HP_STATE_IDLE);
    for (int i = 0; i < 200; i++) rig_tick(&g);
    CHECK_EQ(last_dac, 0);
}

static uint32_t rd32le(const uint8_t *p) {
    return (uint32_t)p[0] | ((uint32_t)p[1] << 8) | ((uint32_t)p[2] << 16) | ((uint32_t)p[3] << 24);
}

/* While rendering, STATUS and RENDER_STATUS come once per HP_RENDER_STATUS_PERIOD_TICKS (the
 * host sleeps between them), and RENDER_STATUS counts every tick exactly once: rendered at full
 * gain, faded (fade in / out) or idle; a lost host is one episode; the counters account for a
 * lost host whose hand stops (the display fades out and goes idle) tick for tick. */
static void test_render_status_counters_and_cadence(void) {
    static rig_t g;
    rig_init(&g, 0.0, 20.0);
    one_component(tex1, 100, 10, 3.0f);
    CHECK_EQ(upload(&g.f, 1, tex1, 100, NS, LEN_NM, CORRUPT_NONE), HP_RESULT_OK);
    for (int i = 0; i < 30; i++) rig_tick(&g); /* 30 idle ticks first */
    CHECK_EQ(start_render(&g.f, 200), HP_RESULT_OK);
    const uint32_t k0 = g.f.ticks;
    size_t statuses = 0, rstatuses = 0;
    uint8_t last_rs[80] = {0};
    const int n = 6 * 3000;
    for (int i = 0; i < n; i++) {
        size_t before = sent_n;
        if (i == 3000) { /* after 1 s the hand stops; the host is silent all along (lost after 200 ms) */
            g.x0_mm = (double)g.count * Q_MM;
            g.v_mm_s = 0.0;
            /* rig_tick's hand is x0 + v t: a stopped hand */
        }
        rig_tick(&g);
        for (size_t j = before; j < sent_n; j++) {
            const uint8_t *m = sent[j & 255];
            if (m[0] == HP_ID_STATUS && g.f.ticks - k0 < 3000) statuses++;
            if (m[0] == HP_ID_RENDER_STATUS) {
                rstatuses++;
                memcpy(last_rs, m, sizeof last_rs);
            }
        }
    }
    /* the first second: rendering throughout, one STATUS per render period (not one per ms) */
    CHECK(statuses <= 3000 / HP_RENDER_STATUS_PERIOD_TICKS + 1);
    CHECK(rstatuses >= 1000 / (HP_RENDER_STATUS_PERIOD_TICKS / 3) - 1);
    CHECK_EQ(g.f.state, HP_STATE_IDLE); /* lost host, still hand: faded out */
    fw_render_t *r = &g.f.render;
    /* every tick since START_RENDER is in exactly one counter (idle ones after the fade-out) */
    CHECK_EQ(r->rendered_ticks + r->faded_ticks + (g.f.idle_ticks - 30), g.f.ticks - k0);
    /* the fade in and the fade out (float steps of 1/150: one tick either way) */
    CHECK(r->faded_ticks >= 2u * HP_RAMP_TICKS - 2 && r->faded_ticks <= 2u * HP_RAMP_TICKS + 2);
    CHECK_EQ(r->host_lost_count, 1);
    /* the last RENDER_STATUS carries the counters as they were at its tick */
    CHECK_EQ(last_rs[HP_RENDER_STATUS_OFF_HOST_LOST_COUNT], 1);
    CHECK(rd32le(last_rs + HP_RENDER_STATUS_OFF_RENDERED_TICKS) <= r->rendered_ticks);
    CHECK(rd32le(last_rs + HP_RENDER_STATUS_OFF_RENDERED_TICKS) > 3000);
    CHECK_EQ(rd32le(last_rs + HP_RENDER_STATUS_OFF_IDLE_TICKS), 30);
    /* idle: STATUS every HP_STATUS_PERIOD_TICKS again */
    size_t before = sent_n;
    for (int i = 0; i < 300; i++) rig_tick(&g);
    CHECK_EQ(sent_n - before, 300 / HP_STATUS_PERIOD_TICKS);
}

static void test_equalizer_sections_and_v1_stop(void) {
    static rig_t a, b;
    rig_init(&a, 0.0, 10.0);
    rig_init(&b, 0.0, 10.0);
    one_component(tex1, 50, 50, 2.0f);
    CHECK_EQ(upload(&a.f, 1, tex1, 50, NS, LEN_NM, CORRUPT_NONE), HP_RESULT_OK);
    CHECK_EQ(upload(&b.f, 1, tex1, 50, NS, LEN_NM, CORRUPT_NONE), HP_RESULT_OK);
    size_t n0 = sent_n;
    set_eq(&b.f, 0, 2, 1.5f, 0, 0, 0, 0); /* first of two: no answer yet */
    CHECK_EQ(sent_n, n0);
    CHECK_EQ(set_eq(&b.f, 1, 2, 2.0f, 0, 0, 0, 0), HP_RESULT_OK); /* gain 3 in all */
    CHECK_EQ(set_eq(&a.f, 0, 1, 1.0f, 0, 0, 0, 1.5f), HP_RESULT_BAD_PARAM); /* unstable */
    CHECK_EQ(set_eq(&a.f, 1, 1, 1.0f, 0, 0, 0, 0), HP_RESULT_BAD_PARAM);   /* index >= n */
    n0 = sent_n;
    set_eq(&a.f, 0, 2, 1.0f, 0, 0, 0, 0); /* one of two, never completed: not installed */
    CHECK_EQ(sent_n, n0);
    CHECK_EQ(a.f.render.n_eq, 0);
    CHECK_EQ(start_render(&a.f, 0), HP_RESULT_OK);
    CHECK_EQ(start_render(&b.f, 0), HP_RESULT_OK);
    int bad = 0;
    for (int i = 0; i < 600; i++) {
        int ca = rig_tick(&a), cb = rig_tick(&b);
        if (abs(cb - 3 * ca) > 2) bad++;
    }
    CHECK_EQ(bad, 0);
    uint8_t stop = HP_ID_STOP; /* v1 STOP while rendering: the 50 ms ramp to zero */
    rm_msg(&a.f, &stop, 1);
    CHECK_EQ(a.f.state, HP_STATE_RAMP_DOWN);
    int t = 0;
    while (a.f.state != HP_STATE_IDLE && t < 1000) rig_tick(&a), t++;
    CHECK(t <= HP_RAMP_TICKS + 1);
    CHECK_EQ(last_dac, 0);
    uint8_t sr = HP_ID_STOP_RENDER; /* STOP_RENDER: a fade of the texture, then idle */
    rm_msg(&b.f, &sr, 1);
    t = 0;
    while (b.f.state != HP_STATE_IDLE && t < 1000) rig_tick(&b), t++;
    CHECK(t >= HP_RAMP_TICKS - 1 && t <= HP_RAMP_TICKS + 2);
}

/* Random bytes and hostile render messages, interleaved with ticks and encoder motion:
 * every DAC code stays within the displacement and slew limits. */
static uint64_t rng = 0x2545F4914F6CDD1Dull;
static uint32_t rnd(void) {
    rng ^= rng << 13, rng ^= rng >> 7, rng ^= rng << 17;
    return (uint32_t)rng;
}
static float hostile_float(void) {
    static const float pool[] = {0.0f, -0.0f, 1.0f, -1.0f, 1e30f, -1e30f, 3.4e38f, 1e-40f, 0.5f, 400.0f,
                                 0.999f, 1.0001f, -1.9999f, 1e6f, 409.6f};
    uint32_t r = rnd() % 20;
    if (r < 15) return pool[r];
    if (r == 15) return NAN;
    if (r == 16) return INFINITY;
    uint32_t u = rnd();
    float v;
    memcpy(&v, &u, 4);
    return v;
}

static void test_random_render_messages_never_break_safety(void) {
    static fw_t f;
    fw_init(&f, 0);
    fake_us = 0;
    int16_t prev = 0;
    long violations = 0, rendering_ticks = 0;
    int64_t pos = 0;
    uint32_t t_edge = 0;
    /* a valid texture first, so that rendering really happens between the garbage */
    for (int i = 0; i < 64; i++) tex1[i] = (float)(i % 5) - 2.0f;
    upload(&f, 1, tex1, 64, 256, 2000000u, CORRUPT_NONE);
    for (long it = 0; it < 200000; it++) {
        uint8_t buf[HP_REPORT_SIZE] = {0};
        size_t n = 1 + rnd() % HP_REPORT_SIZE;
        uint32_t mode = rnd() % 10;
        for (size_t i = 0; i < n; i++) buf[i] = (uint8_t)rnd();
        if (mode < 6) { /* well-formed render messages with hostile values */
            static const uint8_t ids[] = {HP_ID_LOAD_TEXTURE, HP_ID_LOAD_CHUNK, HP_ID_LOAD_END, HP_ID_SET_EQ,
                                          HP_ID_SET_BAND, HP_ID_SET_SCALE, HP_ID_SET_DELAY, HP_ID_START_RENDER,
                                          HP_ID_START_RENDER, HP_ID_STOP_RENDER, HP_ID_SET_LIMITS, HP_ID_START,
                                          HP_ID_STOP};
            buf[0] = ids[rnd() % sizeof ids];
            size_t len = HP_REPORT_SIZE;
            switch (buf[0]) {
            case HP_ID_LOAD_TEXTURE:
                put16(buf + HP_LOAD_TEXTURE_OFF_N_COEFFS, (uint16_t)(rnd() % 600));
                put32(buf + HP_LOAD_TEXTURE_OFF_LENGTH_NM, rnd() % 3 ? 1000000u + rnd() % 20000000u : rnd());
                putf(buf + HP_LOAD_TEXTURE_OFF_SCALE, hostile_float());
                len = HP_LOAD_TEXTURE_SIZE;
                break;
            case HP_ID_LOAD_CHUNK: {
                uint8_t k = (uint8_t)(rnd() % (HP_LOAD_CHUNK_MAX_COEFFS + 1));
                buf[HP_LOAD_CHUNK_OFF_SLOT] = f.render.tex[f.render.staging].slot;
                put16(buf + HP_LOAD_CHUNK_OFF_FIRST, rnd() % 4 ? f.render.received : (uint16_t)rnd());
                buf[HP_LOAD_CHUNK_OFF_COUNT] = k;
                for (unsigned i = 0; i < k; i++) putf(buf + HP_LOAD_CHUNK_SIZE + 4 * i, hostile_float());
                len = HP_LOAD_CHUNK_SIZE + 4u * k;
                break;
            }
            case HP_ID_LOAD_END:
                buf[1] = f.render.tex[f.render.staging].slot;
                /* a CRC that matches, now and then: let hostile textures through */
                if (rnd() % 2) f.render.crc_want = f.render.crc;
                len = HP_LOAD_END_SIZE;
                break;
            case HP_ID_SET_EQ:
                buf[1] = (uint8_t)(rnd() % 3), buf[2] = (uint8_t)(rnd() % 6);
                for (int i = 0; i < 5; i++) putf(buf + 3 + 4 * i, hostile_float());
                len = HP_SET_EQ_SIZE;
                break;
            case HP_ID_SET_BAND: putf(buf + 1, hostile_float()), putf(buf + 5, hostile_float()), len = 9; break;
            case HP_ID_SET_SCALE: putf(buf + 1, hostile_float()), len = 5; break;
            case HP_ID_SET_DELAY: len = 3; break;
            case HP_ID_START_RENDER: len = 3; break;
            case HP_ID_SET_LIMITS: len = 5; break;
            default: len = 1; break;
            }
            memset(buf + len, 0, HP_REPORT_SIZE - len);
            fw_on_message(&f, buf, rnd() % 8 ? HP_REPORT_SIZE : len + rnd() % 3);
        } else if (mode == 6 && rnd() % 8 == 0) { /* a complete, valid upload of hostile values */
            uint16_t nc = (uint16_t)(1 + rnd() % HP_RENDER_MAX_COMPONENTS);
            for (unsigned i = 0; i < nc; i++) {
                float v = hostile_float();
                tex2[i] = isfinite(v) ? v : 1.0f;
            }
            upload(&f, (uint8_t)rnd(), tex2, nc, (uint16_t)(1 + rnd() % 4096), 400u + rnd() % 50000000u,
                   CORRUPT_NONE);
        } else if (mode < 8) {
            fw_on_message(&f, buf, n);
        } else {
            fw_deframer_feed(&f, buf, n);
        }
        const uint16_t lim = f.limit_code, step = f.max_step_code;
        int ticks = (int)(rnd() % 6);
        for (int k = 0; k < ticks; k++) {
            int moves = (int)(rnd() % 8) - 3; /* hand motion, with edges near the tick */
            for (int e = 0; e < abs(moves); e++) {
                pos += moves > 0 ? 1 : -1;
                t_edge = f.ticks * (uint32_t)FW_EDGE_PER_TICK - rnd() % 8000u;
                fw_encoder_edge(&f, GRAY[(uint64_t)pos & 3u], t_edge);
            }
            fake_us = (uint32_t)((uint64_t)f.ticks * 1000000u / HP_SAMPLE_RATE_HZ);
            fw_tick(&f);
            rendering_ticks += f.state == HP_STATE_RENDERING;
            int16_t o = last_dac;
            if ((abs(o) > lim && abs(o) >= abs(prev)) || abs(o - prev) > step) violations++;
            if (o > HP_LIMIT_CODE || o < -HP_LIMIT_CODE || abs(o - prev) > HP_MAX_STEP_CODE) violations++;
            prev = o;
        }
    }
    CHECK_EQ(violations, 0);
    CHECK(rendering_ticks > 10000); /* the device did render between the garbage */
    CHECK(f.render.refused > 1000 && f.malformed > 1000);
    CHECK(f.render.loads > 100); /* and hostile textures were loaded */
    printf("render fuzz: %ld rendering ticks, %u refused, %u malformed, %u loads\n", rendering_ticks,
           f.render.refused, f.malformed, f.render.loads);
}

int main(void) {
    CHECK_EQ(fw_crc32(0, (const uint8_t *)"123456789", 9), 0xCBF43926u); /* CRC-32 check value */
    test_accuracy_sub_count_and_delay();
    test_corrupt_uploads_are_refused_and_change_nothing();
    test_texture_swap_without_a_click();
    test_lost_host_keeps_rendering_while_the_hand_moves();
    test_render_status_counters_and_cadence();
    test_equalizer_sections_and_v1_stop();
    test_random_render_messages_never_break_safety();
    printf("render: %d checks, %d failures\n", g_checks, g_failures);
    return g_failures ? 1 : 0;
}
