/* Gadget port: the firmware core behind a Linux USB gadget, so the host side of the same
 * kernel (or of a machine on the other end of a real cable) sees the display as it is: a HID
 * device 1209:7470 with the board port's descriptors (include/hostd_usb.h), bound by usbhid,
 * with a /dev/hidrawN and a /dev/bus/usb node. Used by the VM rig (tests/hil).
 *
 * The gadget is made through configfs with the kernel's HID function (usb_f_hid): the report
 * descriptor, VID/PID, bcdDevice, strings, serial, report size (= wMaxPacketSize, 64) and the
 * interface class are the board's, byte for byte. Not the board's, and not settable through
 * usb_f_hid: the endpoints' bInterval (the kernel's 10 at full / 4 at high speed, the board's
 * 1 ms) and bcdHID (1.01 vs 1.11); FunctionFS could set those too, but then this program
 * would have to answer the HID class requests itself, which is the USB stack's src/usb/usbd.c and is
 * tested there (tests/test_board_usb.py): what this port adds is the real kernel's host side.
 * The tick, the simulated hand and the DAC log are port/common/sim.c, as in the host port.
 *
 * usage (as root, with configfs, libcomposite, usb_f_hid and a UDC such as dummy_hcd):
 *   hostd-fw-gadget [--udc NAME] [--name NAME] [--serial HEX24] [--unplug-at S:D]...
 *                   [the host port's options: --motion, --log, --duration, --clock, --jump-at, ...]
 * --udc    the controller to bind to (default: the first entry of /sys/class/udc)
 * --name   the gadget's configfs directory (default hostd)
 * --serial the serial number (default: the first 24 hex digits of /etc/machine-id)
 * --unplug-at S:D  unbinds the gadget at S seconds for D seconds (repeatable): the unplug
 * IN reports go out as on the board (usb_fs.c): a STATUS finding the endpoint busy is dropped,
 * other replies wait.
 * Prints "GADGET <udc>" once bound, and "UNPLUG <t>" / "REPLUG <t>" (CLOCK_MONOTONIC seconds) as
 * it unbinds and binds again. SIGTERM/SIGINT ramp the output to zero (the core's STOP) and
 * remove the gadget.
 */
#define _GNU_SOURCE
#include <dirent.h>
#include <errno.h>
#include <fcntl.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/stat.h>
#include <sys/sysmacros.h>
#include <time.h>
#include <unistd.h>

#include "fw.h"
#include "hal.h"
#include "hostd_usb.h"
#include "sim.h"

#define PROG "hostd-fw-gadget"
#define CONFIGFS "/sys/kernel/config/usb_gadget"
#define MAX_UNPLUGS 32

static const uint8_t REPORT_DESC[] = HOSTD_USB_HID_REPORT_DESC;
_Static_assert(sizeof REPORT_DESC == HOSTD_USB_HID_REPORT_DESC_LEN, "hostd_usb.h: length in step");

static char g_udc[256];
static char g_name[64] = "hostd";
static char g_serial[HOSTD_USB_SERIAL_CHARS + 1];
static char g_dir[256]; /* the gadget's configfs directory */
static int g_hidg = -1;
static unsigned long g_send_dropped;
static double g_unplug_at[MAX_UNPLUGS], g_unplug_s[MAX_UNPLUGS];
static int g_n_unplugs, g_next_unplug;
static double g_replug_at = -1; /* while unplugged: when to bind again */

static double mono_s(void) {
    struct timespec t;
    clock_gettime(CLOCK_MONOTONIC, &t);
    return (double)t.tv_sec + (double)t.tv_nsec * 1e-9;
}

/* IN reports, as the board's usb_fs.c sends them: one in flight; a STATUS the host has not made
 * room for is dropped (a newer one follows within 1 ms), any other reply (IDENT, RENDER_STATUS)
 * waits in a small queue and goes out first when the endpoint is free again. */
#define PENDING_MAX 8
static uint8_t g_pending[PENDING_MAX][HP_REPORT_SIZE];
static unsigned g_pending_head, g_pending_count;
static unsigned long g_reply_dropped;

static bool write_report(const uint8_t rep[HP_REPORT_SIZE]) {
    return g_hidg >= 0 && write(g_hidg, rep, HP_REPORT_SIZE) == (ssize_t)HP_REPORT_SIZE;
}

static void flush_pending(void) {
    while (g_pending_count && write_report(g_pending[g_pending_head])) {
        g_pending_head = (g_pending_head + 1) % PENDING_MAX;
        g_pending_count--;
    }
}

void hal_send(const uint8_t *msg, size_t len) {
    uint8_t rep[HP_REPORT_SIZE] = {0};
    if (len == 0 || len > sizeof rep) return;
    memcpy(rep, msg, len);
    flush_pending();
    if (!g_pending_count && write_report(rep)) return;
    if (msg[0] == HP_ID_STATUS) {
        g_send_dropped++;
    } else if (g_pending_count < PENDING_MAX) {
        memcpy(g_pending[(g_pending_head + g_pending_count) % PENDING_MAX], rep, sizeof rep);
        g_pending_count++;
    } else {
        g_reply_dropped++;
    }
}

static int put(const char *rel, const void *data, size_t n) {
    char p[512];
    snprintf(p, sizeof p, "%s/%s", g_dir, rel);
    int fd = open(p, O_WRONLY | O_CLOEXEC);
    if (fd < 0) {
        fprintf(stderr, PROG ": cannot write %s: %s\n", p, strerror(errno));
        return -1;
    }
    ssize_t w = write(fd, data, n);
    int e = errno;
    close(fd);
    if (w != (ssize_t)n) {
        fprintf(stderr, PROG ": cannot write %s: %s\n", p, strerror(e));
        return -1;
    }
    return 0;
}

static int puts_(const char *rel, const char *s) { return put(rel, s, strlen(s)); }

static int mkd(const char *rel) {
    char p[512];
    snprintf(p, sizeof p, "%s%s%s", g_dir, *rel ? "/" : "", rel);
    if (mkdir(p, 0755) != 0) {
        fprintf(stderr, PROG ": cannot create %s: %s\n", p, strerror(errno));
        return -1;
    }
    return 0;
}

static void rm(const char *rel, int link) {
    char p[512];
    snprintf(p, sizeof p, "%s%s%s", g_dir, *rel ? "/" : "", rel);
    if ((link ? unlink(p) : rmdir(p)) != 0 && errno != ENOENT)
        fprintf(stderr, PROG ": cannot remove %s: %s\n", p, strerror(errno));
}

static int bind_udc(bool on) { return on ? puts_("UDC", g_udc) : puts_("UDC", "\n"); }

/* the gadget's /dev/hidgN: the class device whose dev number is the function's */
static int open_hidg(void) {
    char want[32] = {0}, p[512];
    snprintf(p, sizeof p, "%s/functions/hid.usb0/dev", g_dir);
    FILE *fp = fopen(p, "r");
    if (!fp || !fgets(want, sizeof want, fp)) {
        if (fp) fclose(fp);
        fprintf(stderr, PROG ": cannot read %s\n", p);
        return -1;
    }
    fclose(fp);
    unsigned maj, min;
    if (sscanf(want, "%u:%u", &maj, &min) != 2) return -1;
    /* devtmpfs names it hidgN; udev may not have run yet, so make sure by number */
    for (int tries = 0; tries < 200; tries++) {
        DIR *d = opendir("/dev");
        struct dirent *e;
        while (d && (e = readdir(d))) {
            if (strncmp(e->d_name, "hidg", 4) != 0) continue;
            snprintf(p, sizeof p, "/dev/%s", e->d_name);
            struct stat st;
            if (stat(p, &st) == 0 && S_ISCHR(st.st_mode) && major(st.st_rdev) == maj && minor(st.st_rdev) == min) {
                closedir(d);
                int fd = open(p, O_RDWR | O_NONBLOCK | O_CLOEXEC);
                if (fd < 0) fprintf(stderr, PROG ": cannot open %s: %s\n", p, strerror(errno));
                return fd;
            }
        }
        if (d) closedir(d);
        usleep(10000);
    }
    fprintf(stderr, PROG ": no /dev/hidg* node with device number %u:%u\n", maj, min);
    return -1;
}

static void teardown(void) {
    if (g_hidg >= 0) close(g_hidg), g_hidg = -1;
    bind_udc(false);
    rm("configs/c.1/hid.usb0", 1);
    rm("configs/c.1/strings/0x409", 0);
    rm("configs/c.1", 0);
    rm("functions/hid.usb0", 0);
    rm("strings/0x409", 0);
    rm("", 0);
}

static int create_gadget(void) {
    char buf[64];
    if (access(CONFIGFS, F_OK) != 0) {
        fprintf(stderr, PROG ": %s is missing: mount configfs and load the gadget modules "
                        "(modprobe libcomposite usb_f_hid; a UDC, e.g. modprobe dummy_hcd)\n", CONFIGFS);
        return -1;
    }
    snprintf(g_dir, sizeof g_dir, CONFIGFS "/%s", g_name);
    if (access(g_dir, F_OK) == 0) {
        fprintf(stderr, PROG ": %s exists (another gadget port running?): stop it or pass --name\n", g_dir);
        return -1;
    }
    if (mkd("")) return -1;
    snprintf(buf, sizeof buf, "0x%04x", HP_USB_VID);
    if (puts_("idVendor", buf)) return -1;
    snprintf(buf, sizeof buf, "0x%04x", HP_USB_PID);
    if (puts_("idProduct", buf)) return -1;
    snprintf(buf, sizeof buf, "0x%04x", HOSTD_USB_BCD_DEVICE);
    if (puts_("bcdDevice", buf) || puts_("bcdUSB", "0x0200")) return -1;
    if (mkd("strings/0x409") || puts_("strings/0x409/manufacturer", HOSTD_USB_MANUFACTURER) ||
        puts_("strings/0x409/product", HOSTD_USB_PRODUCT) || puts_("strings/0x409/serialnumber", g_serial))
        return -1;
    if (mkd("configs/c.1") || puts_("configs/c.1/bmAttributes", "0x80")) return -1;
    snprintf(buf, sizeof buf, "%d", HOSTD_USB_MAX_POWER_MA);
    if (puts_("configs/c.1/MaxPower", buf)) return -1;
    if (mkd("functions/hid.usb0")) {
        fprintf(stderr, PROG ": (is usb_f_hid loaded? modprobe usb_f_hid)\n");
        return -1;
    }
    snprintf(buf, sizeof buf, "%d", HOSTD_USB_HID_SUBCLASS);
    if (puts_("functions/hid.usb0/subclass", buf)) return -1;
    snprintf(buf, sizeof buf, "%d", HOSTD_USB_HID_PROTOCOL);
    if (puts_("functions/hid.usb0/protocol", buf)) return -1;
    snprintf(buf, sizeof buf, "%d", HP_REPORT_SIZE);
    if (puts_("functions/hid.usb0/report_length", buf)) return -1;
    if (put("functions/hid.usb0/report_desc", REPORT_DESC, sizeof REPORT_DESC)) return -1;
    char from[512], to[512];
    snprintf(from, sizeof from, "%s/functions/hid.usb0", g_dir);
    snprintf(to, sizeof to, "%s/configs/c.1/hid.usb0", g_dir);
    if (symlink(from, to) != 0) {
        fprintf(stderr, PROG ": cannot link %s: %s\n", to, strerror(errno));
        return -1;
    }
    return 0;
}

static void default_udc(void) {
    DIR *d = opendir("/sys/class/udc");
    struct dirent *e;
    while (d && (e = readdir(d))) {
        if (e->d_name[0] == '.') continue;
        if (!g_udc[0] || strcmp(e->d_name, g_udc) < 0) snprintf(g_udc, sizeof g_udc, "%s", e->d_name);
    }
    if (d) closedir(d);
}

static void default_serial(void) {
    char id[64] = {0};
    FILE *fp = fopen("/etc/machine-id", "r");
    if (fp && fgets(id, sizeof id, fp) && strlen(id) >= HOSTD_USB_SERIAL_CHARS) {
        for (unsigned i = 0; i < HOSTD_USB_SERIAL_CHARS; i++)
            g_serial[i] = (char)(id[i] >= 'a' && id[i] <= 'f' ? id[i] - 'a' + 'A' : id[i]);
    } else {
        memset(g_serial, '0', HOSTD_USB_SERIAL_CHARS);
    }
    if (fp) fclose(fp);
}

static int option(const char *a, const char *v) {
    if (!v) return 0;
    if (!strcmp(a, "--udc")) {
        snprintf(g_udc, sizeof g_udc, "%s", v);
        return 2;
    }
    if (!strcmp(a, "--name")) {
        if (!*v || strchr(v, '/') || strlen(v) >= sizeof g_name) {
            fprintf(stderr, PROG ": --name wants a directory name (no '/', < 64 characters)\n");
            return -1;
        }
        snprintf(g_name, sizeof g_name, "%s", v);
        return 2;
    }
    if (!strcmp(a, "--serial")) {
        size_t n = strlen(v);
        if (n != HOSTD_USB_SERIAL_CHARS || strspn(v, "0123456789ABCDEF") != n) {
            fprintf(stderr, PROG ": --serial wants %u upper-case hex digits\n", HOSTD_USB_SERIAL_CHARS);
            return -1;
        }
        memcpy(g_serial, v, n + 1);
        return 2;
    }
    if (!strcmp(a, "--unplug-at")) {
        double s, d;
        if (g_n_unplugs == MAX_UNPLUGS || sscanf(v, "%lf:%lf", &s, &d) != 2 || s < 0 || d <= 0 ||
            (g_n_unplugs && s < g_unplug_at[g_n_unplugs - 1] + g_unplug_s[g_n_unplugs - 1])) {
            fprintf(stderr, PROG ": --unplug-at wants SECONDS:DURATION (D > 0, in time order, at most %d)\n",
                    MAX_UNPLUGS);
            return -1;
        }
        g_unplug_at[g_n_unplugs] = s, g_unplug_s[g_n_unplugs] = d, g_n_unplugs++;
        return 2;
    }
    return 0;
}

/* every OUT report the host sent so far, to the core; and the scheduled unplugs */
static void poll_gadget(fw_t *f, double t_s) {
    if (g_replug_at >= 0 && t_s >= g_replug_at) {
        g_replug_at = -1;
        if (bind_udc(true) == 0) g_hidg = open_hidg();
        printf("REPLUG %.6f\n", mono_s());
        fflush(stdout);
    } else if (g_replug_at < 0 && g_next_unplug < g_n_unplugs && t_s >= g_unplug_at[g_next_unplug]) {
        if (g_hidg >= 0) close(g_hidg), g_hidg = -1;
        g_pending_count = 0;
        bind_udc(false);
        printf("UNPLUG %.6f\n", mono_s());
        fflush(stdout);
        g_replug_at = t_s + g_unplug_s[g_next_unplug++];
    }
    flush_pending();
    uint8_t rep[HP_REPORT_SIZE + 1];
    while (g_hidg >= 0) {
        ssize_t n = read(g_hidg, rep, sizeof rep);
        if (n <= 0) break;
        fw_on_message(f, rep, (size_t)n);
        sim_scenario_rx(rep, (size_t)n);
    }
}

int main(int argc, char **argv) {
    static const sim_port_t port = {PROG, option, poll_gadget, true};
    default_serial();
    int rc = sim_parse(&port, argc, argv);
    if (rc) return rc;
    if (!g_udc[0]) default_udc();
    if (!g_udc[0]) {
        fprintf(stderr, PROG ": no USB device controller in /sys/class/udc (modprobe dummy_hcd, or pass --udc)\n");
        return 2;
    }
    struct timespec t0 = sim_start(); /* signals: from here on, a SIGTERM still removes the gadget */
    if (create_gadget() != 0 || bind_udc(true) != 0 || (g_hidg = open_hidg()) < 0) {
        if (g_dir[0] && access(g_dir, F_OK) == 0) teardown();
        return 1;
    }
    static fw_t f;
    fw_init(&f, 0);
    clock_gettime(CLOCK_MONOTONIC, &t0);
    printf("GADGET %s T0 %.6f\n", g_udc, (double)t0.tv_sec + (double)t0.tv_nsec * 1e-9);
    fflush(stdout);
    sim_run(&f, &port, t0);
    sim_finish(&f, &port, g_send_dropped);
    if (g_reply_dropped) fprintf(stderr, PROG ": %lu replies dropped (queue full)\n", g_reply_dropped);
    teardown();
    return 0;
}
