/*
 * Body of _rollout_kernel.c, included once per precision with REAL, SUFFIX, SIN, COS, LOG
 * and SQRT defined. Every loop over `l` runs over the LANES samples of a block.
 */

#define LOOP for (int l = 0; l < LANES; ++l)
#define INL static inline __attribute__((always_inline))

/* xdot = f(x) + g(x) u of the built-in models (torchcbf/dynamics/models.py). */
INL void SUFFIX(xdot)(const problem_t *pr, REAL (*x)[LANES], REAL (*u)[LANES],
                      REAL (*k)[LANES]) {
    const int dim = pr->dim;
    switch (pr->model) {
    case M_SINGLE:
        for (int i = 0; i < dim; ++i) LOOP k[i][l] = u[i][l];
        break;
    case M_DOUBLE:
        for (int i = 0; i < dim; ++i) LOOP {
                k[i][l] = x[dim + i][l];
                k[dim + i][l] = u[i][l];
            }
        break;
    case M_UNICYCLE:
        /* separate loops: gcc would merge sin and cos of one argument into a sincos
         * call, which has no vector variant */
        LOOP k[0][l] = u[0][l] * COS(x[2][l]);
        LOOP k[1][l] = u[0][l] * SIN(x[2][l]);
        LOOP k[2][l] = u[1][l];
        break;
    default: /* M_ACCEL_UNICYCLE */
        LOOP k[0][l] = x[2][l] * COS(x[3][l]);
        LOOP k[1][l] = x[2][l] * SIN(x[3][l]);
        LOOP {
            k[2][l] = u[0][l];
            k[3][l] = u[1][l];
        }
        break;
    }
}

/* One integration step of x in place (torchcbf/integrators.py: euler, rk4). */
INL void SUFFIX(integrate)(const problem_t *pr, REAL (*x)[LANES], REAL (*u)[LANES],
                           REAL (*k1)[LANES], REAL (*k2)[LANES], REAL (*k3)[LANES],
                           REAL (*k4)[LANES], REAL (*xt)[LANES]) {
    const int n = pr->n;
    const REAL dt = (REAL)pr->dt;
    SUFFIX(xdot)(pr, x, u, k1);
    if (pr->integrator == I_EULER) {
        for (int i = 0; i < n; ++i) LOOP x[i][l] = x[i][l] + dt * k1[i][l];
        return;
    }
    const REAL half = (REAL)(0.5 * pr->dt), sixth = (REAL)(pr->dt / 6.0);
    for (int i = 0; i < n; ++i) LOOP xt[i][l] = x[i][l] + half * k1[i][l];
    SUFFIX(xdot)(pr, xt, u, k2);
    for (int i = 0; i < n; ++i) LOOP xt[i][l] = x[i][l] + half * k2[i][l];
    SUFFIX(xdot)(pr, xt, u, k3);
    for (int i = 0; i < n; ++i) LOOP xt[i][l] = x[i][l] + dt * k3[i][l];
    SUFFIX(xdot)(pr, xt, u, k4);
    for (int i = 0; i < n; ++i) LOOP {
            REAL incr = k1[i][l] + (REAL)2 * k2[i][l] + (REAL)2 * k3[i][l] + k4[i][l];
            x[i][l] = x[i][l] + sixth * incr;
        }
}

/* h(x) of an Ellipse or Ball barrier (torchcbf/barriers/shapes.py). */
INL void SUFFIX(shape_h)(const shape_t *S, REAL (*x)[LANES], REAL *h) {
    const REAL sign = (REAL)S->sign;
    const REAL c0 = S->kind == S_BALL ? (REAL)S->radius * (REAL)S->radius : (REAL)1;
    const int ball = S->kind == S_BALL;
    if (S->d == 2) {
        const REAL *px = x[S->idx[0]], *py = x[S->idx[1]];
        const REAL cx = (REAL)S->center[0], cy = (REAL)S->center[1];
        const REAL ax = (REAL)S->axes[0], ay = (REAL)S->axes[1];
        if (S->rotated) {
            const REAL co = COS((REAL)S->angle), si = SIN((REAL)S->angle);
            LOOP {
                REAL u = px[l] - cx, v = py[l] - cy;
                REAL q0 = (co * u + si * v) / ax, q1 = (-si * u + co * v) / ay;
                h[l] = sign * ((q0 * q0 + q1 * q1) - c0);
            }
        } else if (ball) {
            LOOP {
                REAL u = px[l] - cx, v = py[l] - cy;
                h[l] = sign * ((u * u + v * v) - c0);
            }
        } else {
            LOOP {
                REAL q0 = (px[l] - cx) / ax, q1 = (py[l] - cy) / ay;
                h[l] = sign * ((q0 * q0 + q1 * q1) - c0);
            }
        }
        return;
    }
    LOOP h[l] = 0;
    for (int i = 0; i < S->d; ++i) {
        const REAL *pi = x[S->idx[i]];
        const REAL ci = (REAL)S->center[i], ai = (REAL)S->axes[i];
        if (ball)
            LOOP {
                REAL q = pi[l] - ci;
                h[l] += q * q;
            }
        else
            LOOP {
                REAL q = (pi[l] - ci) / ai;
                h[l] += q * q;
            }
    }
    LOOP h[l] = sign * (h[l] - c0);
}

/* |p - c|^2 over the term's index */
INL void SUFFIX(sq_dist)(const term_t *T, REAL (*x)[LANES], REAL *s) {
    LOOP s[l] = 0;
    for (int i = 0; i < T->d; ++i) {
        const REAL *pi = x[T->idx[i]];
        const REAL ci = (REAL)T->center[i];
        LOOP {
            REAL q = pi[l] - ci;
            s[l] += q * q;
        }
    }
}

/* Stage (and, on the last step, terminal) terms at the state x after step j. stage,
 * terminal and whole accumulate the three parts of the total in the order of SumCost. Each
 * shape is evaluated once per step into hcur (terms over the same barrier share its
 * records); the discrete-time barrier terms read the previous step's values in hprev (and
 * stop after their `steps`). The caller alternates the two buffers, so this step's hcur is
 * the next step's hprev. */
INL void SUFFIX(costs)(const problem_t *pr, REAL (*x)[LANES], int j, REAL *stage,
                       REAL *terminal, REAL *whole, REAL (*hprev)[LANES],
                       REAL (*hcur)[LANES]) {
    REAL st[LANES], tmp[LANES], h[LANES], pen[LANES];
    unsigned char have[SMAX] = {0};
    const int last = j == pr->H - 1;
    int first = 1;
    for (int t = 0; t < pr->nterms; ++t) {
        const term_t *T = &pr->terms[t];
        if (T->type == T_DISCRETE_BARRIER && j >= T->steps) continue; /* past its steps */
        if (T->type == T_DISCRETE_BARRIER || T->type == T_BARRIER)
            for (int s = T->shape0; s < T->shape0 + T->nshape; ++s) {
                if (!have[s]) SUFFIX(shape_h)(&pr->shapes[s], x, hcur[s]);
                have[s] = 1;
            }
        if (T->type == T_DISCRETE_BARRIER && T->paired) continue; /* in its barrier term */
        if (T->type == T_DISCRETE_BARRIER) {
            const REAL g1 = (REAL)(1.0 - T->extra);
            LOOP tmp[l] = 0;
            for (int s = T->shape0; s < T->shape0 + T->nshape; ++s) {
                const REAL *hc = hcur[s], *hp = hprev[s];
                LOOP {
                    REAL v = g1 * hp[l] - hc[l];
                    tmp[l] += v < 0 ? 0 : v;
                }
            }
            const REAL w = (REAL)T->weight;
            LOOP whole[l] += w * tmp[l];
            continue;
        }
        if (T->type == T_GOAL) {
            SUFFIX(sq_dist)(T, x, h);
            const REAL w = (REAL)T->weight, tw = (REAL)T->extra;
            LOOP tmp[l] = w * h[l];
            if (last && T->extra != 0.0) LOOP terminal[l] += tw * h[l];
        } else if (T->type == T_OBSTACLE) {
            SUFFIX(sq_dist)(T, x, h);
            const REAL r = (REAL)T->radius, ko = (REAL)T->extra, e = (REAL)T->eps;
            LOOP {
                REAL dist = SQRT(h[l]) - r;
                tmp[l] = ko / (dist < e ? e : dist);
            }
        } else if (T->pair < 0 || j >= pr->terms[T->pair].steps) {
            /* T_BARRIER: sum over the barrier's outputs */
            const REAL w = (REAL)T->weight, e = (REAL)T->eps;
            for (int s = 0; s < T->nshape; ++s) {
                const REAL *hc = hcur[T->shape0 + s];
                if (s == 0)
                    LOOP tmp[l] = w / (hc[l] < e ? e : hc[l]);
                else
                    LOOP tmp[l] += w / (hc[l] < e ? e : hc[l]);
            }
        } else { /* T_BARRIER and its discrete-time term, one pass over the values */
            const term_t *D = &pr->terms[T->pair];
            const REAL w = (REAL)T->weight, e = (REAL)T->eps, g1 = (REAL)(1.0 - D->extra);
            for (int s = 0; s < T->nshape; ++s) {
                const REAL *hc = hcur[T->shape0 + s], *hp = hprev[T->shape0 + s];
                if (s == 0)
                    LOOP {
                        REAL hv = hc[l], v = g1 * hp[l] - hv;
                        tmp[l] = w / (hv < e ? e : hv);
                        pen[l] = v < 0 ? 0 : v;
                    }
                else
                    LOOP {
                        REAL hv = hc[l], v = g1 * hp[l] - hv;
                        tmp[l] += w / (hv < e ? e : hv);
                        pen[l] += v < 0 ? 0 : v;
                    }
            }
            const REAL wd = (REAL)D->weight;
            LOOP whole[l] += wd * pen[l];
        }
        if (first)
            LOOP st[l] = tmp[l];
        else
            LOOP st[l] += tmp[l];
        first = 0;
    }
    if (!first) LOOP stage[l] += st[l];
}

/* Store the `count` lanes of V[dim][LANES] as step j of a rollout output: sample-major
 * rows [P, steps, dim] at positions p0 + lane, or component-major blocks [B, dim, steps, K]
 * at the consecutive samples k0 + lane of environment b. */
INL void SUFFIX(store)(REAL *out, REAL V[][LANES], int dim, int steps, int j, int count,
                              int cmajor, int64_t b, int64_t K, int64_t k0, int64_t p0) {
    for (int i = 0; i < dim; ++i) {
        if (cmajor) {
            REAL *dst = out + ((b * dim + i) * (int64_t)steps + j) * K + k0;
            for (int l = 0; l < count; ++l) dst[l] = V[i][l];
        } else {
            for (int l = 0; l < count; ++l) out[((p0 + l) * (int64_t)steps + j) * dim + i] = V[i][l];
        }
    }
}

/* One block: `count` samples kk[0..count) of environment b, outputs at positions
 * p0 + lane. See the exported function for the arguments. */
CLONES static void SUFFIX(block)(const problem_t *pr, const REAL *x0, const REAL *plan,
                                 const REAL *wctrl, uint64_t key, const int64_t *kk,
                                 int count, int64_t b, int64_t p0, int cmajor, REAL *cost,
                                 REAL *states, REAL *controls, REAL *eps,
                                 const REAL *weights, double *wsum) {
    const int n = pr->n, m = pr->m, H = pr->H, P = (pr->m + 1) / 2;
    const int dyn = states != NULL || (cost != NULL && pr->nterms > 0);
    const int clamp = pr->has_lo || pr->has_hi;
    REAL X[NMAX][LANES], U[MMAX][LANES], E[MMAX][LANES], Z[MMAX][LANES];
    REAL K1[NMAX][LANES], K2[NMAX][LANES], K3[NMAX][LANES], K4[NMAX][LANES], XT[NMAX][LANES];
    REAL hring[2][SMAX][LANES], w[LANES], R[LANES], A[LANES];
    REAL stage[LANES], terminal[LANES], whole[LANES], ctrl[LANES], keep[LANES], tmp[LANES];
    uint64_t ks[LANES];
    REAL lo[MMAX], hi[MMAX], L[MMAX * MMAX];
    for (int i = 0; i < MMAX; ++i) {
        lo[i] = (REAL)pr->lo[i];
        hi[i] = (REAL)pr->hi[i];
    }
    for (int i = 0; i < MMAX * MMAX; ++i) L[i] = (REAL)pr->chol[i];
    LOOP {
        int64_t k = kk[l < count ? l : count - 1];
        ks[l] = (uint64_t)k;
        keep[l] = k < pr->zero_noise ? (REAL)0 : (REAL)1;
        w[l] = (weights != NULL && l < count) ? weights[p0 + l] : (REAL)0;
        stage[l] = terminal[l] = whole[l] = ctrl[l] = 0;
    }
    for (int i = 0; i < n; ++i) LOOP X[i][l] = x0[i];
    for (int t = 0; t < pr->nterms; ++t) {
        const term_t *T = &pr->terms[t];
        if (T->type != T_DISCRETE_BARRIER) continue;
        for (int s = 0; s < T->nshape; ++s)
            SUFFIX(shape_h)(&pr->shapes[T->shape0 + s], X, hring[0][T->shape0 + s]);
    }
    if (states != NULL) SUFFIX(store)(states, X, n, H + 1, 0, count, cmajor, b, pr->K, kk[0], p0);

    const REAL scale = (REAL)4.656612873077393e-10; /* 2^-31 */
    const REAL two_pi = (REAL)6.283185307179586;
    for (int j = 0; j < H; ++j) {
        /* standard normals: one hash gives one Box-Muller pair */
        for (int q = 0; q < P; ++q) {
            REAL *z0 = Z[2 * q], *z1 = Z[2 * q + 1 < MMAX ? 2 * q + 1 : 2 * q];
            const uint64_t base = (uint64_t)j * (uint64_t)P + (uint64_t)q;
            const uint64_t stride = (uint64_t)H * (uint64_t)P;
            LOOP {
                uint64_t h = mix64(key + (ks[l] * stride + base + 1) * GOLDEN);
                REAL u1 = ((REAL)(int32_t)(h >> 33) + (REAL)0.5) * scale;
                REAL u2 = (REAL)(int32_t)((h >> 2) & 0x7fffffffu) * scale;
                R[l] = keep[l] * SQRT((REAL)-2 * LOG(u1));
                A[l] = two_pi * u2;
            }
            LOOP z0[l] = R[l] * COS(A[l]);
            LOOP z1[l] = R[l] * SIN(A[l]);
        }
        /* eps = L z, controls clamped, eps recomputed from the clamped controls */
        for (int i = m - 1; i >= 0; --i) {
            LOOP E[i][l] = L[i * MMAX] * Z[0][l];
            for (int c = 1; c <= i; ++c) LOOP E[i][l] += L[i * MMAX + c] * Z[c][l];
        }
        for (int i = 0; i < m; ++i) {
            const REAL pj = plan[j * m + i], lo_i = lo[i], hi_i = hi[i];
            if (clamp) {
                const int has_lo = pr->has_lo, has_hi = pr->has_hi;
                LOOP {
                    REAL u = pj + E[i][l];
                    if (has_lo) u = u < lo_i ? lo_i : u;
                    if (has_hi) u = u > hi_i ? hi_i : u;
                    U[i][l] = u;
                    E[i][l] = u - pj;
                }
            } else {
                LOOP U[i][l] = pj + E[i][l];
            }
        }
        if (wctrl != NULL) {
            /* sum_i eps_i W_i of this step, then added over the steps (the torch order) */
            const REAL w0 = wctrl[j * m];
            LOOP tmp[l] = E[0][l] * w0;
            for (int i = 1; i < m; ++i) {
                const REAL wi = wctrl[j * m + i];
                LOOP tmp[l] += E[i][l] * wi;
            }
            LOOP ctrl[l] += tmp[l];
        }
        if (wsum != NULL) {
            /* padded lanes have weight 0; eight partial sums in a fixed order vectorise
             * and keep the result independent of the machine */
            for (int i = 0; i < m; ++i) {
                double part[8] = {0, 0, 0, 0, 0, 0, 0, 0};
                for (int l = 0; l < LANES; l += 8)
                    for (int r = 0; r < 8; ++r) part[r] += (double)(w[l + r] * E[i][l + r]);
                double acc = 0;
                for (int r = 0; r < 8; ++r) acc += part[r];
                wsum[j * m + i] += acc;
            }
        }
        if (controls != NULL) SUFFIX(store)(controls, U, m, H, j, count, cmajor, b, pr->K, kk[0], p0);
        if (eps != NULL) SUFFIX(store)(eps, E, m, H, j, count, cmajor, b, pr->K, kk[0], p0);
        if (!dyn) continue;
        SUFFIX(integrate)(pr, X, U, K1, K2, K3, K4, XT);
        if (states != NULL)
            SUFFIX(store)(states, X, n, H + 1, j + 1, count, cmajor, b, pr->K, kk[0], p0);
        if (cost != NULL && pr->nterms > 0)
            SUFFIX(costs)(pr, X, j, stage, terminal, whole, hring[j & 1],
                          hring[(j + 1) & 1]);
    }
    if (cost != NULL) {
        const REAL gamma = (REAL)pr->gamma;
        for (int l = 0; l < count; ++l) {
            REAL c = (stage[l] + terminal[l]) + whole[l];
            if (wctrl != NULL) c = c + gamma * ctrl[l];
            cost[p0 + l] = c;
        }
    }
}

/*
 * Process the samples p in [p_lo, p_hi): sample p is (b, k) = (pairs[2p], pairs[2p+1]), or
 * (p / K, p % K) when pairs is NULL (consecutive samples of one environment share a block).
 *
 *   cfg       configuration (layout in _rollout_kernel.c)
 *   x0        [B, n] start states;  plan [B, H, m] nominal controls;  keys [B] noise keys
 *   wctrl     [B, H, m] plan @ Sigma^-1 (control cost; NULL: none)
 *   cost      [P] total cost of sample p (NULL: not computed)
 *   states    [P, H+1, n], controls / eps [P, H, m] rows of sample p (NULL: not stored);
 *             with cmajor != 0 (pairs NULL) component-major blocks [B, n, H+1, K] and
 *             [B, m, H, K] indexed by (b, k) instead (samples contiguous, for a torch cost)
 *   weights   [P] and wsum [B, H, m] (float64): wsum[b] += weights[p] * eps_p (NULL: none)
 *
 * Returns 0, or a negative code for a configuration the kernel does not accept.
 */
int SUFFIX(torchcbf_mppi_run)(const double *cfg, int64_t p_lo, int64_t p_hi,
                              const int64_t *pairs, const REAL *x0, const REAL *plan,
                              const REAL *wctrl, const int64_t *keys, REAL *cost,
                              REAL *states, REAL *controls, REAL *eps, const REAL *weights,
                              double *wsum, int cmajor) {
    problem_t pr;
    int rc = parse(cfg, &pr);
    if (rc != 0) return rc;
    if (cmajor && pairs != NULL) return -7; /* component-major outputs need samples in order */
    const int n = pr.n, m = pr.m, H = pr.H;
    int64_t kk[LANES];
    int64_t p = p_lo;
    while (p < p_hi) {
        const int64_t b = pairs != NULL ? pairs[2 * p] : p / pr.K;
        int count = 0;
        while (p + count < p_hi && count < LANES) {
            const int64_t q = p + count;
            const int64_t bq = pairs != NULL ? pairs[2 * q] : q / pr.K;
            if (bq != b) break;
            kk[count++] = pairs != NULL ? pairs[2 * q + 1] : q % pr.K;
        }
        SUFFIX(block)(&pr, x0 + b * n, plan + b * (int64_t)H * m,
                      wctrl != NULL ? wctrl + b * (int64_t)H * m : NULL, (uint64_t)keys[b], kk,
                      count, b, p, cmajor, cost, states, controls, eps, weights,
                      wsum != NULL ? wsum + b * (int64_t)H * m : NULL);
        p += count;
    }
    return 0;
}

/* Box-Muller pairs q of step j for the LANES samples from k0 of the environment with
 * `key`: Z[2q] and Z[2q + 1] (the counter-based normals of the block). */
INL void SUFFIX(pairs)(uint64_t key, int64_t k0, int j, int H, int P, REAL (*Z)[LANES]) {
    const uint64_t stride = (uint64_t)H * (uint64_t)P;
    const REAL scale = (REAL)4.656612873077393e-10; /* 2^-31 */
    const REAL two_pi = (REAL)6.283185307179586;
    REAL R[LANES], A[LANES];
    for (int q = 0; q < P; ++q) {
        const uint64_t base = (uint64_t)j * (uint64_t)P + (uint64_t)q;
        LOOP {
            uint64_t h = mix64(key + (((uint64_t)k0 + l) * stride + base + 1) * GOLDEN);
            REAL u1 = ((REAL)(int32_t)(h >> 33) + (REAL)0.5) * scale;
            REAL u2 = (REAL)(int32_t)((h >> 2) & 0x7fffffffu) * scale;
            R[l] = SQRT((REAL)-2 * LOG(u1));
            A[l] = two_pi * u2;
        }
        LOOP Z[2 * q][l] = R[l] * COS(A[l]);
        LOOP Z[2 * q + 1][l] = R[l] * SIN(A[l]);
    }
}

/* The `count` lanes of V as elements k0.. of a row with sample stride sk. */
INL void SUFFIX(put)(REAL *row, int64_t sk, const REAL *V, int count) {
    if (sk == 1)
        memcpy(row, V, (size_t)count * sizeof(REAL));
    else
        for (int l = 0; l < count; ++l) row[l * sk] = V[l];
}

/*
 * The torch path's noise for environment `key`, samples [k_lo, k_hi): with `ctrl` NULL,
 * the standard normals of the counter-based noise times L[0] into eps (the same as the
 * block's, before the zero-noise samples, the factor and the limits are applied); else
 * the sampled controls ctrl = clamp(plan + L z) (plan[j * m + i], L row-major lower
 * triangular MMAX x MMAX, limits lo/hi where has_lo/has_hi) and eps = ctrl - plan.
 * Element (k, j, i) goes to k * sk + j * sj + i * si (ck, cj, ci for ctrl). With
 * sample-contiguous rows (sk = 1) the steps are the outer loop, so the writes stream along
 * the rows; otherwise the samples are, so each sample's values are written together.
 */
CLONES static void SUFFIX(noise_rows)(uint64_t key, int64_t k_lo, int64_t k_hi, int H, int m,
                                      const double *L, const REAL *plan, const double *lo,
                                      const double *hi, int has_lo, int has_hi, REAL *eps,
                                      int64_t sk, int64_t sj, int64_t si, REAL *ctrl,
                                      int64_t ck, int64_t cj, int64_t ci) {
    const int P = (m + 1) / 2, steps_outer = sk == 1 && (ctrl == NULL || ck == 1);
    const int64_t nblocks = (k_hi - k_lo + LANES - 1) / LANES;
    const int64_t outer = steps_outer ? H : nblocks, inner = steps_outer ? nblocks : H;
    REAL Z[MMAX + 1][LANES], E[LANES], U[LANES], Lr[MMAX * MMAX], lo_r[MMAX], hi_r[MMAX];
    for (int i = 0; i < MMAX * MMAX; ++i) Lr[i] = (REAL)L[i];
    for (int i = 0; i < MMAX; ++i) lo_r[i] = (REAL)lo[i], hi_r[i] = (REAL)hi[i];
    for (int64_t o = 0; o < outer; ++o) {
        for (int64_t in = 0; in < inner; ++in) {
            const int j = (int)(steps_outer ? o : in);
            const int64_t k0 = k_lo + (steps_outer ? in : o) * LANES;
            const int count = k_hi - k0 < LANES ? (int)(k_hi - k0) : LANES;
            SUFFIX(pairs)(key, k0, j, H, P, Z);
            for (int i = 0; i < m; ++i) {
                REAL *e = eps + k0 * sk + j * sj + i * si;
                if (ctrl == NULL) {
                    LOOP E[l] = Lr[0] * Z[i][l];
                    SUFFIX(put)(e, sk, E, count);
                    continue;
                }
                const REAL pj = plan[j * m + i];
                LOOP E[l] = Lr[i * MMAX] * Z[0][l];
                for (int c = 1; c <= i; ++c) LOOP E[l] += Lr[i * MMAX + c] * Z[c][l];
                LOOP {
                    REAL u = pj + E[l];
                    if (has_lo) u = u < lo_r[i] ? lo_r[i] : u;
                    if (has_hi) u = u > hi_r[i] ? hi_r[i] : u;
                    U[l] = u;
                    E[l] = u - pj;
                }
                SUFFIX(put)(e, sk, E, count);
                SUFFIX(put)(ctrl + k0 * ck + j * cj + i * ci, ck, U, count);
            }
        }
    }
}

/*
 * The standard normals of the counter-based noise times `std` (see noise_rows) for
 * environments [b_lo, b_hi) and samples [k_lo, k_hi): element (b, k, j, i) goes to
 * out[b * sb + k * sk + j * sj + i * si].
 */
int SUFFIX(torchcbf_mppi_normals)(const int64_t *keys, int64_t b_lo, int64_t b_hi,
                                  int64_t k_lo, int64_t k_hi, int64_t H, int64_t m, double std,
                                  REAL *out, int64_t sb, int64_t sk, int64_t sj, int64_t si) {
    if (H < 1 || m < 1 || m > MMAX || k_lo < 0 || k_hi < k_lo || b_lo < 0 || b_hi < b_lo)
        return -1;
    double L[MMAX * MMAX] = {0}, none[MMAX] = {0};
    L[0] = std;
    for (int64_t b = b_lo; b < b_hi; ++b)
        SUFFIX(noise_rows)((uint64_t)keys[b], k_lo, k_hi, (int)H, (int)m, L, NULL, none, none,
                           0, 0, out + b * sb, sk, sj, si, NULL, 0, 0, 0);
    return 0;
}

/*
 * The torch path's sampled controls in one pass (see noise_rows) for environments
 * [b_lo, b_hi) and samples [k_lo, k_hi): plan[b * H * m + j * m + i]; element (b, k, j, i)
 * of eps and ctrl goes to b * sb + k * sk + j * sj + i * si (cb, ck, cj, ci for ctrl).
 */
int SUFFIX(torchcbf_mppi_perturb)(const int64_t *keys, int64_t b_lo, int64_t b_hi,
                                  int64_t k_lo, int64_t k_hi, int64_t H, int64_t m,
                                  const double *L, const REAL *plan, const double *lo,
                                  const double *hi, int has_lo, int has_hi, REAL *eps,
                                  int64_t sb, int64_t sk, int64_t sj, int64_t si, REAL *ctrl,
                                  int64_t cb, int64_t ck, int64_t cj, int64_t ci) {
    if (H < 1 || m < 1 || m > MMAX || k_lo < 0 || k_hi < k_lo || b_lo < 0 || b_hi < b_lo)
        return -1;
    for (int64_t b = b_lo; b < b_hi; ++b)
        SUFFIX(noise_rows)((uint64_t)keys[b], k_lo, k_hi, (int)H, (int)m, L, plan + b * H * m,
                           lo, hi, has_lo, has_hi, eps + b * sb, sk, sj, si, ctrl + b * cb, ck,
                           cj, ci);
    return 0;
}

#undef LOOP
#undef INL
