/* The hand as boxes in its end-effector site frame, turned by the arm's orientation (hand.py,
 * obstacle.py's extent_of), shared by obstacle_approach.c and arm_separation.c. */
#ifndef CAPEVO_GOVERNANCE_HAND_H
#define CAPEVO_GOVERNANCE_HAND_H

#include "kernel.h"

/* pose.DOWN: the orientation of an arm state without one. */
extern const double cv_down[9];

/* extent_of(hand)(rot) (= hand.hand_extent(hand, rot)): the world-frame offsets lo[3], hi[3]
 * from the site of the axis-aligned box bounding the hand's boxes turned by ``rot`` (row-major
 * 3x3). ``shapes`` holds n_boxes rows of 6 (c0, c1, c2, h0, h1, h2: centre and half sizes, as
 * obstacle.kernel_shapes lists them); no boxes gives zero offsets. Bit for bit Python's, NaN
 * included (a NaN candidate never replaces the running inf / -inf). */
void cv_hand_extent(const double *shapes, long n_boxes, const double *rot, double lo[3], double hi[3]);

/* Whether all nine entries of ``rot`` are finite. */
int cv_rot_finite(const double *rot);

#endif
