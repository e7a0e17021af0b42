/*
 * The safety filter's QP on a few states, in one call: assembly, solve, residuals (loaded
 * through ctypes by torchcbf/filters/realtime.py, linked with torchcbf/qp/_dual_kernel.c).
 *
 * On one state per control tick, building the filter QP out of tensor or numpy operations
 * costs several times the solve. This file builds it as torchcbf/filters/qp_data.py's
 * assemble() documents it (the torch assembly is the reference; the tests compare the two
 * paths), with the finite control limits and the slack signs as rows, solves it with the
 * dual active-set kernel and computes the filter's outputs. It answers only when the kernel
 * certifies every row; the caller then runs the general path, so both give one answer.
 */
#include <math.h>
#include <stdint.h>
#include <stdlib.h>
#include <string.h>

#include "../barriers/_lie_kernel.h"
#include "../qp/_dual_kernel.h"

/* Bumped whenever an exported signature or its meaning changes (see _native.py); the version
 * reported folds in the linked QP kernel's, whose solver this library carries. */
#define FILTER_KERNEL_VERSION 11

int torchcbf_filter_version(void) {
    return 100 * FILTER_KERNEL_VERSION + TORCHCBF_DUAL_KERNEL_VERSION;
}

/* slack modes, as SLACK_CODES in realtime.py */
enum { SLACK_NONE = 0, SLACK_SHARED = 1, SLACK_PER_ROW = 2 };

/* the filter statuses written (FilterStatus in safety_filter.py) */
enum { STATUS_SOLVED = 0, STATUS_RELAXED = 1 };

/* Whether the states x [nx], controls u [nu] and times t [nt] (float64) are all finite: the
 * real-time path's test before any computation on them. */
int torchcbf_filter_inputs_finite(int64_t nx, const double *x, int64_t nu, const double *u,
                                  int64_t nt, const double *t) {
    return torchcbf_dual_all_finite(nx, x) && torchcbf_dual_all_finite(nu, u) &&
           torchcbf_dual_all_finite(nt, t);
}

/* The filter QP of one state over z = [u (m); s (ks); delta (c)]: P [N,N], q [N],
 * G [M,N], h [M] with N = m + ks + c and M = k + c + (finite limits) + ks + c. */
static void assemble_one(int m, int k, int c, int ks, int slack, const double *a_cbf,
                         const double *b_cbf, const double *a_clf, const double *b_clf,
                         const double *u_nom, const double *R, const double *lo,
                         const double *hi, double cbf_weight, double clf_weight, int N, int M,
                         double *P, double *q, double *G, double *h) {
    double rbar = 0.0;
    for (int i = 0; i < m; ++i) rbar += R[i * m + i];
    rbar /= m;
    memset(P, 0, sizeof(double) * N * N);
    memset(q, 0, sizeof(double) * N);
    memset(G, 0, sizeof(double) * M * N);
    memset(h, 0, sizeof(double) * M);
    for (int i = 0; i < m; ++i) {
        double s = 0.0;
        for (int j = 0; j < m; ++j) {
            P[i * N + j] = 0.5 * (R[i * m + j] + R[j * m + i]);
            s += R[i * m + j] * u_nom[j];
        }
        q[i] = -s;
    }
    for (int j = 0; j < c; ++j) P[(m + ks + j) * (N + 1)] = clf_weight * rbar;
    /* CBF rows: -(a_i / n_i) u - s <= b_i / n_i */
    double viol = 0.0;
    for (int i = 0; i < k; ++i) {
        const double *a = a_cbf + i * m;
        double nrm = 0.0, au = 0.0;
        for (int j = 0; j < m; ++j) {
            nrm += a[j] * a[j];
            au += a[j] * u_nom[j];
        }
        nrm = sqrt(nrm);
        if (!(nrm >= 1e-6)) nrm = 1e-6; /* MIN_ROW_NORM */
        for (int j = 0; j < m; ++j) G[i * N + j] = -a[j] / nrm;
        h[i] = b_cbf[i] / nrm;
        double v = -(au + b_cbf[i]) / nrm;
        if (v > viol) viol = v;
        if (slack == SLACK_SHARED) G[i * N + m] = -1.0;
        else if (slack == SLACK_PER_ROW) G[i * N + m + i] = -1.0;
    }
    if (ks) {
        double w = cbf_weight * rbar;
        if (slack == SLACK_SHARED) { /* w (1 + v): v estimates the hard multipliers */
            double box = 0.0;
            for (int j = 0; j < m; ++j) {
                double u = u_nom[j], clip = u < lo[j] ? lo[j] : (u > hi[j] ? hi[j] : u);
                if (fabs(u - clip) > box) box = fabs(u - clip);
            }
            double scale = viol + box;
            w *= 1.0 + (scale < 1e3 ? scale : 1e3); /* MAX_PENALTY_SCALE */
            q[m] = w;
        }
        for (int j = 0; j < ks; ++j) P[(m + j) * (N + 1)] = w;
    }
    /* CLF rows: a_j u - delta_j <= -b_j */
    for (int j = 0; j < c; ++j) {
        double *row = G + (k + j) * N;
        for (int l = 0; l < m; ++l) row[l] = a_clf[j * m + l];
        row[m + ks + j] = -1.0;
        h[k + j] = -b_clf[j];
    }
    int r = k + c;
    for (int j = 0; j < m; ++j)
        if (isfinite(hi[j])) {
            G[r * N + j] = 1.0;
            h[r++] = hi[j];
        }
    for (int j = 0; j < m; ++j)
        if (isfinite(lo[j])) {
            G[r * N + j] = -1.0;
            h[r++] = -lo[j];
        }
    for (int j = m; j < N; ++j) G[(r++) * N + j] = -1.0; /* s >= 0, delta >= 0 */
}

/*
 * The filter on B states. Inputs (float64, C-contiguous, batch first): CBF conditions
 * a . u + b >= 0 (a_cbf [B,k,m], b_cbf [B,k]), CLF conditions a . u + b <= delta (a_clf
 * [B,c,m], b_clf [B,c]), u_nom [B,m], R [m,m], limits lo, hi [m] (NULL, or infinite
 * entries, where absent). The caller checks the states and times (inputs_finite above).
 * two_pass: also solve the hard QP (CBF slack columns zeroed) and prefer its solution; a
 * row whose hard QP the kernel proves infeasible takes the elastic one.
 * Outputs: u_out [B,m]; slack_out [B,k+c] (CBF violations, then CLF relaxations);
 * value_out [B,k+c] (a . u + b for CBF rows, -(a . u + b) for CLF rows); status [B] (SOLVED
 * or RELAXED: a CBF slack above slack_tol).
 * Returns 0 when every row was certified, 1 when not (outputs then undefined: the caller
 * takes its general path), -1 when memory ran out or the sizes are invalid. The solver may
 * take max(max_iter, 4 (rows + variables)) steps (torchcbf.qp._function.dual_budget).
 */
int torchcbf_filter_solve(int64_t B, int m, int k, int c, int slack, int two_pass,
                          const double *a_cbf, const double *b_cbf, const double *a_clf,
                          const double *b_clf, const double *u_nom, const double *R,
                          const double *lo, const double *hi, double cbf_weight,
                          double clf_weight, double eps, int max_iter, double slack_tol,
                          double max_condition, double *u_out, double *slack_out,
                          double *value_out, int64_t *status) {
    if (B < 1 || m < 1 || k < 0 || c < 0 || k + c < 1) return -1;
    int ks = (k == 0 || slack == SLACK_NONE) ? 0 : (slack == SLACK_PER_ROW ? k : 1);
    int N = m + ks + c;
    if (N > TORCHCBF_DUAL_NMAX) return 1;
    double lo_v[TORCHCBF_DUAL_NMAX], hi_v[TORCHCBF_DUAL_NMAX]; /* NULL limits: none */
    for (int j = 0; j < m; ++j) {
        lo_v[j] = lo ? lo[j] : -INFINITY;
        hi_v[j] = hi ? hi[j] : INFINITY;
    }
    lo = lo_v, hi = hi_v;
    int limits = 0;
    for (int j = 0; j < m; ++j) limits += isfinite(lo[j]) + isfinite(hi[j]);
    int M = k + c + limits + ks + c;
    /* problems: [elastic (B); hard (B); with CLFs, the CBF rows' elastic problems of the
     * rows whose hard problem is infeasible (at most B, solved in a second call)] */
    int64_t Bq = two_pass && ks ? (c > 0 ? 3 * B : 2 * B) : B;
    /* u_nom was checked with the states (inputs_finite); the conditions come from them */
    const double *inputs[] = {a_cbf, b_cbf, a_clf, b_clf, R};
    const int64_t sizes[] = {(int64_t)k * m * B, (int64_t)k * B, (int64_t)c * m * B,
                             (int64_t)c * B, m * m};
    for (int i = 0; i < 5; ++i)
        if (!torchcbf_dual_all_finite(sizes[i], inputs[i])) return 1;
    size_t per = (size_t)N * N + N + (size_t)M * N + M + N + M + (size_t)N * N;
    double *buf = malloc(sizeof(double) * per * Bq + sizeof(double) * N * N);
    int64_t *ints = malloc(sizeof(int64_t) * (N + 1) * Bq);
    uint8_t *bytes = malloc((size_t)(M + 2) * Bq);
    if (!buf || !ints || !bytes) {
        free(buf), free(ints), free(bytes);
        return -1;
    }
    double *P = buf, *q = P + Bq * N * N, *G = q + Bq * N, *h = G + Bq * M * N;
    double *x = h + Bq * M, *z = x + Bq * N, *L = z + Bq * M, *inv = L + Bq * N * N;
    int64_t *slots = ints, *iters = slots + Bq * N;
    uint8_t *active = bytes, *ok = active + Bq * M, *infeasible = ok + Bq;
    for (int64_t b = 0; b < B; ++b)
        assemble_one(m, k, c, ks, slack, a_cbf + b * k * m, b_cbf + b * k, a_clf + b * c * m,
                     b_clf + b * c, u_nom + b * m, R, lo, hi, cbf_weight, clf_weight, N, M,
                     P + b * N * N, q + b * N, G + b * M * N, h + b * M);
    if (Bq > B) { /* the hard copies: CBF slack columns zeroed */
        memcpy(P + B * N * N, P, sizeof(double) * B * N * N);
        memcpy(q + B * N, q, sizeof(double) * B * N);
        memcpy(G + B * M * N, G, sizeof(double) * B * M * N);
        memcpy(h + B * M, h, sizeof(double) * B * M);
        for (int64_t b = B; b < Bq; ++b)
            for (int i = 0; i < k; ++i)
                for (int j = m; j < m + ks; ++j) G[b * M * N + i * N + j] = 0.0;
    }
    int budget = max_iter > 4 * (M + N) ? max_iter : 4 * (M + N);
    int64_t Bs = Bq > 2 * B ? 2 * B : Bq; /* solved in the first call */
    /* the problems solved first; P, q, G and h are each laid out for all Bq problems */
    int code = torchcbf_dual_all_finite(Bs * N * N, P) && torchcbf_dual_all_finite(Bs * N, q) &&
                       torchcbf_dual_all_finite(Bs * M * N, G) && torchcbf_dual_all_finite(Bs * M, h)
                   ? 0
                   : 1;
    if (code == 0 && torchcbf_dual_forward(Bs, N, M, P, q, G, h, eps, budget, x, z, active,
                                           slots, L, ok, iters, infeasible) != 0)
        code = -1;
    /* with CLFs, where the hard problem is infeasible: the elastic problem of the CBF rows
     * alone (the CLF rows' controls and right-hand sides zeroed: delta sits at 0), whose
     * slack is the least violation a CLF's pull on the elastic problem may not exceed;
     * row b's at 2B + (its rank among those rows) */
    int64_t extra = 0;
    for (int64_t b = 0; Bq > Bs && b < B && code == 0; ++b) {
        if (ok[B + b] || !infeasible[B + b]) continue;
        int64_t e = 2 * B + extra++;
        memcpy(P + e * N * N, P + b * N * N, sizeof(double) * N * N);
        memcpy(q + e * N, q + b * N, sizeof(double) * N);
        memcpy(G + e * M * N, G + b * M * N, sizeof(double) * M * N);
        memcpy(h + e * M, h + b * M, sizeof(double) * M);
        for (int i = k; i < k + c; ++i) {
            for (int j = 0; j < m; ++j) G[e * M * N + i * N + j] = 0.0;
            h[e * M + i] = 0.0;
        }
    }
    if (code == 0 && extra > 0 &&
        torchcbf_dual_forward(extra, N, M, P + 2 * B * N * N, q + 2 * B * N, G + 2 * B * M * N,
                              h + 2 * B * M, eps, budget, x + 2 * B * N, z + 2 * B * M,
                              active + 2 * B * M, slots + 2 * B * N, L + 2 * B * N * N,
                              ok + 2 * B, iters + 2 * B, infeasible + 2 * B) != 0)
        code = -1;
    /* the solution each row keeps; the dual method is trusted only on Q it conditions well */
    for (int64_t b = 0, e = 2 * B; b < B && code == 0; ++b) {
        int64_t pick = b;
        int least = 0; /* the CBF rows' own problem answers: delta follows from u */
        if (Bq > B) {
            if (ok[B + b]) pick = B + b;
            else if (!infeasible[B + b]) code = 1;
            else if (Bq > Bs) {
                double s_el = 0.0, s_cbf = 0.0;
                for (int j = 0; j < ks; ++j) {
                    s_el = fmax(s_el, x[b * N + m + j]);
                    s_cbf = fmax(s_cbf, x[e * N + m + j]);
                }
                if (ok[e] && (!ok[b] || s_el > s_cbf + slack_tol)) pick = e, least = 1;
                ++e;
            }
        }
        if (code != 0 || !ok[pick]) {
            code = 1;
            break;
        }
        if (!torchcbf_dual_diagonally_dominant(N, P + pick * N * N) &&
            !(torchcbf_dual_condition_estimate(N, L + pick * N * N, inv) <= max_condition))
            code = 1;
        if (code != 0) break;
        const double *zb = x + pick * N, *s = zb + m, *delta = zb + m + ks;
        double *slk = slack_out + b * (k + c), *val = value_out + b * (k + c);
        memcpy(u_out + b * m, zb, sizeof(double) * m);
        int relaxed = 0;
        for (int j = 0; j < ks; ++j) relaxed |= s[j] > slack_tol;
        for (int i = 0; i < k; ++i) {
            double v = b_cbf[b * k + i];
            for (int j = 0; j < m; ++j) v += a_cbf[(b * k + i) * m + j] * zb[j];
            val[i] = v;
            slk[i] = v < 0.0 ? -v : 0.0;
        }
        for (int i = 0; i < c; ++i) {
            double v = b_clf[b * c + i];
            for (int j = 0; j < m; ++j) v += a_clf[(b * c + i) * m + j] * zb[j];
            val[k + i] = -v;
            double d = least ? v : delta[i];
            slk[k + i] = d > 0.0 ? d : 0.0;
        }
        status[b] = relaxed ? STATUS_RELAXED : STATUS_SOLVED;
    }
    free(buf), free(ints), free(bytes);
    return code;
}

/* The Lie-term kernel of torchcbf/barriers/_lie_kernel.c (its torchcbf_lie_quadrics), whose
 * arguments _lie_kernel.h names; this file fills the slots of its outputs lgh [B, K, m] and
 * of the condition b [B, K]. */
typedef int (*lie_kernel)(const int64_t *meta, const double *reals, void *const *ptrs);

/*
 * torchcbf_filter_solve with the CBF conditions of quadric barriers computed first by the
 * Lie-term kernel `lie` (version `lie_version`) from its arguments lie_meta, lie_reals and
 * lie_ptrs (prepared by torchcbf/barriers/native.py for B states and m controls, with an
 * affine condition and the h output set; the PT_LGH and PT_B slots are filled here with a
 * workspace), so no tensor holds the conditions.
 * Returns as torchcbf_filter_solve; 1 also when the Lie kernel declines, is another version
 * or was prepared for other sizes.
 */
int torchcbf_filter_quadrics(lie_kernel lie, int lie_version, const int64_t *lie_meta,
                             const double *lie_reals, void **lie_ptrs, int64_t B, int m, int k,
                             int c, int slack, int two_pass, const double *a_clf,
                             const double *b_clf, const double *u_nom, const double *R,
                             const double *lo, const double *hi, double cbf_weight,
                             double clf_weight, double eps, int max_iter, double slack_tol,
                             double max_condition, double *u_out, double *slack_out,
                             double *value_out, int64_t *status) {
    if (!lie || lie_version != LIE_KERNEL_VERSION || B < 1 || m < 1 || k < 1 ||
        lie_meta[L_B] != B || lie_meta[L_M] != m)
        return 1;
    double *ab = malloc(sizeof(double) * (size_t)(B * k * (m + 1)));
    if (!ab) return -1;
    lie_ptrs[PT_LGH] = ab, lie_ptrs[PT_B] = ab + B * k * m;
    int code = lie(lie_meta, lie_reals, lie_ptrs) ? 1 : 0;
    if (code == 0)
        code = torchcbf_filter_solve(B, m, k, c, slack, two_pass, ab, ab + B * k * m, a_clf,
                                     b_clf, u_nom, R, lo, hi, cbf_weight, clf_weight, eps,
                                     max_iter, slack_tol, max_condition, u_out, slack_out,
                                     value_out, status);
    lie_ptrs[PT_LGH] = lie_ptrs[PT_B] = NULL;
    free(ab);
    return code;
}
