/* Unit tests of the firmware core, with a fake HAL. Usage: test_fw VECTORS_FILE */
#include <stdint.h>
#include <stdlib.h>
#include <string.h>

#include "check.h"
#include "fw.h"
#include "hal.h"

int g_checks, g_failures;

/* ---- fake HAL ---- */
static uint32_t fake_us;
static int16_t dac_log[1 << 16];
static size_t dac_n;
static uint8_t sent[64][80];
static size_t sent_len[64];
static size_t sent_n;

uint32_t hal_time_us(void) { return fake_us; }
void hal_dac_write(int16_t code) { dac_log[dac_n++ & 0xFFFF] = code; }
void hal_send(const uint8_t *msg, size_t len) {
    size_t i = sent_n++ & 63;
    memcpy(sent[i], msg, len);
    sent_len[i] = len;
}
static void reset_fakes(void) { fake_us = 0, dac_n = 0, sent_n = 0; }
static void tick(fw_t *f) {
    fake_us += 333;
    fw_tick(f);
}

/* ---- helpers ---- */
static size_t unhex(const char *h, uint8_t *out, size_t cap) {
    size_t n = 0;
    while (h[0] && h[1] && n < cap) {
        unsigned v;
        if (sscanf(h, "%2x", &v) != 1) break;
        out[n++] = (uint8_t)v;
        h += 2;
    }
    return n;
}
static uint32_t rd(const uint8_t *p, int size) {
    uint32_t v = 0;
    for (int i = 0; i < size; i++) v |= (uint32_t)p[i] << (8 * i);
    return v;
}
static long long field_value(const char *fields, const char *name, int *found) {
    char key[64];
    snprintf(key, sizeof key, " %s=", name);
    const char *p = strstr(fields, key);
    *found = p != NULL;
    return p ? atoll(p + strlen(key)) : 0;
}

static float f32_of_bits(uint32_t raw) {
    float v;
    memcpy(&v, &raw, sizeof v);
    return v;
}
static uint32_t bits_of_f32(float v) {
    uint32_t raw;
    memcpy(&raw, &v, sizeof raw);
    return raw;
}
static double field_double(const char *fields, const char *name) {
    char key[64];
    snprintf(key, sizeof key, " %s=", name);
    const char *p = strstr(fields, key);
    return p ? strtod(p + strlen(key), NULL) : 0.0;
}

/* Check a message's bytes against its field list through the generated layout tables
 * (kind 0 unsigned, 1 signed, 2 float32: compared bit for bit). */
#define CHECK_FIELD(name, off, size, kind)                                                     \
    {                                                                                          \
        int found;                                                                             \
        long long want = field_value(fields, #name, &found);                                   \
        CHECK(found);                                                                          \
        uint32_t raw = rd(msg + (off), (size));                                                \
        if ((kind) == 2) {                                                                     \
            CHECK_EQ(raw, bits_of_f32((float)field_double(fields, #name)));                    \
            (void)f32_of_bits;                                                                 \
        } else {                                                                               \
            long long got = (kind) ? ((size) == 2 ? (long long)(int16_t)raw : (long long)(int32_t)raw) \
                                   : (long long)raw;                                           \
            CHECK_EQ(got, want);                                                               \
        }                                                                                      \
    }

static void check_vector_fields(const uint8_t *msg, size_t len, const char *fields) {
    switch (msg[0]) {
    case HP_ID_SAMPLES: HP_SAMPLES_FIELDS(CHECK_FIELD) break;
    case HP_ID_START: HP_START_FIELDS(CHECK_FIELD) break;
    case HP_ID_STOP: HP_STOP_FIELDS(CHECK_FIELD) break;
    case HP_ID_SET_LIMITS: HP_SET_LIMITS_FIELDS(CHECK_FIELD) break;
    case HP_ID_SET_TIMEOUT: HP_SET_TIMEOUT_FIELDS(CHECK_FIELD) break;
    case HP_ID_IDENTIFY: HP_IDENTIFY_FIELDS(CHECK_FIELD) break;
    case HP_ID_STATUS: HP_STATUS_FIELDS(CHECK_FIELD) CHECK_EQ(len, HP_STATUS_SIZE); break;
    case HP_ID_IDENT: HP_IDENT_FIELDS(CHECK_FIELD) CHECK_EQ(len, HP_IDENT_SIZE); break;
    case HP_ID_LOAD_TEXTURE: HP_LOAD_TEXTURE_FIELDS(CHECK_FIELD) CHECK_EQ(len, HP_LOAD_TEXTURE_SIZE); break;
    case HP_ID_LOAD_CHUNK: HP_LOAD_CHUNK_FIELDS(CHECK_FIELD) break;
    case HP_ID_LOAD_END: HP_LOAD_END_FIELDS(CHECK_FIELD) CHECK_EQ(len, HP_LOAD_END_SIZE); break;
    case HP_ID_SET_EQ: HP_SET_EQ_FIELDS(CHECK_FIELD) CHECK_EQ(len, HP_SET_EQ_SIZE); break;
    case HP_ID_SET_BAND: HP_SET_BAND_FIELDS(CHECK_FIELD) CHECK_EQ(len, HP_SET_BAND_SIZE); break;
    case HP_ID_SET_SCALE: HP_SET_SCALE_FIELDS(CHECK_FIELD) CHECK_EQ(len, HP_SET_SCALE_SIZE); break;
    case HP_ID_SET_DELAY: HP_SET_DELAY_FIELDS(CHECK_FIELD) CHECK_EQ(len, HP_SET_DELAY_SIZE); break;
    case HP_ID_START_RENDER: HP_START_RENDER_FIELDS(CHECK_FIELD) CHECK_EQ(len, HP_START_RENDER_SIZE); break;
    case HP_ID_STOP_RENDER: HP_STOP_RENDER_FIELDS(CHECK_FIELD) CHECK_EQ(len, HP_STOP_RENDER_SIZE); break;
    case HP_ID_ACK: HP_ACK_FIELDS(CHECK_FIELD) CHECK_EQ(len, HP_ACK_SIZE); break;
    case HP_ID_CAPS: HP_CAPS_FIELDS(CHECK_FIELD) CHECK_EQ(len, HP_CAPS_SIZE); break;
    case HP_ID_RENDER_STATUS: HP_RENDER_STATUS_FIELDS(CHECK_FIELD) CHECK_EQ(len, HP_RENDER_STATUS_SIZE); break;
    default: CHECK(0 && "unknown id in vectors");
    }
    if (msg[0] == HP_ID_LOAD_CHUNK) { /* the float32 coefficients follow the fixed part */
        const char *c = strstr(fields, " coeffs=");
        CHECK(c != NULL);
        size_t n = msg[HP_LOAD_CHUNK_OFF_COUNT];
        CHECK(n <= HP_LOAD_CHUNK_MAX_COEFFS);
        CHECK_EQ(len, HP_LOAD_CHUNK_SIZE + 4 * n);
        c = c ? c + 8 : "";
        for (size_t i = 0; i < n; i++) {
            double v = strtod(c, (char **)&c);
            CHECK_EQ(rd(msg + HP_LOAD_CHUNK_SIZE + 4 * i, 4), bits_of_f32((float)v));
            if (*c == ',') c++;
        }
    }
    if (msg[0] == HP_ID_SAMPLES) { /* the codes array follows the fixed part */
        const char *c = strstr(fields, " codes=");
        CHECK(c != NULL);
        size_t n = msg[HP_SAMPLES_OFF_COUNT];
        CHECK_EQ(len, HP_SAMPLES_SIZE + 2 * n);
        c = c ? c + 7 : "";
        for (size_t i = 0; i < n; i++) {
            long v = strtol(c, (char **)&c, 10);
            CHECK_EQ((int16_t)rd(msg + HP_SAMPLES_SIZE + 2 * i, 2), v);
            if (*c == ',') c++;
        }
        /* and the device accepts it: codes land in the ring buffer, in order */
        static fw_t f;
        reset_fakes();
        fw_init(&f, 0);
        fw_on_message(&f, msg, len);
        CHECK_EQ(f.malformed, 0);
        CHECK_EQ(fw_ring_fill(&f.ring), n);
    }
}

static void test_vectors(const char *path) {
    FILE *fp = fopen(path, "r");
    CHECK(fp != NULL);
    if (!fp) return;
    char line[4096];
    int n_msg = 0, n_frame = 0, n_bad = 0, n_badframe = 0;
    while (fgets(line, sizeof line, fp)) {
        char kind[16], name[64], hex1[1024], hex2[1024];
        uint8_t a[512], b[512], out[512];
        if (line[0] == '#' || sscanf(line, "%15s %63s %1023s", kind, name, hex1) != 3) continue;
        size_t na = unhex(hex1, a, sizeof a);
        if (!strcmp(kind, "msg")) {
            const char *fields = strstr(line, hex1) + strlen(hex1);
            check_vector_fields(a, na, fields);
            n_msg++;
        } else if (!strcmp(kind, "frame")) {
            CHECK(sscanf(line, "%*s %*s %*s %1023s", hex2) == 1);
            size_t nb = unhex(hex2, b, sizeof b);
            size_t nf = fw_frame(a, na, out, sizeof out);
            CHECK_EQ(nf, nb);
            CHECK(nf == nb && memcmp(out, b, nb) == 0);
            uint8_t msg[128];
            CHECK_EQ(fw_unframe(b, nb - 1, msg, sizeof msg), (long long)na);
            CHECK(memcmp(msg, a, na) == 0);
            n_frame++;
        } else if (!strcmp(kind, "bad")) {
            static fw_t f;
            reset_fakes();
            fw_init(&f, 0);
            fw_on_message(&f, a, na);
            CHECK_EQ(f.malformed, 1);
            CHECK_EQ(fw_ring_fill(&f.ring), 0);
            CHECK_EQ(f.state, HP_STATE_IDLE);
            CHECK_EQ(f.limit_code, HP_LIMIT_CODE);
            CHECK_EQ(f.timeout_ms, HP_DEFAULT_TIMEOUT_MS);
            CHECK_EQ(sent_n, 0);
            n_bad++;
        } else if (!strcmp(kind, "badframe")) {
            static fw_t f;
            reset_fakes();
            fw_init(&f, 0);
            fw_deframer_feed(&f, a, na);
            CHECK_EQ(f.malformed, 1);
            CHECK_EQ(f.state, HP_STATE_IDLE);
            n_badframe++;
        }
    }
    fclose(fp);
    CHECK(n_msg >= 8 && n_frame == n_msg && n_bad >= 8 && n_badframe >= 3);
}

static void test_crc_and_cobs(void) {
    CHECK_EQ(fw_crc16((const uint8_t *)"123456789", 9), 0x29B1); /* CRC-16/CCITT-FALSE check */
    uint8_t m[64], fr[96], back[96];
    for (int len = 1; len <= 64; len++) {
        for (int i = 0; i < len; i++) m[i] = (uint8_t)((i * 37) % 3 == 0 ? 0 : i); /* many zeros */
        size_t n = fw_frame(m, (size_t)len, fr, sizeof fr);
        CHECK(n > 0);
        for (size_t i = 0; i + 1 < n; i++) CHECK(fr[i] != 0);
        CHECK_EQ(fr[n - 1], 0);
        CHECK_EQ(fw_unframe(fr, n - 1, back, sizeof back), len);
        CHECK(memcmp(back, m, (size_t)len) == 0);
    }
}

static void test_ring(void) {
    static fw_ring_t r;
    fw_ring_init(&r);
    int16_t v[HP_BUFFER_CAPACITY];
    for (int i = 0; i < HP_BUFFER_CAPACITY; i++) v[i] = (int16_t)i;
    CHECK(fw_ring_push(&r, v, 200));
    int16_t x;
    for (int i = 0; i < 150; i++) CHECK(fw_ring_pop(&r, &x) && x == i);
    CHECK(fw_ring_push(&r, v, 200)); /* wraps */
    CHECK(!fw_ring_push(&r, v, 7));  /* 250 + 7 > 256: all or nothing */
    CHECK_EQ(fw_ring_fill(&r), 250);
    CHECK(fw_ring_push(&r, v, 6)); /* exactly full */
    CHECK_EQ(fw_ring_fill(&r), HP_BUFFER_CAPACITY);
    CHECK(!fw_ring_push(&r, v, 1));
    for (int i = 150; i < 200; i++) CHECK(fw_ring_pop(&r, &x) && x == i);
    for (int i = 0; i < 200; i++) CHECK(fw_ring_pop(&r, &x) && x == i);
    for (int i = 0; i < 6; i++) CHECK(fw_ring_pop(&r, &x) && x == i);
    CHECK(!fw_ring_pop(&r, &x));
    CHECK_EQ(fw_ring_fill(&r), 0);

    /* the free-running 16-bit indices wrap past 2^16 many times: order and fill hold */
    fw_ring_init(&r);
    int16_t next_in = 0, next_out = 0;
    long bad = 0, pushed = 0;
    for (int round = 0; round < 12000; round++) {
        int16_t batch[HP_MAX_SAMPLES];
        uint16_t n = (uint16_t)(1 + round % HP_MAX_SAMPLES);
        for (uint16_t i = 0; i < n; i++) batch[i] = (int16_t)(next_in + i);
        if (fw_ring_push(&r, batch, n)) next_in = (int16_t)(next_in + n), pushed += n;
        for (int k = 0; k < (round % 7 == 0 ? 60 : 14); k++) {
            if (!fw_ring_pop(&r, &x)) break;
            if (x != next_out) bad++;
            next_out = (int16_t)(next_out + 1);
        }
        if (fw_ring_fill(&r) != (uint16_t)(next_in - next_out)) bad++;
    }
    CHECK_EQ(bad, 0);
    CHECK(pushed > 2 * 65536); /* the indices did wrap past 2^16 */
    CHECK_EQ(atomic_load(&r.tail), (uint16_t)pushed);

    /* a clear asked for by the producer (STOP): drops what was queued then, keeps what the
     * producer pushed after it; the producer counts the dropped slots until the tick applies it */
    fw_ring_init(&r);
    CHECK(fw_ring_push(&r, v, 200));
    CHECK(fw_ring_pop(&r, &x) && x == 0);
    fw_ring_request_clear(&r);
    CHECK_EQ(fw_ring_fill(&r), 0);                /* what the tick will see */
    CHECK(fw_ring_push(&r, v + 100, 50));         /* 199 + 50 <= 256: room without the clear */
    CHECK(!fw_ring_push(&r, v, 10));              /* 249 + 10: the dropped slots still count */
    CHECK_EQ(fw_ring_fill(&r), 50);
    CHECK(fw_ring_pop(&r, &x) && x == 100);       /* the tick applies the clear */
    CHECK(fw_ring_push(&r, v, 200));              /* now the room is back */
    CHECK_EQ(fw_ring_fill(&r), 249);
    /* a clear_to the consumer already played past (rewritten by a second request) is ignored */
    fw_ring_init(&r);
    CHECK(fw_ring_push(&r, v, 10));
    fw_ring_request_clear(&r);                    /* clear_to = 10 */
    CHECK(!fw_ring_pop(&r, &x));                  /* applied: empty */
    CHECK(fw_ring_push(&r, v, 5));
    CHECK(fw_ring_pop(&r, &x) && x == 0);
    atomic_fetch_add(&r.clear_req, 1); /* as if a request's counter landed, its clear_to stale (10) */
    atomic_store(&r.clear_to, 10);
    CHECK(fw_ring_pop(&r, &x) && x == 1); /* 10 is behind head 11: not a step back */
    /* the consumer's clear (host timeout) */
    fw_ring_clear(&r);
    CHECK_EQ(fw_ring_fill(&r), 0);
    CHECK(!fw_ring_pop(&r, &x));
}

static void test_quadrature(void) {
    static const uint8_t g[4] = {0, 1, 3, 2};
    fw_quad_t q;
    fw_quad_init(&q, 0);
    for (int i = 1; i <= 400; i++) fw_quad_update(&q, g[i & 3]);
    CHECK_EQ(q.count, 400);
    for (int i = 399; i >= -100; i--) fw_quad_update(&q, g[i & 3]);
    CHECK_EQ(q.count, (uint32_t)-100); /* wrapped below zero, modulo 2^32 */
    CHECK_EQ(q.errors, 0);
    uint8_t cur = g[(-100) & 3];
    fw_quad_update(&q, cur ^ 3u); /* both pins at once: a missed edge */
    CHECK_EQ(q.errors, 1);
    CHECK_EQ(q.count, (uint32_t)-100);
    fw_quad_update(&q, cur ^ 3u); /* no change: nothing */
    CHECK_EQ(q.errors, 1);
}

static fw_t *running(void) {
    static fw_t f;
    reset_fakes();
    fw_init(&f, 0);
    uint8_t start = HP_ID_START;
    fw_on_message(&f, &start, 1);
    return &f;
}

static void push(fw_t *f, const int16_t *v, uint8_t n, uint16_t seq) {
    uint8_t m[HP_REPORT_SIZE] = {HP_ID_SAMPLES, 0, (uint8_t)seq, (uint8_t)(seq >> 8), n};
    for (uint8_t i = 0; i < n; i++) {
        m[5 + 2 * i] = (uint8_t)((uint16_t)v[i] & 0xFF);
        m[6 + 2 * i] = (uint8_t)((uint16_t)v[i] >> 8);
    }
    fw_on_message(f, m, HP_REPORT_SIZE); /* padded like a HID report */
}

static void test_playout_underrun_and_status(void) {
    fw_t *f = running();
    int16_t v[3] = {10, 20, 30};
    push(f, v, 3, 1);
    for (int i = 0; i < 3; i++) tick(f);
    CHECK_EQ(dac_log[0], 10);
    CHECK_EQ(dac_log[2], 30);
    CHECK_EQ(f->samples_played, 3);
    CHECK_EQ(sent_n, 1); /* a STATUS every 3 ticks */
    CHECK_EQ(sent[0][0], HP_ID_STATUS);
    CHECK_EQ(rd(sent[0] + HP_STATUS_OFF_SAMPLES_PLAYED, 4), 3);
    CHECK_EQ(rd(sent[0] + HP_STATUS_OFF_LAST_SEQ, 2), 1);
    tick(f); /* empty: one underrun, ramp toward zero */
    tick(f);
    CHECK_EQ(f->underruns, 1); /* counted once per episode */
    CHECK_EQ(dac_log[4], 0);
    CHECK(f->state == HP_STATE_RUNNING);
}

static void test_ramp_to_zero_on_stop_and_timeout(void) {
    fw_t *f = running();
    int16_t v[HP_MAX_SAMPLES];
    for (int i = 0; i < HP_MAX_SAMPLES; i++) v[i] = 16383;
    int16_t ramp_in[HP_MAX_SAMPLES];
    for (int k = 0; k < 3; k++) {
        for (int i = 0; i < HP_MAX_SAMPLES; i++) ramp_in[i] = (int16_t)(k * 5000 + i * 100 > 16383 ? 16383 : k * 5000 + i * 100);
        push(f, ramp_in, HP_MAX_SAMPLES, (uint16_t)k);
    }
    for (int k = 0; k < 3; k++) push(f, v, HP_MAX_SAMPLES, (uint16_t)(3 + k));
    for (int i = 0; i < 120; i++) tick(f);
    CHECK_EQ(f->out, 16383);
    uint8_t stop = HP_ID_STOP;
    fw_on_message(f, &stop, 1);
    int ticks = 0;
    while (f->out != 0 && ticks < 1000) tick(f), ticks++;
    CHECK(ticks >= HP_RAMP_TICKS - 1 && ticks <= HP_RAMP_TICKS + 1); /* a 50 ms ramp, not a jump */
    tick(f);
    CHECK_EQ(f->state, HP_STATE_IDLE);
    /* host timeout */
    f = running();
    push(f, v, 3, 1);
    for (int i = 0; i < 3; i++) tick(f);
    for (int i = 0; i < 3 * HP_DEFAULT_TIMEOUT_MS + 300; i++) tick(f);
    CHECK(f->state != HP_STATE_RUNNING);
    CHECK_EQ(f->out, 0);
}

static void test_limits_only_tighten(void) {
    fw_t *f = running();
    uint8_t m[5] = {HP_ID_SET_LIMITS, 0xFF, 0xFF, 0xFF, 0xFF};
    fw_on_message(f, m, 5);
    CHECK_EQ(f->limit_code, HP_LIMIT_CODE);
    CHECK_EQ(f->max_step_code, HP_MAX_STEP_CODE);
    uint8_t t[5] = {HP_ID_SET_LIMITS, 0x10, 0x27, 0x64, 0x00}; /* 10000, 100 */
    fw_on_message(f, t, 5);
    CHECK_EQ(f->limit_code, 10000);
    CHECK_EQ(f->max_step_code, 100);
    int16_t v[3] = {32767, -32768, 32767};
    push(f, v, 3, 1);
    for (int i = 0; i < 3; i++) tick(f);
    CHECK_EQ(dac_log[0], 100);
    CHECK_EQ(dac_log[1], 0);
    CHECK_EQ(dac_log[2], 100);
}

/* Safety under random input: whatever bytes arrive, every DAC code respects the limits. */
static uint64_t rng = 0x9E3779B97F4A7C15ull;
static uint32_t rnd(void) {
    rng ^= rng << 13, rng ^= rng >> 7, rng ^= rng << 17;
    return (uint32_t)rng;
}

static void test_random_bytes_never_break_safety(void) {
    static fw_t f;
    reset_fakes();
    fw_init(&f, 0);
    int16_t prev = 0;
    long violations = 0;
    uint16_t lim = HP_LIMIT_CODE, step = HP_MAX_STEP_CODE;
    for (long it = 0; it < 300000; it++) {
        uint8_t buf[80];
        size_t n = rnd() % sizeof buf;
        uint32_t mode = rnd() % 8;
        for (size_t i = 0; i < n; i++) buf[i] = (uint8_t)rnd();
        if (mode < 3 && n > 0) { /* well-formed-ish messages with hostile values */
            static const uint8_t ids[] = {HP_ID_SAMPLES, HP_ID_START, HP_ID_STOP, HP_ID_SET_LIMITS,
                                          HP_ID_SET_TIMEOUT, HP_ID_IDENTIFY};
            buf[0] = ids[rnd() % 6];
            if (buf[0] == HP_ID_SAMPLES && n >= 5) {
                buf[1] = 0;
                buf[4] = (uint8_t)((n - 5) / 2);
                if (((n - 5) & 1) != 0) buf[n - 1] = 0;
            }
            fw_on_message(&f, buf, n);
        } else if (mode < 5) {
            fw_on_message(&f, buf, n);
        } else {
            fw_deframer_feed(&f, buf, n);
        }
        lim = f.limit_code, step = f.max_step_code;
        int t = (int)(rnd() % 4);
        for (int k = 0; k < t; k++) {
            tick(&f);
            int16_t o = dac_log[(dac_n - 1) & 0xFFFF];
            /* a limit the host tightens below the present output is approached at the slew
             * limit (a jump would break the slew limit): beyond it only while moving in */
            if ((abs(o) > lim && abs(o) >= abs(prev)) || abs(o - prev) > step) violations++;
            if (o > HP_LIMIT_CODE || o < -HP_LIMIT_CODE || abs(o - prev) > HP_MAX_STEP_CODE) violations++;
            prev = o;
        }
    }
    CHECK_EQ(violations, 0);
    CHECK(f.malformed > 1000); /* the generator did produce garbage */
    CHECK(f.samples_played > 1000); /* and samples that played */
}

int main(int argc, char **argv) {
    test_crc_and_cobs();
    test_ring();
    test_quadrature();
    test_playout_underrun_and_status();
    test_ramp_to_zero_on_stop_and_timeout();
    test_limits_only_tighten();
    test_random_bytes_never_break_safety();
    if (argc > 1) {
        test_vectors(argv[1]);
    } else {
        CHECK(0 && "usage: test_fw VECTORS_FILE");
    }
    printf("firmware: %d checks, %d failures\n", g_checks, g_failures);
    return g_failures ? 1 : 0;
}
