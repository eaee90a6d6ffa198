/* Hand geometry shared by the hand-aware checks: see hand.h. */
#include "hand.h"

const double cv_down[9] = {1.0, 0.0, 0.0, 0.0, -1.0, 0.0, 0.0, 0.0, -1.0};

void cv_hand_extent(const double *shapes, long n_boxes, const double *rot, double lo[3], double hi[3]) {
    if (n_boxes <= 0) {
        for (int k = 0; k < 3; k++) lo[k] = hi[k] = 0.0;
        return;
    }
    for (int k = 0; k < 3; k++) {
        lo[k] = INFINITY;
        hi[k] = -INFINITY;
    }
    for (long b = 0; b < n_boxes; b++) {
        const double *sh = shapes + 6 * b;
        const double c0 = sh[0], c1 = sh[1], c2 = sh[2], h0 = sh[3], h1 = sh[4], h2 = sh[5];
        for (int k = 0; k < 3; k++) {
            const double r0 = rot[3 * k], r1 = rot[3 * k + 1], r2 = rot[3 * k + 2];
            /* m, e = r0 * c0 + r1 * c1 + r2 * c2, |r0| * h0 + |r1| * h1 + |r2| * h2 */
            const double m = r0 * c0 + r1 * c1 + r2 * c2;
            const double e = fabs(r0) * h0 + fabs(r1) * h1 + fabs(r2) * h2;
            if (m - e < lo[k]) lo[k] = m - e;
            if (m + e > hi[k]) hi[k] = m + e;
        }
    }
}

int cv_rot_finite(const double *rot) {
    for (int k = 0; k < 9; k++)
        if (!isfinite(rot[k])) return 0;
    return 1;
}
