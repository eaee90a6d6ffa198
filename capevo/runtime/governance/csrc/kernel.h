/* The fused governance kernel: every constraint of a Φ compiled into one C call.
 *
 * The Python constraints (capevo/runtime/governance, one module per kind) are the specification. Each ported
 * check here must return, for every input it accepts, exactly what the Python check returns:
 * the same verdict, the same components bit for bit (signed zeros included) and the same
 * reason strings. Where matching Python exactly would be hard (a reason formatted with values,
 * a non-finite input, an overflow path that Python takes through math.hypot), a check returns
 * CV_FALLBACK and the governor runs the whole call through the Python checks instead.
 *
 * Floating point: compiled with -ffp-contract=off and without -ffast-math, so a * b + c is two
 * roundings as in CPython, and each expression must keep Python's evaluation order (left to
 * right; a + b + c is (a + b) + c). Python's min(x, y) returns x unless y < x; max(x, y)
 * returns x unless y > x (this decides which signed zero or NaN comes out): use cv_pymin and
 * cv_pymax, never fmin/fmax. abs() is fabs().
 */
#ifndef CAPEVO_GOVERNANCE_KERNEL_H
#define CAPEVO_GOVERNANCE_KERNEL_H

#include <math.h>
#include <stddef.h>

#define CV_MAX_DIM 32      /* action components */
#define CV_MAX_ARMS 4
#define CV_MAX_NEAR 64     /* proximity pairs per arm; more falls back to Python */
#define CV_MAX_REASONS 16  /* reasons one check may join with "; " */

/* What a check answers. */
#define CV_ALLOW 0    /* no edit: Python's check returned None */
#define CV_MODIFY 1   /* ``out`` holds a′ (world frame), ``reasons`` the notes joined in order */
#define CV_REJECT 2   /* ⊥ with ``reasons`` */
#define CV_FALLBACK 3 /* this input needs the Python checks (rare paths, formatted reasons) */

/* One arm of RobotState, as the Python checks read it. */
typedef struct {
    double pos[3];   /* eef_pos */
    double force[3]; /* eef_force */
    double rot[9];   /* eef_rot, row-major; only valid when has_rot */
    int has_rot;     /* 0: the arm state has no eef_rot (or it is None): rotation_of() is None */
    int n_near;      /* len(near); 0 when the arm state has no ``near`` */
    const double *near; /* n_near rows of 8: dist, nx, ny, nz, rx, ry, rz, owner (owner exact as a double) */
} cv_arm;

typedef struct {
    int n_arms;
    int dim;
    cv_arm arms[CV_MAX_ARMS];
} cv_state;

/* A constraint compiled for one layout: what its Python ``kernel_spec(layout)`` returned. */
typedef struct {
    const double *f; /* float parameters, in the order kernel_spec lists them */
    int nf;
    const long *i;   /* integer parameters (offsets, flags, counts) */
    int ni;
    int n_reasons;   /* len of the spec's reasons tuple; indices written must be below it */
} cv_spec;

/* Reason indices (into the spec's reasons tuple) a check appends; joined with "; " in order. */
typedef struct {
    int n;
    int idx[CV_MAX_REASONS];
} cv_reasons;

static inline void cv_note(cv_reasons *r, int idx) {
    if (r->n < CV_MAX_REASONS) r->idx[r->n] = idx;
    r->n++; /* n > CV_MAX_REASONS makes the caller fall back */
}

/* A check. ``a`` is the action with each arm's translation in the world frame (read only);
 * ``out`` starts as a copy of ``a`` and is where a modify writes a′. Returns a CV_* code. */
typedef int (*cv_check_fn)(const cv_spec *spec, const cv_state *s, const double *a, double *out, cv_reasons *r);

/* Python's min(x, y) and max(x, y) for two floats. */
static inline double cv_pymin(double x, double y) { return y < x ? y : x; }
static inline double cv_pymax(double x, double y) { return y > x ? y : x; }

/* Whether all three components of a vector (a position, a force) are finite. */
static inline int cv_finite3(const double *v) { return isfinite(v[0]) && isfinite(v[1]) && isfinite(v[2]); }

/* capevo.runtime.governance.cap.SHRINK, passed in by the module at import time. */
extern double cv_shrink;

/* brake.py's brake_along on ``arm`` (the arm's 6 pose components), for the axes given as
 * (component index k, n_k) pairs. Returns 0, or CV_FALLBACK where it cannot match Python. */
int cv_brake_along(double *arm, const int *ks, const double *ns, int n_axes, double q, double sign);

/* The ported checks, one per constraint kind (name as in the kind's registration). */
int cv_check_workspace_box(const cv_spec *, const cv_state *, const double *, double *, cv_reasons *);
int cv_check_contact_force(const cv_spec *, const cv_state *, const double *, double *, cv_reasons *);
int cv_check_velocity_cap(const cv_spec *, const cv_state *, const double *, double *, cv_reasons *);
int cv_check_forbidden_zone(const cv_spec *, const cv_state *, const double *, double *, cv_reasons *);
int cv_check_workspace_guard(const cv_spec *, const cv_state *, const double *, double *, cv_reasons *);
int cv_check_force_ramp(const cv_spec *, const cv_state *, const double *, double *, cv_reasons *);
int cv_check_contact_approach(const cv_spec *, const cv_state *, const double *, double *, cv_reasons *);
int cv_check_surface_approach(const cv_spec *, const cv_state *, const double *, double *, cv_reasons *);
int cv_check_obstacle_approach(const cv_spec *, const cv_state *, const double *, double *, cv_reasons *);
int cv_check_arm_separation(const cv_spec *, const cv_state *, const double *, double *, cv_reasons *);
int cv_check_reach_limit(const cv_spec *, const cv_state *, const double *, double *, cv_reasons *);

#endif
