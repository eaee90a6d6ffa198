/* force_ramp (ramp.py): into-contact speed ramped down between soft_from and max_force,
 * back-off above it.
 *
 * kernel_spec: f = (soft2, lim2, speed, max_force, soft_from, backoff)  soft2 = soft_from²,
 *                  lim2 = max_force², as compile() computes them; the ramp bound is
 *                  speed * (max_force - |f|) / (max_force - soft_from) as ForceRamp.ramp_bound;
 *              i = (offset of arm 0, offset of arm 1, ...);
 *              reasons = per arm i: 2i slowed (ramp), 2i+1 backing off (above the limit).
 * Falls back on: a non-finite force reading once the slow path runs (Python formats the
 * reason), a spec or layout that does not fit (defensive; Python builds it). */
#include "kernel.h"

int cv_check_force_ramp(const cv_spec *spec, const cv_state *s, const double *a, double *out, cv_reasons *r) {
    (void)a; /* out starts as a copy of a and holds Python's ``a if b is None else b`` throughout */
    if (spec->nf < 6 || spec->ni < s->n_arms || spec->n_reasons < 2 * s->n_arms) return CV_FALLBACK;
    const double soft2 = spec->f[0], lim2 = spec->f[1], speed = spec->f[2];
    const double max_force = spec->f[3], soft_from = spec->f[4], backoff = spec->f[5];

    /* The fast path: every arm's squared force at most soft2 (NaN goes to the slow path). */
    int quiet = 1;
    for (int i = 0; i < s->n_arms; i++) {
        const double *fv = s->arms[i].force;
        if (!((fv[0] * fv[0] + fv[1] * fv[1]) + fv[2] * fv[2] <= soft2)) {
            quiet = 0;
            break;
        }
    }
    if (quiet) return CV_ALLOW;

    /* slow(): a non-finite reading anywhere is a reject with a formatted reason. */
    for (int i = 0; i < s->n_arms; i++) {
        const double *fv = s->arms[i].force;
        if (!cv_finite3(fv)) return CV_FALLBACK;
    }
    int edited = 0; /* Python's ``b is not None`` */
    for (int i = 0; i < s->n_arms; i++) {
        const double *fv = s->arms[i].force;
        long o = spec->i[i];
        if (o < 0 || o + 6 > s->dim) return CV_FALLBACK;
        double n2 = (fv[0] * fv[0] + fv[1] * fv[1]) + fv[2] * fv[2];
        if (n2 <= soft2) continue;
        double n = sqrt(n2);
        if (n2 <= lim2) {
            double bound = speed * (max_force - n) / (max_force - soft_from);
            int changed = 0;
            for (int k = 0; k < 3; k++) {
                double v = out[o + k];
                if (((v > 0.0 && fv[k] < 0.0) || (v < 0.0 && fv[k] > 0.0)) && fabs(v) > bound) {
                    edited = 1;
                    out[o + k] = v > 0.0 ? bound : -bound;
                    changed = 1;
                }
            }
            if (changed) cv_note(r, 2 * i);
            continue;
        }
        /* Above the limit: zero motion into the contact, or back off if configured. */
        if (backoff <= 0.0) {
            int changed = 0;
            for (int k = 0; k < 3; k++) {
                double v = out[o + k];
                if ((v > 0.0 && fv[k] < 0.0) || (v < 0.0 && fv[k] > 0.0)) {
                    edited = 1;
                    out[o + k] = 0.0;
                    changed = 1;
                }
            }
            if (changed) cv_note(r, 2 * i + 1);
            continue;
        }
        double arm[6];
        for (int j = 0; j < 6; j++) arm[j] = cv_pymin(cv_pymax(out[o + j], -backoff), backoff);
        for (int k = 0; k < 3; k++) {
            double away = backoff * fabs(fv[k]) / n;
            if (fv[k] > 0.0 && arm[k] < away)
                arm[k] = away;
            else if (fv[k] < 0.0 && arm[k] > -away)
                arm[k] = -away;
        }
        int differ = 0;
        for (int j = 0; j < 6; j++)
            if (arm[j] != out[o + j]) differ = 1;
        if (differ) {
            edited = 1;
            for (int j = 0; j < 6; j++) out[o + j] = arm[j];
            cv_note(r, 2 * i + 1);
        }
    }
    return edited ? CV_MODIFY : CV_ALLOW;
}
