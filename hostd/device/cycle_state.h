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

typedef struct {
    double um_per_count;
    int64_t _last;
    bool _last_set;
    int64_t _total;
} hs_position_t;

typedef struct {
    double _c0;
    double _c1;
    double _c2;
    double _c3;
    double _t_ref;
    double _rest_x;
    bool _rest_x_set;
    int64_t _dt_us;
    int64_t _uniform;
    int64_t _since_restart;
    int64_t glitches;
    int64_t relocks;
    int64_t implausible;
    int64_t _window;
    int64_t _order;
    double _glitch_um;
    double _rest_speed_mm_s;
    double _rest_hold_um;
    double _max_predict_s;
    double _max_gap_s;
    double _max_speed_mm_s;
} hs_motion_t;

typedef struct {
    int64_t n;
    double length_mm;
    double _v_full_mm_s;
    int64_t _w_bucket;
    bool _w_bucket_set;
    double _speed_bucket;
} hs_height_t;

typedef struct {
    double latency_s;
    int64_t _xfade_left;
    int64_t _samples_per_batch;
} hs_renderer_t;

typedef struct {
    int64_t underruns;
    int64_t samples_played;
    int64_t state;
    double _time_s;
    bool _sel_active;
    bool _sel_device;
    bool _sel_started;
    double _sel_due;
    int64_t _sel_played;
} hs_health_t;

typedef struct {
    int64_t target_fill;
    int64_t _seq;
    int64_t _time_hi;
    int64_t _last_us;
    bool _last_us_set;
    double device_time_s;
    double status_host_time;
    double _offset_s;
    bool _offset_s_set;
    double _offset_host_t;
    int64_t _fill_from_seq;
    bool _fill_from_seq_set;
} hs_link_t;

typedef struct {
    int64_t statuses;
    int64_t messages_sent;
    int64_t samples_sent;
} hs_link_stats_t;

typedef struct {
    double period_s;
    int64_t _extra;
    int64_t _fill;
    int64_t _flags_seen;
    int64_t _under_seen;
    int64_t _last_samples_played;
    bool _last_samples_played_set;
    double _last_played_dev_s;
    bool _last_played_dev_s_set;
    double _last_decay;
    int64_t _low_fill;
    double _last_cycle_start;
    bool _last_cycle_start_set;
    int64_t _guard_seq;
    bool _guard_seq_set;
    double _guard_host_t;
    int64_t _base_fill;
    double _quiet_s;
} hs_pump_t;

typedef struct {
    int64_t cycles;
    int64_t deadline_misses;
    int64_t late_batches;
    double max_late_us;
    int64_t samples;
    int64_t relocks;
    int64_t implausible_speed;
} hs_pump_stats_t;

/* X(kind) per record: hs_<kind>_t */
#define HS_RECORDS(X) X(output) X(position) X(motion) X(height) X(renderer) X(health) X(link) X(link_stats) X(pump) X(pump_stats)

#endif
