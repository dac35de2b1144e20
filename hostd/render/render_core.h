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

#include "../device/cycle_state.h" /* hs_output_t: the output stage's record */

#define RC_MAX_N 64             /* the real-time batches are <= equalizer.SMALL_BATCH samples */
#define RC_DENORMAL_GUARD 1e-30 /* equalizer.DENORMAL_GUARD */

/* clenshaw_py: Clenshaw's recurrence in Reinsch's form, from the last non-zero coefficient down
 * to component 1 (components 1..k0-1 are zero). Four phases at a time, interleaved (four
 * independent chains keep the FPU busy; each phase's operations and their order are the
 * reference's). The two forms in one expression: with g = +1 (cos(t) >= 0: near 0) or -1 (near
 * pi), d = (c + u b) + g d and b = d + g b, where x + (-1) y is exactly x - y in IEEE arithmetic
 * (signed zeros included), and the result (u/2) b + g d equals d + (u/2) b or (u/2) b - d. */
#define RC_LANES 4
static void rc_clenshaw(const double *c, ptrdiff_t k, const double *theta, ptrdiff_t n, double *out, long k0) {
    while (k > 0 && c[k - 1] == 0.0)
        k--;
    const long pad = k > 0 ? k0 - 1 : 0;
    for (ptrdiff_t i0 = 0; i0 < n; i0 += RC_LANES) {
        const int m = (int)(n - i0 < RC_LANES ? n - i0 : RC_LANES);
        double u[RC_LANES], g[RC_LANES], b[RC_LANES], d[RC_LANES];
        int finite[RC_LANES];
        for (int l = 0; l < RC_LANES; l++) {
            const double t = l < m ? theta[i0 + l] : 0.0;
            finite[l] = isfinite(t);
            b[l] = d[l] = 0.0;
            if (!finite[l]) {
                u[l] = 0.0;
                g[l] = 1.0;
            } else if (cos(t) >= 0.0) { /* near 0: d_k = b_k - b_(k+1), u = -4 sin^2(t/2) */
                const double h = sin(0.5 * t);
                u[l] = -4.0 * (h * h);
                g[l] = 1.0;
            } else { /* near pi: d_k = b_k + b_(k+1), u = 4 cos^2(t/2) */
                const double h = cos(0.5 * t);
                u[l] = 4.0 * (h * h);
                g[l] = -1.0;
            }
        }
        for (ptrdiff_t j = k - 1; j >= 0; j--) {
            const double cj = c[j];
            for (int l = 0; l < RC_LANES; l++) {
                d[l] = (cj + u[l] * b[l]) + g[l] * d[l];
                b[l] = d[l] + g[l] * b[l];
            }
        }
        for (long j = 0; j < pad; j++) {
            for (int l = 0; l < RC_LANES; l++) {
                d[l] = (0.0 + u[l] * b[l]) + g[l] * d[l];
                b[l] = d[l] + g[l] * b[l];
            }
        }
        for (int l = 0; l < m; l++) /* no phase: no height (the output stage holds its last value) */
            out[i0 + l] = finite[l] ? (0.5 * u[l]) * b[l] + g[l] * d[l] : NAN;
    }
}

/* heights x (n <= RC_MAX_N, µm) -> codes; updates the sections' state z (ns x 2) and the output
 * stage's record o (OutputStage's own fields: last_um, envelope, nonfinite, clipped) */
static void rc_tail(const double *sos, ptrdiff_t ns, double *z, const double *x, ptrdiff_t n, int16_t *codes,
                    hs_output_t *o) {
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
    double last = o->last_um, env = o->envelope;
    const double target = o->target_envelope, lim = o->limit_um, step = o->max_step_um, ramp = o->ramp_step,
                 cpu = o->_codes_per_um;
    const double lcd = (double)o->_limit_code;
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
    o->last_um = last;
    o->envelope = env;
}

#endif
