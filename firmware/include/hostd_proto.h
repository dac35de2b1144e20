/* GENERATED from hostd/device/protocol.toml by `python -m hostd.device.gen_header`.
 * Do not edit: change the TOML and regenerate (a test checks this file is current). */
#ifndef HOSTD_PROTO_H
#define HOSTD_PROTO_H

#define HP_VERSION 2
#define HP_MIN_VERSION 1
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
#define HP_FW_VERSION_MINOR 5
#define HP_FW_VERSION_PATCH 0

#define HP_RENDER_MAX_COMPONENTS 512
#define HP_RENDER_MAX_SECTIONS 4
#define HP_RENDER_CHUNK_COEFFS 14
#define HP_RENDER_EDGE_CLOCK_HZ 12000000
#define HP_RENDER_XFADE_TICKS 150
#define HP_RENDER_STATUS_PERIOD_TICKS 900
#define HP_RENDER_DEFAULT_HOST_LOST_MS 1000
#define HP_RENDER_STILL_MS 500
#define HP_RENDER_MAX_LENGTH_NM 2000000000

#define HP_ID_SAMPLES 0x01
#define HP_ID_START 0x10
#define HP_ID_STOP 0x11
#define HP_ID_SET_LIMITS 0x12
#define HP_ID_SET_TIMEOUT 0x13
#define HP_ID_IDENTIFY 0x14
#define HP_ID_STATUS 0x81
#define HP_ID_IDENT 0x82
#define HP_ID_LOAD_TEXTURE 0x20
#define HP_ID_LOAD_CHUNK 0x21
#define HP_ID_LOAD_END 0x22
#define HP_ID_SET_EQ 0x23
#define HP_ID_SET_BAND 0x24
#define HP_ID_SET_SCALE 0x25
#define HP_ID_SET_DELAY 0x26
#define HP_ID_START_RENDER 0x27
#define HP_ID_STOP_RENDER 0x28
#define HP_ID_ACK 0x83
#define HP_ID_CAPS 0x84
#define HP_ID_RENDER_STATUS 0x85

#define HP_STATE_IDLE 0x00
#define HP_STATE_RUNNING 0x01
#define HP_STATE_RAMP_DOWN 0x02
#define HP_STATE_RENDERING 0x03

#define HP_FAULT_CLIPPED 0x01
#define HP_FAULT_SLEWED 0x02
#define HP_FAULT_UNDERRUN 0x04
#define HP_FAULT_HOST_TIMEOUT 0x08
#define HP_FAULT_OVERFLOW 0x10
#define HP_FAULT_ENCODER 0x20
#define HP_FAULT_REFUSED 0x40
#define HP_FAULT_HOST_LOST 0x80

#define HP_RSTATE_OFF 0x00
#define HP_RSTATE_FADE_IN 0x01
#define HP_RSTATE_ON 0x02
#define HP_RSTATE_CROSSFADE 0x03
#define HP_RSTATE_FADE_OUT 0x04

#define HP_RESULT_OK 0x00
#define HP_RESULT_BAD_CRC 0x01
#define HP_RESULT_TOO_LARGE 0x02
#define HP_RESULT_NONFINITE 0x03
#define HP_RESULT_TRUNCATED 0x04
#define HP_RESULT_OUT_OF_ORDER 0x05
#define HP_RESULT_BAD_PARAM 0x06
#define HP_RESULT_BUSY 0x07
#define HP_RESULT_NO_TEXTURE 0x08

#define HP_SAMPLES_OFF_ID 0
#define HP_SAMPLES_OFF_FLAGS 1
#define HP_SAMPLES_OFF_SEQ 2
#define HP_SAMPLES_OFF_COUNT 4
#define HP_SAMPLES_SIZE 5
#define HP_SAMPLES_MAX_CODES 29
/* X(name, offset, size, kind) per fixed field; kind 0 unsigned, 1 signed, 2 f32 */
#define HP_SAMPLES_FIELDS(X) X(id, 0, 1, 0) X(flags, 1, 1, 0) X(seq, 2, 2, 0) X(count, 4, 1, 0)

#define HP_START_OFF_ID 0
#define HP_START_SIZE 1
/* X(name, offset, size, kind) per fixed field; kind 0 unsigned, 1 signed, 2 f32 */
#define HP_START_FIELDS(X) X(id, 0, 1, 0)

#define HP_STOP_OFF_ID 0
#define HP_STOP_SIZE 1
/* X(name, offset, size, kind) per fixed field; kind 0 unsigned, 1 signed, 2 f32 */
#define HP_STOP_FIELDS(X) X(id, 0, 1, 0)

#define HP_SET_LIMITS_OFF_ID 0
#define HP_SET_LIMITS_OFF_LIMIT_CODE 1
#define HP_SET_LIMITS_OFF_MAX_STEP_CODE 3
#define HP_SET_LIMITS_SIZE 5
/* X(name, offset, size, kind) per fixed field; kind 0 unsigned, 1 signed, 2 f32 */
#define HP_SET_LIMITS_FIELDS(X) X(id, 0, 1, 0) X(limit_code, 1, 2, 0) X(max_step_code, 3, 2, 0)

#define HP_SET_TIMEOUT_OFF_ID 0
#define HP_SET_TIMEOUT_OFF_TIMEOUT_MS 1
#define HP_SET_TIMEOUT_SIZE 3
/* X(name, offset, size, kind) per fixed field; kind 0 unsigned, 1 signed, 2 f32 */
#define HP_SET_TIMEOUT_FIELDS(X) X(id, 0, 1, 0) X(timeout_ms, 1, 2, 0)

#define HP_IDENTIFY_OFF_ID 0
#define HP_IDENTIFY_SIZE 1
/* X(name, offset, size, kind) per fixed field; kind 0 unsigned, 1 signed, 2 f32 */
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
/* X(name, offset, size, kind) per fixed field; kind 0 unsigned, 1 signed, 2 f32 */
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
/* X(name, offset, size, kind) per fixed field; kind 0 unsigned, 1 signed, 2 f32 */
#define HP_IDENT_FIELDS(X) X(id, 0, 1, 0) X(protocol_version, 1, 2, 0) X(fw_major, 3, 1, 0) X(fw_minor, 4, 1, 0) X(fw_patch, 5, 1, 0) X(dac_bits, 6, 1, 0) X(sample_rate_hz, 7, 4, 0) X(limit_code, 11, 2, 0) X(max_step_code, 13, 2, 0) X(buffer_capacity, 15, 2, 0) X(max_samples, 17, 1, 0) X(um_per_count_nm, 18, 2, 0)

#define HP_LOAD_TEXTURE_OFF_ID 0
#define HP_LOAD_TEXTURE_OFF_SLOT 1
#define HP_LOAD_TEXTURE_OFF_N_SAMPLES 2
#define HP_LOAD_TEXTURE_OFF_N_COEFFS 4
#define HP_LOAD_TEXTURE_OFF_LENGTH_NM 6
#define HP_LOAD_TEXTURE_OFF_SCALE 10
#define HP_LOAD_TEXTURE_OFF_CRC32 14
#define HP_LOAD_TEXTURE_SIZE 18
/* X(name, offset, size, kind) per fixed field; kind 0 unsigned, 1 signed, 2 f32 */
#define HP_LOAD_TEXTURE_FIELDS(X) X(id, 0, 1, 0) X(slot, 1, 1, 0) X(n_samples, 2, 2, 0) X(n_coeffs, 4, 2, 0) X(length_nm, 6, 4, 0) X(scale, 10, 4, 2) X(crc32, 14, 4, 0)

#define HP_LOAD_CHUNK_OFF_ID 0
#define HP_LOAD_CHUNK_OFF_SLOT 1
#define HP_LOAD_CHUNK_OFF_FIRST 2
#define HP_LOAD_CHUNK_OFF_COUNT 4
#define HP_LOAD_CHUNK_SIZE 5
#define HP_LOAD_CHUNK_MAX_COEFFS 14
/* X(name, offset, size, kind) per fixed field; kind 0 unsigned, 1 signed, 2 f32 */
#define HP_LOAD_CHUNK_FIELDS(X) X(id, 0, 1, 0) X(slot, 1, 1, 0) X(first, 2, 2, 0) X(count, 4, 1, 0)

#define HP_LOAD_END_OFF_ID 0
#define HP_LOAD_END_OFF_SLOT 1
#define HP_LOAD_END_SIZE 2
/* X(name, offset, size, kind) per fixed field; kind 0 unsigned, 1 signed, 2 f32 */
#define HP_LOAD_END_FIELDS(X) X(id, 0, 1, 0) X(slot, 1, 1, 0)

#define HP_SET_EQ_OFF_ID 0
#define HP_SET_EQ_OFF_INDEX 1
#define HP_SET_EQ_OFF_N_SECTIONS 2
#define HP_SET_EQ_OFF_B0 3
#define HP_SET_EQ_OFF_B1 7
#define HP_SET_EQ_OFF_B2 11
#define HP_SET_EQ_OFF_A1 15
#define HP_SET_EQ_OFF_A2 19
#define HP_SET_EQ_SIZE 23
/* X(name, offset, size, kind) per fixed field; kind 0 unsigned, 1 signed, 2 f32 */
#define HP_SET_EQ_FIELDS(X) X(id, 0, 1, 0) X(index, 1, 1, 0) X(n_sections, 2, 1, 0) X(b0, 3, 4, 2) X(b1, 7, 4, 2) X(b2, 11, 4, 2) X(a1, 15, 4, 2) X(a2, 19, 4, 2)

#define HP_SET_BAND_OFF_ID 0
#define HP_SET_BAND_OFF_F_STOP_HZ 1
#define HP_SET_BAND_OFF_FADE_START 5
#define HP_SET_BAND_SIZE 9
/* X(name, offset, size, kind) per fixed field; kind 0 unsigned, 1 signed, 2 f32 */
#define HP_SET_BAND_FIELDS(X) X(id, 0, 1, 0) X(f_stop_hz, 1, 4, 2) X(fade_start, 5, 4, 2)

#define HP_SET_SCALE_OFF_ID 0
#define HP_SET_SCALE_OFF_CODES_PER_UM 1
#define HP_SET_SCALE_SIZE 5
/* X(name, offset, size, kind) per fixed field; kind 0 unsigned, 1 signed, 2 f32 */
#define HP_SET_SCALE_FIELDS(X) X(id, 0, 1, 0) X(codes_per_um, 1, 4, 2)

#define HP_SET_DELAY_OFF_ID 0
#define HP_SET_DELAY_OFF_DELAY_US 1
#define HP_SET_DELAY_SIZE 3
/* X(name, offset, size, kind) per fixed field; kind 0 unsigned, 1 signed, 2 f32 */
#define HP_SET_DELAY_FIELDS(X) X(id, 0, 1, 0) X(delay_us, 1, 2, 1)

#define HP_START_RENDER_OFF_ID 0
#define HP_START_RENDER_OFF_HOST_LOST_MS 1
#define HP_START_RENDER_SIZE 3
/* X(name, offset, size, kind) per fixed field; kind 0 unsigned, 1 signed, 2 f32 */
#define HP_START_RENDER_FIELDS(X) X(id, 0, 1, 0) X(host_lost_ms, 1, 2, 0)

#define HP_STOP_RENDER_OFF_ID 0
#define HP_STOP_RENDER_SIZE 1
/* X(name, offset, size, kind) per fixed field; kind 0 unsigned, 1 signed, 2 f32 */
#define HP_STOP_RENDER_FIELDS(X) X(id, 0, 1, 0)

#define HP_ACK_OFF_ID 0
#define HP_ACK_OFF_FOR_ID 1
#define HP_ACK_OFF_SLOT 2
#define HP_ACK_OFF_RESULT 3
#define HP_ACK_OFF_DETAIL 4
#define HP_ACK_OFF_REFUSED 6
#define HP_ACK_SIZE 8
/* X(name, offset, size, kind) per fixed field; kind 0 unsigned, 1 signed, 2 f32 */
#define HP_ACK_FIELDS(X) X(id, 0, 1, 0) X(for_id, 1, 1, 0) X(slot, 2, 1, 0) X(result, 3, 1, 0) X(detail, 4, 2, 0) X(refused, 6, 2, 0)

#define HP_CAPS_OFF_ID 0
#define HP_CAPS_OFF_RENDER 1
#define HP_CAPS_OFF_MAX_COMPONENTS 2
#define HP_CAPS_OFF_MAX_SECTIONS 4
#define HP_CAPS_OFF_CHUNK_COEFFS 5
#define HP_CAPS_OFF_EDGE_CLOCK_HZ 6
#define HP_CAPS_OFF_XFADE_TICKS 10
#define HP_CAPS_SIZE 12
/* X(name, offset, size, kind) per fixed field; kind 0 unsigned, 1 signed, 2 f32 */
#define HP_CAPS_FIELDS(X) X(id, 0, 1, 0) X(render, 1, 1, 0) X(max_components, 2, 2, 0) X(max_sections, 4, 1, 0) X(chunk_coeffs, 5, 1, 0) X(edge_clock_hz, 6, 4, 0) X(xfade_ticks, 10, 2, 0)

#define HP_RENDER_STATUS_OFF_ID 0
#define HP_RENDER_STATUS_OFF_RENDER_STATE 1
#define HP_RENDER_STATUS_OFF_ACTIVE_SLOT 2
#define HP_RENDER_STATUS_OFF_HOST_LOST 3
#define HP_RENDER_STATUS_OFF_SPEED_MM_S 4
#define HP_RENDER_STATUS_OFF_REFUSED 8
#define HP_RENDER_STATUS_OFF_LOADS 10
#define HP_RENDER_STATUS_OFF_HOST_SILENT_MS 12
#define HP_RENDER_STATUS_OFF_HOST_LOST_COUNT 14
#define HP_RENDER_STATUS_OFF_DEVICE_TIME_US 16
#define HP_RENDER_STATUS_OFF_RENDERED_TICKS 20
#define HP_RENDER_STATUS_OFF_FADED_TICKS 24
#define HP_RENDER_STATUS_OFF_IDLE_TICKS 28
#define HP_RENDER_STATUS_SIZE 32
/* X(name, offset, size, kind) per fixed field; kind 0 unsigned, 1 signed, 2 f32 */
#define HP_RENDER_STATUS_FIELDS(X) X(id, 0, 1, 0) X(render_state, 1, 1, 0) X(active_slot, 2, 1, 0) X(host_lost, 3, 1, 0) X(speed_mm_s, 4, 4, 2) X(refused, 8, 2, 0) X(loads, 10, 2, 0) X(host_silent_ms, 12, 2, 0) X(host_lost_count, 14, 2, 0) X(device_time_us, 16, 4, 0) X(rendered_ticks, 20, 4, 0) X(faded_ticks, 24, 4, 0) X(idle_ticks, 28, 4, 0)

#endif
