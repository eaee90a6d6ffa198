/* contact_approach (contact_approach.py): closing speed along each sensed pair braked by distance.
 *
 * kernel_spec (ContactApproach._compiled, shared with compile()):
 *   f = (band, clearance, brake, touch, brake_loose, touch_loose, 1 - touch, 1 - touch_loose,
 *        lever, lever2)   brake_loose is ``brake`` when unset; lever2 = lever * lever * (1 - 1e-12);
 *   i = (split, rotation, n_arms, offset of arm 0, ..., offset of arm n_arms - 1);
 *   reasons = per arm, "arm i: hand near a contact: motion towards it braked".
 *
 * Falls back on a pair whose dist or normal is not finite (Python rejects it with a formatted
 * reason); every other input is decided here, operation for operation as the Python check. */
#include "kernel.h"

/* Python's ``x = (dist - cl) / br; x = 0.0 if x < 0.0 else 1.0 if x > 1.0 else x; t + u * x``. */
static double bound(double dist, double cl, double br, double t, double u) {
    double x = (dist - cl) / br;
    x = x < 0.0 ? 0.0 : x > 1.0 ? 1.0 : x;
    return t + u * x;
}

int cv_check_contact_approach(const cv_spec *spec, const cv_state *s, const double *a, double *out, cv_reasons *r) {
    if (spec->nf < 10 || spec->ni < 3) return CV_FALLBACK;
    const int n_arms = s->n_arms;
    if (n_arms > CV_MAX_ARMS || spec->i[2] != n_arms || spec->ni < 3 + n_arms || spec->n_reasons < n_arms)
        return CV_FALLBACK;

    /* check(): only states with a pair somewhere take the slow path. */
    int any = 0;
    for (int i = 0; i < n_arms; i++)
        if (s->arms[i].n_near > 0) any = 1;
    if (!any) return CV_ALLOW;

    const double band = spec->f[0], cl = spec->f[1], br_fixed = spec->f[2], t_fixed = spec->f[3];
    const double br_loose = spec->f[4], t_loose = spec->f[5], u_fixed = spec->f[6], u_loose = spec->f[7];
    const double lever = spec->f[8], lever2 = spec->f[9];
    const int split = spec->i[0] != 0, turn = spec->i[1] != 0;
    const long *offsets = spec->i + 3;
    for (int i = 0; i < n_arms; i++)
        if (offsets[i] < 0 || offsets[i] + 6 > s->dim) return CV_FALLBACK;

    const int K3[3] = {0, 1, 2};
    double poses[CV_MAX_ARMS][6];
    double q_rot[CV_MAX_ARMS];
    int edited[CV_MAX_ARMS];
    for (int i = 0; i < n_arms; i++) {
        for (int j = 0; j < 6; j++) poses[i][j] = a[offsets[i] + j];
        q_rot[i] = INFINITY;
        edited[i] = 0;
    }

    for (int i = 0; i < n_arms; i++) {
        double *arm = poses[i];
        double qr_i = q_rot[i];
        const cv_arm *st = &s->arms[i];
        for (int p = 0; p < st->n_near; p++) {
            const double *pair = st->near + 8 * p;
            const double dist = pair[0], nx = pair[1], ny = pair[2], nz = pair[3];
            const double rx = pair[4], ry = pair[5], rz = pair[6], owner = pair[7];
            if (!isfinite(dist) || !isfinite(nx) || !isfinite(ny) || !isfinite(nz))
                return CV_FALLBACK; /* formatted reason */
            if (dist >= band) continue;
            double q, q_down;
            if (split && owner == -2.0) { /* LOOSE */
                q = bound(dist, cl, br_loose, t_loose, u_loose);
                q_down = nz < 0.0 ? bound(dist, cl, br_fixed, t_fixed, u_fixed) : q;
            } else {
                q = q_down = bound(dist, cl, br_fixed, t_fixed, u_fixed);
            }
            if (q >= 1.0 && q_down >= 1.0) continue;
            double v0 = arm[0] * nx, v1 = arm[1] * ny, v2 = arm[2] * nz;
            double c = v0 > 0.0 ? v0 : 0.0;
            if (v1 > 0.0) c += v1;
            if (q_down < q) {
                if (v2 > q_down) {
                    arm[2] = q_down / nz * cv_shrink;
                    edited[i] = 1;
                }
                if (c > q) {
                    const double ns[2] = {nx, ny};
                    if (cv_brake_along(arm, K3, ns, 2, q, 1.0) != 0) return CV_FALLBACK;
                    edited[i] = 1;
                }
                q = q_down;
            } else {
                if (v2 > 0.0) c += v2;
                if (c > q) {
                    const double ns[3] = {nx, ny, nz};
                    if (cv_brake_along(arm, K3, ns, 3, q, 1.0) != 0) return CV_FALLBACK;
                    edited[i] = 1;
                }
            }
            if (turn) {
                double rr = rx * rx + ry * ry + rz * rz;
                double qr;
                if (rr < lever2) {
                    qr = q;
                } else {
                    double rl = isfinite(rx + ry + rz) ? sqrt(rr) : INFINITY;
                    qr = q * (rl > lever ? lever / rl : 1.0);
                }
                if (qr < qr_i) qr_i = qr;
            }
            if (owner >= 0.0 && owner < (double)n_arms && owner != (double)i) {
                const int j = (int)owner;
                double *other = poses[j];
                double w0 = -other[0] * nx, w1 = -other[1] * ny, w2 = -other[2] * nz;
                double co = w0 > 0.0 ? w0 : 0.0;
                if (w1 > 0.0) co += w1;
                if (w2 > 0.0) co += w2;
                if (co > q) {
                    const double ns[3] = {nx, ny, nz};
                    if (cv_brake_along(other, K3, ns, 3, q, -1.0) != 0) return CV_FALLBACK;
                    edited[j] = 1;
                }
                if (turn && q < q_rot[j]) q_rot[j] = q;
            }
        }
        q_rot[i] = qr_i;
    }

    int modified = 0;
    for (int i = 0; i < n_arms; i++) {
        double *arm = poses[i];
        const double qr = q_rot[i];
        const long o = offsets[i];
        if (qr < INFINITY) {
            for (int k = 3; k < 6; k++) {
                double v = arm[k];
                if (fabs(v) > qr) {
                    arm[k] = v > 0.0 ? qr : -qr;
                    edited[i] = 1;
                }
            }
        }
        if (!edited[i]) continue;
        int differs = 0;
        for (int j = 0; j < 6; j++)
            if (arm[j] != a[o + j]) differs = 1;
        if (!differs) continue;
        for (int j = 0; j < 6; j++) out[o + j] = arm[j];
        cv_note(r, i);
        modified = 1;
    }
    return modified ? CV_MODIFY : CV_ALLOW;
}
