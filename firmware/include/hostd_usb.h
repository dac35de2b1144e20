/* The display's USB identity: one source for the board port (src/usb/usbd.c builds its
 * descriptors from it) and the Linux USB gadget port (port/gadget/main.c writes it into
 * configfs), so what the VM rig (tests/hil) enumerates is what the board enumerates as.
 * VID/PID, endpoints and the report size come from hostd_proto.h (generated from
 * hostd/device/protocol.toml). */
#ifndef HOSTD_USB_H
#define HOSTD_USB_H

#include "hostd_proto.h"

#define HOSTD_USB_MANUFACTURER "hostd"
#define HOSTD_USB_PRODUCT "hostd vibrotactile display"
/* bcdDevice: the firmware version, 0xMMmp */
#define HOSTD_USB_BCD_DEVICE ((HP_FW_VERSION_MAJOR << 8) | (HP_FW_VERSION_MINOR << 4) | HP_FW_VERSION_PATCH)
#define HOSTD_USB_MAX_POWER_MA 100
#define HOSTD_USB_INTERVAL_MS 1
/* the serial number: the chip's 96-bit unique ID as 24 upper-case hex digits */
#define HOSTD_USB_SERIAL_CHARS 24u
/* HID interface: class 3, no boot subclass, no protocol */
#define HOSTD_USB_HID_SUBCLASS 0
#define HOSTD_USB_HID_PROTOCOL 0

/* The HID report descriptor, as an initializer: vendor-defined page, no report IDs, one
 * HP_REPORT_SIZE-byte input and one output report. */
#define HOSTD_USB_HID_REPORT_DESC                                                                 \
    {                                                                                              \
        0x06, 0x00, 0xFF,           /* Usage Page (Vendor Defined 0xFF00) */                       \
            0x09, 0x01,             /* Usage (1) */                                                \
            0xA1, 0x01,             /* Collection (Application) */                                 \
            0x15, 0x00,             /*   Logical Minimum (0) */                                    \
            0x26, 0xFF, 0x00,       /*   Logical Maximum (255) */                                  \
            0x75, 0x08,             /*   Report Size (8) */                                        \
            0x95, HP_REPORT_SIZE,   /*   Report Count (HP_REPORT_SIZE) */                          \
            0x09, 0x02,             /*   Usage (2) */                                              \
            0x81, 0x02,             /*   Input (Data, Variable, Absolute) */                       \
            0x95, HP_REPORT_SIZE,   /*   Report Count (HP_REPORT_SIZE) */                          \
            0x09, 0x03,             /*   Usage (3) */                                              \
            0x91, 0x02,             /*   Output (Data, Variable, Absolute) */                      \
            0xC0,                   /* End Collection */                                           \
    }
#define HOSTD_USB_HID_REPORT_DESC_LEN 27u

#endif
