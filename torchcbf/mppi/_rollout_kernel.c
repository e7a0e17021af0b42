/*
 * Fused MPPI rollouts on the CPU (loaded through ctypes by torchcbf/mppi/_rollout.py).
 *
 * For a block of up to LANES samples of one environment the kernel generates the Gaussian
 * control noise (counter-based: a hash of the environment's key and the sample, step and
 * component indices, then Box-Muller), applies the Cholesky factor of the noise covariance,
 * clamps the controls to the limits, integrates a built-in model (euler or rk4) and
 * accumulates the built-in cost terms and the control cost, without storing the rollout.
 * State, control and noise rows are optional outputs (the planner asks for them when a
 * torch cost scores the rollouts, and to re-roll the best sample); a weighted sum of the
 * noise is the output of the update pass. The torch implementation in planner.py and
 * costs.py is the reference for every formula here.
 *
 * Lanes are stored component-major (x[i][lane]) so that every inner loop runs over the
 * lanes and vectorises; on glibc/x86-64 the transcendental functions are declared with
 * their libmvec vector variants and the hot function is compiled for AVX-512, AVX2 and the
 * baseline (target_clones), picked at load time.
 *
 * The body is written once in _rollout_kernel.h and included for float and for double.
 */
#include <math.h>
#include <stdint.h>
#include <stdlib.h>
#include <string.h>

/* Bumped whenever an exported signature or the meaning of the configuration changes;
 * _rollout.py refuses a built library of another version. */
#define KERNEL_VERSION 6

#define LANES 64
#define NMAX 8
#define MMAX 4
#define DMAX 4
#define TMAX 16
#define SMAX 32

#if defined(__GNUC__) && !defined(__clang__) && defined(__x86_64__) && defined(__GLIBC__) && \
    !defined(__FAST_MATH__)
/* glibc ships vector variants of these in libmvec; declaring them lets gcc vectorise the
 * lane loops that call them (math.h declares them only under -ffast-math). */
extern float sinf(float) __attribute__((simd("notinbranch")));
extern float cosf(float) __attribute__((simd("notinbranch")));
extern float logf(float) __attribute__((simd("notinbranch")));
extern double sin(double) __attribute__((simd("notinbranch")));
extern double cos(double) __attribute__((simd("notinbranch")));
extern double log(double) __attribute__((simd("notinbranch")));
#define CLONES __attribute__((target_clones("arch=x86-64-v4", "arch=x86-64-v3", "default")))
#else
#define CLONES
#endif

int torchcbf_mppi_version(void) { return KERNEL_VERSION; }
int torchcbf_mppi_lanes(void) { return LANES; }

/* models and integrators (codes shared with _rollout.py) */
enum { M_SINGLE = 0, M_DOUBLE = 1, M_UNICYCLE = 2, M_ACCEL_UNICYCLE = 3 };
enum { I_EULER = 0, I_RK4 = 1 };
/* cost terms */
enum { T_GOAL = 0, T_OBSTACLE = 1, T_BARRIER = 2, T_DISCRETE_BARRIER = 3 };
/* shapes */
enum { S_ELLIPSE = 0, S_BALL = 1 };

/* The configuration is one float64 vector, built by _rollout.py from the names below (it
 * reads them from this file): the header's fields, lo[MMAX], hi[MMAX] and chol[MMAX*MMAX]
 * from HDR on, then nterms term records of TREC values and nshapes shape records of SREC.
 * A term's eps is, for a discrete-time barrier term, the number of steps it penalises (-1:
 * every step). Changing a layout changes KERNEL_VERSION. */
enum { H_VERSION, H_MODEL, H_INTEGRATOR, H_N, H_M, H_H, H_K, H_DIM, H_ZERO_NOISE, H_HAS_LO,
       H_HAS_HI, H_NTERMS, H_NSHAPES, H_DT, H_GAMMA, HDR = 16 };
enum { TR_TYPE, TR_WEIGHT, TR_EXTRA, TR_EPS, TR_D, TR_IDX, TR_CENTER = TR_IDX + DMAX,
       TR_RADIUS = TR_CENTER + DMAX, TR_SHAPE0, TR_NSHAPE, TREC };
enum { SR_KIND, SR_D, SR_IDX, SR_CENTER = SR_IDX + DMAX, SR_AXES = SR_CENTER + DMAX,
       SR_RADIUS = SR_AXES + DMAX, SR_SIGN, SR_ROTATED, SR_ANGLE, SREC = 20 };

typedef struct {
    int type, d, idx[DMAX], shape0, nshape, steps;
    double weight, extra, eps, radius, center[DMAX];
    /* derived by parse(): a barrier term's discrete-time term over the same shapes (-1:
     * none), evaluated in the barrier term's loop; `paired` marks that discrete term */
    int pair, paired;
} term_t;

typedef struct {
    int kind, d, idx[DMAX], rotated;
    double sign, radius, angle, center[DMAX], axes[DMAX];
} shape_t;

typedef struct {
    int model, integrator, n, m, H, dim, has_lo, has_hi, nterms, nshapes;
    int64_t K, zero_noise;
    double dt, gamma;
    double lo[MMAX], hi[MMAX], chol[MMAX * MMAX];
    term_t terms[TMAX];
    shape_t shapes[SMAX];
} problem_t;

/* 0 on success, else a negative code (bad configuration). */
static int parse(const double *cfg, problem_t *pr) {
    memset(pr, 0, sizeof(*pr));
    if ((int)cfg[H_VERSION] != KERNEL_VERSION) return -1;
    pr->model = (int)cfg[H_MODEL];
    pr->integrator = (int)cfg[H_INTEGRATOR];
    pr->n = (int)cfg[H_N];
    pr->m = (int)cfg[H_M];
    pr->H = (int)cfg[H_H];
    pr->K = (int64_t)cfg[H_K];
    pr->dim = (int)cfg[H_DIM];
    pr->zero_noise = (int64_t)cfg[H_ZERO_NOISE];
    pr->has_lo = (int)cfg[H_HAS_LO];
    pr->has_hi = (int)cfg[H_HAS_HI];
    pr->nterms = (int)cfg[H_NTERMS];
    pr->nshapes = (int)cfg[H_NSHAPES];
    pr->dt = cfg[H_DT];
    pr->gamma = cfg[H_GAMMA];
    if (pr->n < 1 || pr->n > NMAX || pr->m < 1 || pr->m > MMAX || pr->H < 1 || pr->K < 1)
        return -2;
    if (pr->nterms < 0 || pr->nterms > TMAX || pr->nshapes < 0 || pr->nshapes > SMAX) return -3;
    const double *p = cfg + HDR;
    for (int i = 0; i < MMAX; ++i) pr->lo[i] = p[i];
    for (int i = 0; i < MMAX; ++i) pr->hi[i] = p[MMAX + i];
    for (int i = 0; i < MMAX * MMAX; ++i) pr->chol[i] = p[2 * MMAX + i];
    p += 2 * MMAX + MMAX * MMAX;
    for (int t = 0; t < pr->nterms; ++t, p += TREC) {
        term_t *T = &pr->terms[t];
        T->type = (int)p[TR_TYPE];
        T->weight = p[TR_WEIGHT];
        T->extra = p[TR_EXTRA];
        T->eps = p[TR_EPS];
        T->d = (int)p[TR_D];
        if (T->d < 0 || T->d > DMAX) return -4;
        for (int i = 0; i < DMAX; ++i) {
            T->idx[i] = (int)p[TR_IDX + i];
            T->center[i] = p[TR_CENTER + i];
            if (i < T->d && (T->idx[i] < 0 || T->idx[i] >= pr->n)) return -4;
        }
        T->radius = p[TR_RADIUS];
        T->shape0 = (int)p[TR_SHAPE0];
        T->nshape = (int)p[TR_NSHAPE];
        if (T->shape0 < 0 || T->nshape < 0 || T->shape0 + T->nshape > pr->nshapes) return -5;
        T->pair = -1;
        if (T->type == T_DISCRETE_BARRIER) {
            if (T->eps != -1 && !(T->eps >= 0 && T->eps == floor(T->eps))) return -8;
            T->steps = T->eps == -1 || T->eps > pr->H ? pr->H : (int)T->eps;
        }
    }
    /* the next discrete-time term after a barrier term, over the same shapes: its sum goes
     * into `whole` at the barrier term's place, still the first after the earlier ones */
    for (int t = 0; t < pr->nterms; ++t) {
        term_t *T = &pr->terms[t];
        if (T->type != T_BARRIER || T->nshape == 0) continue;
        for (int u = t + 1; u < pr->nterms; ++u) {
            term_t *D = &pr->terms[u];
            if (D->type != T_DISCRETE_BARRIER) continue;
            if (!D->paired && D->shape0 == T->shape0 && D->nshape == T->nshape)
                T->pair = u, D->paired = 1;
            break;
        }
    }
    for (int s = 0; s < pr->nshapes; ++s, p += SREC) {
        shape_t *S = &pr->shapes[s];
        S->kind = (int)p[SR_KIND];
        S->d = (int)p[SR_D];
        if (S->d < 1 || S->d > DMAX) return -6;
        for (int i = 0; i < DMAX; ++i) {
            S->idx[i] = (int)p[SR_IDX + i];
            S->center[i] = p[SR_CENTER + i];
            S->axes[i] = p[SR_AXES + i];
            if (i < S->d && (S->idx[i] < 0 || S->idx[i] >= pr->n)) return -6;
        }
        S->radius = p[SR_RADIUS];
        S->sign = p[SR_SIGN];
        S->rotated = (int)p[SR_ROTATED];
        S->angle = p[SR_ANGLE];
        if (S->rotated && S->d != 2) return -6;
    }
    return 0;
}

/* Stafford's 64-bit finaliser ("mix13") of key + (counter + 1) * golden ratio: a
 * counter-based generator, every (sample, step, component) has its own counter. */
static inline uint64_t mix64(uint64_t z) {
    z = (z ^ (z >> 30)) * 0xBF58476D1CE4E5B9ull;
    z = (z ^ (z >> 27)) * 0x94D049BB133111EBull;
    return z ^ (z >> 31);
}
#define GOLDEN 0x9E3779B97F4A7C15ull

#define REAL float
#define SUFFIX(name) name##_f32
#define SIN sinf
#define COS cosf
#define LOG logf
#define SQRT sqrtf
#include "_rollout_kernel.h"
#undef REAL
#undef SUFFIX
#undef SIN
#undef COS
#undef LOG
#undef SQRT

#define REAL double
#define SUFFIX(name) name##_f64
#define SIN sin
#define COS cos
#define LOG log
#define SQRT sqrt
#include "_rollout_kernel.h"
