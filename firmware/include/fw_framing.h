/* Serial framing: COBS(msg + CRC16/CCITT-FALSE LE) + 0x00 (docs/protocol.md), src/framing.c.
 * The one C implementation of it: the firmware's, and the host's compiled modules' too
 * (hostd/device/_fastpump.c, _fastlink.c build src/framing.c in), whose reference is
 * hostd.device.protocol (cobs, binascii.crc_hqx). No dependency but the protocol header. */
#ifndef HOSTD_FW_FRAMING_H
#define HOSTD_FW_FRAMING_H

#include <stddef.h>
#include <stdint.h>

#include "hostd_proto.h"

uint16_t fw_crc16(const uint8_t *p, size_t n);
/* Returns the frame length (delimiter included), 0 if out is too small. */
size_t fw_frame(const uint8_t *msg, size_t len, uint8_t *out, size_t cap);
/* Decodes one frame body (without the 0x00 delimiter); returns the message length or -1. */
int fw_unframe(const uint8_t *body, size_t len, uint8_t *out, size_t cap);

#define FW_FRAME_MAX (HP_REPORT_SIZE + 8)

#endif
