/* workspace_guard (guard.py): brake before the box's faces, steer back when outside, stop
 * turning near them.
 *
 * kernel_spec: f = (lowx, lowy, lowz, highx, highy, highz, margin, brake, restore, band,
 *                   ilx, ily, ilz, ihx, ihy, ihz)  band = margin + brake, (il, ih) the inner box
 *                  low + band, high - band outside of which the slow path runs;
 *              i = (freeze_rotation 0/1, offset of arm 0, offset of arm 1, ...);
 *              reasons = per arm i: 3i braked, 3i+1 steered back inward, 3i+2 rotation stopped.
 * Falls back on: a non-finite end-effector position once the slow path runs (Python formats the
 * reason), a spec or layout that does not fit (defensive; Python builds it). */
#include "kernel.h"

int cv_check_workspace_guard(const cv_spec *spec, const cv_state *s, const double *a, double *out, cv_reasons *r) {
    (void)a; /* out starts as a copy of a and holds Python's ``a if b is None else b`` throughout */
    if (spec->nf < 16 || spec->ni < 1 + s->n_arms || spec->n_reasons < 3 * s->n_arms) return CV_FALLBACK;
    const double *f = spec->f;
    const double *low = f, *high = f + 3;
    const double m = f[6], br = f[7], rs = f[8], band = f[9];
    const double ilx = f[10], ily = f[11], ilz = f[12], ihx = f[13], ihy = f[14], ihz = f[15];
    const int freeze = spec->i[0] != 0;

    /* The fast path: every arm strictly inside the inner box. */
    int inside = 1;
    for (int i = 0; i < s->n_arms; i++) {
        double x = s->arms[i].pos[0], y = s->arms[i].pos[1], z = s->arms[i].pos[2];
        if (!(ilx < x && x < ihx && ily < y && y < ihy && ilz < z && z < ihz)) {
            inside = 0;
            break;
        }
    }
    if (inside) return CV_ALLOW;

    /* slow(): a non-finite position anywhere is a reject with a formatted reason. */
    for (int i = 0; i < s->n_arms; i++) {
        const double *p = s->arms[i].pos;
        if (!cv_finite3(p)) return CV_FALLBACK;
    }
    int edited = 0; /* Python's ``b is not None`` */
    for (int i = 0; i < s->n_arms; i++) {
        const double *p = s->arms[i].pos;
        long o = spec->i[1 + i];
        if (o < 0 || o + 6 > s->dim) return CV_FALLBACK;
        int braked = 0, near = 0;
        int n_out = 0, out_k[3];
        double out_inward[3];
        for (int k = 0; k < 3; k++) {
            for (int face = 0; face < 2; face++) {
                double d = face == 0 ? high[k] - p[k] : p[k] - low[k];
                double sg = face == 0 ? 1.0 : -1.0;
                if (d >= band && d > m) continue;
                if (d <= m) near = 1;
                if (d < 0.0 && rs > 0.0 && n_out < 3) {
                    out_k[n_out] = k;
                    out_inward[n_out] = -sg;
                    n_out++;
                }
                double bound = br > 0.0 ? (d - m) / br : 0.0;
                if (bound < 0.0) bound = 0.0;
                double v = out[o + k];
                if (v * sg > bound) {
                    edited = 1;
                    out[o + k] = bound * sg;
                    braked = 1;
                }
            }
        }
        if (n_out > 0) {
            double arm[6];
            for (int j = 0; j < 6; j++) arm[j] = cv_pymin(cv_pymax(out[o + j], -rs), rs);
            for (int q = 0; q < n_out; q++) {
                int k = out_k[q];
                double inward = out_inward[q];
                if (arm[k] * inward < rs) arm[k] = rs * inward;
            }
            int differ = 0;
            for (int j = 0; j < 6; j++)
                if (arm[j] != out[o + j]) differ = 1;
            if (differ) {
                edited = 1;
                for (int j = 0; j < 6; j++) out[o + j] = arm[j];
                cv_note(r, 3 * i + 1);
            } else if (braked) {
                cv_note(r, 3 * i);
            }
        } else if (braked) {
            cv_note(r, 3 * i);
        }
        if (freeze && near) {
            if (out[o + 3] != 0.0 || out[o + 4] != 0.0 || out[o + 5] != 0.0) {
                edited = 1;
                out[o + 3] = out[o + 4] = out[o + 5] = 0.0;
                cv_note(r, 3 * i + 2);
            }
        }
    }
    return edited ? CV_MODIFY : CV_ALLOW;
}
