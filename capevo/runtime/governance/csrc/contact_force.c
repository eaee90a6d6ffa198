/* contact_force (force.py): above the force limit, motion into the contact zeroed per axis.
 *
 * kernel_spec: f = (lim2) the limit squared, max_force * max_force;
 * i = (offset of each arm); reasons = per arm, the three axes (x, y, z): reason 3 * arm + axis.
 *
 * Falls back on: a force reading whose squared norm is not finite and that has a non-finite
 * component (the Python check rejects with a reason formatted from the reading). */
#include "kernel.h"

int cv_check_contact_force(const cv_spec *spec, const cv_state *s, const double *a, double *out, cv_reasons *r) {
    if (spec->nf < 1 || spec->ni < s->n_arms) return CV_FALLBACK;
    const double lim2 = spec->f[0];
    int edited = 0;
    for (int i = 0; i < s->n_arms; i++) {
        const double fx = s->arms[i].force[0], fy = s->arms[i].force[1], fz = s->arms[i].force[2];
        const double n2 = fx * fx + fy * fy + fz * fz;
        if (n2 <= lim2) continue; /* at or below the limit, hence also finite */
        if (!(n2 < INFINITY) && (fx - fx != 0.0 || fy - fy != 0.0 || fz - fz != 0.0))
            return CV_FALLBACK; /* Python rejects with the reading formatted into the reason */
        const long o = spec->i[i];
        if (o < 0 || o + 3 > s->dim) return CV_FALLBACK;
        const double ax = a[o], ay = a[o + 1], az = a[o + 2];
        /* Signs, not products, as in Python (a * f can underflow to -0.0). */
        const int zx = (ax > 0.0 && fx < 0.0) || (ax < 0.0 && fx > 0.0);
        const int zy = (ay > 0.0 && fy < 0.0) || (ay < 0.0 && fy > 0.0);
        const int zz = (az > 0.0 && fz < 0.0) || (az < 0.0 && fz > 0.0);
        if (!(zx || zy || zz)) continue;
        edited = 1;
        if (zx) {
            out[o] = 0.0;
            cv_note(r, 3 * i);
        }
        if (zy) {
            out[o + 1] = 0.0;
            cv_note(r, 3 * i + 1);
        }
        if (zz) {
            out[o + 2] = 0.0;
            cv_note(r, 3 * i + 2);
        }
    }
    return edited ? CV_MODIFY : CV_ALLOW;
}
