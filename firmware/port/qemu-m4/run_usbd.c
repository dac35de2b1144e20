/* The board's USB control-request tests (port/stm32g4/tests/test_usbd.c, unchanged) on the
 * emulated Cortex-M4F. */
int test_main(int argc, char **argv);

int qemu_main(void) {
    static char arg0[] = "test_usbd";
    char *argv[] = {arg0, 0};
    return test_main(1, argv);
}
