/* Host port: the firmware core running in real time on Linux.
 *
 * The serial framing on a pseudo-terminal (its slave path is printed on stdout as "PTY <path>");
 * the 3 kHz tick, the simulated hand turned into encoder edges and the log of every DAC code
 * (binary records, see log_tick) are port/common/sim.c, shared with the USB gadget port.
 *
 * usage: hostd-fw-host [--ppm N] [--ppm-after SECONDS:N]
 *                      [--motion none|constant:MM_S|metronome|steps:PERIOD_S:MM]
 *                      [--log FILE] [--duration SECONDS] [--glitch-at SECONDS]
 *                      [--jump-at SECONDS:MM] [--clock FILE] [--scenario FILE]
 *
 * --clock writes, for every tick, when it actually ran: 12-byte records LE u32 tick, f64
 * CLOCK_MONOTONIC seconds (so tests can place host events, e.g. a SIGCONT, on the device's
 * tick axis even when the host port itself ran late); flushed every 30 ticks, so a test can
 * follow the device's clock while the port runs.
 * --jump-at moves the simulated hand by MM at once at SECONDS (and keeps it there): a real
 * jump (the hand lifted and set down elsewhere), which the host's motion estimate must re-lock
 * to. The encoder still steps through every count in between, within one tick.
 * --scenario FILE writes everything the core was given, as a fw-replay scenario (received
 * bytes "r HEX", timed edges, ticks).
 */
#define _GNU_SOURCE
#include <errno.h>
#include <fcntl.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <termios.h>
#include <unistd.h>

#include "fw.h"
#include "hal.h"
#include "sim.h"

static int g_master = -1;
static unsigned long g_send_dropped;

void hal_send(const uint8_t *msg, size_t len) {
    uint8_t fr[FW_FRAME_MAX + 4];
    size_t n = fw_frame(msg, len, fr, sizeof fr);
    if (n == 0 || g_master < 0) {
        return;
    }
    ssize_t w = write(g_master, fr, n);
    if (w != (ssize_t)n) {
        g_send_dropped++; /* host not reading: like a NAKed IN endpoint, drop */
    }
}

static int open_pty(char *name, size_t cap, int *slave_keep) {
    int m = posix_openpt(O_RDWR | O_NOCTTY);
    if (m < 0 || grantpt(m) != 0 || unlockpt(m) != 0) {
        return -1;
    }
    if (ptsname_r(m, name, cap) != 0) {
        return -1;
    }
    /* raw mode on the slave: no echo, no line editing, no CR/NL translation */
    int s = open(name, O_RDWR | O_NOCTTY);
    if (s < 0) {
        return -1;
    }
    struct termios tio;
    tcgetattr(s, &tio);
    cfmakeraw(&tio);
    tcsetattr(s, TCSANOW, &tio);
    *slave_keep = s; /* kept open so the master never sees a hang-up between host sessions */
    fcntl(m, F_SETFL, fcntl(m, F_GETFL) | O_NONBLOCK);
    return m;
}

/* everything the host has written to the pty so far, through the deframer. The port reads until
 * nothing is left, and so waits, when the host's bytes are still in the pty's flip buffer, for
 * the kernel's buffer work (n_tty_read -> tty_buffer_flush_work) to hand them over: a late tick
 * that the log flags (LATE_TICK), which the tests and the latency bench count as the rig's own.
 * Reading only what TIOCINQ counts (as the host's side does) made no tick late but left those
 * bytes for a later tick: the device then ran dry with neither a late tick nor a host pause to
 * show for it (the clock-drift test under a loaded suite, 2026-11-27). A real display has no
 * kworker between the wire and its buffer; this wait is the pty's, and is said as such. */
static void poll_pty(fw_t *f, double t_s) {
    (void)t_s;
    uint8_t rx[4096];
    for (;;) {
        ssize_t n = read(g_master, rx, sizeof rx);
        if (n <= 0) break;
        fw_deframer_feed(f, rx, (size_t)n);
        sim_scenario_rx(rx, (size_t)n);
    }
}

int main(int argc, char **argv) {
    static const sim_port_t port = {"hostd-fw-host", NULL, poll_pty, false};
    int rc = sim_parse(&port, argc, argv);
    if (rc) return rc;
    char name[128];
    int slave = -1;
    g_master = open_pty(name, sizeof name, &slave);
    if (g_master < 0) {
        fprintf(stderr, "hostd-fw-host: cannot open a pseudo-terminal: %s\n", strerror(errno));
        return 1;
    }
    static fw_t f;
    fw_init(&f, 0);
    struct timespec t0 = sim_start();
    /* T0: CLOCK_MONOTONIC of tick 0, so tests can map host events to ticks (tick k is due at
     * T0 + k / 3000 s at 0 ppm) */
    printf("PTY %s T0 %.6f\n", name, (double)t0.tv_sec + (double)t0.tv_nsec * 1e-9);
    fflush(stdout);
    sim_run(&f, &port, t0);
    sim_finish(&f, &port, g_send_dropped);
    close(slave);
    close(g_master);
    return 0;
}
