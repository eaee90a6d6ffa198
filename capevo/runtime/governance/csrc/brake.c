/* brake.py's brake_along, operation for operation. */
#include "kernel.h"

int cv_brake_along(double *arm, const int *ks, const double *ns, int n_axes, double q, double sign) {
    double c = 0.0;
    for (int j = 0; j < n_axes; j++) {
        double v = sign * arm[ks[j]] * ns[j];
        if (v > 0.0) c += v;
    }
    if (c <= q) return 0;
    int ak[8];
    double an[8];
    int n = 0;
    if (n_axes > 8) return CV_FALLBACK;
    for (int j = 0; j < n_axes; j++)
        if (sign * arm[ks[j]] * ns[j] > 0.0) {
            ak[n] = ks[j];
            an[n] = ns[j];
            n++;
        }
    double excess = c - q * cv_shrink;
    while (n > 0 && excess > 0.0) {
        double nn = 0.0;
        for (int j = 0; j < n; j++) nn += an[j] * an[j];
        if (!(nn > 0.0)) {
            /* Directions so small their squares underflow: scale by one factor instead. */
            c = 0.0;
            for (int j = 0; j < n; j++) c += sign * arm[ak[j]] * an[j];
            double f = c > q ? q / c * cv_shrink : 1.0;
            for (int j = 0; j < n; j++) arm[ak[j]] *= f;
            return 0;
        }
        double lam = excess / nn;
        /* min(active, key=|arm[k] / n|): the first of the smallest keys, as Python's min keeps it. */
        int m = 0;
        double best = fabs(arm[ak[0]] / an[0]);
        for (int j = 1; j < n; j++) {
            double key = fabs(arm[ak[j]] / an[j]);
            if (key < best) {
                best = key;
                m = j;
            }
        }
        int k0 = ak[m];
        double n0 = an[m];
        if (lam * fabs(n0) < fabs(arm[k0])) {
            for (int j = 0; j < n; j++) {
                double v = arm[ak[j]] - sign * lam * an[j];
                arm[ak[j]] = v * arm[ak[j]] > 0.0 ? v : 0.0;
            }
            return 0;
        }
        excess -= sign * arm[k0] * n0;
        arm[k0] = 0.0;
        /* active.remove((k0, n0)): the first equal pair, which is the one at m or an earlier duplicate. */
        int r = 0;
        while (r < n && !(ak[r] == k0 && an[r] == n0)) r++;
        for (int j = r; j + 1 < n; j++) {
            ak[j] = ak[j + 1];
            an[j] = an[j + 1];
        }
        n--;
    }
    return 0;
}
