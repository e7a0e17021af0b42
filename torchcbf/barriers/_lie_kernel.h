/*
 * The arguments of torchcbf_lie_quadrics (_lie_kernel.c), named once: the kernel and the
 * filter kernel (_filter_kernel.c) include this file, and torchcbf/barriers/native.py reads
 * these names from it (torchcbf._native.constants) to build the arguments.
 */
#ifndef TORCHCBF_LIE_KERNEL_H
#define TORCHCBF_LIE_KERNEL_H

/* Bumped whenever an exported signature or its meaning changes (see _native.py). */
#define LIE_KERNEL_VERSION 6

/* The header of `meta`: the number of states, n, m, q, the outer model's code and size, the
 * number of blocks, the strides per output of the condition's gain and offset, the number of
 * groups; then the blocks' and the groups' integers. */
enum { L_B, L_N, L_M, L_Q, L_OUTER, L_OUTER_DIM, L_BLOCKS, L_GAIN_STRIDE, L_OFFSET_STRIDE,
       L_GROUPS, META_HEADER };
/* The header of `reals`: the condition's trace weight, gain scale and offset scale; then one
 * rate per block and one temperature per group. */
enum { R_TRACE_WEIGHT, R_GAIN_SCALE, R_OFFSET_SCALE, R_NOISE_SCALE, REALS_HEADER };
/* The pointers before the blocks' own: the state and diffusion, the seven outputs, the
 * condition's gain and offset. */
enum { PT_X, PT_SIGMA, PT_H, PT_LFH, PT_DHDT, PT_LGH, PT_HESS, PT_DHDX, PT_B, PT_GAIN,
       PT_OFFSET, PTRS_HEADER };

/* the transforms phi, as TRANSFORM_CODES in native.py */
enum { NO_TRANSFORM = 0, RADIUS = 1, EXP = 2 };

/* A block's integers in `meta` (then its d indices) and its pointers in `params`; M_CENTER to
 * M_SCALE and M_OUTER are the strides per output of the constants of those names (0: one
 * value shared by all outputs). */
enum {
    M_K, M_D, M_CENTER, M_AXES, M_RADIUS, M_ANGLE, M_SCALE, M_SIGN, M_TRANSFORM, M_OUTER,
    M_INNER, M_INNER_DIM, M_FIXED
};
enum { P_CENTER, P_AXES, P_RADIUS, P_ANGLE, P_SCALE, P_OUTER, P_K0, P_FIXED };

/* A group's integers in `meta`: its reduction (as REDUCTION_CODES in native.py), whether it
 * is smooth, its number of blocks and of outputs. */
enum { G_MODE, G_SMOOTH, G_BLOCKS, G_OUTPUTS, G_FIXED };
enum { NO_REDUCTION = 0, REDUCE_MIN = 1, REDUCE_MAX = 2 };

#endif
