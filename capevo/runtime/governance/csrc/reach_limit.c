/* reach_limit (reach.py): the reach sphere (braking along u, restoring beyond it) and the base
 * column (braking towards it, pushing out of it) per arm, operation for operation as
 * ReachLimit.compile's check() (the fast path) and slow().
 *
 * kernel_spec: f = (margin, brake, restore, creep, band, max_radius, min_radius, lever,
 *                   far_out2, near_in2, far_w2, near_in2_safe, point x, y, z, DOWN[0..8],
 *                   then per arm its centre x, y, z);
 *              i = (number of arms n, then the offset of each arm);
 *              reasons = per arm the four of compile(): near the reach (braked), beyond the reach
 *                   (steered back), near the column (braked), inside the column (steered out).
 *
 * Falls back on: a non-finite end-effector position or (with a lever) orientation once slow()
 * runs (Python rejects with a formatted reason), a non-finite or overflowing vector to the
 * centre (polar() is specified for finite vectors only), and a spec or state it does not expect. */
#include "kernel.h"

#define F_M 0
#define F_BR 1
#define F_RS 2
#define F_CREEP 3
#define F_BAND 4
#define F_ROUT 5
#define F_RIN 6
#define F_LEVER 7
#define F_FAR_OUT2 8
#define F_NEAR_IN2 9
#define F_FAR_W2 10
#define F_NEAR_IN2_SAFE 11
#define F_PT 12
#define F_DOWN 15
#define F_CENTRES 24

/* polar(v): r = |v| and u = v / |v| scaled by the largest component; 0 for the zero vector (u
 * unset), 1 otherwise. v must be finite. */
static int polar(double v0, double v1, double v2, double *r, double u[3]) {
    double mx = cv_pymax(cv_pymax(fabs(v0), fabs(v1)), fabs(v2));
    if (mx == 0.0) {
        *r = 0.0;
        return 0;
    }
    double x = v0 / mx, y = v1 / mx, z = v2 / mx;
    double n = sqrt(x * x + y * y + z * z);
    *r = mx * n;
    u[0] = x / n;
    u[1] = y / n;
    u[2] = z / n;
    return 1;
}

/* compile()'s limit(d). */
static double limit(double d, double m, double br) {
    if (br > 0.0) {
        double q = (d - m) / br;
        return q > 0.0 ? q : 0.0;
    }
    return 0.0;
}

static const double *rotation(const cv_spec *spec, const cv_arm *arm) {
    return arm->has_rot ? arm->rot : spec->f + F_DOWN;
}

int cv_check_reach_limit(const cv_spec *spec, const cv_state *s, const double *a, double *out, cv_reasons *r) {
    (void)a; /* ``out`` starts as a copy of it and is what slow() reads (its ``src``) */
    if (spec->ni < 1) return CV_FALLBACK;
    const long n = spec->i[0];
    if (n < 1 || n > s->n_arms || n > CV_MAX_ARMS || spec->ni < 1 + n || spec->nf < F_CENTRES + 3 * n ||
        spec->n_reasons < 4 * n)
        return CV_FALLBACK;
    for (long i = 0; i < n; i++)
        if (spec->i[1 + i] < 0 || spec->i[1 + i] + 6 > s->dim) return CV_FALLBACK;

    const double *f = spec->f;
    const double m = f[F_M], br = f[F_BR], rs = f[F_RS], creep = f[F_CREEP], band = f[F_BAND];
    const double r_out = f[F_ROUT], r_in = f[F_RIN], lever = f[F_LEVER];
    const double far_out2 = f[F_FAR_OUT2], near_in2 = f[F_NEAR_IN2], far_w2 = f[F_FAR_W2];
    const double near_in2_safe = f[F_NEAR_IN2_SAFE];
    const double pt0 = f[F_PT], pt1 = f[F_PT + 1], pt2 = f[F_PT + 2];

    /* check(): the fast path; every arm provably clear is an allow. */
    int clear = 1;
    for (long i = 0; i < n && clear; i++) {
        const cv_arm *arm = &s->arms[i];
        const double *c = f + F_CENTRES + 3 * i;
        double x = arm->pos[0], y = arm->pos[1], z = arm->pos[2];
        double dx = x - c[0], dy = y - c[1], dz = z - c[2];
        double h2 = dx * dx + dy * dy;
        if (h2 + dz * dz < far_out2 && h2 > near_in2) continue;
        if (lever > 0.0 && h2 > near_in2_safe) {
            const double *rot = rotation(spec, arm);
            double wx = x + rot[0] * pt0 + rot[1] * pt1 + rot[2] * pt2 - c[0];
            double wy = y + rot[3] * pt0 + rot[4] * pt1 + rot[5] * pt2 - c[1];
            double wz = z + rot[6] * pt0 + rot[7] * pt1 + rot[8] * pt2 - c[2];
            if (wx * wx + wy * wy + wz * wz < far_w2) continue;
        }
        clear = 0;
    }
    if (clear) return CV_ALLOW;

    /* slow() rejects with a formatted reason at the first arm whose position (or, with a lever,
     * orientation) is not finite, whatever the arms before it did: that is Python's. */
    for (long i = 0; i < n; i++) {
        const cv_arm *arm = &s->arms[i];
        if (!cv_finite3(arm->pos)) return CV_FALLBACK;
        if (lever > 0.0 && arm->has_rot)
            for (int k = 0; k < 9; k++)
                if (!isfinite(arm->rot[k])) return CV_FALLBACK;
    }

    /* slow() */
    int edited = 0;
    for (long i = 0; i < n; i++) {
        const cv_arm *arm = &s->arms[i];
        const double *c = f + F_CENTRES + 3 * i;
        const double *p = arm->pos;
        const long o = spec->i[1 + i];
        double v[6];
        /* slow()'s src: ``a`` until an arm was edited, then b; ``out`` is exactly that. */
        for (int j = 0; j < 6; j++) v[j] = out[o + j];
        int why[2], n_why = 0;

        /* Outer sphere. */
        double w0 = p[0], w1 = p[1], w2 = p[2];
        if (lever > 0.0) {
            const double *rot = rotation(spec, arm);
            w0 = p[0] + rot[0] * pt0 + rot[1] * pt1 + rot[2] * pt2;
            w1 = p[1] + rot[3] * pt0 + rot[4] * pt1 + rot[5] * pt2;
            w2 = p[2] + rot[6] * pt0 + rot[7] * pt1 + rot[8] * pt2;
        }
        double e0 = w0 * 0.5 - c[0] * 0.5, e1 = w1 * 0.5 - c[1] * 0.5, e2 = w2 * 0.5 - c[2] * 0.5;
        if (!isfinite(e0) || !isfinite(e1) || !isfinite(e2)) return CV_FALLBACK;
        double rr, u[3];
        int has_u = polar(e0, e1, e2, &rr, u);
        if (has_u && !cv_finite3(u)) return CV_FALLBACK;
        rr *= 2.0;
        double d = r_out - rr;
        if ((d < band || d <= m) && has_u) {
            double q = limit(d, m, br);
            if (d > 0.0 && q < creep) q = creep;
            double b0 = v[0], b1 = v[1], b2 = v[2];
            static const int ks[3] = {0, 1, 2};
            if (cv_brake_along(v, ks, u, 3, q, 1.0) != 0) return CV_FALLBACK;
            int hit = !(v[0] == b0 && v[1] == b1 && v[2] == b2);
            if (d < 0.0 && rs > 0.0) {
                for (int j = 0; j < 6; j++) v[j] = cv_pymin(cv_pymax(v[j], -rs), rs);
                for (int k = 0; k < 3; k++) {
                    double back = rs * fabs(u[k]);
                    if (u[k] > 0.0 && v[k] > -back)
                        v[k] = -back;
                    else if (u[k] < 0.0 && v[k] < back)
                        v[k] = back;
                }
                why[n_why++] = 4 * (int)i + 1;
            } else if (hit) {
                why[n_why++] = 4 * (int)i + 0;
            }
        }

        /* Inner column, in the horizontal plane (along +x when exactly on the axis). */
        if (r_in > 0.0) {
            double rho, h[3];
            int has_h = polar(p[0] * 0.5 - c[0] * 0.5, p[1] * 0.5 - c[1] * 0.5, 0.0, &rho, h);
            rho *= 2.0;
            double dd = rho - r_in;
            if (dd < band || dd <= m) {
                int hit = 0;
                if (has_h) {
                    double cap_k = limit(dd, m, br) / (fabs(h[0]) + fabs(h[1]));
                    for (int k = 0; k < 2; k++)
                        if (v[k] * h[k] < 0.0 && fabs(v[k]) > cap_k) {
                            v[k] = v[k] > 0.0 ? cap_k : -cap_k;
                            hit = 1;
                        }
                }
                double ux = has_h ? h[0] : 1.0, uy = has_h ? h[1] : 0.0;
                if (dd < 0.0 && rs > 0.0) {
                    for (int j = 0; j < 6; j++) v[j] = cv_pymin(cv_pymax(v[j], -rs), rs);
                    const double ws[2] = {ux, uy};
                    for (int k = 0; k < 2; k++) {
                        double outk = rs * fabs(ws[k]);
                        if (ws[k] > 0.0 && v[k] < outk)
                            v[k] = outk;
                        else if (ws[k] < 0.0 && v[k] > -outk)
                            v[k] = -outk;
                    }
                    why[n_why++] = 4 * (int)i + 3;
                } else if (hit) {
                    why[n_why++] = 4 * (int)i + 2;
                }
            }
        }

        /* The arm is written back (all six components) only if a value changed. */
        int changed = 0;
        for (int j = 0; j < 6; j++)
            if (v[j] != out[o + j]) changed = 1;
        if (changed) {
            for (int j = 0; j < 6; j++) out[o + j] = v[j];
            for (int k = 0; k < n_why; k++) cv_note(r, why[k]);
            edited = 1;
        }
    }
    return edited ? CV_MODIFY : CV_ALLOW;
}
