/* Prints the board port's USB descriptors as hex, one line each: "device HEX", "config HEX",
 * "report HEX". tests/test_hil.py compares them with what the kernel read from the gadget port. */
#include <stdio.h>

#include "usbd.h"

static void line(const char *name, const uint8_t *p, unsigned n) {
    printf("%s ", name);
    for (unsigned i = 0; i < n; i++) printf("%02x", p[i]);
    printf("\n");
}

int main(void) {
    line("device", usbd_device_desc, sizeof usbd_device_desc);
    line("config", usbd_config_desc, USBD_CONFIG_DESC_LEN);
    line("report", usbd_hid_report_desc, usbd_hid_report_desc_len);
    return 0;
}
