/* reach_limit: not ported yet; every call falls back to the Python check. */
#include "kernel.h"

int cv_check_reach_limit(const cv_spec *spec, const cv_state *s, const double *a, double *out, cv_reasons *r) {
    (void)spec; (void)s; (void)a; (void)out; (void)r;
    return CV_FALLBACK;
}
