/* What the firmware's Linux ports share (port/host: a pseudo-terminal, port/gadget: a USB
 * gadget): the 3 kHz tick from clock_nanosleep(TIMER_ABSTIME), the simulated hand turned into
 * encoder edges, the DAC log and the per-tick clock log, and the options for all of these.
 * A port supplies hal_send, its own options and a poll hook that feeds what the host sent.
 *
 * Options handled here:
 *   --ppm N  --ppm-after SECONDS:N  --motion none|constant:MM_S|metronome|steps:PERIOD_S:MM
 *   --log FILE  --duration SECONDS  --glitch-at SECONDS  --jump-at SECONDS:MM  --clock FILE
 *   --scenario FILE
 * (see port/host/main.c for what each does) */
#ifndef HOSTD_PORT_SIM_H
#define HOSTD_PORT_SIM_H

#include <stdbool.h>
#include <stddef.h>
#include <stdint.h>
#include <time.h>

#include "fw.h"

typedef struct {
    const char *prog; /* program name for messages */
    /* a port option: returns 2 if it took `a` and its value `v`, 1 if it took `a` alone, 0 if
     * it does not know `a`, -1 after printing a one-line error (exit code 2) */
    int (*option)(const char *a, const char *v);
    /* every tick, before the core's tick: hand the core what the host sent; t_s is real time
     * since tick 0 */
    void (*poll)(fw_t *f, double t_s);
    /* on SIGTERM/SIGINT: stop the output through the core's own STOP ramp before returning */
    bool ramp_on_stop;
} sim_port_t;

/* Parses argv (the shared options and the port's); returns 0, or the exit code (1 or 2). */
int sim_parse(const sim_port_t *port, int argc, char **argv);
/* Installs the signal handlers and reads the clock of tick 0. */
struct timespec sim_start(void);
/* Runs ticks until --duration or a signal; returns the number of ticks run. */
void sim_run(fw_t *f, const sim_port_t *port, struct timespec t0);
/* Closes the logs and prints the summary line on stderr. */
void sim_finish(const fw_t *f, const sim_port_t *port, unsigned long sends_dropped);
/* For a port's poll: record received raw bytes in the --scenario file. */
void sim_scenario_rx(const uint8_t *bytes, size_t n);
/* True once SIGTERM/SIGINT arrived (for a port's blocking waits). */
bool sim_stopping(void);

#endif
