"""Writes tests/vectors/protocol.txt, the protocol's golden vectors (PYTHONPATH=. python ...).

Read by BOTH tests/test_protocol.py and firmware/tests/test_fw.c. One vector per line:
  msg NAME HEX field=value ...        a message and its decoded fields (codes=a,b,c; floats
                                      are float32 values written so they parse back exactly)
  frame NAME MSGHEX FRAMEHEX          a message and its serial frame (delimiter included)
  bad NAME HEX                        a message the device must drop and count as malformed
  badframe NAME HEX                   serial bytes whose frame must be dropped and counted
"""

from pathlib import Path

from hostd.device import protocol as pr

OUT = Path(__file__).with_name("protocol.txt")

MSGS = [
    ("samples_3", "SAMPLES", dict(seq=7, codes=[100, -200, 16383])),
    ("samples_max", "SAMPLES", dict(seq=65535, codes=[(-1) ** i * 1000 * i for i in range(pr.MAX_SAMPLES)])),
    ("samples_zero_codes", "SAMPLES", dict(seq=0, codes=[0, 0, 0])),  # zeros inside a frame: COBS
    ("start", "START", {}),
    ("stop", "STOP", {}),
    ("set_limits", "SET_LIMITS", dict(limit_code=8000, max_step_code=500)),
    ("set_timeout", "SET_TIMEOUT", dict(timeout_ms=250)),
    ("identify", "IDENTIFY", {}),
    ("status", "STATUS", dict(state=1, fault_flags=0x0005, device_time_us=4_000_000_123,
                              encoder_count=0xFFFFFFF0, samples_played=123456, buffer_fill=12,
                              last_seq=4242, underruns=1, malformed=3, encoder_errors=2)),
    # a version-1 device's IDENT: v1 messages stay byte-identical in v2
    ("ident", "IDENT", dict(protocol_version=1, fw_major=0, fw_minor=1, fw_patch=0,
                            dac_bits=16, sample_rate_hz=3000, limit_code=16383,
                            max_step_code=8192, buffer_capacity=256, max_samples=29,
                            um_per_count_nm=400)),
    # version 2: device-side rendering
    ("ident_v2", "IDENT", dict(protocol_version=2, fw_major=0, fw_minor=2, fw_patch=0,
                               dac_bits=16, sample_rate_hz=3000, limit_code=16383,
                               max_step_code=8192, buffer_capacity=256, max_samples=29,
                               um_per_count_nm=400)),
    ("load_texture", "LOAD_TEXTURE", dict(slot=3, n_samples=2048, n_coeffs=300, length_nm=12_500_000,
                                          scale=1.5, crc32=0xCBF43926)),
    ("load_chunk", "LOAD_CHUNK", dict(slot=3, first=14, coeffs=[0.1, -2.5, 1e-6, 0.0, 3.25, -0.0078125,
                                                                 1000.0, 0.0, 0.0, 0.5, -0.5, 7.0,
                                                                 1.0, -1.0])),
    ("load_chunk_short", "LOAD_CHUNK", dict(slot=3, first=294, coeffs=[0.25, 0.0])),
    ("load_end", "LOAD_END", dict(slot=3)),
    ("set_eq", "SET_EQ", dict(index=1, n_sections=2, b0=2.0, b1=-1.5, b2=0.625, a1=-0.5, a2=0.25)),
    ("set_band", "SET_BAND", dict(f_stop_hz=400.0, fade_start=0.8)),
    ("set_scale", "SET_SCALE", dict(codes_per_um=409.6)),
    ("set_delay", "SET_DELAY", dict(delay_us=-440)),
    ("start_render", "START_RENDER", dict(host_lost_ms=1000)),
    ("stop_render", "STOP_RENDER", {}),
    ("ack", "ACK", dict(for_id=0x22, slot=3, result=1, detail=300, refused=7)),
    ("caps", "CAPS", dict(render=1, max_components=512, max_sections=4, chunk_coeffs=14,
                          edge_clock_hz=12_000_000, xfade_ticks=150)),
    ("render_status", "RENDER_STATUS", dict(render_state=2, active_slot=3, host_lost=0, speed_mm_s=-52.5,
                                            refused=2, loads=5, host_silent_ms=1, host_lost_count=1,
                                            device_time_us=4_000_000_123, rendered_ticks=0xFFFFFF00,
                                            faded_ticks=450, idle_ticks=123456)),
]

BAD = [
    ("unknown_id", bytes([0x7F])),
    ("empty_id_zero", bytes([0x00, 0x00])),
    ("samples_short", bytes([0x01, 0x00, 0x01])),
    ("samples_count_too_big", bytes([0x01, 0x00, 0x01, 0x00, 30]) + bytes(60)[:59]),
    ("samples_truncated", bytes([0x01, 0x00, 0x01, 0x00, 3, 1, 0, 2, 0])),
    ("samples_flags_set", bytes([0x01, 0x80, 0x01, 0x00, 1, 5, 0])),
    ("start_trailing_garbage", bytes([0x10, 0x01])),
    ("set_limits_zero_step", bytes([0x12, 0x10, 0x00, 0x00, 0x00])),
    ("set_timeout_zero", bytes([0x13, 0x00, 0x00])),
    ("status_from_host", pr.encode("STATUS")),
    ("load_chunk_count_too_big", bytes([0x21, 0x00, 0x00, 0x00, 15]) + bytes(59)),
    ("load_chunk_truncated", bytes([0x21, 0x00, 0x00, 0x00, 2, 0, 0, 0x80, 0x3F])),
    ("load_texture_short", bytes([0x20, 0x00, 0x10, 0x00])),
    ("set_eq_trailing_garbage", pr.encode("SET_EQ") + b"\x01"),
    ("ack_from_host", pr.encode("ACK")),
    ("render_status_from_host", pr.encode("RENDER_STATUS")),
]


def main() -> None:
    fmt = [row for row in __doc__.splitlines() if row.startswith("  ")]
    lines = ["# protocol golden vectors, generated by make_protocol_vectors.py; formats:"] + [
        "#" + row for row in fmt]
    for name, kind, fields in MSGS:
        msg = pr.encode(kind, **fields)
        _, dec = pr.decode(msg)
        parts = [f"{k}={','.join(repr(c) for c in v) if isinstance(v, list) else repr(v)}"
                 for k, v in dec.items()]
        lines.append(f"msg {name} {msg.hex()} " + " ".join(parts))
        lines.append(f"frame {name} {msg.hex()} {pr.frame(msg).hex()}")
    for name, raw in BAD:
        lines.append(f"bad {name} {raw.hex()}")
    good = pr.frame(pr.encode("START"))
    corrupt = bytearray(good)
    corrupt[1] ^= 0x40
    lines.append(f"badframe crc_flip {bytes(corrupt).hex()}")
    lines.append(f"badframe too_short {bytes([0x02, 0x10, 0x00]).hex()}")
    lines.append(f"badframe cobs_code_overrun {bytes([0x09, 0x10, 0x20, 0x00]).hex()}")
    oversize = bytes([0xFF]) + bytes(range(1, 200)) + bytes([0x00])  # longer than any frame
    lines.append(f"badframe oversize {oversize.hex()}")
    OUT.write_text("\n".join(lines) + "\n")
    print(OUT)


if __name__ == "__main__":
    main()
