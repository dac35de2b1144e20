/* A minimal test harness: CHECK(cond) records a failure with file:line and goes on. */
#ifndef CHECK_H
#define CHECK_H
#include <stdio.h>

extern int g_checks, g_failures;
#define CHECK(c)                                                                  \
    do {                                                                          \
        g_checks++;                                                               \
        if (!(c)) {                                                               \
            g_failures++;                                                         \
            fprintf(stderr, "%s:%d: CHECK failed: %s\n", __FILE__, __LINE__, #c); \
        }                                                                         \
    } while (0)
#define CHECK_EQ(a, b)                                                                       \
    do {                                                                                     \
        long long _a = (long long)(a), _b = (long long)(b);                                  \
        g_checks++;                                                                          \
        if (_a != _b) {                                                                      \
            g_failures++;                                                                    \
            fprintf(stderr, "%s:%d: %s == %s failed: %lld != %lld\n", __FILE__, __LINE__, #a, \
                    #b, _a, _b);                                                             \
        }                                                                                    \
    } while (0)
#endif
