/*
 * The exported entry points of _dual_kernel.c, for other C sources linked with it (the
 * safety filter's kernel, torchcbf/filters/_filter_kernel.c). Meanings as documented there.
 */
#ifndef TORCHCBF_DUAL_KERNEL_H
#define TORCHCBF_DUAL_KERNEL_H
#include <stdint.h>

/* Bumped whenever an exported signature or its meaning changes; _dual_native.py refuses a
 * built library of another version (e.g. an editable install not rebuilt after an edit). */
#define TORCHCBF_DUAL_KERNEL_VERSION 9

/* most variables a problem may have */
#define TORCHCBF_DUAL_NMAX 64

int torchcbf_dual_version(void);

int torchcbf_dual_forward(int64_t B, int N, int M, const double *P, const double *q,
                          const double *G, const double *h, double eps, int max_iter,
                          double *x, double *z, uint8_t *active, int64_t *slots, double *L,
                          uint8_t *ok, int64_t *iters, uint8_t *infeasible);

int torchcbf_dual_backward(int64_t B, int N, int M, const double *G, const double *L,
                           const int64_t *slots, const uint8_t *ok, const double *gx,
                           const double *gz, double *w_x, double *wz);

int torchcbf_dual_all_finite(int64_t n, const double *v);

int torchcbf_dual_diagonally_dominant(int N, const double *P);

double torchcbf_dual_condition_estimate(int N, const double *L, double *inv);

int torchcbf_dual_solve_small(int64_t B, int N, int M, const double *P, const double *q,
                              const double *G, const double *h, const double *lb,
                              const double *ub, double eps, int max_iter,
                              double max_condition, double *x, double *z, double *z_lb,
                              double *z_ub, int64_t *iters);

int torchcbf_dual_check_condition(int64_t B, int N, const double *L, double max_condition,
                                  uint8_t *ok);

int torchcbf_dual_tight_rows(int64_t B, int N, int M, const double *G, const double *h,
                             const double *x, const uint8_t *solved, double tight,
                             uint8_t *active);
int torchcbf_dual_certify(int64_t B, int N, int M, const double *P, const double *q,
                          const double *G, const double *h, const uint8_t *todo,
                          const uint8_t *active, const uint8_t *conv, double eps, int max_iter,
                          double prox_weight, int prox_steps, double rounding, double *x,
                          double *z, uint8_t *certified);
int torchcbf_dual_solve_small_eq(int64_t B, int n, int m, int k, const double *P,
                                 const double *q, const double *G, const double *h,
                                 const double *A, const double *b, const double *lb,
                                 const double *ub, double eps, int max_iter,
                                 double max_condition, double rank_tol, double span_tol,
                                 double rounding, double *x, double *z, double *y,
                                 double *z_lb, double *z_ub, int64_t *iters);
#endif
