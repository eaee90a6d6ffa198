/* velocity_cap (cap.py): each arm's six pose components scaled down to just under the cap.
 *
 * kernel_spec: f = (cap2, target): max_norm * max_norm and max_norm * SHRINK;
 * i = (offset of each arm); reasons = one per arm.
 *
 * Falls back on: a sum of squares that overflows to inf (Python rescales and takes math.hypot,
 * which libm's hypot does not match bit for bit). */
#include "kernel.h"

int cv_check_velocity_cap(const cv_spec *spec, const cv_state *s, const double *a, double *out, cv_reasons *r) {
    if (spec->nf < 2 || spec->ni < s->n_arms) return CV_FALLBACK;
    const double cap2 = spec->f[0], target = spec->f[1];
    int edited = 0;
    for (int i = 0; i < s->n_arms; i++) {
        const long o = spec->i[i];
        if (o < 0 || o + 6 > s->dim) return CV_FALLBACK;
        const double x0 = a[o], x1 = a[o + 1], x2 = a[o + 2], x3 = a[o + 3], x4 = a[o + 4], x5 = a[o + 5];
        const double n2 = x0 * x0 + x1 * x1 + x2 * x2 + x3 * x3 + x4 * x4 + x5 * x5;
        if (n2 <= cap2) continue;
        if (!(n2 < INFINITY)) return CV_FALLBACK; /* overflow (or NaN): Python's math.hypot path */
        const double sc = target / sqrt(n2);
        out[o] = x0 * sc;
        out[o + 1] = x1 * sc;
        out[o + 2] = x2 * sc;
        out[o + 3] = x3 * sc;
        out[o + 4] = x4 * sc;
        out[o + 5] = x5 * sc;
        edited = 1;
        cv_note(r, i);
    }
    return edited ? CV_MODIFY : CV_ALLOW;
}
