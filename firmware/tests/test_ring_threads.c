/* The ring under real concurrency: a producer thread (message handling) and a consumer thread
 * (the tick) on two cores, built with ThreadSanitizer (make ring-tsan): every sample comes
 * out once and in order, clears asked for by the producer drop only older samples, and TSan
 * reports no data race. Usage: test_ring_threads [SAMPLES] */
#include <pthread.h>
#include <stdio.h>
#include <stdlib.h>

#include "fw.h"

static fw_ring_t g_ring;
static long g_total = 2000000;
static _Atomic int g_done;
static _Atomic long g_pushed;
static _Atomic long g_cleared_before; /* the producer's sequence number at its last clear */

static void *producer(void *arg) {
    (void)arg;
    long seq = 0;
    unsigned rng = 12345;
    while (seq < g_total) {
        int16_t batch[HP_MAX_SAMPLES];
        rng = rng * 1103515245u + 12345u;
        uint16_t n = (uint16_t)(1 + (rng >> 16) % HP_MAX_SAMPLES);
        for (uint16_t i = 0; i < n; i++) batch[i] = (int16_t)((seq + i) & 0x7FFF);
        if (fw_ring_push(&g_ring, batch, n)) {
            seq += n;
            if ((rng >> 8) % 997 == 0) { /* now and then a STOP */
                atomic_store(&g_cleared_before, seq);
                fw_ring_request_clear(&g_ring);
            }
        }
    }
    atomic_store(&g_pushed, seq);
    atomic_store(&g_done, 1);
    return NULL;
}

int main(int argc, char **argv) {
    if (argc > 1) g_total = atol(argv[1]);
    fw_ring_init(&g_ring);
    pthread_t t;
    pthread_create(&t, NULL, producer, NULL);
    long got = 0, bad = 0, skipped = 0;
    int16_t expect = 0, x;
    for (;;) {
        if (fw_ring_pop(&g_ring, &x)) {
            if (x != expect) {
                /* only a clear may skip ahead, and only forward */
                int16_t gap = (int16_t)((x - expect) & 0x7FFF);
                if (gap <= 0 || gap > HP_BUFFER_CAPACITY) bad++;
                skipped += gap;
            }
            expect = (int16_t)((x + 1) & 0x7FFF);
            got++;
            if (fw_ring_fill(&g_ring) > HP_BUFFER_CAPACITY) bad++;
        } else if (atomic_load(&g_done) && fw_ring_fill(&g_ring) == 0) {
            break;
        }
    }
    pthread_join(t, NULL);
    printf("ring threads: %ld popped, %ld dropped by clears, %ld out of order\n", got, skipped, bad);
    return (bad == 0 && got > 0 && got + skipped <= atomic_load(&g_pushed)) ? 0 : 1;
}
