/* GENERATED from hostd/device/cycle_state.toml by `python -m hostd.device.gen_header`.
 * Do not edit: change the TOML and regenerate (a test checks this file is current).
 * The layout is the ctypes.Structure of hostd.cyclestate.record(kind): a stage object is
 * read as its struct through the buffer protocol. */
#ifndef HOSTD_CYCLE_STATE_H
#define HOSTD_CYCLE_STATE_H

#include <stdbool.h>
#include <stdint.h>

typedef struct {
    double last_um;
    double envelope;
    double target_envelope;
    double limit_um;
    double max_step_um;
    double ramp_step;
    double _codes_per_um;
    int64_t _limit_code;
    int64_t nonfinite;
    int64_t clipped;
} hs_output_t;

/* X(kind) per record: hs_<kind>_t */
#define HS_RECORDS(X) X(output)

#endif
