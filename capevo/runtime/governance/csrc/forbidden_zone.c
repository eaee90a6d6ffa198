/* forbidden_zone (zone.py): motion towards (or, inside, deeper into) a zone zeroed per axis.
 *
 * kernel_spec: f = per zone 15 floats: grown low (3), grown high (3) (the zone grown by the
 * margin), zone low (3), zone high (3), centre (3);
 * i = (number of zones, offset of each arm);
 * reasons = for each arm, each zone, outside-but-within-margin then inside, the three axes:
 * reason ((arm * n_zones + zone) * 2 + inside) * 3 + axis.
 *
 * Falls back on: a non-finite end-effector position of any arm once some arm is not provably
 * outside every grown zone (the Python check rejects with the position formatted into the
 * reason). */
#include "kernel.h"

int cv_check_forbidden_zone(const cv_spec *spec, const cv_state *s, const double *a, double *out, cv_reasons *r) {
    if (spec->ni < 1) return CV_FALLBACK;
    const long nz = spec->i[0];
    if (nz < 1 || spec->nf != 15 * nz || spec->ni < 1 + s->n_arms) return CV_FALLBACK;
    const double *zf = spec->f;
    (void)a; /* the components are read from out: a, or a′ as earlier zones left it */

    /* The fast test: is some arm not provably outside some grown zone (NaN is not outside)? */
    int near = 0;
    for (int i = 0; i < s->n_arms && !near; i++) {
        const double x = s->arms[i].pos[0], y = s->arms[i].pos[1], z = s->arms[i].pos[2];
        for (long zi = 0; zi < nz; zi++) {
            const double *g = zf + 15 * zi;
            if (!(x < g[0] || x > g[3] || y < g[1] || y > g[4] || z < g[2] || z > g[5])) {
                near = 1;
                break;
            }
        }
    }
    if (!near) return CV_ALLOW;

    int edited = 0;
    for (int i = 0; i < s->n_arms; i++) {
        const double *p = s->arms[i].pos;
        if (!cv_finite3(p)) return CV_FALLBACK; /* formatted reason */
        const long o = spec->i[1 + i];
        if (o < 0 || o + 3 > s->dim) return CV_FALLBACK;
        for (long zi = 0; zi < nz; zi++) {
            const double *g_lo = zf + 15 * zi, *g_hi = g_lo + 3, *z_lo = g_lo + 6, *z_hi = g_lo + 9,
                         *centre = g_lo + 12;
            if (!(g_lo[0] <= p[0] && p[0] <= g_hi[0] && g_lo[1] <= p[1] && p[1] <= g_hi[1] && g_lo[2] <= p[2] &&
                  p[2] <= g_hi[2]))
                continue;
            const int inside = z_lo[0] <= p[0] && p[0] <= z_hi[0] && z_lo[1] <= p[1] && p[1] <= z_hi[1] &&
                               z_lo[2] <= p[2] && p[2] <= z_hi[2];
            const double *lo = inside ? centre : z_lo, *hi = inside ? centre : z_hi;
            for (int k = 0; k < 3; k++) {
                const double v = out[o + k];
                if ((v > 0.0 && p[k] < lo[k]) || (v < 0.0 && p[k] > hi[k])) {
                    out[o + k] = 0.0;
                    edited = 1;
                    cv_note(r, (int)(((i * nz + zi) * 2 + inside) * 3 + k));
                }
            }
        }
    }
    return edited ? CV_MODIFY : CV_ALLOW;
}
