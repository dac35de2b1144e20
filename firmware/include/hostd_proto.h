/* GENERATED from hostd/device/protocol.toml by `python -m hostd.device.gen_header`.
 * Do not edit: change the TOML and regenerate (a test checks this file is current). */
#ifndef HOSTD_PROTO_H
#define HOSTD_PROTO_H

#define HP_VERSION 1
#define HP_REPORT_SIZE 64
#define HP_MAX_SAMPLES 29
#define HP_SAMPLE_RATE_HZ 3000
#define HP_STATUS_PERIOD_TICKS 3
#define HP_BUFFER_CAPACITY 256
#define HP_DEFAULT_TIMEOUT_MS 50
#define HP_RAMP_TICKS 150
#define HP_DAC_BITS 16
#define HP_LIMIT_CODE 16383
#define HP_MAX_STEP_CODE 8192
#define HP_UM_PER_COUNT_NM 400
#define HP_USB_VID 0x1209
#define HP_USB_PID 0x7470
#define HP_USB_EP_OUT 0x1
#define HP_USB_EP_IN 0x81
#define HP_FW_VERSION_MAJOR 0
#define HP_FW_VERSION_MINOR 1
#define HP_FW_VERSION_PATCH 0

#define HP_ID_SAMPLES 0x01
#define HP_ID_START 0x10
#define HP_ID_STOP 0x11
#define HP_ID_SET_LIMITS 0x12
#define HP_ID_SET_TIMEOUT 0x13
#define HP_ID_IDENTIFY 0x14
#define HP_ID_STATUS 0x81
#define HP_ID_IDENT 0x82

#define HP_STATE_IDLE 0x00
#define HP_STATE_RUNNING 0x01
#define HP_STATE_RAMP_DOWN 0x02

#define HP_FAULT_CLIPPED 0x01
#define HP_FAULT_SLEWED 0x02
#define HP_FAULT_UNDERRUN 0x04
#define HP_FAULT_HOST_TIMEOUT 0x08
#define HP_FAULT_OVERFLOW 0x10
#define HP_FAULT_ENCODER 0x20

#define HP_SAMPLES_OFF_ID 0
#define HP_SAMPLES_OFF_FLAGS 1
#define HP_SAMPLES_OFF_SEQ 2
#define HP_SAMPLES_OFF_COUNT 4
#define HP_SAMPLES_SIZE 5
/* X(name, offset, size, is_signed) for each fixed field */
#define HP_SAMPLES_FIELDS(X) X(id, 0, 1, 0) X(flags, 1, 1, 0) X(seq, 2, 2, 0) X(count, 4, 1, 0)

#define HP_START_OFF_ID 0
#define HP_START_SIZE 1
/* X(name, offset, size, is_signed) for each fixed field */
#define HP_START_FIELDS(X) X(id, 0, 1, 0)

#define HP_STOP_OFF_ID 0
#define HP_STOP_SIZE 1
/* X(name, offset, size, is_signed) for each fixed field */
#define HP_STOP_FIELDS(X) X(id, 0, 1, 0)

#define HP_SET_LIMITS_OFF_ID 0
#define HP_SET_LIMITS_OFF_LIMIT_CODE 1
#define HP_SET_LIMITS_OFF_MAX_STEP_CODE 3
#define HP_SET_LIMITS_SIZE 5
/* X(name, offset, size, is_signed) for each fixed field */
#define HP_SET_LIMITS_FIELDS(X) X(id, 0, 1, 0) X(limit_code, 1, 2, 0) X(max_step_code, 3, 2, 0)

#define HP_SET_TIMEOUT_OFF_ID 0
#define HP_SET_TIMEOUT_OFF_TIMEOUT_MS 1
#define HP_SET_TIMEOUT_SIZE 3
/* X(name, offset, size, is_signed) for each fixed field */
#define HP_SET_TIMEOUT_FIELDS(X) X(id, 0, 1, 0) X(timeout_ms, 1, 2, 0)

#define HP_IDENTIFY_OFF_ID 0
#define HP_IDENTIFY_SIZE 1
/* X(name, offset, size, is_signed) for each fixed field */
#define HP_IDENTIFY_FIELDS(X) X(id, 0, 1, 0)

#define HP_STATUS_OFF_ID 0
#define HP_STATUS_OFF_STATE 1
#define HP_STATUS_OFF_FAULT_FLAGS 2
#define HP_STATUS_OFF_DEVICE_TIME_US 4
#define HP_STATUS_OFF_ENCODER_COUNT 8
#define HP_STATUS_OFF_SAMPLES_PLAYED 12
#define HP_STATUS_OFF_BUFFER_FILL 16
#define HP_STATUS_OFF_LAST_SEQ 18
#define HP_STATUS_OFF_UNDERRUNS 20
#define HP_STATUS_OFF_MALFORMED 22
#define HP_STATUS_OFF_ENCODER_ERRORS 24
#define HP_STATUS_SIZE 26
/* X(name, offset, size, is_signed) for each fixed field */
#define HP_STATUS_FIELDS(X) X(id, 0, 1, 0) X(state, 1, 1, 0) X(fault_flags, 2, 2, 0) X(device_time_us, 4, 4, 0) X(encoder_count, 8, 4, 0) X(samples_played, 12, 4, 0) X(buffer_fill, 16, 2, 0) X(last_seq, 18, 2, 0) X(underruns, 20, 2, 0) X(malformed, 22, 2, 0) X(encoder_errors, 24, 2, 0)

#define HP_IDENT_OFF_ID 0
#define HP_IDENT_OFF_PROTOCOL_VERSION 1
#define HP_IDENT_OFF_FW_MAJOR 3
#define HP_IDENT_OFF_FW_MINOR 4
#define HP_IDENT_OFF_FW_PATCH 5
#define HP_IDENT_OFF_DAC_BITS 6
#define HP_IDENT_OFF_SAMPLE_RATE_HZ 7
#define HP_IDENT_OFF_LIMIT_CODE 11
#define HP_IDENT_OFF_MAX_STEP_CODE 13
#define HP_IDENT_OFF_BUFFER_CAPACITY 15
#define HP_IDENT_OFF_MAX_SAMPLES 17
#define HP_IDENT_OFF_UM_PER_COUNT_NM 18
#define HP_IDENT_SIZE 20
/* X(name, offset, size, is_signed) for each fixed field */
#define HP_IDENT_FIELDS(X) X(id, 0, 1, 0) X(protocol_version, 1, 2, 0) X(fw_major, 3, 1, 0) X(fw_minor, 4, 1, 0) X(fw_patch, 5, 1, 0) X(dac_bits, 6, 1, 0) X(sample_rate_hz, 7, 4, 0) X(limit_code, 11, 2, 0) X(max_step_code, 13, 2, 0) X(buffer_capacity, 15, 2, 0) X(max_samples, 17, 1, 0) X(um_per_count_nm, 18, 2, 0)

#endif
