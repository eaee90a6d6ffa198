/* workspace_box (box.py): outward motion zeroed within the margin of a face.
 *
 * kernel_spec: f = (lx, ly, lz, hx, hy, hz) the box shrunk by the margin;
 * i = (offset of each arm); reasons = per arm, the six faces (+x, -x, +y, -y, +z, -z). */
#include "kernel.h"

int cv_check_workspace_box(const cv_spec *spec, const cv_state *s, const double *a, double *out, cv_reasons *r) {
    const double lx = spec->f[0], ly = spec->f[1], lz = spec->f[2];
    const double hx = spec->f[3], hy = spec->f[4], hz = spec->f[5];
    int edited = 0;
    for (int i = 0; i < s->n_arms; i++) {
        double x = s->arms[i].pos[0], y = s->arms[i].pos[1], z = s->arms[i].pos[2];
        if (lx < x && x < hx && ly < y && y < hy && lz < z && z < hz) continue;
        if (!isfinite(x) || !isfinite(y) || !isfinite(z)) return CV_FALLBACK; /* formatted reason */
        long o = spec->i[i];
        double ax = a[o], ay = a[o + 1], az = a[o + 2];
        int zx = (ax > 0.0 && x >= hx) || (ax < 0.0 && x <= lx);
        int zy = (ay > 0.0 && y >= hy) || (ay < 0.0 && y <= ly);
        int zz = (az > 0.0 && z >= hz) || (az < 0.0 && z <= lz);
        if (!(zx || zy || zz)) continue;
        edited = 1;
        if (zx) {
            out[o] = 0.0;
            cv_note(r, 6 * i + (ax > 0.0 ? 0 : 1));
        }
        if (zy) {
            out[o + 1] = 0.0;
            cv_note(r, 6 * i + (ay > 0.0 ? 2 : 3));
        }
        if (zz) {
            out[o + 2] = 0.0;
            cv_note(r, 6 * i + (az > 0.0 ? 4 : 5));
        }
    }
    return edited ? CV_MODIFY : CV_ALLOW;
}
