/* The real-time batch's arithmetic, shared by hostd/render/_fastrender.c and
 * hostd/device/_fastpump.c (one definition, two callers):
 *
 *   rc_clenshaw  sum_j c[j] cos((k0 + j) theta_i): hostd.render.series.clenshaw_py
 *   rc_tail      equalizer (second-order sections, transposed direct form II) -> output stage
 *                (soft-start envelope, displacement limit, slew limit, non-finite guard) ->
 *                DAC codes: hostd.render.equalizer.Equalizer.__call__ (its scalar path) and
 *                hostd.render.output.OutputStage.process / to_codes
 *
 * Sample-equal to those Python references by construction: the same IEEE double operations in
 * the same order, one sample at a time, compiled with -ffp-contract=off (setup.py) so that no
 * multiply and add are fused into an FMA. cos() is libm's, as Python's math.cos; rint() rounds
 * half to even in the default rounding mode, as numpy's rint does.
 */
#ifndef HOSTD_RENDER_CORE_H
#define HOSTD_RENDER_CORE_H

#include <math.h>
#include <stddef.h>
#include <stdint.h>

#define RC_MAX_N 64             /* the real-time batches are <= equalizer.SMALL_BATCH samples */
#define RC_DENORMAL_GUARD 1e-30 /* equalizer.DENORMAL_GUARD */

/* clenshaw_py: Clenshaw's recurrence in Reinsch's form, from the last non-zero coefficient down
 * to component 1 (components 1..k0-1 are zero) */
static void rc_clenshaw(const double *c, ptrdiff_t k, const double *theta, ptrdiff_t n, double *out, long k0) {
    while (k > 0 && c[k - 1] == 0.0)
        k--;
    const long pad = k > 0 ? k0 - 1 : 0;
    for (ptrdiff_t i = 0; i < n; i++) {
        const double t = theta[i];
        if (!isfinite(t)) { /* no phase: no height (the output stage holds its last value) */
            out[i] = NAN;    /* the positive quiet NaN, as Python's math.nan */
            continue;
        }
        double b = 0.0, d = 0.0;
        if (cos(t) >= 0.0) { /* near 0: d_k = b_k - b_(k+1), u = 2 cos(t) - 2 = -4 sin^2(t/2) */
            const double h = sin(0.5 * t);
            const double u = -4.0 * (h * h);
            for (ptrdiff_t j = k - 1; j >= 0; j--) {
                d = (c[j] + u * b) + d;
                b = d + b;
            }
            for (long j = 0; j < pad; j++) {
                d = (0.0 + u * b) + d;
                b = d + b;
            }
            out[i] = d + (0.5 * u) * b;
        } else { /* near pi: d_k = b_k + b_(k+1), u = 2 cos(t) + 2 = 4 cos^2(t/2) */
            const double h = cos(0.5 * t);
            const double u = 4.0 * (h * h);
            for (ptrdiff_t j = k - 1; j >= 0; j--) {
                d = (c[j] + u * b) - d;
                b = d - b;
            }
            for (long j = 0; j < pad; j++) {
                d = (0.0 + u * b) - d;
                b = d - b;
            }
            out[i] = (0.5 * u) * b - d;
        }
    }
}

typedef struct {
    double last, env, target, lim, step, ramp, codes_per_um;
    long limit_code;
    long nonfinite, clipped; /* added to */
} rc_out_t;

/* heights x (n <= RC_MAX_N, µm) -> codes; updates the sections' state z (ns x 2) and o */
static void rc_tail(const double *sos, ptrdiff_t ns, double *z, const double *x, ptrdiff_t n, int16_t *codes,
                    rc_out_t *o) {
    double ys[RC_MAX_N];
    for (ptrdiff_t i = 0; i < n; i++)
        ys[i] = x[i];
    for (ptrdiff_t k = 0; k < ns; k++) {
        const double b0 = sos[6 * k], b1 = sos[6 * k + 1], b2 = sos[6 * k + 2], a1 = sos[6 * k + 4],
                     a2 = sos[6 * k + 5];
        double z0 = z[2 * k], z1 = z[2 * k + 1];
        for (ptrdiff_t i = 0; i < n; i++) {
            const double v = ys[i];
            const double y = b0 * v + z0;
            z0 = b1 * v - a1 * y + z1;
            z1 = b2 * v - a2 * y;
            ys[i] = y;
        }
        z[2 * k] = fabs(z0) >= RC_DENORMAL_GUARD ? z0 : 0.0;
        z[2 * k + 1] = fabs(z1) >= RC_DENORMAL_GUARD ? z1 : 0.0;
    }
    double last = o->last, env = o->env;
    const double target = o->target, lim = o->lim, step = o->step, ramp = o->ramp, cpu = o->codes_per_um;
    const double lcd = (double)o->limit_code;
    for (ptrdiff_t i = 0; i < n; i++) {
        double v = ys[i];
        if (!isfinite(v)) {
            o->nonfinite++;
            v = last;
        }
        if (env != target) {
            if (target > env) {
                const double e = env + ramp;
                env = (1.0 < e) ? 1.0 : e; /* Python's min(e, 1.0) */
            } else {
                const double e = env - ramp;
                env = (0.0 > e) ? 0.0 : e; /* Python's max(e, 0.0) */
            }
        }
        v *= env;
        if (v > lim || v < -lim) {
            o->clipped++;
            v = v > 0 ? lim : -lim;
        }
        const double d = v - last;
        if (d > step)
            v = last + step;
        else if (d < -step)
            v = last - step;
        last = v;
        double c = rint(v * cpu); /* OutputStage.to_codes: rint, clip, astype */
        if (c < -lcd)
            c = -lcd;
        else if (c > lcd)
            c = lcd;
        codes[i] = (int16_t)c;
    }
    o->last = last;
    o->env = env;
}

#endif
