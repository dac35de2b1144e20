/* The core's unit tests (tests/test_fw.c, unchanged) on the emulated Cortex-M4F: their
 * main() becomes test_main, fed the golden vectors through semihosting file I/O. */
int test_main(int argc, char **argv);

int qemu_main(void) {
    static char arg0[] = "test_fw", arg1[] = "../tests/vectors/protocol.txt";
    char *argv[] = {arg0, arg1, 0};
    return test_main(2, argv);
}
