/*
 * Lie terms of quadric barriers on a few states, in one call (loaded through ctypes by
 * torchcbf/barriers/native.py).
 *
 * On one state per control tick the closed forms of torchcbf/barriers (shapes.py, compose.py,
 * rectify.py, lie.py) cost a few hundred tensor operations; this file evaluates the same
 * formulas in a loop. The torch closed forms are the reference (the tests compare the two).
 *
 * A block is k quadrics on the position p = x[index] (d components):
 *     b_j = w_j (sum_i (q_ji / a_ji)^2 - r_j^2),  q_j = R(angle_j)' (p - c_j)  (d = 2 to rotate)
 * with gradient grad_p b_j = 2 w_j R diag(1 / a^2) q_j and constant Hessian
 * B_p = 2 w_j R diag(1 / a^2) R', optionally transformed and scaled: h_j = s_j phi(b_j) with
 * phi(b) = sqrt(b + 1) - 1 ("radius") or 1 - exp(-rate b) ("exp"), as compose.py's Transformed:
 *     grad h = s phi1 grad b,  H = s (phi2 grad b grad b' + phi1 B),
 *     dH[v] = s (phi3 (grad b . v) grad b grad b' + phi2 (B v grad b' + grad b v' B
 *                + (grad b . v) B))
 * (phi1, phi2, phi3 the derivatives of phi at b; B is constant). A rectified block is the
 * exponential CBF of relative degree two of those functions along the model "inner" (drift f,
 * Jacobian J):
 *     h_e = grad h . f + k0 h,  grad h_e = H f + J' grad h + k0 grad h,
 *     tr(S' hess(h_e) S) = tr(S' dH[f] S) + sum(H S * (2 J + k0 I) S)
 *                          + sum_i (grad h)_i tr(S' hess f_i S).
 * The Lie terms follow along the model "outer": L_f = grad . f, L_g = grad' g and, with a
 * diffusion S = sigma [n, q], the Hessian trace tr(S' hess S).
 *
 * A group of blocks either gives their outputs as they are or reduces them, as compose.py's
 * Intersection (min) and Union (max): its c columns (the blocks' outputs concatenated) make
 * K outputs, output j the reduction of the columns j, j + K, j + 2 K, ... (K = 1: one
 * reduction of every column; K = k: k reductions of children with k outputs each). The
 * hard reduction takes the active column's terms, the mean of the active columns' at a tie
 * (as autograd of amin/amax), and a NaN first of all;
 * the smooth one, with z_i = +-v_i / T (+ for max) and weights w = softmax(z),
 *     h = +-T logsumexp(z),  grad h = sum_i w_i grad_i,
 *     tr(S' hess h S) = sum_i w_i tr_i +- (sum_i w_i |S' grad_i|^2 - |S' grad h|^2) / T
 * (_minmax.py's combine), accumulated over the columns with a running maximum of z.
 */
#include <math.h>
#include <stdint.h>
#include <string.h>

#include "_lie_kernel.h"

/* largest state, control, position and noise sizes (larger problems: torch) */
#define LIE_NMAX 32

/* the models, as MODEL_CODES in torchcbf/_native.py */
enum { SINGLE_INTEGRATOR = 0, DOUBLE_INTEGRATOR = 1, UNICYCLE = 2, ACCEL_UNICYCLE = 3 };

int torchcbf_lie_version(void) { return LIE_KERNEL_VERSION; }

/* State size of a model, or -1 for an unknown code. */
static int model_size(int code, int dim) {
    switch (code) {
    case SINGLE_INTEGRATOR: return dim;
    case DOUBLE_INTEGRATOR: return 2 * dim;
    case UNICYCLE: return 3;
    case ACCEL_UNICYCLE: return 4;
    default: return -1;
    }
}

/* Control size of a model. */
static int model_controls(int code, int dim) {
    return code == SINGLE_INTEGRATOR || code == DOUBLE_INTEGRATOR ? dim : 2;
}

/* Drift f [n], and where asked its Jacobian J [n, n] and the control matrix g [n, m]. */
static void model_eval(int code, int dim, int n, int m, const double *x, double *f, double *J,
                       double *g) {
    memset(f, 0, sizeof(double) * n);
    if (J) memset(J, 0, sizeof(double) * n * n);
    if (g) memset(g, 0, sizeof(double) * n * m);
    switch (code) {
    case SINGLE_INTEGRATOR:
        if (g)
            for (int i = 0; i < dim; ++i) g[i * m + i] = 1.0;
        break;
    case DOUBLE_INTEGRATOR:
        for (int i = 0; i < dim; ++i) {
            f[i] = x[dim + i];
            if (J) J[i * n + dim + i] = 1.0;
            if (g) g[(dim + i) * m + i] = 1.0;
        }
        break;
    case UNICYCLE:
        if (g) {
            g[0 * m + 0] = cos(x[2]);
            g[1 * m + 0] = sin(x[2]);
            g[2 * m + 1] = 1.0;
        }
        break;
    case ACCEL_UNICYCLE: {
        double v = x[2], c = cos(x[3]), s = sin(x[3]);
        f[0] = v * c;
        f[1] = v * s;
        if (J) {
            J[0 * n + 2] = c, J[0 * n + 3] = -v * s;
            J[1 * n + 2] = s, J[1 * n + 3] = v * c;
        }
        if (g) {
            g[2 * m + 0] = 1.0;
            g[3 * m + 1] = 1.0;
        }
        break;
    }
    }
}

/* t [n] with t_i = tr(S' hess f_i S) for S [n, q] (zero for the drifts linear in x). */
static void model_hess_traces(int code, int n, int q, const double *x, const double *S,
                              double *t) {
    memset(t, 0, sizeof(double) * n);
    if (code != ACCEL_UNICYCLE) return;
    /* d2f/dv dtheta = (-sin, cos), d2f/dtheta2 = -v (cos, sin) on the rows (x, y) */
    double v = x[2], c = cos(x[3]), s = sin(x[3]), sv_st = 0.0, st2 = 0.0;
    for (int l = 0; l < q; ++l) {
        sv_st += S[2 * q + l] * S[3 * q + l];
        st2 += S[3 * q + l] * S[3 * q + l];
    }
    t[0] = -2.0 * sv_st * s - v * st2 * c;
    t[1] = 2.0 * sv_st * c - v * st2 * s;
}

/* phi and its first three derivatives at b (compose.py's Transformed._phi and _phi3). */
static void transform(int code, double rate, double b, double *phi) {
    if (code == RADIUS) {
        double r = sqrt(b + 1.0), r3 = r * r * r;
        phi[0] = r - 1.0, phi[1] = 0.5 / r, phi[2] = -0.25 / r3;
        phi[3] = 0.375 / (r3 * r * r); /* (b + 1)^-2.5 */
    } else if (code == EXP) {
        double e = exp(-rate * b);
        phi[0] = -expm1(-rate * b), phi[1] = rate * e, phi[2] = -rate * rate * e;
        phi[3] = rate * rate * rate * e;
    } else {
        phi[0] = b, phi[1] = 1.0, phi[2] = 0.0, phi[3] = 0.0;
    }
}

/* One quadric at the position p [d]: its value, its gradient over p (g [d]) and its Hessian
 * over p (Bp [d, d]); `angle` NULL: no rotation, `a` NULL: unit axes. */
static double quadric(int d, const double *p, const double *c, const double *a, double r,
                      const double *angle, double w, double *g, double *Bp) {
    double cs = 1.0, sn = 0.0, qv[LIE_NMAX], inv_a2[LIE_NMAX], value = 0.0;
    if (angle) cs = cos(*angle), sn = sin(*angle);
    for (int i = 0; i < d; ++i) {
        qv[i] = p[i] - c[i];
        inv_a2[i] = a ? 1.0 / (a[i] * a[i]) : 1.0;
    }
    if (angle) { /* body coordinates R' (p - c) */
        double u = qv[0], v = qv[1];
        qv[0] = cs * u + sn * v, qv[1] = -sn * u + cs * v;
    }
    for (int i = 0; i < d; ++i) {
        double t = a ? qv[i] / a[i] : qv[i];
        value += t * t;
    }
    for (int i = 0; i < d; ++i) g[i] = 2.0 * w * inv_a2[i] * qv[i];
    if (angle) { /* back to the world axes */
        double u = g[0], v = g[1];
        g[0] = cs * u - sn * v, g[1] = sn * u + cs * v;
    }
    for (int i = 0; i < d; ++i) /* 2 w R diag(1 / a^2) R' */
        for (int l = 0; l < d; ++l) {
            double e = i == l ? inv_a2[i] : 0.0;
            if (angle) {
                double Ri[2] = {i == 0 ? cs : sn, i == 0 ? -sn : cs};
                double Rl[2] = {l == 0 ? cs : sn, l == 0 ? -sn : cs};
                e = Ri[0] * Rl[0] * inv_a2[0] + Ri[1] * Rl[1] * inv_a2[1];
            }
            Bp[i * d + l] = 2.0 * w * e;
        }
    return w * (value - r * r);
}

/* A block's integers after `mb`'s (its d indices included). */
static const int64_t *next_block(const int64_t *mb) { return mb + M_FIXED + mb[M_D]; }

/* The constants of one quadric output, as column() reads them. */
typedef struct {
    const double *center, *axes, *angle; /* [d] each (axes, angle: NULL for none) */
    const int64_t *index;                 /* [d] */
    double radius, w, rate;
    int d, code;
} Shape;

/* Whether a and b are the same function of the state. */
static int same_shape(const Shape *a, const Shape *b) {
    if (a->center != b->center || a->axes != b->axes || a->angle != b->angle ||
        a->radius != b->radius || a->w != b->w || a->rate != b->rate || a->d != b->d ||
        a->code != b->code)
        return 0;
    for (int i = 0; i < a->d; ++i)
        if (a->index[i] != b->index[i]) return 0;
    return 1;
}

/* What the columns of one state share: the sizes, the diffusion (SS = sigma sigma' [n, n];
 * both NULL without one), the state, the outer model's f and g, the inner model's f, J
 * and, with a diffusion, J SS and the traces tr(S' hess f_i S) (evaluated at its first
 * rectified column), and the last quadric output evaluated (`shape`, valid where `has_shape`:
 * its value b0, gradient gb_p [d] and Hessian Bp [d, d] over the position and phi), which
 * the next column reuses when it is the same (two blocks on one shape, as the children of
 * an intersection are). */
typedef struct {
    int n, m, q;
    const double *sigma, *SS, *x;
    double f_out[LIE_NMAX], g_out[LIE_NMAX * LIE_NMAX];
    double f_in[LIE_NMAX], J_in[LIE_NMAX * LIE_NMAX], JSS[LIE_NMAX * LIE_NMAX];
    double hess_in[LIE_NMAX];
    int inner_done, inner_done_dim;
    Shape shape;
    int has_shape;
    double b0, gb_p[LIE_NMAX], Bp[LIE_NMAX * LIE_NMAX], phi[4];
} Point;

/* Output j of the block (integers mb, pointers pb, rate of its transform) at the point: its
 * value, its gradient over the state (grad [n]) and tr(S' hess S) in *trace_out (0 without
 * a diffusion). */
static double column(Point *pt, const int64_t *mb, void *const *pb, double rate, int j,
                     double *grad, double *trace_out) {
    int n = pt->n, q = pt->q;
    const double *SS = pt->SS, *xs = pt->x, *f_in = pt->f_in, *J_in = pt->J_in;
    const double *center = pb[P_CENTER], *axes = pb[P_AXES], *radius = pb[P_RADIUS];
    const double *angle = pb[P_ANGLE], *scale = pb[P_SCALE], *outer_scale = pb[P_OUTER];
    int d = (int)mb[M_D], inner = (int)mb[M_INNER], code = (int)mb[M_TRANSFORM];
    const int64_t *index = mb + M_FIXED;
    double p[LIE_NMAX], gb[LIE_NMAX], gh[LIE_NMAX], H[LIE_NMAX * LIE_NMAX], Bf[LIE_NMAX];
    if (inner >= 0 && (inner != pt->inner_done || mb[M_INNER_DIM] != pt->inner_done_dim)) {
        model_eval(inner, (int)mb[M_INNER_DIM], n, pt->m, xs, pt->f_in, pt->J_in, NULL);
        pt->inner_done = inner, pt->inner_done_dim = (int)mb[M_INNER_DIM];
        if (SS) {
            for (int i = 0; i < n; ++i)
                for (int l = 0; l < n; ++l) {
                    double e = 0.0;
                    for (int t = 0; t < n; ++t) e += J_in[i * n + t] * SS[t * n + l];
                    pt->JSS[i * n + l] = e;
                }
            model_hess_traces(inner, n, q, xs, pt->sigma, pt->hess_in);
        }
    }
    double sj = outer_scale ? outer_scale[j * mb[M_OUTER]] : 1.0;
    Shape shape = {center + j * mb[M_CENTER], axes ? axes + j * mb[M_AXES] : NULL,
                   angle ? angle + j * mb[M_ANGLE] : NULL, index,
                   radius ? radius[j * mb[M_RADIUS]] : 1.0,
                   (double)mb[M_SIGN] * (scale ? scale[j * mb[M_SCALE]] : 1.0), rate, d, code};
    if (!pt->has_shape || !same_shape(&shape, &pt->shape)) {
        for (int i = 0; i < d; ++i) p[i] = xs[index[i]];
        pt->b0 = quadric(d, p, shape.center, shape.axes, shape.radius, shape.angle, shape.w,
                         pt->gb_p, pt->Bp);
        transform(code, rate, pt->b0, pt->phi);
        pt->shape = shape, pt->has_shape = 1;
    }
    const double *gb_p = pt->gb_p, *Bp = pt->Bp, *phi = pt->phi;
    /* grad b, grad h and H over the whole state */
    memset(gb, 0, sizeof(double) * n);
    for (int i = 0; i < d; ++i) gb[index[i]] += gb_p[i];
    for (int i = 0; i < n; ++i) gh[i] = sj * phi[1] * gb[i];
    for (int i = 0; i < n; ++i)
        for (int l = 0; l < n; ++l) H[i * n + l] = sj * phi[2] * gb[i] * gb[l];
    for (int i = 0; i < d; ++i)
        for (int l = 0; l < d; ++l) H[index[i] * n + index[l]] += sj * phi[1] * Bp[i * d + l];
    double value = sj * phi[0], trace = 0.0;
    if (inner < 0) {
        memcpy(grad, gh, sizeof(double) * n);
        if (SS)
            for (int i = 0; i < n * n; ++i) trace += H[i] * SS[i];
        *trace_out = trace;
        return value;
    }
    double k0 = *(const double *)pb[P_K0];
    value *= k0;
    for (int i = 0; i < n; ++i) {
        double e = k0 * gh[i];
        for (int l = 0; l < n; ++l) e += H[i * n + l] * f_in[l] + J_in[l * n + i] * gh[l];
        value += gh[i] * f_in[i];
        grad[i] = e;
    }
    if (SS) {
        /* sum(H S * (2 J + k0 I) S) = sum_il H_il (2 (J SS)_li + k0 SS_li) */
        const double *JSS = pt->JSS;
        for (int i = 0; i < n; ++i)
            for (int l = 0; l < n; ++l)
                trace += H[i * n + l] * (2.0 * JSS[l * n + i] + k0 * SS[l * n + i]);
        for (int i = 0; i < n; ++i) trace += gh[i] * pt->hess_in[i];
    }
    if (SS && code != NO_TRANSFORM) { /* tr(S' dH[f] S) */
        double gf = 0.0, gSSg = 0.0, BfSSg = 0.0, trBSS = 0.0;
        memset(Bf, 0, sizeof(double) * n);
        for (int i = 0; i < d; ++i)
            for (int l = 0; l < d; ++l) {
                Bf[index[i]] += Bp[i * d + l] * f_in[index[l]];
                trBSS += Bp[i * d + l] * SS[index[l] * n + index[i]];
            }
        for (int i = 0; i < n; ++i) {
            gf += gb[i] * f_in[i];
            for (int l = 0; l < n; ++l) {
                gSSg += gb[i] * SS[i * n + l] * gb[l];
                BfSSg += Bf[i] * SS[i * n + l] * gb[l];
            }
        }
        trace += sj * (phi[3] * gf * gSSg + phi[2] * (2.0 * BfSSg + gf * trBSS));
    }
    *trace_out = trace;
    return value;
}

/* |S' g|^2 = g' SS g */
static double noise_norm2(int n, const double *SS, const double *g) {
    double out = 0.0;
    for (int i = 0; i < n; ++i) {
        double e = 0.0;
        for (int l = 0; l < n; ++l) e += SS[i * n + l] * g[l];
        out += g[i] * e;
    }
    return out;
}

/* Output j of a reducing group (`mode`, `smooth`, temperature T) whose first block's integers,
 * pointers and rates are mb, pb and rates, with `columns` columns and K outputs: its value,
 * its gradient (grad [n]) and its trace (*trace_out). */
static double reduced(Point *pt, const int64_t *mb, void *const *pb, const double *rates,
                      int64_t columns, int64_t K, int64_t j, int mode, int smooth, double T,
                      double *grad, double *trace_out) {
    int n = pt->n, found = 0, nan = 0, ties = 0;
    double g[LIE_NMAX], tr, sign = mode == REDUCE_MAX ? 1.0 : -1.0;
    /* hard: the active column so far; smooth: sums weighted by exp((u_i - umax) / T) with
     * u_i = +-v_i, shifted before the division, so a subnormal T does not overflow */
    double best = 0.0, umax = -INFINITY, s = 0.0, tr_sum = 0.0, gg_sum = 0.0;
    int64_t first = 0; /* the first column of block b */
    int b = 0;
    memset(grad, 0, sizeof(double) * n);
    *trace_out = 0.0;
    for (int64_t c = j; c < columns; c += K) {
        while (c >= first + mb[M_K]) first += mb[M_K], mb = next_block(mb), ++b;
        double v = column(pt, mb, pb + P_FIXED * b, rates[b], (int)(c - first), g, &tr);
        if (!smooth) {
            int better = isnan(v) || (mode == REDUCE_MIN ? v < best : v > best);
            if (!found || (!isnan(best) && better)) {
                best = v, found = 1, ties = 1, *trace_out = tr;
                memcpy(grad, g, sizeof(double) * n);
            } else if (v == best) { /* a tie: summed here, averaged below */
                ++ties, *trace_out += tr;
                for (int i = 0; i < n; ++i) grad[i] += g[i];
            }
            continue;
        }
        double u = sign * v, e = 1.0;
        if (isnan(u)) nan = 1;
        if (u > umax) { /* the new largest term: the sums so far scaled down to it */
            if (umax > -INFINITY) {
                double r = exp((umax - u) / T);
                s *= r, tr_sum *= r, gg_sum *= r;
                for (int i = 0; i < n; ++i) grad[i] *= r;
            }
            umax = u;
            if (isinf(u)) e = NAN; /* softmax: exp(inf - inf) */
        } else {
            e = u == -INFINITY ? 0.0 : exp((u - umax) / T); /* softmax gives -inf no weight */
        }
        s += e, tr_sum += e * tr;
        for (int i = 0; i < n; ++i) grad[i] += e * g[i];
        if (pt->SS) gg_sum += e * noise_norm2(n, pt->SS, g);
    }
    if (!smooth) {
        if (ties > 1) {
            for (int i = 0; i < n; ++i) grad[i] /= ties;
            *trace_out /= ties;
        }
        return best;
    }
    for (int i = 0; i < n; ++i) grad[i] /= s;
    if (pt->SS)
        *trace_out = tr_sum / s + sign * (gg_sum / s - noise_norm2(n, pt->SS, grad)) / T;
    if (nan) return NAN;
    return isinf(umax) ? sign * umax : sign * (umax + T * log(s));
}

/* Where the terms go: the outputs of torchcbf_lie_quadrics (NULL: not written) and the
 * condition's constants. */
typedef struct {
    double *h, *lfh, *dhdt, *lgh, *hess, *dhdx, *b;
    const double *gain, *offset;
    int64_t gain_stride, offset_stride;
    double trace_weight, gain_scale, offset_scale, noise_scale;
} Sink;

/* Writes the terms of output `col` at `row` (s K + col for state s) from its value, gradient
 * and trace. */
static void emit(const Sink *o, const Point *pt, int64_t row, int64_t col, double value,
                 const double *grad, double trace) {
    int n = pt->n, m = pt->m;
    double lf = 0.0;
    for (int i = 0; i < n; ++i) lf += grad[i] * pt->f_out[i];
    o->h[row] = value;
    if (o->lfh) o->lfh[row] = lf;
    if (o->dhdt) o->dhdt[row] = 0.0;
    for (int l = 0; l < m; ++l) {
        double e = 0.0;
        for (int i = 0; i < n; ++i) e += grad[i] * pt->g_out[i * m + l];
        o->lgh[row * m + l] = e;
    }
    if (o->dhdx) memcpy(o->dhdx + row * n, grad, sizeof(double) * n);
    if (pt->sigma && o->hess) o->hess[row] = trace;
    if (o->b) {
        double gj = o->gain ? o->gain[col * o->gain_stride] : 1.0;
        double oj = o->offset ? o->offset[col * o->offset_stride] : 0.0;
        /* |sigma' g|^2 rounds below zero where it vanishes */
        double noise = o->noise_scale != 0.0 ? sqrt(fmax(noise_norm2(n, pt->SS, grad), 0.0)) : 0.0;
        o->b[row] = lf + o->trace_weight * trace + o->gain_scale * gj * value +
                    o->offset_scale * oj + o->noise_scale * noise;
    }
}

/*
 * Lie terms of the groups of blocks at B states, the outputs of all groups concatenated (K in
 * all). `meta` holds B, n, m, q, the outer model's code and size, the number of blocks, the
 * strides per output of the condition's gain and offset (below) and the number of groups, then
 * per block M_FIXED integers and its d indices, then per group G_FIXED integers (the groups
 * take the blocks in order); `reals` holds the condition's trace weight, gain scale, offset
 * scale and noise scale, then one number per block (the rate of the "exp" transform), then
 * one per group (the temperature of a smooth reduction). `ptrs` holds x [B, n] (float64,
 * C-contiguous), sigma [n, q] (NULL: no Hessian trace), the outputs h, lfh, dhdt (zeros: the
 * blocks are time-invariant) [B, K], lgh [B, K, m], hess [B, K] (written where sigma is
 * given), dhdx [B, K, n] and the condition b [B, K], then the condition's gain and offset,
 * then per block P_FIXED pointers: center [k or 1, d], axes (NULL: unit), radius (NULL: 1),
 * angle (NULL: none), scale w and outer scale s (NULL: 1), and k0 (rectified blocks). Every
 * output but h and lgh may be NULL (not written). The affine CBF condition, where b is
 * given, is
 *     b = lfh + dhdt + trace_weight tr + gain_scale gain h + offset_scale offset
 *         + noise_scale |sigma' dh/dx|
 * (gain, offset: NULL for 1 and 0; a noise scale other than 0 needs sigma). The outer model
 * (code, size) is the one of the Lie terms;
 * a rectified block (inner code >= 0) takes the drift of its inner model.
 * Returns 0, or 1 when the sizes are out of range (the caller takes its torch path).
 */
int torchcbf_lie_quadrics(const int64_t *meta, const double *reals, void *const *ptrs) {
    int64_t B = meta[L_B];
    int n = (int)meta[L_N], m = (int)meta[L_M], q = (int)meta[L_Q];
    int outer = (int)meta[L_OUTER], outer_dim = (int)meta[L_OUTER_DIM];
    int64_t blocks = meta[L_BLOCKS], groups = meta[L_GROUPS];
    const double *x = ptrs[PT_X], *sigma = ptrs[PT_SIGMA];
    Sink out = {ptrs[PT_H],    ptrs[PT_LFH],  ptrs[PT_DHDT],         ptrs[PT_LGH],
                ptrs[PT_HESS], ptrs[PT_DHDX], ptrs[PT_B],            ptrs[PT_GAIN],
                ptrs[PT_OFFSET], meta[L_GAIN_STRIDE], meta[L_OFFSET_STRIDE],
                reals[R_TRACE_WEIGHT], reals[R_GAIN_SCALE], reals[R_OFFSET_SCALE],
                reals[R_NOISE_SCALE]};
    void *const *params = ptrs + PTRS_HEADER;
    const int64_t *block_meta = meta + META_HEADER;
    const double *rates = reals + REALS_HEADER;
    if (B < 0 || n < 1 || n > LIE_NMAX || m < 1 || m > LIE_NMAX || q < 0 || q > LIE_NMAX ||
        blocks < 0 || groups < 0 || !out.h || !out.lgh || (sigma && q < 1) ||
        (out.noise_scale != 0.0 && !sigma) ||
        out.gain_stride < 0 || out.offset_stride < 0 || model_size(outer, outer_dim) != n ||
        model_controls(outer, outer_dim) != m)
        return 1;
    const int64_t *mb = block_meta;
    for (int64_t b = 0; b < blocks; ++b, mb = next_block(mb)) {
        void *const *pb = params + P_FIXED * b;
        int64_t d = mb[M_D];
        if (mb[M_K] < 1 || d < 1 || d > n || !pb[P_CENTER] || (pb[P_ANGLE] && d != 2) ||
            mb[M_TRANSFORM] < NO_TRANSFORM || mb[M_TRANSFORM] > EXP)
            return 1;
        if (mb[M_INNER] >= 0 &&
            (!pb[P_K0] || model_size((int)mb[M_INNER], (int)mb[M_INNER_DIM]) != n))
            return 1;
        for (int i = 0; i < d; ++i)
            if (mb[M_FIXED + i] < 0 || mb[M_FIXED + i] >= n) return 1;
    }
    const int64_t *group_meta = mb;
    const double *temperatures = rates + blocks;
    int64_t K = 0, taken = 0;
    mb = block_meta;
    for (int64_t g = 0; g < groups; ++g) {
        const int64_t *gm = group_meta + G_FIXED * g;
        int64_t columns = 0, outputs = gm[G_OUTPUTS];
        if (gm[G_BLOCKS] < 1 || gm[G_BLOCKS] > blocks - taken || gm[G_MODE] < NO_REDUCTION ||
            gm[G_MODE] > REDUCE_MAX || outputs < 1)
            return 1;
        for (int64_t b = 0; b < gm[G_BLOCKS]; ++b, mb = next_block(mb)) columns += mb[M_K];
        if (gm[G_MODE] == NO_REDUCTION ? outputs != columns : columns % outputs != 0)
            return 1;
        if (gm[G_MODE] != NO_REDUCTION && gm[G_SMOOTH] && !(temperatures[g] > 0.0)) return 1;
        taken += gm[G_BLOCKS];
        K += outputs;
    }
    if (taken != blocks) return 1;
    double SS[LIE_NMAX * LIE_NMAX]; /* sigma sigma' [n, n]: tr(S' H S) = sum(H * SS) */
    if (sigma)
        for (int i = 0; i < n; ++i)
            for (int l = 0; l < n; ++l) {
                double e = 0.0;
                for (int t = 0; t < q; ++t) e += sigma[i * q + t] * sigma[l * q + t];
                SS[i * n + l] = e;
            }
    Point pt;
    pt.n = n, pt.m = m, pt.q = q, pt.sigma = sigma, pt.SS = sigma ? SS : NULL;
    double grad[LIE_NMAX];
    for (int64_t s = 0; s < B; ++s) {
        pt.x = x + s * n;
        pt.inner_done = pt.inner_done_dim = -1, pt.has_shape = 0;
        model_eval(outer, outer_dim, n, m, pt.x, pt.f_out, NULL, pt.g_out);
        int64_t col = 0, b = 0; /* the output being written, the group's first block */
        mb = block_meta;
        for (int64_t g = 0; g < groups; ++g) {
            const int64_t *gm = group_meta + G_FIXED * g;
            const int64_t *first = mb;
            int64_t columns = 0, nb = gm[G_BLOCKS];
            if (gm[G_MODE] == NO_REDUCTION) {
                for (int64_t i = 0; i < nb; ++i, mb = next_block(mb))
                    for (int j = 0; j < (int)mb[M_K]; ++j, ++col) {
                        double trace;
                        double value = column(&pt, mb, params + P_FIXED * (b + i), rates[b + i],
                                              j, grad, &trace);
                        emit(&out, &pt, s * K + col, col, value, grad, trace);
                    }
            } else {
                for (int64_t i = 0; i < nb; ++i, mb = next_block(mb)) columns += mb[M_K];
                for (int64_t j = 0; j < gm[G_OUTPUTS]; ++j, ++col) {
                    double trace;
                    double value = reduced(&pt, first, params + P_FIXED * b, rates + b, columns,
                                           gm[G_OUTPUTS], j, (int)gm[G_MODE], (int)gm[G_SMOOTH],
                                           temperatures[g], grad, &trace);
                    emit(&out, &pt, s * K + col, col, value, grad, trace);
                }
            }
            b += nb;
        }
    }
    return 0;
}
