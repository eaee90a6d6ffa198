/* arm_separation (separation.py): approach between the arms' hands slowed with distance, down
 * to a floor speed; each arm's hand boxes turned by its orientation and bounded (hand.c).
 *
 * kernel_spec:
 *   f = (clearance, brake, floor, band = clearance + brake, CENTRE_TIE,
 *        per pair i < j in order (0,1), (0,2), ..., (1,2), ...: reach,
 *        per arm, per hand box: c0, c1, c2, h0, h1, h2);
 *   i = (rotation flag, n arms, offset of each arm, hand box count of each arm);
 *   reasons = one per pair, in pair order.
 * Falls back on: a non-finite position or orientation of any arm once some pair is not provably
 * far apart (formatted ⊥ reasons); a spec or layout it does not expect. */
#include "hand.h"

int cv_check_arm_separation(const cv_spec *spec, const cv_state *s, const double *a, double *out, cv_reasons *r) {
    (void)a; /* ``out`` holds a until this check edits it */
    if (spec->ni < 2 || spec->nf < 5) return CV_FALLBACK;
    const long turn = spec->i[0], n = spec->i[1];
    if (n < 2 || n > CV_MAX_ARMS || n != s->n_arms || spec->ni != 2 + 2 * n) return CV_FALLBACK;
    const long *offsets = spec->i + 2, *counts = spec->i + 2 + n;
    const long n_pairs = n * (n - 1) / 2;
    long total = 0;
    for (long k = 0; k < n; k++) {
        if (offsets[k] < 0 || offsets[k] + 6 > s->dim || counts[k] < 0 || counts[k] > 1000) return CV_FALLBACK;
        total += counts[k];
    }
    if (spec->nf != 5 + n_pairs + 6 * total) return CV_FALLBACK;
    const double *f = spec->f;
    const double cl = f[0], br = f[1], fl = f[2], band = f[3], tie = f[4];
    const double *reach = f + 5;

    /* check(): the slow path as soon as one pair is not provably far apart (NaN included). */
    int slow = 0;
    for (long i = 0, p = 0; i < n && !slow; i++)
        for (long j = i + 1; j < n; j++, p++) {
            const double *pi = s->arms[i].pos, *pj = s->arms[j].pos;
            const double dx = pi[0] - pj[0], dy = pi[1] - pj[1], dz = pi[2] - pj[2];
            if (!(dx * dx + dy * dy + dz * dz > reach[p] * reach[p])) {
                slow = 1;
                break;
            }
        }
    if (!slow) return CV_ALLOW;

    /* boxes(): every arm's hand as a world-frame box. */
    double hl[CV_MAX_ARMS][3], hh[CV_MAX_ARMS][3];
    const double *shapes = f + 5 + n_pairs;
    for (long i = 0; i < n; i++) {
        const cv_arm *arm = &s->arms[i];
        const double px = arm->pos[0], py = arm->pos[1], pz = arm->pos[2];
        if (!(isfinite(px) && isfinite(py) && isfinite(pz))) return CV_FALLBACK; /* formatted ⊥ */
        const double *rot = cv_down;
        if (arm->has_rot) {
            if (!cv_rot_finite(arm->rot)) return CV_FALLBACK; /* formatted ⊥ */
            rot = arm->rot;
        }
        double l[3], h[3];
        cv_hand_extent(shapes, counts[i], rot, l, h);
        shapes += 6 * counts[i];
        hl[i][0] = px + l[0];
        hl[i][1] = py + l[1];
        hl[i][2] = pz + l[2];
        hh[i][0] = px + h[0];
        hh[i][1] = py + h[1];
        hh[i][2] = pz + h[2];
    }

    int edited = 0;
    for (long i = 0, p = 0; i < n; i++)
        for (long j = i + 1; j < n; j++, p++) {
            const double *li = hl[i], *hi_ = hh[i], *lj = hl[j], *hj = hh[j];
            double sep[3] = {0.0, 0.0, 0.0}, side[3] = {0.0, 0.0, 0.0}; /* +1: arm i approaches j moving +k */
            for (int k = 0; k < 3; k++) {
                if (hi_[k] < lj[k]) {
                    sep[k] = lj[k] - hi_[k];
                    side[k] = 1.0;
                } else if (hj[k] < li[k]) {
                    sep[k] = li[k] - hj[k];
                    side[k] = -1.0;
                }
            }
            const double dist = sqrt(sep[0] * sep[0] + sep[1] * sep[1] + sep[2] * sep[2]);
            if (dist >= band && dist > cl) continue;
            const double q = (br > 0.0 && dist > cl) ? (dist - cl) / br : 0.0;
            double bound;
            if (dist > 0.0) {
                bound = cv_pymax(fl, q * dist / (sep[0] + sep[1] + sep[2]));
            } else {
                for (int k = 0; k < 3; k++) {
                    const double ci = (li[k] + hi_[k]) / 2.0, cj = (lj[k] + hj[k]) / 2.0;
                    side[k] = cj > ci + tie ? 1.0 : cj < ci - tie ? -1.0 : 0.0;
                }
                bound = fl;
            }
            const double rb = dist > 0.0 ? cv_pymax(fl, q) : fl;
            int changed = 0;
            for (int t = 0; t < 2; t++) {
                const long o = offsets[t == 0 ? i : j];
                const double sign = t == 0 ? 1.0 : -1.0;
                for (int k = 0; k < 3; k++) {
                    const double v = out[o + k];
                    if (side[k] != 0.0 && v * side[k] * sign > 0.0 && fabs(v) > bound) {
                        out[o + k] = v > 0.0 ? bound : -bound;
                        changed = 1;
                    }
                }
                if (turn)
                    for (int k = 3; k < 6; k++) {
                        const double v = out[o + k];
                        if (fabs(v) > rb) {
                            out[o + k] = v > 0.0 ? rb : -rb;
                            changed = 1;
                        }
                    }
            }
            if (changed) {
                cv_note(r, (int)p);
                edited = 1;
            }
        }
    return edited ? CV_MODIFY : CV_ALLOW;
}
