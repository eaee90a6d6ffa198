/* surface_approach (surface.py): motion towards a horizontal surface braked in proportion to
 * the height of the hand's lowest point above it.
 *
 * kernel_spec: f = (top, stop, br, lat, then per hand box lo_x, lo_y, lo_z, hi_x, hi_y, hi_z)
 *   with top = stop + hand_reach(hand) + br (the fast-path height), stop = height + clearance,
 *   br = brake, lat = lateral (0.0 when unset; see has_lat);
 * i = (turn: the rotation flag, has_lat: 1 when lateral is set, n_boxes, offset of each arm);
 * reasons = per arm, "arm i: hand near the surface at ... m: motion towards it braked".
 *
 * Falls back on: a non-finite end-effector height or a non-finite orientation entry on the slow
 * path (Python formats the reason), and a spec or layout that does not fit the state. */
#include "kernel.h"

/* hand.py's lowest_offset for the boxes at f[0..6*n_boxes), the same operations in order. */
static double lowest_offset(const double *box, long n_boxes, const double *rot) {
    const double r6 = rot[6], r7 = rot[7], r8 = rot[8];
    double best = n_boxes == 0 ? 0.0 : INFINITY;
    for (long k = 0; k < n_boxes; k++, box += 6) {
        const double v = ((r6 > 0.0 ? r6 * box[0] : r6 * box[3]) + (r7 > 0.0 ? r7 * box[1] : r7 * box[4])) +
                         (r8 > 0.0 ? r8 * box[2] : r8 * box[5]);
        if (v < best) best = v;
    }
    return best;
}

static const double DOWN[9] = {1.0, 0.0, 0.0, 0.0, -1.0, 0.0, 0.0, 0.0, -1.0};

int cv_check_surface_approach(const cv_spec *spec, const cv_state *s, const double *a, double *out, cv_reasons *r) {
    if (spec->nf < 4 || spec->ni < 3) return CV_FALLBACK;
    const double top = spec->f[0], stop = spec->f[1], br = spec->f[2], lat = spec->f[3];
    const long turn = spec->i[0], has_lat = spec->i[1], n_boxes = spec->i[2];
    if (n_boxes < 0 || (long)spec->nf - 4 < 6 * n_boxes || (long)spec->ni - 3 < s->n_arms ||
        spec->n_reasons < s->n_arms)
        return CV_FALLBACK;

    /* The fast path: every end effector above top (and finite). */
    int fast = 1;
    for (int i = 0; i < s->n_arms; i++) {
        const double z = s->arms[i].pos[2];
        if (!(top < z && z < INFINITY)) {
            fast = 0;
            break;
        }
    }
    if (fast) return CV_ALLOW;

    int edited = 0;
    for (int i = 0; i < s->n_arms; i++) {
        const cv_arm *arm = &s->arms[i];
        const double z = arm->pos[2];
        if (!isfinite(z)) return CV_FALLBACK; /* formatted reason */
        const double *rot = DOWN;
        if (arm->has_rot) {
            for (int k = 0; k < 9; k++)
                if (!isfinite(arm->rot[k])) return CV_FALLBACK; /* formatted reason */
            rot = arm->rot;
        }
        const long o = spec->i[3 + i];
        if (o < 0 || o + (turn ? 6 : 3) > (long)s->dim) return CV_FALLBACK;
        const double gap = (z + lowest_offset(spec->f + 4, n_boxes, rot)) - stop;
        if (gap >= br && gap > 0.0) continue;
        const double q = gap > 0.0 ? (br > 0.0 ? gap / br : 0.0) : 0.0;
        const double nq = -q;
        /* ``out`` is Python's ``src``: ``a`` with the earlier arms' edits (other components). */
        int hit = out[o + 2] < nq;
        if (turn) hit = hit || fabs(out[o + 3]) > q || fabs(out[o + 4]) > q || fabs(out[o + 5]) > q;
        const double ql = has_lat ? (lat > q ? lat : q) : INFINITY;
        hit = hit || fabs(out[o]) > ql || fabs(out[o + 1]) > ql;
        if (!hit) continue;
        edited = 1;
        if (out[o + 2] < nq) out[o + 2] = nq;
        if (turn)
            for (long j = o + 3; j < o + 6; j++) out[j] = cv_pymin(cv_pymax(out[j], nq), q);
        if (has_lat) {
            const double nql = -ql;
            for (long j = o; j < o + 2; j++) out[j] = cv_pymin(cv_pymax(out[j], nql), ql);
        }
        cv_note(r, i);
    }
    (void)a;
    return edited ? CV_MODIFY : CV_ALLOW;
}
