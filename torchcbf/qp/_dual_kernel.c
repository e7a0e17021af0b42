/*
 * CPU kernel of the dual active-set method of torchcbf/qp/_dual.py, one problem at a time
 * (loaded through ctypes by torchcbf/qp/_dual_native.py).
 *
 * The torch implementation in _dual.py is the reference: this file runs the same algorithm
 * (same pivots, candidate choice, tolerances, exact multiplier re-solve and KKT check) but
 * keeps each small problem in registers and cache instead of streaming ~200 tensor
 * operations over the batch per step. It is built as an optional extension at install
 * time (setup.py); the functions below take raw float64 pointers, batch first,
 * C-contiguous. Without it, _dual.py's torch code runs on every device.
 *
 * Problem: min 1/2 x'Px + q'x  s.t.  Gx <= h,  P [N,N] positive definite, G [M,N], N <= 64.
 *
 * Beyond the torch implementation, the kernel certifies infeasibility: when no step can
 * restore the violated row p (it depends on the active rows, all of whose multipliers would
 * grow), y = (1 on p, -d on the active rows) >= 0 combines the rows into 0 <= h'y < 0, a
 * Farkas certificate. It is checked in floating point (see farkas()) and the row reported
 * infeasible; otherwise (a degenerate vertex, where p is tight to rounding) the exact final
 * check judges the point, as in the torch implementation.
 */
#include <math.h>
#include <stdint.h>
#include <stdlib.h>
#include <string.h>

#include "_dual_kernel.h"

/* largest N (local arrays are sized by it); N <= NUNROLL get a copy with N a constant */
#define NMAX TORCHCBF_DUAL_NMAX
#define NUNROLL 8

int torchcbf_dual_version(void) { return TORCHCBF_DUAL_KERNEL_VERSION; }

/* Every helper is inlined into one copy of the row solver per N (1..NUNROLL), so that N is a
 * compile-time constant and the small loops unroll; larger N share one copy. */
#if defined(__GNUC__)
#define INLINE static inline __attribute__((always_inline))
#define RESTRICT __restrict__
#else
#define INLINE static __forceinline
#define RESTRICT __restrict
#endif

/* max/min of non-NaN values without a libm call (NaN rows are caught by explicit checks) */
INLINE double dmax(double a, double b) { return a > b ? a : b; }
INLINE double dmin(double a, double b) { return a < b ? a : b; }

/* Lower Cholesky factor L [N,N] of P and the reciprocals of its diagonal, dinv [N]; 0 when
 * a pivot is below 1e-13 of its diagonal. */
INLINE int cholesky(int n, const double *P, double *L, double *dinv) {
    memset(L, 0, sizeof(double) * n * n);
    for (int j = 0; j < n; ++j) {
        double piv = P[j * n + j];
        for (int k = 0; k < j; ++k) piv -= L[j * n + k] * L[j * n + k];
        if (!(piv > 1e-13 * fabs(P[j * n + j]))) return 0;
        double d = sqrt(piv);
        L[j * n + j] = d;
        dinv[j] = 1.0 / d;
        for (int i = j + 1; i < n; ++i) {
            double s = P[i * n + j];
            for (int k = 0; k < j; ++k) s -= L[i * n + k] * L[j * n + k];
            L[i * n + j] = s * dinv[j];
        }
    }
    return 1;
}

/* y = (L L')^{-1} b, in place; dinv [N] holds 1 / diag(L) (no division on the chain). */
INLINE void cho_solve(int n, const double *L, const double *dinv, double *y) {
    for (int i = 0; i < n; ++i) {
        double s = y[i];
        for (int k = 0; k < i; ++k) s -= L[i * n + k] * y[k];
        y[i] = s * dinv[i];
    }
    for (int i = n - 1; i >= 0; --i) {
        double s = y[i];
        for (int k = i + 1; k < n; ++k) s -= L[k * n + i] * y[k];
        y[i] = s * dinv[i];
    }
}

INLINE double dot(int n, const double *a, const double *b) {
    double s = 0.0;
    for (int c = 0; c < n; ++c) s += a[c] * b[c];
    return s;
}

/* The scale |h_i| + max|g_i| (1 + x_max) of row g [n], h_i's residual at a point of
 * largest entry x_max (torchcbf/qp/_kkt.py's row_scale). */
INLINE double scale_at(int n, const double *g, double hi, double x_max) {
    double gmax = 0.0;
    for (int c = 0; c < n; ++c) gmax = dmax(gmax, fabs(g[c]));
    return fabs(hi) + gmax * (1.0 + x_max);
}

/* Solve W mu = r for symmetric W [K,K] (upper triangle read) by symmetric Gaussian
 * elimination without pivoting, as _enum._eliminate; returns 0 when a pivot is below
 * piv_tol times its diagonal entry. W and r are overwritten. */
INLINE int eliminate(int K, double *W, double *r, double piv_tol, double *mu) {
    double piv[NMAX], diag[NMAX]; /* the pivots are judged against the original diagonal */
    int nonsing = 1;
    for (int j = 0; j < K; ++j) diag[j] = W[j * K + j];
    for (int j = 0; j < K; ++j) {
        piv[j] = W[j * K + j];
        if (!(piv[j] > piv_tol * diag[j])) nonsing = 0;
        double inv = 1.0 / piv[j];
        for (int i = j + 1; i < K; ++i) {
            double f = W[j * K + i] * inv;
            for (int k = i; k < K; ++k) W[i * K + k] -= f * W[j * K + k];
            r[i] -= f * r[j];
        }
    }
    for (int j = K - 1; j >= 0; --j) {
        double s = r[j];
        for (int i = j + 1; i < K; ++i) s -= W[j * K + i] * mu[i];
        mu[j] = s / piv[j];
    }
    return nonsing;
}

/* Build W_SS = R_S P^{-1} R_S' on the N slots (identity on empty ones) in W [N*N] and solve
 * W_SS mu = rhs; US[c*N + k] is component c of P^{-1} R_{S_k}' (zero on empty slots). */
INLINE int slot_solve(int N, int M, const double *G, const double *US, const int64_t *S,
                      const double *rhs, double piv_tol, double *mu, double *RESTRICT W) {
    double r[NMAX];
    for (int k = 0; k < N; ++k) {
        r[k] = rhs[k];
        for (int l = 0; l < N; ++l) {
            if (S[k] == M || S[l] == M) {
                W[k * N + l] = (k == l) ? 1.0 : 0.0;
                continue;
            }
            double w = 0.0;
            for (int c = 0; c < N; ++c) w += G[S[k] * N + c] * US[c * N + l];
            W[k * N + l] = w;
        }
    }
    int nonsing = eliminate(N, W, r, piv_tol, mu);
    for (int k = 0; k < N; ++k)
        if (S[k] == M) mu[k] = 0.0;
    return nonsing;
}

/* Whether y = (1 on row p, -d[k] on the active slots) proves Gx <= h infeasible: y >= 0,
 * h'y < 0 beyond rounding, and G'y so small that any feasible point would need
 * |x|_inf > 1e6 (1 + |x_u|_inf), i.e. none exists at the scale of the problem. */
INLINE int farkas(int N, int M, const double *G, const double *h, const int64_t *S,
                  const double *d, int64_t p, const double *row_scale, double xu_max) {
    const double mach = 2.220446049250313e-16;
    double r[NMAX];
    double gap = h[p], noise = row_scale[p];
    for (int c = 0; c < N; ++c) r[c] = G[p * N + c];
    for (int k = 0; k < N; ++k) {
        if (S[k] == M || d[k] == 0.0) continue;
        if (d[k] > 0.0) return 0;
        gap -= d[k] * h[S[k]];
        noise -= d[k] * row_scale[S[k]];
        for (int c = 0; c < N; ++c) r[c] -= d[k] * G[S[k] * N + c];
    }
    double r1 = 0.0;
    for (int c = 0; c < N; ++c) r1 += fabs(r[c]);
    return isfinite(gap) && -gap > 1e4 * mach * noise && r1 * 1e6 * (1.0 + xu_max) < -gap;
}

/* Doubles of workspace one problem needs. */
#define WORKSPACE(N, M) ((size_t)(M) * (2 * (N) + 5))

/* One problem. The workspace holds, component-major so that loops over the M rows run in
 * SIMD: Ut [N][M] = P^{-1} G', Y [N][M] (scratch of the substitutions), and per row the
 * scale, add tolerance, 1/||row||_{P^{-1}}, violation and membership of the active set
 * (WORKSPACE doubles in all). Outputs as in
 * solve_dual: x [N], z [M], active [M], slots [N] (M: empty), L [N*N]; returns ok. */
INLINE int solve_one(int N, int M, const double *RESTRICT P, const double *RESTRICT q,
                     const double *RESTRICT G, const double *RESTRICT h, double eps,
                     int max_iter, double *RESTRICT work, double *RESTRICT x_out,
                     double *RESTRICT z_out, uint8_t *RESTRICT active, int64_t *RESTRICT S_out,
                     double *RESTRICT L_out, int64_t *RESTRICT iters,
                     uint8_t *RESTRICT infeasible, double *RESTRICT US, double *RESTRICT H,
                     double *RESTRICT L, double *RESTRICT W) {
    const double mach = 2.220446049250313e-16;
    double *RESTRICT Ut = work;
    double *RESTRICT Y = work + (size_t)N * M;
    double *RESTRICT row_scale = Y + (size_t)N * M;
    double *RESTRICT tol = row_scale + M;
    double *RESTRICT inv_norm = tol + M;
    double *RESTRICT v = inv_norm + M;
    double *RESTRICT member = v + M;
    double dinv[NMAX], xu[NMAX], x[NMAX], lam[NMAX], dx[NMAX], d[NMAX], Wsp[NMAX], Hk[NMAX];
    /* N*N matrices from the caller (locals of the per-N copies, the heap past NUNROLL):
     * US[c*N + k] is component c of P^{-1} R_{S_k}', H the inverse of W_SS (identity on
     * empty slots), L the Cholesky factor, W scratch of the final multiplier solve */
    int64_t S[NMAX];
    int pending = 0, done = 0, fail = 0;
    int64_t p = 0, it = 0;

    memset(x_out, 0, sizeof(double) * N);
    memset(z_out, 0, sizeof(double) * M);
    memset(active, 0, M);
    for (int k = 0; k < N; ++k) S[k] = S_out[k] = M;
    *iters = 0;
    *infeasible = 0;
    int pd = cholesky(N, P, L, dinv);
    memcpy(L_out, L, sizeof(double) * N * N);
    if (!pd) return 0;

    for (int c = 0; c < N; ++c) xu[c] = -q[c];
    cho_solve(N, L, dinv, xu);
    double xu_max = 0.0;
    for (int c = 0; c < N; ++c) xu_max = dmax(xu_max, fabs(xu[c]));
    /* Ut = L^{-T} L^{-1} G', every substitution step over all M rows at once */
    for (int c = 0; c < N; ++c) {
        double *RESTRICT y = Y + (size_t)c * M;
        for (int i = 0; i < M; ++i) y[i] = G[i * N + c];
        for (int k = 0; k < c; ++k) {
            const double *RESTRICT yk = Y + (size_t)k * M;
            const double l = L[c * N + k];
            for (int i = 0; i < M; ++i) y[i] -= l * yk[i];
        }
        for (int i = 0; i < M; ++i) y[i] *= dinv[c];
    }
    for (int c = N - 1; c >= 0; --c) {
        double *RESTRICT u = Ut + (size_t)c * M;
        const double *RESTRICT y = Y + (size_t)c * M;
        for (int i = 0; i < M; ++i) u[i] = y[i];
        for (int k = c + 1; k < N; ++k) {
            const double *RESTRICT uk = Ut + (size_t)k * M;
            const double l = L[k * N + c];
            for (int i = 0; i < M; ++i) u[i] -= l * uk[i];
        }
        for (int i = 0; i < M; ++i) u[i] *= dinv[c];
    }
    for (int i = 0; i < M; ++i) {
        double w = 0.0;
        for (int c = 0; c < N; ++c) w += G[i * N + c] * Ut[(size_t)c * M + i];
        row_scale[i] = scale_at(N, G + i * N, h[i], xu_max);
        tol[i] = 1e4 * mach * row_scale[i];
        inv_norm[i] = w > 0 ? 1.0 / sqrt(dmax(w, 1e-300)) : 0.0;
        member[i] = 0.0;
    }

    memcpy(x, xu, sizeof(double) * N);
    memset(lam, 0, sizeof(double) * N);
    memset(US, 0, sizeof(double) * N * N);
    for (int k = 0; k < N; ++k)
        for (int l = 0; l < N; ++l) H[k * N + l] = (k == l) ? 1.0 : 0.0;
    double lam_p = 0.0;

    for (int step = 0; step < max_iter; ++step) {
        if (!pending) { /* the farthest violated row that is not active joins */
            for (int i = 0; i < M; ++i) v[i] = -h[i];
            for (int c = 0; c < N; ++c)
                for (int i = 0; i < M; ++i) v[i] += G[i * N + c] * x[c];
            double best = -INFINITY;
            int64_t pnew = -1;
            for (int i = 0; i < M; ++i) {
                if (member[i] != 0.0 || !(v[i] > tol[i])) continue;
                double score = v[i] * inv_norm[i];
                if (score > best) {
                    best = score;
                    pnew = i;
                }
            }
            if (pnew < 0) {
                done = 1;
                break;
            }
            p = pnew;
        }
        const double *Rp = G + p * N;
        double Up[NMAX];
        for (int c = 0; c < N; ++c) Up[c] = Ut[(size_t)c * M + p];
        double v_p = dot(N, Rp, x) - h[p];
        double W_pp = dot(N, Up, Rp);
        for (int k = 0; k < N; ++k) {
            double s = 0.0;
            for (int c = 0; c < N; ++c) s += US[c * N + k] * Rp[c];
            Wsp[k] = s;
        }
        int first_free = -1;
        for (int k = 0; k < N; ++k) {
            if (S[k] == M) {
                if (first_free < 0) first_free = k;
                d[k] = 0.0;
            } else {
                d[k] = dot(N, H + k * N, Wsp);
            }
        }
        double zs = W_pp - dot(N, Wsp, d);
        for (int c = 0; c < N; ++c) {
            double s = -Up[c];
            for (int k = 0; k < N; ++k) s += US[c * N + k] * d[k];
            dx[c] = s;
        }
        double t_full = (zs <= 1e-10 * W_pp || first_free < 0) ? INFINITY : v_p / zs;
        double t_part = INFINITY;
        int k_drop = 0;
        for (int k = 0; k < N; ++k) {
            double ratio = d[k] > 0 ? lam[k] / d[k] : INFINITY;
            if (ratio < t_part) {
                t_part = ratio;
                k_drop = k;
            }
        }
        double t = dmin(t_full, t_part);
        if (!isfinite(t)) { /* infeasible (certified), or stalled: the final check judges */
            *infeasible = (uint8_t)farkas(N, M, G, h, S, d, p, row_scale, xu_max);
            fail = *infeasible;
            done = 1;
            break;
        }
        it += 1;
        for (int c = 0; c < N; ++c) x[c] += t * dx[c];
        for (int k = 0; k < N; ++k) lam[k] -= t * d[k];
        lam_p += t;
        if (t_full <= t_part) { /* p becomes tight: bordering update of H, p fills a slot */
            int f = first_free;
            d[f] -= 1.0;
            H[f * N + f] -= 1.0;
            double a = 1.0 / zs;
            for (int k = 0; k < N; ++k)
                for (int l = 0; l < N; ++l) H[k * N + l] += a * d[k] * d[l];
            for (int c = 0; c < N; ++c) US[c * N + f] = Up[c];
            lam[f] = lam_p;
            lam_p = 0.0;
            S[f] = p;
            member[p] = 1.0;
            pending = 0;
        } else { /* an active multiplier reached zero first: its row leaves */
            int k = k_drop;
            for (int l = 0; l < N; ++l) Hk[l] = H[k * N + l];
            double b = 1.0 / Hk[k];
            for (int i = 0; i < N; ++i)
                for (int l = 0; l < N; ++l) H[i * N + l] -= b * Hk[i] * Hk[l];
            for (int l = 0; l < N; ++l) H[k * N + l] = H[l * N + k] = 0.0;
            H[k * N + k] = 1.0;
            for (int c = 0; c < N; ++c) US[c * N + k] = 0.0;
            lam[k] = 0.0;
            member[S[k]] = 0.0;
            S[k] = M;
            pending = 1;
        }
    }
    *iters = it;
    memcpy(S_out, S, sizeof(int64_t) * N);

    /* exact multipliers and point on the final active set, then the KKT check */
    double rhs[NMAX], mu[NMAX];
    for (int k = 0; k < N; ++k) {
        rhs[k] = S[k] == M ? 0.0 : dot(N, G + S[k] * N, xu) - h[S[k]];
        for (int c = 0; c < N; ++c) US[c * N + k] = S[k] == M ? 0.0 : Ut[(size_t)c * M + S[k]];
    }
    int nonsing = slot_solve(N, M, G, US, S, rhs, 1e-12, mu, W);
    for (int c = 0; c < N; ++c) x[c] = xu[c] - dot(N, US + c * N, mu);
    /* Rows are judged on the scale of the point found, not of xu: far outside the feasible
     * set (|xu| >> |x|) x = xu - P^{-1} G_S' mu keeps errors of about |xu| mach, which xu's
     * scale would pass as rounding (a control far outside its limits, say) */
    const double tiny = 2.2250738585072014e-308;
    double x_max = 0.0;
    for (int c = 0; c < N; ++c) x_max = dmax(x_max, fabs(x[c]));
    if (nonsing) {
        /* one refinement step on the active rows' residual G_S x - h_S: the Schur complement
         * loses the digits of a large multiplier over a weak curvature (x then lies off its
         * active rows by about |mu| mach / P_jj, a filter's slack weight over a control's),
         * or of a large xu; the correction W_SS dmu = G_S x - h_S, x -= P^{-1} G_S' dmu, of
         * small numbers, restores them and keeps x stationary */
        double res_S[NMAX], dmu[NMAX], worst = 0.0;
        for (int k = 0; k < N; ++k) {
            res_S[k] = S[k] == M ? 0.0 : dot(N, G + S[k] * N, x) - h[S[k]];
            if (S[k] != M) {
                double sc = scale_at(N, G + S[k] * N, h[S[k]], x_max);
                worst = dmax(worst, fabs(res_S[k]) / dmax(sc, tiny));
            }
        }
        if (worst > 1e4 * mach && slot_solve(N, M, G, US, S, res_S, 1e-12, dmu, W)) {
            for (int c = 0; c < N; ++c) x[c] -= dot(N, US + c * N, dmu);
            for (int k = 0; k < N; ++k) mu[k] += dmu[k];
            x_max = 0.0;
            for (int c = 0; c < N; ++c) x_max = dmax(x_max, fabs(x[c]));
        }
    }
    double pviol = 0.0;
    for (int i = 0; i < M; ++i) {
        double sc = scale_at(N, G + i * N, h[i], x_max);
        double vi = (dot(N, G + i * N, x) - h[i]) / dmax(sc, tiny);
        pviol = dmax(pviol, member[i] != 0.0 ? fabs(vi) : vi);
    }
    double lam_min = INFINITY, lam_abs = 0.0, qmax = 0.0, rl = 0.0, stat = 0.0;
    int finite = 1;
    for (int k = 0; k < N; ++k) {
        lam_min = dmin(lam_min, mu[k]);
        lam_abs = dmax(lam_abs, fabs(mu[k]));
        finite &= isfinite(mu[k]) != 0;
    }
    for (int c = 0; c < N; ++c) qmax = dmax(qmax, fabs(q[c]));
    for (int k = 0; k < N; ++k) {
        if (S[k] == M) continue;
        double gmax = 0.0;
        for (int c = 0; c < N; ++c) gmax = dmax(gmax, fabs(G[S[k] * N + c]));
        rl = dmax(rl, gmax * fabs(mu[k]));
    }
    for (int c = 0; c < N; ++c) {
        double s = dot(N, P + c * N, x) + q[c];
        for (int k = 0; k < N; ++k)
            if (S[k] != M) s += G[S[k] * N + c] * mu[k];
        stat = dmax(stat, fabs(s));
        finite &= isfinite(x[c]) != 0;
    }
    int ok = !fail && done && nonsing && finite && pviol <= eps &&
             lam_min >= -eps * (1.0 + lam_abs) && stat <= eps * (1.0 + qmax + rl);
    if (!ok) return 0;
    memcpy(x_out, x, sizeof(double) * N);
    for (int k = 0; k < N; ++k) {
        if (S[k] == M) continue;
        z_out[S[k]] = dmax(mu[k], 0.0);
        active[S[k]] = 1;
    }
    return 1;
}

/* Rows [0, B) of a batch, with a workspace of WORKSPACE(N, M) doubles. */
#define FORWARD_ROWS(NN)                                                                   \
    static void forward_rows_##NN(int64_t B, int M, const double *P, const double *q,      \
                                  const double *G, const double *h, double eps,            \
                                  int max_iter, double *work, double *x, double *z,        \
                                  uint8_t *active, int64_t *slots, double *L, uint8_t *ok, \
                                  int64_t *iters, uint8_t *infeasible) {                   \
        const int N = NN;                                                                  \
        double US[NN * NN], H[NN * NN], Lw[NN * NN], W[NN * NN];                           \
        for (int64_t b = 0; b < B; ++b)                                                    \
            ok[b] = (uint8_t)solve_one(N, M, P + b * N * N, q + b * N, G + b * M * N,      \
                                       h + b * M, eps, max_iter, work, x + b * N,          \
                                       z + b * M, active + b * M, slots + b * N,           \
                                       L + b * N * N, iters + b, infeasible + b, US, H,    \
                                       Lw, W);                                             \
    }
FORWARD_ROWS(1)
FORWARD_ROWS(2)
FORWARD_ROWS(3)
FORWARD_ROWS(4)
FORWARD_ROWS(5)
FORWARD_ROWS(6)
FORWARD_ROWS(7)
FORWARD_ROWS(8)

/* N > NUNROLL: one copy, N read at run time; its four N*N matrices follow the workspace */
static void forward_rows_any(int N, int64_t B, int M, const double *P, const double *q,
                             const double *G, const double *h, double eps, int max_iter,
                             double *work, double *x, double *z, uint8_t *active,
                             int64_t *slots, double *L, uint8_t *ok, int64_t *iters,
                             uint8_t *infeasible) {
    double *US = work + WORKSPACE(N, M), *H = US + N * N, *Lw = H + N * N, *W = Lw + N * N;
    for (int64_t b = 0; b < B; ++b)
        ok[b] = (uint8_t)solve_one(N, M, P + b * N * N, q + b * N, G + b * M * N, h + b * M,
                                   eps, max_iter, work, x + b * N, z + b * M, active + b * M,
                                   slots + b * N, L + b * N * N, iters + b, infeasible + b, US,
                                   H, Lw, W);
}

typedef void (*forward_rows_fn)(int64_t, int, const double *, const double *, const double *,
                                const double *, double, int, double *, double *, double *,
                                uint8_t *, int64_t *, double *, uint8_t *, int64_t *,
                                uint8_t *);
static const forward_rows_fn FORWARD_ROWS_N[NUNROLL + 1] = {
    NULL,           forward_rows_1, forward_rows_2, forward_rows_3, forward_rows_4,
    forward_rows_5, forward_rows_6, forward_rows_7, forward_rows_8};

/* Rows [0, B) of a batch; returns -1 for N outside 1..NMAX, M < 1, or no workspace.
 * infeasible [B]: rows proved infeasible by a Farkas certificate (ok is 0 there). */
int torchcbf_dual_forward(int64_t B, int N, int M, const double *P, const double *q,
                          const double *G, const double *h, double eps, int max_iter,
                          double *x, double *z, uint8_t *active, int64_t *slots, double *L,
                          uint8_t *ok, int64_t *iters, uint8_t *infeasible) {
    if (N < 1 || N > NMAX || M < 1) return -1;
    size_t mats = N > NUNROLL ? (size_t)4 * N * N : 0; /* forward_rows_any's matrices */
    double *work = malloc(sizeof(double) * (WORKSPACE(N, M) + mats));
    if (!work) return -1;
    if (N <= NUNROLL)
        FORWARD_ROWS_N[N](B, M, P, q, G, h, eps, max_iter, work, x, z, active, slots, L, ok,
                          iters, infeasible);
    else
        forward_rows_any(N, B, M, P, q, G, h, eps, max_iter, work, x, z, active, slots, L, ok,
                         iters, infeasible);
    free(work);
    return 0;
}

/* One problem of the backward: w_x [N] and wz [M] (zeros unless ok and finite). */
INLINE void adjoint_one(int N, int M, const double *RESTRICT G, const double *RESTRICT L,
                        const int64_t *RESTRICT S, int ok, const double *RESTRICT gx,
                        const double *RESTRICT gz, double *RESTRICT wx, double *RESTRICT wz,
                        double *RESTRICT US, double *RESTRICT W) {
    memset(wx, 0, sizeof(double) * N);
    memset(wz, 0, sizeof(double) * M);
    if (!ok) return;
    double dinv[NMAX], a[NMAX], rhs[NMAX], mu[NMAX], out[NMAX], u[NMAX];
    /* US [N*N] (component c of P^{-1} R_{S_k}' at c*N + k) and W [N*N] from the caller */
    for (int c = 0; c < N; ++c) {
        dinv[c] = 1.0 / L[c * N + c];
        a[c] = gx[c];
    }
    cho_solve(N, L, dinv, a);
    for (int k = 0; k < N; ++k) {
        if (S[k] != M) memcpy(u, G + S[k] * N, sizeof(double) * N);
        else memset(u, 0, sizeof(double) * N);
        cho_solve(N, L, dinv, u);
        for (int c = 0; c < N; ++c) US[c * N + k] = u[c];
        rhs[k] = S[k] == M ? 0.0 : dot(N, G + S[k] * N, a) - gz[S[k]];
    }
    slot_solve(N, M, G, US, S, rhs, 1e-12, mu, W); /* nonsingular: the forward checked it */
    int finite = 1;
    for (int c = 0; c < N; ++c) {
        out[c] = a[c] - dot(N, US + c * N, mu);
        finite &= isfinite(out[c]) != 0;
    }
    for (int k = 0; k < N; ++k) finite &= isfinite(mu[k]) != 0;
    if (!finite) return;
    memcpy(wx, out, sizeof(double) * N);
    for (int k = 0; k < N; ++k)
        if (S[k] != M) wz[S[k]] = mu[k];
}

#define BACKWARD_ROWS(NN)                                                                  \
    static void backward_rows_##NN(int64_t B, int M, const double *G, const double *L,     \
                                   const int64_t *slots, const uint8_t *ok,                \
                                   const double *gx, const double *gz, double *w_x,        \
                                   double *wz) {                                           \
        const int N = NN;                                                                  \
        double US[NN * NN], W[NN * NN];                                                    \
        for (int64_t b = 0; b < B; ++b)                                                    \
            adjoint_one(N, M, G + b * M * N, L + b * N * N, slots + b * N, ok[b],          \
                        gx + b * N, gz + b * M, w_x + b * N, wz + b * M, US, W);           \
    }
BACKWARD_ROWS(1)
BACKWARD_ROWS(2)
BACKWARD_ROWS(3)
BACKWARD_ROWS(4)
BACKWARD_ROWS(5)
BACKWARD_ROWS(6)
BACKWARD_ROWS(7)
BACKWARD_ROWS(8)

static void backward_rows_any(int N, int64_t B, int M, const double *G, const double *L,
                              const int64_t *slots, const uint8_t *ok, const double *gx,
                              const double *gz, double *w_x, double *wz, double *mats) {
    for (int64_t b = 0; b < B; ++b)
        adjoint_one(N, M, G + b * M * N, L + b * N * N, slots + b * N, ok[b], gx + b * N,
                    gz + b * M, w_x + b * N, wz + b * M, mats, mats + N * N);
}

typedef void (*backward_rows_fn)(int64_t, int, const double *, const double *, const int64_t *,
                                 const uint8_t *, const double *, const double *, double *,
                                 double *);
static const backward_rows_fn BACKWARD_ROWS_N[NUNROLL + 1] = {
    NULL,            backward_rows_1, backward_rows_2, backward_rows_3, backward_rows_4,
    backward_rows_5, backward_rows_6, backward_rows_7, backward_rows_8};

/* Adjoint of the KKT system on the final active slots, rows [0, B): w_x [B,N] and the
 * multiplier adjoint scattered to rows wz [B,M] (zeros on rows not ok or where the result
 * is not finite). Gradients are then, in torch,
 * dP = -(w_x x' + x w_x')/2, dq = -w_x, dG = -(z w_x' + wz x'), dh = wz. */
int torchcbf_dual_backward(int64_t B, int N, int M, const double *G, const double *L,
                           const int64_t *slots, const uint8_t *ok, const double *gx,
                           const double *gz, double *w_x, double *wz) {
    if (N < 1 || N > NMAX || M < 1) return -1;
    if (N <= NUNROLL) {
        BACKWARD_ROWS_N[N](B, M, G, L, slots, ok, gx, gz, w_x, wz);
        return 0;
    }
    double *mats = malloc(sizeof(double) * 2 * N * N);
    if (!mats) return -1;
    backward_rows_any(N, B, M, G, L, slots, ok, gx, gz, w_x, wz, mats);
    free(mats);
    return 0;
}

/* Whether v [n] holds no NaN and no infinity. */
int torchcbf_dual_all_finite(int64_t n, const double *v) {
    double s = 0.0;
    for (int64_t i = 0; i < n; ++i) s += v[i] * 0.0;
    return s == 0.0; /* NaN or an infinity makes the sum NaN */
}

/* Whether the Jacobi-scaled P [N,N] has off-diagonal row sums at most 1/2: its eigenvalues
 * then lie in [1/2, 3/2] (Gershgorin) and no condition estimate is needed. */
int torchcbf_dual_diagonally_dominant(int N, const double *P) {
    for (int i = 0; i < N; ++i) {
        double s = 0.0;
        for (int j = 0; j < N; ++j)
            s += fabs(P[i * N + j]) / sqrt(fabs(P[i * N + i]) * fabs(P[j * N + j]));
        if (!(s <= 1.5 + 1e-12)) return 0;
    }
    return 1;
}

/* max_i |row i of L|^2 |column i of L^{-1}|^2 for the lower factor L [N,N] (the estimate of
 * torchcbf.qp._function.condition_estimate); inv [N*N] is scratch. NaN propagates. */
double torchcbf_dual_condition_estimate(int N, const double *L, double *inv) {
    for (int j = 0; j < N; ++j) /* column j of L^{-1} by forward substitution */
        for (int i = 0; i < N; ++i) {
            double s = (i == j) ? 1.0 : 0.0;
            for (int k = j; k < i; ++k) s -= L[i * N + k] * inv[k * N + j];
            inv[i * N + j] = i < j ? 0.0 : s / L[i * N + i];
        }
    double worst = 0.0;
    for (int i = 0; i < N; ++i) {
        double row = 0.0, col = 0.0;
        for (int k = 0; k < N; ++k) {
            row += L[i * N + k] * L[i * N + k];
            col += inv[k * N + i] * inv[k * N + i];
        }
        double c = row * col;
        if (isnan(c)) return c;
        worst = dmax(worst, c);
    }
    return worst;
}

/* A few QPs in one call (the real-time path of solve_qp): P [B,N,N] (symmetrised here),
 * q [B,N], G [B,M,N] and h [B,M] (M = 0: both NULL), bounds lb, ub [B,N] (NULL: none;
 * infinite entries: none), turned into rows (upper, then lower). Outputs: x [B,N],
 * z [B,M] (multipliers of G), z_lb, z_ub [B,N] (zeros where absent), iters [B]. Returns 0
 * when every row is certified and its P conditioned well enough for the dual method
 * (condition estimate at most max_condition, unless diagonally dominant), 1 otherwise (the
 * caller takes its general path), -1 when memory ran out or the sizes are invalid. */
int torchcbf_dual_solve_small(int64_t B, int N, int M, const double *P, const double *q,
                              const double *G, const double *h, const double *lb,
                              const double *ub, double eps, int max_iter,
                              double max_condition, double *x, double *z, double *z_lb,
                              double *z_ub, int64_t *iters) {
    if (N < 1 || N > NMAX || M < 0 || B < 1) return -1;
    int Mt = M + (ub ? N : 0) + (lb ? N : 0);
    if (Mt < 1) return 1;
    size_t per = (size_t)N * N + (size_t)Mt * N + Mt + Mt + (size_t)N * N;
    double *buf = malloc(sizeof(double) * (per * B + N * N));
    int64_t *slots = malloc(sizeof(int64_t) * N * B);
    uint8_t *bytes = malloc((size_t)(Mt + 2) * B);
    if (!buf || !slots || !bytes) {
        free(buf), free(slots), free(bytes);
        return -1;
    }
    double *Ps = buf, *Gs = Ps + B * N * N, *hs = Gs + B * Mt * N, *zs = hs + B * Mt;
    double *L = zs + B * Mt, *inv = L + B * N * N;
    uint8_t *active = bytes, *ok = active + B * Mt, *infeasible = ok + B;
    int code = 0;
    for (int64_t b = 0; b < B && code == 0; ++b) {
        const double *Pb = P + b * N * N;
        double *P2 = Ps + b * N * N, *G2 = Gs + b * Mt * N, *h2 = hs + b * Mt;
        for (int i = 0; i < N; ++i)
            for (int j = 0; j < N; ++j) P2[i * N + j] = 0.5 * (Pb[i * N + j] + Pb[j * N + i]);
        if (M) {
            memcpy(G2, G + b * M * N, sizeof(double) * M * N);
            memcpy(h2, h + b * M, sizeof(double) * M);
        }
        memset(G2 + M * N, 0, sizeof(double) * (Mt - M) * N);
        int r = M;
        for (int pass = 0; pass < 2; ++pass) { /* upper bounds, then lower bounds */
            const double *bound = pass == 0 ? ub : lb;
            double sign = pass == 0 ? 1.0 : -1.0;
            if (!bound) continue;
            for (int j = 0; j < N; ++j, ++r) {
                double v = bound[b * N + j];
                if (isnan(v) || v == -sign * INFINITY) code = 1; /* NaN, lb = +inf, ub = -inf */
                int finite = isfinite(v);
                G2[r * N + j] = finite ? sign : 0.0;
                h2[r] = finite ? sign * v : 1.0;
            }
        }
    }
    if (code == 0 && !(torchcbf_dual_all_finite(B * N * N, Ps) &&
                       torchcbf_dual_all_finite(B * N, q) &&
                       torchcbf_dual_all_finite(B * Mt * N, Gs) &&
                       torchcbf_dual_all_finite(B * Mt, hs)))
        code = 1;
    if (code == 0 && torchcbf_dual_forward(B, N, Mt, Ps, q, Gs, hs, eps, max_iter, x, zs,
                                           active, slots, L, ok, iters, infeasible) != 0)
        code = -1;
    for (int64_t b = 0; b < B && code == 0; ++b) {
        if (!ok[b]) code = 1;
        else if (!torchcbf_dual_diagonally_dominant(N, Ps + b * N * N) &&
                 !(torchcbf_dual_condition_estimate(N, L + b * N * N, inv) <= max_condition))
            code = 1;
    }
    for (int64_t b = 0; b < B && code == 0; ++b) {
        const double *zb = zs + b * Mt;
        if (M) memcpy(z + b * M, zb, sizeof(double) * M);
        int r = M;
        for (int pass = 0; pass < 2; ++pass) {
            const double *bound = pass == 0 ? ub : lb;
            double *out = pass == 0 ? z_ub : z_lb;
            if (bound) memcpy(out + b * N, zb + r, sizeof(double) * N), r += N;
            else memset(out + b * N, 0, sizeof(double) * N);
        }
    }
    free(buf), free(slots), free(bytes);
    return code;
}

/* ok[b] &= (the condition estimate of the factor L_b is at most max_condition), rows
 * [0, B): the rows the dual method may keep (torch reference: the test in
 * torchcbf.qp._function._forward_dual). Returns -1 when memory ran out. */
int torchcbf_dual_check_condition(int64_t B, int N, const double *L, double max_condition,
                                  uint8_t *ok) {
    double *inv = malloc(sizeof(double) * N * N);
    if (!inv) return -1;
    for (int64_t b = 0; b < B; ++b)
        if (ok[b])
            ok[b] = torchcbf_dual_condition_estimate(N, L + b * N * N, inv) <= max_condition;
    free(inv);
    return 0;
}

/* active[b, i] |= solved[b] and h_i - G_i x_b <= tight (|h_i| + max_j |G_ij| (1 + max|x_b|)),
 * rows [0, B): the rows tight at x join the backward's active set (torch reference:
 * torchcbf.qp._kkt.with_tight_rows). */
int torchcbf_dual_tight_rows(int64_t B, int N, int M, const double *G, const double *h,
                             const double *x, const uint8_t *solved, double tight,
                             uint8_t *active) {
    for (int64_t b = 0; b < B; ++b) {
        if (!solved[b]) continue;
        const double *xb = x + b * N;
        double xmax = 0.0;
        for (int c = 0; c < N; ++c) xmax = dmax(xmax, fabs(xb[c]));
        for (int i = 0; i < M; ++i) {
            const double *g = G + (b * M + i) * N;
            double gx = 0.0, gmax = 0.0;
            for (int c = 0; c < N; ++c) {
                gx += g[c] * xb[c];
                gmax = dmax(gmax, fabs(g[c]));
            }
            double hi = h[b * M + i];
            if (hi - gx <= tight * (fabs(hi) + gmax * (1.0 + xmax))) active[b * M + i] = 1;
        }
    }
    return 0;
}

/* ---- Certification of the rows the dual method leaves (torch reference:
 * torchcbf.qp._function._certify_ill_conditioned, torchcbf.qp._kkt.solve_active and
 * kkt_point). A row is certified where a point is a KKT point to rounding and no certificate
 * of unboundedness can exist (P - tau I positive definite, or q'x >= 0). */

#define CERT_ROUNDING (1e4 * 2.220446049250313e-16)
/* stationarity's tolerance: its terms can cancel by orders of magnitude (torch's STATIONARY) */
#define CERT_STATIONARY (3e5 * 2.220446049250313e-16)
#define CERT_REFINED (4.0 * 2.220446049250313e-16)
#define CERT_TINY 2.2250738585072014e-308

/* Whether (x, z) is a KKT point of the row's problem to rounding: no row violated and no
 * row with a positive multiplier loose, each on its own scale |h_i| + max|G_i| (1 + max|x|),
 * multipliers nonnegative and stationarity |Px + q + G'z| within rounding of its terms. */
static int kkt_point_row(int N, int M, const double *P, const double *q, const double *G,
                         const double *h, const double *x, const double *z) {
    const double r = CERT_ROUNDING;
    double xmax = 0.0, viol = 0.0;
    for (int c = 0; c < N; ++c) {
        if (!isfinite(x[c])) return 0;
        xmax = dmax(xmax, fabs(x[c]));
    }
    for (int i = 0; i < M; ++i)
        if (!isfinite(z[i])) return 0;
    /* stationarity's terms; the objective's gradient scale max(|q|, |Px|) */
    double res[NMAX], terms[NMAX], smax = 0.0, grad = 0.0;
    for (int c = 0; c < N; ++c) {
        double s = 0.0, t = 0.0;
        for (int j = 0; j < N; ++j) {
            s += P[c * N + j] * x[j];
            t += fabs(P[c * N + j]) * fabs(x[j]);
        }
        grad = dmax(grad, dmax(fabs(q[c]), fabs(s)));
        res[c] = s + q[c], terms[c] = t + fabs(q[c]);
    }
    /* each multiplier judged as its stationarity term z_i max|G_i| against the largest term
     * (torch's multiplier_size): the test does not depend on the units */
    double zscale = grad;
    for (int i = 0; i < M; ++i) {
        const double *g = G + (size_t)i * N;
        double gmax = 0.0;
        for (int c = 0; c < N; ++c) gmax = dmax(gmax, fabs(g[c]));
        zscale = dmax(zscale, fabs(z[i]) * gmax);
    }
    if (!(zscale > 0.0)) zscale = 1.0;
    for (int i = 0; i < M; ++i) {
        const double *g = G + (size_t)i * N;
        double gx = 0.0, gmax = 0.0;
        for (int c = 0; c < N; ++c) {
            gx += g[c] * x[c];
            gmax = dmax(gmax, fabs(g[c]));
        }
        double scale = dmax(fabs(h[i]) + gmax * (1.0 + xmax), CERT_TINY);
        double slack = (h[i] - gx) / scale, size = z[i] * gmax;
        viol = dmax(viol, -slack);
        if (size < -r * zscale) return 0;
        if (size > r * zscale && slack > r) return 0;
    }
    if (!(viol <= r)) return 0;
    for (int i = 0; i < M; ++i) {
        if (z[i] == 0.0) continue;
        const double *g = G + (size_t)i * N;
        for (int c = 0; c < N; ++c) {
            res[c] += g[c] * z[i];
            terms[c] += fabs(g[c]) * fabs(z[i]);
        }
    }
    for (int c = 0; c < N; ++c) smax = dmax(smax, terms[c]);
    for (int c = 0; c < N; ++c) {
        double s = dmax(terms[c] + r * smax, CERT_TINY);
        if (!(fabs(res[c]) <= CERT_STATIONARY * s)) return 0;
    }
    return 1;
}

/* LU factorisation with partial pivoting of A [n,n] in place; 0 on a zero or non-finite
 * pivot. */
static int lu_factor(int n, double *A, int *piv) {
    for (int j = 0; j < n; ++j) {
        int p = j;
        double best = fabs(A[j * n + j]);
        for (int i = j + 1; i < n; ++i)
            if (fabs(A[i * n + j]) > best) best = fabs(A[i * n + j]), p = i;
        if (!(best > 0.0) || !isfinite(best)) return 0;
        piv[j] = p;
        if (p != j)
            for (int k = 0; k < n; ++k) {
                double t = A[j * n + k];
                A[j * n + k] = A[p * n + k], A[p * n + k] = t;
            }
        double inv = 1.0 / A[j * n + j];
        for (int i = j + 1; i < n; ++i) {
            double f = (A[i * n + j] *= inv);
            if (f != 0.0)
                for (int k = j + 1; k < n; ++k) A[i * n + k] -= f * A[j * n + k];
        }
    }
    return 1;
}

static void lu_solve(int n, const double *LU, const int *piv, double *b) {
    for (int j = 0; j < n; ++j)
        if (piv[j] != j) {
            double t = b[j];
            b[j] = b[piv[j]], b[piv[j]] = t;
        }
    for (int i = 0; i < n; ++i) {
        double s = b[i];
        for (int k = 0; k < i; ++k) s -= LU[i * n + k] * b[k];
        b[i] = s;
    }
    for (int i = n - 1; i >= 0; --i) {
        double s = b[i];
        for (int k = i + 1; k < n; ++k) s -= LU[i * n + k] * b[k];
        b[i] = s / LU[i * n + i];
    }
}

/* The solution with the rows act [M] held tight: x [N], z [M] (zero off act), the KKT
 * system [[P, G_a'], [G_a, 0]] solved on its equilibrated, regularised factor with up to
 * `steps` refinement steps on the system itself, as torchcbf.qp._kkt.solve_active. work
 * holds 3 K^2 + 6 K doubles, K = N + |act| <= 2 N (more active rows: 0, not solved). */
static int solve_active_row(int N, int M, const double *P, const double *q, const double *G,
                            const double *h, const uint8_t *act, int steps, double *work,
                            double *x, double *z) {
    int rows[NMAX], k = 0;
    for (int i = 0; i < M; ++i)
        if (act[i]) {
            if (k == N) return 0;
            rows[k++] = i;
        }
    const int K = N + k;
    double *Km = work, *LU = Km + K * K, *d = LU + K * K, *rhs = d + K, *w = rhs + K;
    double *res = w + K, *step = res + K;
    int *piv = (int *)(step + K);
    memset(Km, 0, sizeof(double) * K * K);
    for (int i = 0; i < N; ++i)
        for (int j = 0; j < N; ++j) Km[i * K + j] = P[i * N + j];
    for (int a = 0; a < k; ++a)
        for (int c = 0; c < N; ++c) {
            double g = G[(size_t)rows[a] * N + c];
            Km[(N + a) * K + c] = g, Km[c * K + N + a] = g;
        }
    for (int i = 0; i < K; ++i) d[i] = 1.0;
    for (int sweep = 0; sweep < 3; ++sweep) {
        for (int i = 0; i < K; ++i) {
            double row = 0.0;
            for (int j = 0; j < K; ++j) row = dmax(row, fabs(d[i] * Km[i * K + j] * d[j]));
            res[i] = row > 0.0 ? exp2(round(log2(1.0 / sqrt(row)))) : 1.0;
        }
        for (int i = 0; i < K; ++i) d[i] *= res[i];
    }
    double big = 1.0;
    for (int i = 0; i < K; ++i)
        for (int j = 0; j < K; ++j) {
            double v = d[i] * Km[i * K + j] * d[j];
            LU[i * K + j] = v;
            big = dmax(big, fabs(v));
        }
    for (int i = 0; i < K; ++i) LU[i * K + i] += (i < N ? 1e-11 : -1e-11) * big;
    if (!lu_factor(K, LU, piv)) return 0;
    for (int c = 0; c < N; ++c) rhs[c] = -q[c];
    for (int a = 0; a < k; ++a) rhs[N + a] = h[rows[a]];
    for (int i = 0; i < K; ++i) w[i] = d[i] * rhs[i];
    lu_solve(K, LU, piv, w);
    for (int i = 0; i < K; ++i) w[i] *= d[i];
    for (int s = 0; s < steps; ++s) {
        for (int i = 0; i < K; ++i) {
            double v = rhs[i];
            for (int j = 0; j < K; ++j) v -= Km[i * K + j] * w[j];
            step[i] = d[i] * v;
        }
        lu_solve(K, LU, piv, step);
        double smax = 0.0, wmax = 0.0;
        for (int i = 0; i < K; ++i) {
            w[i] += (step[i] *= d[i]);
            smax = dmax(smax, fabs(step[i]));
        }
        for (int i = 0; i < K; ++i) wmax = dmax(wmax, fabs(w[i]));
        if (!(smax > CERT_REFINED * wmax)) break;
    }
    for (int i = 0; i < K; ++i)
        if (!isfinite(w[i])) return 0;
    memcpy(x, w, sizeof(double) * N);
    memset(z, 0, sizeof(double) * M);
    for (int a = 0; a < k; ++a) z[rows[a]] = dmax(w[N + a], 0.0);
    return 1;
}

/* Whether a point x can stand: q'x >= 0, or P - tau I positive definite with tau = 2 N
 * rounding max_i sum_j |P_ij| (no direction of unbounded descent can exist). Otherwise the
 * caller's torch test decides (an eigendecomposition). */
static int no_descent_direction(int N, const double *P, const double *q, const double *x,
                                double rounding, double *L, double *Pt) {
    double qx = 0.0, rowmax = 0.0, dinv[NMAX];
    for (int c = 0; c < N; ++c) qx += q[c] * x[c];
    if (qx >= 0.0) return 1;
    for (int i = 0; i < N; ++i) {
        double s = 0.0;
        for (int j = 0; j < N; ++j) s += fabs(P[i * N + j]);
        rowmax = dmax(rowmax, s);
    }
    double tau = 2.0 * N * rounding * rowmax;
    memcpy(Pt, P, sizeof(double) * N * N);
    for (int i = 0; i < N; ++i) Pt[i * N + i] -= tau;
    return cholesky(N, Pt, L, dinv);
}

/* Rows [0, B) with todo[b]: certify the dual method's answer (x, z, active, converged
 * conv[b]) as in torchcbf.qp._function._certify_ill_conditioned: the method's own point,
 * then its active set, then the active sets of up to prox_steps proximal steps (the dual
 * method on P + rho I, q - rho c, rho = prox_weight max_i P_ii, c the last step's point).
 * x [B,N] and z [B,M] are overwritten on the rows certified (certified[b] = 1); rounding is
 * the inputs' unit roundoff (the unboundedness test's threshold). Returns -1 when memory
 * ran out or the sizes are invalid. */
int torchcbf_dual_certify(int64_t B, int N, int M, const double *P, const double *q,
                          const double *G, const double *h, const uint8_t *todo,
                          const uint8_t *active, const uint8_t *conv, double eps, int max_iter,
                          double prox_weight, int prox_steps, double rounding, double *x,
                          double *z, uint8_t *certified) {
    if (N < 1 || N > NMAX || M < 1) return -1;
    const int K = 2 * N;
    size_t need = (size_t)3 * K * K + 7 * K + 4 * (size_t)N * N + 2 * (size_t)N + 2 * (size_t)M;
    double *work = malloc(sizeof(double) * need);
    uint8_t *pact = malloc((size_t)M);
    if (!work || !pact) {
        free(work), free(pact);
        return -1;
    }
    double *kkt = work, *Pr = kkt + 3 * K * K + 7 * K, *Lr = Pr + N * N, *Pt = Lr + N * N;
    double *Lt = Pt + N * N, *xp = Lt + N * N, *center = xp + N, *zp = center + N;
    double *zprox = zp + M;
    int code = 0;
    for (int64_t b = 0; b < B && code == 0; ++b) {
        certified[b] = 0;
        if (!todo[b]) continue;
        const double *Pb = P + b * N * N, *qb = q + b * N, *Gb = G + b * M * N, *hb = h + b * M;
        double *xb = x + b * N, *zb = z + b * M;
        int good = 0;
        if (conv[b]) {
            if (kkt_point_row(N, M, Pb, qb, Gb, hb, xb, zb)) {
                if (!no_descent_direction(N, Pb, qb, xb, rounding, Lt, Pt)) continue;
                good = 1;
            } else if (solve_active_row(N, M, Pb, qb, Gb, hb, active + b * M, 8, kkt, xp, zp) &&
                       kkt_point_row(N, M, Pb, qb, Gb, hb, xp, zp)) {
                if (!no_descent_direction(N, Pb, qb, xp, rounding, Lt, Pt)) continue;
                memcpy(xb, xp, sizeof(double) * N), memcpy(zb, zp, sizeof(double) * M);
                good = 1;
            }
        }
        double rho = 0.0;
        for (int c = 0; c < N; ++c) rho = dmax(rho, Pb[c * N + c]);
        rho *= prox_weight;
        memcpy(Pr, Pb, sizeof(double) * N * N);
        for (int c = 0; c < N; ++c) Pr[c * N + c] += rho, center[c] = 0.0;
        for (int s = 0; s < prox_steps && !good; ++s) {
            double qr[NMAX], xr[NMAX];
            int64_t slots[NMAX], iters;
            uint8_t ok, infeasible;
            for (int c = 0; c < N; ++c) qr[c] = qb[c] - rho * center[c];
            if (torchcbf_dual_forward(1, N, M, Pr, qr, Gb, hb, eps, max_iter, xr, zprox, pact,
                                      slots, Lr, &ok, &iters, &infeasible) != 0) {
                code = -1;
                break;
            }
            if (ok) memcpy(center, xr, sizeof(double) * N);
            if (solve_active_row(N, M, Pb, qb, Gb, hb, pact, 8, kkt, xp, zp) &&
                kkt_point_row(N, M, Pb, qb, Gb, hb, xp, zp)) {
                if (!no_descent_direction(N, Pb, qb, xp, rounding, Lt, Pt)) break;
                memcpy(xb, xp, sizeof(double) * N), memcpy(zb, zp, sizeof(double) * M);
                good = 1;
            }
        }
        certified[b] = (uint8_t)good;
    }
    free(work), free(pact);
    return code;
}

/* ---- A few QPs with equality rows Ax = b (the real-time path; torch reference:
 * reduce_equalities, reduced_objective, reduced_rows and equality_multipliers of
 * torchcbf/qp/_eliminate.py): x = xp + Z w with A' = [Y Z] [R; 0] (Householder QR), the
 * reduced problem in w solved by torchcbf_dual_solve_small. */

/* Householder QR of At [n,k] (row-major, n > k): Qf [n,n] orthogonal (columns: Y, then Z)
 * and R [k,k] upper triangular with At = Y R. work: 2 n k doubles. */
static void householder_qr(int n, int k, const double *At, double *Qf, double *R,
                           double *work) {
    double *V = work, *H = work + (size_t)n * k; /* At reduced in place; reflectors [k][n] */
    double beta[NMAX];
    memcpy(V, At, sizeof(double) * n * k);
    for (int j = 0; j < k; ++j) {
        double *v = H + (size_t)j * n, norm = 0.0;
        for (int i = j; i < n; ++i) norm += V[i * k + j] * V[i * k + j];
        norm = sqrt(norm);
        double alpha = V[j * k + j] > 0.0 ? -norm : norm;
        for (int i = 0; i < n; ++i) v[i] = i < j ? 0.0 : V[i * k + j];
        v[j] -= alpha;
        double vv = 0.0;
        for (int i = j; i < n; ++i) vv += v[i] * v[i];
        beta[j] = vv > 0.0 ? 2.0 / vv : 0.0;
        for (int c = j; c < k; ++c) { /* V <- (I - beta v v') V */
            double t = 0.0;
            for (int i = j; i < n; ++i) t += v[i] * V[i * k + c];
            t *= beta[j];
            for (int i = j; i < n; ++i) V[i * k + c] -= t * v[i];
        }
    }
    for (int i = 0; i < k; ++i)
        for (int c = 0; c < k; ++c) R[i * k + c] = c < i ? 0.0 : V[i * k + c];
    /* Qf = H_0 H_1 ... H_{k-1}, applied to the identity from the last reflector on */
    for (int i = 0; i < n; ++i)
        for (int c = 0; c < n; ++c) Qf[i * n + c] = i == c ? 1.0 : 0.0;
    for (int j = k - 1; j >= 0; --j) {
        const double *v = H + (size_t)j * n;
        for (int c = 0; c < n; ++c) {
            double t = 0.0;
            for (int i = j; i < n; ++i) t += v[i] * Qf[i * n + c];
            t *= beta[j];
            for (int i = j; i < n; ++i) Qf[i * n + c] -= t * v[i];
        }
    }
}

/* A few QPs with equality rows (the real-time path of solve_qp): P [B,n,n] (symmetrised
 * here), q [B,n], G [B,m,n] and h [B,m] (m = 0: both NULL; h_i = +inf bounds nothing),
 * A [B,k,n], b [B,k] with 0 < k < n, bounds lb, ub [B,n] (NULL: none; infinite entries:
 * none), turned into rows (upper, then lower) as in torchcbf_dual_solve_small. Each problem
 * is reduced to x = xp + Z w (A' = [Y Z] [R; 0]; a row of A within rank_tol of the span of
 * the rows before it, |R_ii| <= rank_tol |A_i|, refuses the batch), rows of G Z at most
 * span_tol of |G_i| made exactly zero (their right-hand side rounded up to zero where it is
 * negative by at most eps of its scale), and the reduced problem solved by
 * torchcbf_dual_solve_small; a reduced Hessian Z'PZ that is not positive definite by more
 * than the inputs' rounding of P (Z'PZ - tau I, tau = 2 n rounding max_i sum_j |P_ij|, has no
 * Cholesky factor) refuses the batch: its minimiser would lie far along a direction of
 * unbounded descent. Outputs: x [B,n], z [B,m], y [B,k] (A'y = -(Px + q + G'z + ...)),
 * z_lb, z_ub [B,n], iters [B]. Returns as torchcbf_dual_solve_small: 0 when every problem
 * is solved and certified, 1 otherwise (the caller takes its general path), -1 when memory
 * ran out or the sizes are invalid. */
int torchcbf_dual_solve_small_eq(int64_t B, int n, int m, int k, const double *P,
                                 const double *q, const double *G, const double *h,
                                 const double *A, const double *b, const double *lb,
                                 const double *ub, double eps, int max_iter,
                                 double max_condition, double rank_tol, double span_tol,
                                 double rounding, double *x, double *z, double *y,
                                 double *z_lb, double *z_ub, int64_t *iters) {
    if (n < 2 || n > NMAX || k < 1 || k >= n || m < 0 || B < 1) return -1;
    const int Mt = m + (ub ? n : 0) + (lb ? n : 0), nr = n - k;
    if (Mt < 1) return 1;
    size_t need = (size_t)Mt * n + Mt + (size_t)n * n * 2 + (size_t)k * k + 2 * (size_t)n * k +
                  (size_t)nr * nr + (size_t)Mt * nr + Mt + 3 * (size_t)n + Mt + 2 * (size_t)nr +
                  (size_t)n * k;
    double *buf = malloc(sizeof(double) * need);
    if (!buf) return -1;
    double *Gt = buf, *ht = Gt + (size_t)Mt * n, *Ps = ht + Mt, *Qf = Ps + n * n;
    double *R = Qf + n * n, *qrw = R + k * k, *Pr = qrw + 2 * n * k, *Gr = Pr + nr * nr;
    double *hr = Gr + (size_t)Mt * nr, *xp = hr + Mt, *tmp = xp + n, *grad = tmp + n;
    double *zt = grad + n, *w = zt + Mt, *unused = w + nr, *At = unused + nr;
    int code = 0;
    for (int64_t bi = 0; bi < B && code == 0; ++bi) {
        const double *Pb = P + bi * n * n, *qb = q + bi * n, *Ab = A + bi * k * n;
        const double *bb = b + bi * k;
        /* rows: G (h = +inf: a zero row, 0 * G keeping a NaN for the finiteness test), then
         * the finite bounds */
        for (int i = 0; i < m; ++i) {
            double hi = h[bi * m + i];
            int free_row = hi == INFINITY;
            for (int c = 0; c < n; ++c)
                Gt[i * n + c] = (free_row ? 0.0 : 1.0) * G[(bi * m + i) * n + c];
            ht[i] = free_row ? 1.0 : hi;
        }
        memset(Gt + (size_t)m * n, 0, sizeof(double) * (Mt - m) * n);
        int r = m;
        for (int pass = 0; pass < 2; ++pass) {
            const double *bound = pass == 0 ? ub : lb;
            double sign = pass == 0 ? 1.0 : -1.0;
            if (!bound) continue;
            for (int j = 0; j < n; ++j, ++r) {
                double v = bound[bi * n + j];
                if (isnan(v) || v == -sign * INFINITY) code = 1;
                int finite = isfinite(v);
                Gt[r * n + j] = finite ? sign : 0.0;
                ht[r] = finite ? sign * v : 1.0;
            }
        }
        for (int i = 0; i < n; ++i)
            for (int j = 0; j < n; ++j) Ps[i * n + j] = 0.5 * (Pb[i * n + j] + Pb[j * n + i]);
        if (code != 0 || !(torchcbf_dual_all_finite(n * n, Ps) && torchcbf_dual_all_finite(n, qb) &&
                           torchcbf_dual_all_finite((int64_t)Mt * n, Gt) &&
                           torchcbf_dual_all_finite(Mt, ht) &&
                           torchcbf_dual_all_finite((int64_t)k * n, Ab) &&
                           torchcbf_dual_all_finite(k, bb))) {
            code = 1;
            break;
        }
        /* A' = [Y Z] [R; 0]; full row rank to rank_tol */
        for (int i = 0; i < n; ++i)
            for (int j = 0; j < k; ++j) At[i * k + j] = Ab[j * n + i];
        householder_qr(n, k, At, Qf, R, qrw);
        for (int j = 0; j < k; ++j) {
            double row = 0.0;
            for (int c = 0; c < n; ++c) row += Ab[j * n + c] * Ab[j * n + c];
            if (!(R[j * k + j] * R[j * k + j] > rank_tol * rank_tol * row)) code = 1;
        }
        if (code) break;
        /* xp = Y R^{-T} b */
        double u[NMAX];
        for (int i = 0; i < k; ++i) {
            double s = bb[i];
            for (int l = 0; l < i; ++l) s -= R[l * k + i] * u[l];
            u[i] = s / R[i * k + i];
        }
        double xp_max = 0.0;
        for (int c = 0; c < n; ++c) {
            double s = 0.0;
            for (int l = 0; l < k; ++l) s += Qf[c * n + l] * u[l];
            xp[c] = s;
            xp_max = dmax(xp_max, fabs(s));
        }
        /* Pr = Z' P Z, qr = Z' (P xp + q), Gr = G Z, hr = h - G xp, with Z [n, nr] copied
         * row-major so that the inner loops run over contiguous rows (axpy form) */
        double qr[NMAX], Zr[NMAX * NMAX], PZ[NMAX * NMAX];
        for (int c = 0; c < n; ++c) {
            memcpy(Zr + c * nr, Qf + c * n + k, sizeof(double) * nr);
            tmp[c] = dot(n, Ps + c * n, xp) + qb[c];
        }
        memset(qr, 0, sizeof(double) * nr);
        memset(PZ, 0, sizeof(double) * n * nr);
        memset(Pr, 0, sizeof(double) * nr * nr);
        for (int c = 0; c < n; ++c) {
            const double *zc = Zr + c * nr;
            for (int a = 0; a < nr; ++a) qr[a] += tmp[c] * zc[a];
            for (int d = 0; d < n; ++d) {
                const double pcd = Ps[c * n + d], *zd = Zr + d * nr;
                double *row = PZ + c * nr;
                for (int a = 0; a < nr; ++a) row[a] += pcd * zd[a];
            }
        }
        for (int c = 0; c < n; ++c) {
            const double *pz = PZ + c * nr;
            for (int a = 0; a < nr; ++a) {
                const double zca = Zr[c * nr + a];
                double *row = Pr + a * nr;
                for (int e = 0; e < nr; ++e) row[e] += zca * pz[e];
            }
        }
        {
            double rowsum = 0.0, S[NMAX * NMAX], Ls[NMAX * NMAX], dinv_s[NMAX];
            for (int i = 0; i < n; ++i) {
                double r = 0.0;
                for (int j = 0; j < n; ++j) r += fabs(Ps[i * n + j]);
                rowsum = dmax(rowsum, r);
            }
            memcpy(S, Pr, sizeof(double) * nr * nr);
            for (int a = 0; a < nr; ++a) S[a * nr + a] -= 2.0 * n * rounding * rowsum;
            if (!cholesky(nr, S, Ls, dinv_s)) {
                code = 1;
                break;
            }
        }
        for (int i = 0; i < Mt; ++i) {
            const double *g = Gt + (size_t)i * n;
            double *gr = Gr + (size_t)i * nr, gmax = 0.0, rmax = 0.0;
            memset(gr, 0, sizeof(double) * nr);
            for (int c = 0; c < n; ++c) {
                gmax = dmax(gmax, fabs(g[c]));
                if (g[c] == 0.0) continue;
                const double gc = g[c], *zc = Zr + c * nr;
                for (int a = 0; a < nr; ++a) gr[a] += gc * zc[a];
            }
            for (int a = 0; a < nr; ++a) rmax = dmax(rmax, fabs(gr[a]));
            hr[i] = ht[i] - dot(n, g, xp);
            if (rmax <= span_tol * gmax) { /* in the span of A's rows */
                double scale = fabs(ht[i]) + gmax * (1.0 + xp_max);
                if (hr[i] >= -eps * scale) hr[i] = dmax(hr[i], 0.0);
                for (int a = 0; a < nr; ++a) Gr[(size_t)i * nr + a] = 0.0;
            }
        }
        code = torchcbf_dual_solve_small(1, nr, Mt, Pr, qr, Gr, hr, NULL, NULL, eps, max_iter,
                                         max_condition, w, zt, unused, unused, iters + bi);
        if (code) break;
        /* x = xp + Z w; y = -R^{-1} Y' (P x + q + G' z) */
        double *xb = x + bi * n;
        for (int c = 0; c < n; ++c) xb[c] = xp[c] + dot(nr, Zr + c * nr, w);
        for (int c = 0; c < n; ++c) grad[c] = dot(n, Ps + c * n, xb) + qb[c];
        for (int i = 0; i < Mt; ++i)
            if (zt[i] != 0.0)
                for (int c = 0; c < n; ++c) grad[c] += Gt[(size_t)i * n + c] * zt[i];
        for (int l = 0; l < k; ++l) {
            double s = 0.0;
            for (int c = 0; c < n; ++c) s += Qf[c * n + l] * grad[c];
            u[l] = s;
        }
        for (int i = k - 1; i >= 0; --i) {
            double s = u[i];
            for (int l = i + 1; l < k; ++l) s -= R[i * k + l] * y[bi * k + l];
            y[bi * k + i] = s / R[i * k + i];
        }
        for (int i = 0; i < k; ++i) y[bi * k + i] = -y[bi * k + i];
        if (m) memcpy(z + bi * m, zt, sizeof(double) * m);
        r = m;
        for (int pass = 0; pass < 2; ++pass) {
            const double *bound = pass == 0 ? ub : lb;
            double *out = pass == 0 ? z_ub : z_lb;
            for (int j = 0; j < n; ++j)
                out[bi * n + j] = bound && isfinite(bound[bi * n + j]) ? zt[r + j] : 0.0;
            if (bound) r += n;
        }
    }
    free(buf);
    return code;
}
