/* obstacle_approach (obstacle.py): motion towards fixed boxes limited in proportion to the hand's
 * distance from them; each hand box turned by the arm's orientation (hand.c).
 *
 * kernel_spec:
 *   f = (clearance, brake, band = clearance + brake, glx, gly, glz, ghx, ghy, ghz,
 *        per obstacle j: lo[3], hi[3], centre[3], grown lo[3], grown hi[3]   (15 each),
 *        per hand box: c0, c1, c2, h0, h1, h2                                (6 each));
 *   i = (rotation flag, n obstacles, n hand boxes, n governed arms, per governed arm: index, offset);
 *   reasons = arm-major: "arm i: hand near obstacle j: ..." at i * n_obstacles + j, for every arm
 *             of the layout.
 * Falls back on: a non-finite position of a governed arm (once any governed arm is not provably
 * clear) and a non-finite orientation of an arm near an obstacle (both formatted ⊥ reasons);
 * more than CV_OBSTACLE_MAX_PARTS hand boxes; a spec or layout it does not expect. */
#include "hand.h"

#define CV_OBSTACLE_MAX_PARTS 16

int cv_check_obstacle_approach(const cv_spec *spec, const cv_state *s, const double *a, double *out, cv_reasons *r) {
    if (spec->ni < 4 || spec->nf < 9) return CV_FALLBACK;
    const long turn = spec->i[0], n_obs = spec->i[1], n_boxes = spec->i[2], n_gov = spec->i[3];
    if (n_obs < 1 || n_boxes < 0 || n_boxes > CV_OBSTACLE_MAX_PARTS || n_gov < 0 || n_gov > CV_MAX_ARMS)
        return CV_FALLBACK;
    if (spec->ni != 4 + 2 * n_gov || spec->nf != 9 + 15 * n_obs + 6 * n_boxes) return CV_FALLBACK;
    const double *f = spec->f;
    const double cl = f[0], br = f[1], band = f[2];
    const double glx = f[3], gly = f[4], glz = f[5], ghx = f[6], ghy = f[7], ghz = f[8];
    const double *obs = f + 9, *shapes = f + 9 + 15 * n_obs;
    const long *gov = spec->i + 4;

    (void)a; /* ``out`` holds a until this check edits it */
    for (long g = 0; g < n_gov; g++) {
        const long i = gov[2 * g], o = gov[2 * g + 1];
        if (i < 0 || i >= s->n_arms || o < 0 || o + 6 > s->dim) return CV_FALLBACK;
    }

    /* check(): the slow path as soon as one governed arm is not provably clear (NaN included). */
    int slow = 0;
    for (long g = 0; g < n_gov; g++) {
        const long i = gov[2 * g];
        const double x = s->arms[i].pos[0], y = s->arms[i].pos[1], z = s->arms[i].pos[2];
        if (!(x < glx || x > ghx || y < gly || y > ghy || z < glz || z > ghz)) {
            slow = 1;
            break;
        }
    }
    if (!slow) return CV_ALLOW;

    const long n_parts = n_boxes > 0 ? n_boxes : 1;
    int edited = 0;
    for (long g = 0; g < n_gov; g++) {
        const long i = gov[2 * g], o = gov[2 * g + 1];
        const cv_arm *arm = &s->arms[i];
        const double px = arm->pos[0], py = arm->pos[1], pz = arm->pos[2];
        if (!(isfinite(px) && isfinite(py) && isfinite(pz))) return CV_FALLBACK; /* formatted ⊥ */
        long near0 = -1;
        for (long j = 0; j < n_obs && near0 < 0; j++) {
            const double *gb = obs + 15 * j + 9;
            if (gb[0] <= px && px <= gb[3] && gb[1] <= py && py <= gb[4] && gb[2] <= pz && pz <= gb[5]) near0 = j;
        }
        if (near0 < 0) continue;
        const double *rot = cv_down;
        if (arm->has_rot) {
            if (!cv_rot_finite(arm->rot)) return CV_FALLBACK; /* formatted ⊥ */
            rot = arm->rot;
        }
        double hl[CV_OBSTACLE_MAX_PARTS][3], hh[CV_OBSTACLE_MAX_PARTS][3];
        for (long p = 0; p < n_parts; p++) {
            double l[3], h[3];
            cv_hand_extent(shapes + 6 * p, n_boxes > 0 ? 1 : 0, rot, l, h);
            hl[p][0] = px + l[0];
            hl[p][1] = py + l[1];
            hl[p][2] = pz + l[2];
            hh[p][0] = px + h[0];
            hh[p][1] = py + h[1];
            hh[p][2] = pz + h[2];
        }
        double arm_a[6];
        for (int k = 0; k < 6; k++) arm_a[k] = out[o + k];
        double q_rot = INFINITY;
        long hit[CV_MAX_REASONS];
        int n_hit = 0;
        for (long j = near0; j < n_obs; j++) {
            const double *ob = obs + 15 * j;
            const double *gb = ob + 9;
            if (!(gb[0] <= px && px <= gb[3] && gb[1] <= py && py <= gb[4] && gb[2] <= pz && pz <= gb[5])) continue;
            const double *lo = ob, *hi = ob + 3, *centre = ob + 6;
            for (long p = 0; p < n_parts; p++) {
                const double *L = hl[p], *H = hh[p];
                double sep[3];
                int side[3];
                for (int k = 0; k < 3; k++) {
                    if (H[k] < lo[k]) {
                        sep[k] = lo[k] - H[k];
                        side[k] = 1;
                    } else if (L[k] > hi[k]) {
                        sep[k] = L[k] - hi[k];
                        side[k] = -1;
                    } else {
                        sep[k] = 0.0;
                        side[k] = 0;
                    }
                }
                const double dist = sqrt(sep[0] * sep[0] + sep[1] * sep[1] + sep[2] * sep[2]);
                if (dist >= band && dist > cl) continue;
                const double q = (br > 0.0 && dist > cl) ? (dist - cl) / br : 0.0;
                int changed = 0;
                if (dist > 0.0) {
                    const double bound = q * dist / (sep[0] + sep[1] + sep[2]);
                    for (int k = 0; k < 3; k++) {
                        const double v = arm_a[k], sd = (double)side[k];
                        if (side[k] && v * sd > 0.0 && fabs(v) > bound) {
                            arm_a[k] = bound * sd;
                            changed = 1;
                        }
                    }
                } else {
                    for (int k = 0; k < 3; k++) {
                        const double v = arm_a[k];
                        const double mid = (L[k] + H[k]) / 2.0;
                        if ((v > 0.0 && mid < centre[k]) || (v < 0.0 && mid > centre[k])) {
                            arm_a[k] = 0.0;
                            changed = 1;
                        }
                    }
                }
                if (turn && q < q_rot) q_rot = q;
                if (changed) {
                    int seen = 0;
                    for (int h = 0; h < n_hit; h++) seen |= hit[h] == j;
                    if (!seen) {
                        if (n_hit >= CV_MAX_REASONS) return CV_FALLBACK;
                        hit[n_hit++] = j;
                    }
                }
            }
        }
        if (turn && q_rot < INFINITY) {
            for (int k = 3; k < 6; k++) {
                const double v = arm_a[k];
                if (fabs(v) > q_rot) {
                    arm_a[k] = v > 0.0 ? q_rot : -q_rot;
                    if (n_hit == 0) hit[n_hit++] = near0;
                }
            }
        }
        int differs = 0;
        for (int k = 0; k < 6; k++) differs |= arm_a[k] != out[o + k];
        if (!differs) continue;
        if (n_hit == 0) return CV_FALLBACK; /* Python would note nothing: not a path it takes */
        for (int k = 0; k < 6; k++) out[o + k] = arm_a[k];
        for (int h = 0; h < n_hit; h++) cv_note(r, (int)(i * n_obs + hit[h]));
        edited = 1;
    }
    return edited ? CV_MODIFY : CV_ALLOW;
}
