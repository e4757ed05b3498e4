/* The estimators' C kernels: the Gauss-Newton normal equations of the cooperative solves.

   joint_system  the joint snapshot's (joint.py :func:`solve`), every position of a neighbourhood;
   joint_step    its Gauss-Newton step solved block-sparse, without the dense H (joint.py);
   detect        the double-threshold test of the residual matrix (detection.py :func:`detect`);
   own_system    one node's own position against its neighbours' broadcasts (rounds.py
                 :func:`normal_equations`: the round solves, the commit, the reported solve);
   own_meat      the sandwich "meat" of those links (rounds.py :func:`link_meat`);
   cho_solve     the two triangular solves after numpy's Cholesky factorisation (joint.py);
   spd_solve     a whole Cholesky solve of a small system (joint.py, up to ~60 unknowns);
   own_tdoa      the passive-listening links of own_system's solve (rounds.py :func:`normal_equations`);
   tdoa_res      their residuals and innovation variances (rounds.py :func:`tdoa_residuals`).

   joint_system:

   One Gauss-Newton iteration of the neighbourhood snapshot builds H (3n x 3n) and g (3n) from n
   Gaussian position priors, m range factors and M az/el factors (eq. 27). In numpy that takes ~40
   small array calls per iteration (~0.3 ms of call overhead at n = 18); here it is one loop over
   the factors. The models are those of swarmnav.models.uwb_range and .bearing:

     range  k: ends (ia, ib), z = d, h = |x_a - x_b|, u = (x_a - x_b)/max(h, 1e-9), weight a = w/σ²:
               B = a u uᵀ, v = a u (d - h)   -> H_aa += B, H_bb += B, H_ab -= B, H_ba -= B; g_a += v, g_b -= v
     az/el k: target t, observer o, δ = x_t - x_o = (e, n, u); J = ∂(az, el)/∂x_t (2 x 3),
               residual (wrap(z_az - az), z_el - el), weight c = w/σ²:
               B = c JᵀJ, v = c Jᵀ res          -> the same pattern on (t, o)
     prior i:  H_ii += Λ_i, g_i += Λ_i (μ_i - x_i)

   Units: m, rad. Inputs are C-contiguous, 8-byte aligned float64 (indices int64); the callers own
   the shapes; they are checked here anyway: a wrong dtype, size, alignment, an index out of range,
   a system too large to address, or an output that shares memory with another argument raises
   ValueError (never a read or write outside the buffers). No I/O; spd_solve, own_meat and joint_step
   allocate scratch (PyMem, freed on every path). */
#define PY_SSIZE_T_CLEAN
#include <Python.h>
#include <math.h>
#include <stdint.h>
#include <stdlib.h>
#include <string.h>

static double wrap_angle(double a) {
    /* numpy's wrap_angle: pi - mod(pi - a, 2 pi), mod with the sign of the divisor */
    double y = 2.0 * M_PI, x = M_PI - a;
    double m = fabs(x) < y ? x : fmod(x, y); /* fmod is exact: x itself when |x| < y (the usual case) */
    if (m != 0.0 && ((y < 0) != (m < 0))) m += y;
    return M_PI - m;
}

/* The models' shared pieces (swarmnav.models.uwb_range, .bearing), each in the one order of
   operations every kernel uses (so results do not depend on which kernel computed them). */

/* d (3,) -> its length h; u = d / max(h, 1e-9) */
static double unit_of(const double *d, double *u) {
    double h = sqrt(d[0] * d[0] + d[1] * d[1] + d[2] * d[2]);
    double hh = h > 1e-9 ? h : 1e-9;
    for (int q = 0; q < 3; q++) u[q] = d[q] / hh;
    return h;
}

/* acc + uᵀ P u, accumulated row by row (P 3 x 3 row-major) */
static double add_quad(double acc, const double *P, const double *u) {
    for (int q = 0; q < 3; q++) acc += u[q] * (P[3 * q] * u[0] + P[3 * q + 1] * u[1] + P[3 * q + 2] * u[2]);
    return acc;
}

/* az/el of δ = (e, n, u) (target − observer) and J = ∂(az, el)/∂target (2 x 3, row-major); *h_out the
   horizontal distance (floored at 1e-6 m) */
static void azel_jacobian(double e, double nn, double uu, double *J, double *h_out) {
    double h2 = e * e + nn * nn;
    if (h2 < 1e-12) h2 = 1e-12;
    double h = sqrt(h2), r2 = h2 + uu * uu, hr2 = h * r2;
    J[0] = -nn / h2; J[1] = e / h2; J[2] = 0.0;
    J[3] = -e * uu / hr2; J[4] = -nn * uu / hr2; J[5] = h / r2;
    *h_out = h;
}

/* The joint snapshot's range and az/el factors at x, one at a time: add(ctx, A, B, Bm, v) with the
   factor's 3 x 3 block Bm (symmetric) and gradient part v, to be added as H_AA += Bm, H_BB += Bm,
   H_AB -= Bm, H_BA -= Bm, g_A += v, g_B -= v (the models: see joint_system above). A factor between
   a node and itself (A == B) adds nothing (its four H terms and two g terms cancel) and is skipped
   here, for both kernels: added term by term, an az/el one (|J| ~ 1e6 at δ = 0) left the rounding of
   a ~1e16 block in the dense H (O(1) on H_AA), so joint_system and joint_step disagreed; add is
   never called with A == B. */
typedef void (*factor_add_t)(void *ctx, Py_ssize_t A, Py_ssize_t Bn, const double *Bm, const double *v);

static void joint_factors(const double *x, const long long *ia, const long long *ib, const double *d, const double *a,
                          Py_ssize_t m, const long long *obs, const long long *tgt, const double *z, const double *c,
                          Py_ssize_t M, factor_add_t add, void *ctx) {
    for (Py_ssize_t k = 0; k < m; k++) {
        Py_ssize_t ea = ia[k], eb = ib[k];
        if (ea == eb) continue;
        double dv[3] = {x[3 * ea] - x[3 * eb], x[3 * ea + 1] - x[3 * eb + 1], x[3 * ea + 2] - x[3 * eb + 2]};
        double u[3], B[9], v[3];
        double h = unit_of(dv, u);
        double res = d[k] - h;
        for (int p = 0; p < 3; p++) {
            double up = u[p] * a[k];
            v[p] = up * res;
            for (int s = 0; s < 3; s++) B[3 * p + s] = u[s] * up;
        }
        add(ctx, ea, eb, B, v);
    }
    for (Py_ssize_t k = 0; k < M; k++) {
        Py_ssize_t t = tgt[k], ob = obs[k];
        if (t == ob) continue;
        double e = x[3 * t] - x[3 * ob], nn = x[3 * t + 1] - x[3 * ob + 1], uu = x[3 * t + 2] - x[3 * ob + 2];
        double J[6], h;
        azel_jacobian(e, nn, uu, J, &h);
        double res0 = wrap_angle(z[2 * k] - atan2(nn, e)), res1 = z[2 * k + 1] - atan2(uu, h);
        double B[9], v[3], ck = c[k];
        for (int p = 0; p < 3; p++) {
            double j0 = J[p] * ck, j1 = J[3 + p] * ck;
            v[p] = j0 * res0 + j1 * res1;
            for (int s = 0; s < 3; s++) B[3 * p + s] = j0 * J[s] + j1 * J[3 + s];
        }
        add(ctx, t, ob, B, v);
    }
}

typedef struct { double *H, *g; Py_ssize_t N; } dense_t;

static void dense_add(void *vctx, Py_ssize_t A, Py_ssize_t Bn, const double *Bm, const double *v) {
    dense_t *ctx = vctx;
    double *H = ctx->H, *g = ctx->g;
    Py_ssize_t N = ctx->N;
    for (int p = 0; p < 3; p++) {
        g[3 * A + p] += v[p];
        g[3 * Bn + p] -= v[p];
        for (int s = 0; s < 3; s++) {
            double bb = Bm[3 * p + s];
            H[(3 * A + p) * N + 3 * A + s] += bb;
            H[(3 * Bn + p) * N + 3 * Bn + s] += bb;
            H[(3 * A + p) * N + 3 * Bn + s] -= bb;
            H[(3 * Bn + p) * N + 3 * A + s] -= bb;
        }
    }
}

typedef struct { Py_buffer b; int held; } buf_t;

static int get_buf(PyObject *o, buf_t *bt, const char *fmt, int writable, const char *name) {
    int flags = PyBUF_C_CONTIGUOUS | PyBUF_FORMAT | (writable ? PyBUF_WRITABLE : 0);
    bt->held = 0;
    if (PyObject_GetBuffer(o, &bt->b, flags) < 0) return -1;
    bt->held = 1;
    const char *f = bt->b.format ? bt->b.format : "B";
    if (f[0] == '<' || f[0] == '=' || f[0] == '@') f++;
    int ok = 0;
    if (fmt[0] == 'd') ok = (strcmp(f, "d") == 0);
    else ok = (strcmp(f, "q") == 0 || strcmp(f, "l") == 0) && bt->b.itemsize == 8;
    if (!ok) {
        PyErr_Format(PyExc_ValueError, "%s: expected %s", name, fmt[0] == 'd' ? "float64" : "int64");
        return -1;
    }
    if (((uintptr_t)bt->b.buf & 7) != 0) {
        PyErr_Format(PyExc_ValueError, "%s: not 8-byte aligned (pass a fresh array)", name);
        return -1;
    }
    return 0;
}

/* 1 if buffers i and j share any byte. */
static int overlap(const buf_t *b, int i, int j) {
    const char *a0 = b[i].b.buf, *b0 = b[j].b.buf;
    return b[i].b.len > 0 && b[j].b.len > 0 && a0 < b0 + b[j].b.len && b0 < a0 + b[i].b.len;
}

/* Systems up to this many unknowns (far beyond any neighbourhood: 3 per UAV) keep n*n*8 well inside
   Py_ssize_t; a larger one is refused before any size product is formed. */
#define MAX_UNKNOWNS ((Py_ssize_t)1 << 20)

/* Acquire the n buffers of a call's positional arguments (fmts[i]: 'd' float64, 'q' int64; the
   arguments from first_writable on are outputs). On failure the exception is set, every buffer
   acquired so far is released and -1 returned. */
static int get_bufs(PyObject *args, buf_t *b, int n, const char *fmts, const char **names, int first_writable,
                    const char *fn) {
    int i;
    for (i = 0; i < n; i++) b[i].held = 0;
    if (!PyTuple_Check(args) || PyTuple_GET_SIZE(args) != n) {
        PyErr_Format(PyExc_TypeError, "%s takes %d arrays", fn, n);
        return -1;
    }
    for (i = 0; i < n; i++) {
        const char f[2] = {fmts[i], 0};
        if (get_buf(PyTuple_GET_ITEM(args, i), &b[i], f, i >= first_writable, names[i]) < 0) {
            for (int j = 0; j <= i; j++)
                if (b[j].held) PyBuffer_Release(&b[j].b);
            return -1;
        }
    }
    /* an output must not share memory with any other argument: a kernel checks its inputs (e.g.
       indices) once, before it writes */
    for (i = first_writable; i < n; i++)
        for (int j = 0; j < n; j++)
            if (j != i && overlap(b, i, j)) {
                PyErr_Format(PyExc_ValueError, "%s: output %s shares memory with %s", fn, names[i], names[j]);
                for (int k = 0; k < n; k++)
                    if (b[k].held) PyBuffer_Release(&b[k].b);
                return -1;
            }
    return 0;
}

static void release_bufs(buf_t *b, int n) {
    for (int i = 0; i < n; i++)
        if (b[i].held) PyBuffer_Release(&b[i].b);
}

/* ia, ib (m each), obs, tgt (M each) copied into dst (2m + 2M), then checked there (every index a
   node of n): the indices are used from the copy, since another thread may write the caller's arrays
   meanwhile (a numpy call that releases the GIL) while the copy stays as checked. -1 with ValueError. */
static int copy_indices(long long *dst, const void *ia, const void *ib, Py_ssize_t m, const void *obs,
                        const void *tgt, Py_ssize_t M, Py_ssize_t n, const char *fn) {
    memcpy(dst, ia, (size_t)m * 8);
    memcpy(dst + m, ib, (size_t)m * 8);
    memcpy(dst + 2 * m, obs, (size_t)M * 8);
    memcpy(dst + 2 * m + M, tgt, (size_t)M * 8);
    for (Py_ssize_t k = 0; k < 2 * m + 2 * M; k++)
        if (dst[k] < 0 || dst[k] >= n) {
            PyErr_Format(PyExc_ValueError, "%s: %s end out of range", fn, k < 2 * m ? "range" : "az/el");
            return -1;
        }
    return 0;
}

/* The joint kernels' shared argument checks (x, prior_mean, prior_info, ia, ib, d, a, obs, tgt, z, c
   in b[0..10]): sizes consistent with n nodes, m ranges and M az/el rows, every index a node. */
static long long *joint_check(const buf_t *b, Py_ssize_t n, Py_ssize_t m, Py_ssize_t M, const char *fn) {
    if (3 * n > MAX_UNKNOWNS) {
        PyErr_Format(PyExc_ValueError, "%s: system too large", fn);
        return NULL;
    }
    if (b[0].b.len != n * 24 || b[1].b.len != n * 24 || b[2].b.len != n * 72 || b[4].b.len != m * 8 ||
        b[5].b.len != m * 8 || b[6].b.len != m * 8 || b[8].b.len != M * 8 || b[9].b.len != M * 16 ||
        b[10].b.len != M * 8) {
        PyErr_Format(PyExc_ValueError, "%s: inconsistent array sizes", fn);
        return NULL;
    }
    long long *idx = PyMem_Malloc((size_t)(2 * m + 2 * M + 1) * sizeof(long long));
    if (idx == NULL) {
        PyErr_NoMemory();
        return NULL;
    }
    if (copy_indices(idx, b[3].b.buf, b[4].b.buf, m, b[7].b.buf, b[8].b.buf, M, n, fn) < 0) {
        PyMem_Free(idx);
        return NULL;
    }
    return idx;
}

static PyObject *joint_system(PyObject *self, PyObject *args) {
    static const char *names[13] = {"x", "prior_mean", "prior_info", "ia", "ib", "d", "a", "obs", "tgt",
                                    "z", "c", "H", "g"};
    buf_t b[13];
    PyObject *ret = NULL;
    if (get_bufs(args, b, 13, "dddqqddqqdddd", names, 11, "joint_system") < 0) return NULL;
    Py_ssize_t n = b[0].b.len / (3 * 8), m = b[3].b.len / 8, M = b[7].b.len / 8, N = 3 * n;
    long long *idx = NULL;
    if (N > MAX_UNKNOWNS) { /* before N * N is formed */
        PyErr_SetString(PyExc_ValueError, "joint_system: system too large");
        goto done;
    }
    if (b[11].b.len != N * N * 8 || b[12].b.len != N * 8) {
        PyErr_SetString(PyExc_ValueError, "joint_system: inconsistent array sizes");
        goto done;
    }
    if ((idx = joint_check(b, n, m, M, "joint_system")) == NULL) goto done;
    const double *x = b[0].b.buf, *pm = b[1].b.buf, *pi = b[2].b.buf, *d = b[5].b.buf, *a = b[6].b.buf,
                 *z = b[9].b.buf, *c = b[10].b.buf;
    const long long *ia = idx, *ib = idx + m, *obs = idx + 2 * m, *tgt = idx + 2 * m + M;
    double *H = b[11].b.buf, *g = b[12].b.buf;
    memset(H, 0, (size_t)N * N * sizeof(double));
    for (Py_ssize_t q = 0; q < n; q++) {
        const double *L = pi + 9 * q;
        double r[3] = {pm[3 * q] - x[3 * q], pm[3 * q + 1] - x[3 * q + 1], pm[3 * q + 2] - x[3 * q + 2]};
        for (int p = 0; p < 3; p++) {
            g[3 * q + p] = L[3 * p] * r[0] + L[3 * p + 1] * r[1] + L[3 * p + 2] * r[2];
            for (int s = 0; s < 3; s++) H[(3 * q + p) * N + 3 * q + s] = L[3 * p + s];
        }
    }
    dense_t ctx = {H, g, N};
    joint_factors(x, ia, ib, d, a, m, obs, tgt, z, c, M, dense_add, &ctx);
    ret = Py_None;
    Py_INCREF(ret);
done:
    PyMem_Free(idx);
    release_bufs(b, 13);
    return ret;
}


/* own_system(p, pj, Pj, w, lev, sig2, z, pt, Pt, wt, st2, zt, H, g): add to H (3, 3) and g (3,) the
   range and az/el factors of one node's position p (3,) against its neighbours (rounds.py):
     range  k: δ = p + lev_k - pj_k, h = |δ|, u = δ/max(h, 1e-9), var = σ²_k + uᵀ Pj_k u (the
               neighbour's covariance along the line of sight), a = w_k/var:
               H += a u uᵀ, g += a u (z_k - h)
     az/el k: δ = pt_k - p, J = ∂(az, el)/∂pt (2 x 3) (∂/∂p = -J), C = J Pt_k Jᵀ + σ²_k I,
               Ci = w_k C⁻¹, res = (wrap(z_az - az), z_el - el): H += Jᵀ Ci J, g -= Jᵀ Ci res
   The caller initialises H and g (the prior's Λ and Λ(p_loc - p), or zeros). */
static PyObject *own_system(PyObject *self, PyObject *args) {
    static const char *names[14] = {"p", "pj", "Pj", "w", "lev", "sig2", "z", "pt", "Pt", "wt", "st2", "zt",
                                    "H", "g"};
    buf_t b[14];
    PyObject *ret = NULL;
    if (get_bufs(args, b, 14, "dddddddddddddd", names, 12, "own_system") < 0) return NULL;
    Py_ssize_t R = b[3].b.len / 8, A = b[9].b.len / 8;
    if (b[0].b.len != 24 || b[1].b.len != R * 24 || b[2].b.len != R * 72 || b[4].b.len != R * 24 ||
        b[5].b.len != R * 8 || b[6].b.len != R * 8 || b[7].b.len != A * 24 || b[8].b.len != A * 72 ||
        b[10].b.len != A * 8 || b[11].b.len != A * 16 || b[12].b.len != 72 || b[13].b.len != 24) {
        PyErr_SetString(PyExc_ValueError, "own_system: inconsistent array sizes");
        goto done;
    }
    const double *p = b[0].b.buf, *pj = b[1].b.buf, *Pj = b[2].b.buf, *w = b[3].b.buf, *lev = b[4].b.buf,
                 *sig2 = b[5].b.buf, *z = b[6].b.buf, *pt = b[7].b.buf, *Pt = b[8].b.buf, *wt = b[9].b.buf,
                 *st2 = b[10].b.buf, *zt = b[11].b.buf;
    double *H = b[12].b.buf, *g = b[13].b.buf;
    for (Py_ssize_t k = 0; k < R; k++) {
        double d[3], u[3];
        for (int q = 0; q < 3; q++) d[q] = p[q] + lev[3 * k + q] - pj[3 * k + q];
        double h = unit_of(d, u);
        double a = w[k] / add_quad(sig2[k], Pj + 9 * k, u), res = z[k] - h;
        for (int q = 0; q < 3; q++) {
            double ua = u[q] * a;
            g[q] += ua * res;
            for (int s = 0; s < 3; s++) H[3 * q + s] += ua * u[s];
        }
    }
    for (Py_ssize_t k = 0; k < A; k++) {
        double e = pt[3 * k] - p[0], nn = pt[3 * k + 1] - p[1], uu = pt[3 * k + 2] - p[2];
        double J[6], h;
        azel_jacobian(e, nn, uu, J, &h);
        const double *P = Pt + 9 * k;
        double JP[6];  /* J P (2 x 3) */
        for (int r = 0; r < 2; r++)
            for (int s = 0; s < 3; s++)
                JP[3 * r + s] = J[3 * r] * P[s] + J[3 * r + 1] * P[3 + s] + J[3 * r + 2] * P[6 + s];
        double c00 = JP[0] * J[0] + JP[1] * J[1] + JP[2] * J[2] + st2[k];
        double c01 = JP[0] * J[3] + JP[1] * J[4] + JP[2] * J[5];
        double c10 = JP[3] * J[0] + JP[4] * J[1] + JP[5] * J[2];
        double c11 = JP[3] * J[3] + JP[4] * J[4] + JP[5] * J[5] + st2[k];
        double det = c00 * c11 - c01 * c10;
        double i00 = wt[k] * c11 / det, i01 = -wt[k] * c01 / det, i10 = -wt[k] * c10 / det,
               i11 = wt[k] * c00 / det;
        double res0 = wrap_angle(zt[2 * k] - atan2(nn, e)), res1 = zt[2 * k + 1] - atan2(uu, h);
        double CJ[6];  /* Ci J (2 x 3) */
        for (int s = 0; s < 3; s++) {
            CJ[s] = i00 * J[s] + i01 * J[3 + s];
            CJ[3 + s] = i10 * J[s] + i11 * J[3 + s];
        }
        for (int q = 0; q < 3; q++) {
            g[q] -= CJ[q] * res0 + CJ[3 + q] * res1;
            for (int s = 0; s < 3; s++) H[3 * q + s] += J[q] * CJ[s] + J[3 + q] * CJ[3 + s];
        }
    }
    ret = Py_None;
    Py_INCREF(ret);
done:
    release_bufs(b, 14);
    return ret;
}

/* own_meat(p, pj, Pj, w, lev, sig2, Pj_true, group, pt, Pt, wt, st2, Pt_true, meat): add to meat (3, 3)
   the sandwich "meat" M = Σ Jᵀ W·R·W J of the range and az/el links of own_system (rounds.py
   link_meat), W the weights of the links as solved (neighbour covariances Pj / Pt), R their error
   covariances under the error model (Pj_true / Pt_true):
     range  k: u, var as in own_system, a = w_k/var;
               no groups (group empty):  M += a² (σ²_k + uᵀ Pj_true_k u) u uᵀ
               groups (group (R,) ids ≥ 0, rows of one neighbour share its position error):
                 M += Σ_k a² σ²_k u uᵀ + Σ_g G_g Pj_true_first(g) G_g,  G_g = Σ_{k in g} a u uᵀ,
                 groups in ascending id, first(g) its first row
     az/el k: J, C = J Pt_k Jᵀ + σ²_k I as in own_system, CiJ = w_k C⁻¹ J,
               M += CiJᵀ (J Pt_true_k Jᵀ + σ²_k I) CiJ */
static PyObject *own_meat(PyObject *self, PyObject *args) {
    static const char *names[14] = {"p", "pj", "Pj", "w", "lev", "sig2", "Pj_true", "group", "pt", "Pt", "wt",
                                    "st2", "Pt_true", "meat"};
    buf_t b[14];
    PyObject *ret = NULL;
    double *G = NULL;
    Py_ssize_t *first = NULL;
    if (get_bufs(args, b, 14, "dddddddqdddddd", names, 13, "own_meat") < 0) return NULL;
    Py_ssize_t R = b[3].b.len / 8, A = b[10].b.len / 8, NG = b[7].b.len / 8;
    if (b[0].b.len != 24 || b[1].b.len != R * 24 || b[2].b.len != R * 72 || b[4].b.len != R * 24 ||
        b[5].b.len != R * 8 || b[6].b.len != R * 72 || (NG != 0 && NG != R) || b[8].b.len != A * 24 ||
        b[9].b.len != A * 72 || b[11].b.len != A * 8 || b[12].b.len != A * 72 || b[13].b.len != 72) {
        PyErr_SetString(PyExc_ValueError, "own_meat: inconsistent array sizes");
        goto done;
    }
    const double *p = b[0].b.buf, *pj = b[1].b.buf, *Pj = b[2].b.buf, *w = b[3].b.buf, *lev = b[4].b.buf,
                 *sig2 = b[5].b.buf, *Pjt = b[6].b.buf, *pt = b[8].b.buf, *Pt = b[9].b.buf, *wt = b[10].b.buf,
                 *st2 = b[11].b.buf, *Ptt = b[12].b.buf;
    const long long *group = b[7].b.buf;
    double *M = b[13].b.buf;
    Py_ssize_t ng = 0;  /* number of group slots: max id + 1 */
    for (Py_ssize_t k = 0; k < NG; k++) {
        if (group[k] < 0 || group[k] >= MAX_UNKNOWNS) {
            PyErr_SetString(PyExc_ValueError, "own_meat: group id out of range");
            goto done;
        }
        if (group[k] + 1 > ng) ng = (Py_ssize_t)group[k] + 1;
    }
    if (NG) {
        G = PyMem_Calloc((size_t)ng * 9, sizeof(double));
        first = PyMem_Malloc((size_t)ng * sizeof(Py_ssize_t));
        if (G == NULL || first == NULL) {
            PyErr_NoMemory();
            goto done;
        }
        for (Py_ssize_t q = 0; q < ng; q++) first[q] = -1;
    }
    for (Py_ssize_t k = 0; k < R; k++) {
        double d[3], u[3];
        for (int q = 0; q < 3; q++) d[q] = p[q] + lev[3 * k + q] - pj[3 * k + q];
        unit_of(d, u);
        double a = w[k] / add_quad(sig2[k], Pj + 9 * k, u);
        double c = NG ? a * a * sig2[k] : a * a * add_quad(sig2[k], Pjt + 9 * k, u);
        for (int q = 0; q < 3; q++)
            for (int s2 = 0; s2 < 3; s2++) M[3 * q + s2] += c * u[q] * u[s2];
        if (NG) {
            Py_ssize_t gq = (Py_ssize_t)group[k];
            if (first[gq] < 0) first[gq] = k;
            double *Gg = G + 9 * gq;
            for (int q = 0; q < 3; q++)
                for (int s2 = 0; s2 < 3; s2++) Gg[3 * q + s2] += a * u[q] * u[s2];
        }
    }
    for (Py_ssize_t gq = 0; gq < ng; gq++) {  /* Σ_g G P G, in ascending group id */
        if (first[gq] < 0) continue;
        const double *Gg = G + 9 * gq, *P = Pjt + 9 * first[gq];
        double GP[9];
        for (int q = 0; q < 3; q++)
            for (int s2 = 0; s2 < 3; s2++)
                GP[3 * q + s2] = Gg[3 * q] * P[s2] + Gg[3 * q + 1] * P[3 + s2] + Gg[3 * q + 2] * P[6 + s2];
        for (int q = 0; q < 3; q++)
            for (int s2 = 0; s2 < 3; s2++)
                M[3 * q + s2] += GP[3 * q] * Gg[s2] + GP[3 * q + 1] * Gg[3 + s2] + GP[3 * q + 2] * Gg[6 + s2];
    }
    for (Py_ssize_t k = 0; k < A; k++) {
        double e = pt[3 * k] - p[0], nn = pt[3 * k + 1] - p[1], uu = pt[3 * k + 2] - p[2];
        double J[6], h;
        azel_jacobian(e, nn, uu, J, &h);
        double C[4], Ct[4];
        for (int which = 0; which < 2; which++) {  /* C = J P Jᵀ + σ² I with P = Pt (which 0), Pt_true (1) */
            const double *P = (which ? Ptt : Pt) + 9 * k;
            double JP[6];
            for (int r = 0; r < 2; r++)
                for (int s2 = 0; s2 < 3; s2++)
                    JP[3 * r + s2] = J[3 * r] * P[s2] + J[3 * r + 1] * P[3 + s2] + J[3 * r + 2] * P[6 + s2];
            double *out = which ? Ct : C;
            for (int r = 0; r < 2; r++)
                for (int c2 = 0; c2 < 2; c2++)
                    out[2 * r + c2] = JP[3 * r] * J[3 * c2] + JP[3 * r + 1] * J[3 * c2 + 1] + JP[3 * r + 2] * J[3 * c2 + 2];
            out[0] += st2[k];
            out[3] += st2[k];
        }
        double det = C[0] * C[3] - C[1] * C[2];
        double i00 = wt[k] * C[3] / det, i01 = -wt[k] * C[1] / det, i10 = -wt[k] * C[2] / det,
               i11 = wt[k] * C[0] / det;
        double CJ[6];  /* w C⁻¹ J (2 x 3) */
        for (int s2 = 0; s2 < 3; s2++) {
            CJ[s2] = i00 * J[s2] + i01 * J[3 + s2];
            CJ[3 + s2] = i10 * J[s2] + i11 * J[3 + s2];
        }
        double RC[6];  /* R_true CiJ (2 x 3) */
        for (int s2 = 0; s2 < 3; s2++) {
            RC[s2] = Ct[0] * CJ[s2] + Ct[1] * CJ[3 + s2];
            RC[3 + s2] = Ct[2] * CJ[s2] + Ct[3] * CJ[3 + s2];
        }
        for (int q = 0; q < 3; q++)
            for (int s2 = 0; s2 < 3; s2++) M[3 * q + s2] += CJ[q] * RC[s2] + CJ[3 + q] * RC[3 + s2];
    }
    ret = Py_None;
    Py_INCREF(ret);
done:
    PyMem_Free(G);
    PyMem_Free(first);
    release_bufs(b, 14);
    return ret;
}

/* x = (L Lᵀ)⁻¹ rhs for a lower-triangular L (n x n): forward, then back substitution (x may be rhs). */
static void triangular_solves(const double *L, Py_ssize_t n, const double *rhs, double *x) {
    for (Py_ssize_t i = 0; i < n; i++) {  /* L y = b */
        double s = rhs[i];
        for (Py_ssize_t k = 0; k < i; k++) s -= L[i * n + k] * x[k];
        x[i] = s / L[i * n + i];
    }
    for (Py_ssize_t i = n - 1; i >= 0; i--) {  /* Lᵀ x = y */
        double s = x[i];
        for (Py_ssize_t k = i + 1; k < n; k++) s -= L[k * n + i] * x[k];
        x[i] = s / L[i * n + i];
    }
}

/* cho_solve(L, b, x): x = (L Lᵀ)⁻¹ b for a lower-triangular Cholesky factor L (n x n, as
   numpy.linalg.cholesky returns it): forward, then back substitution (O(n²); the factorisation,
   O(n³), stays in LAPACK through numpy). */
static PyObject *cho_solve(PyObject *self, PyObject *args) {
    static const char *names[3] = {"L", "b", "x"};
    buf_t b[3];
    PyObject *ret = NULL;
    if (get_bufs(args, b, 3, "ddd", names, 2, "cho_solve") < 0) return NULL;
    Py_ssize_t n = b[1].b.len / 8;
    if (n > MAX_UNKNOWNS) {
        PyErr_SetString(PyExc_ValueError, "cho_solve: system too large");
        goto done;
    }
    if (b[0].b.len != n * n * 8 || b[2].b.len != n * 8) {
        PyErr_SetString(PyExc_ValueError, "cho_solve: inconsistent array sizes");
        goto done;
    }
    triangular_solves(b[0].b.buf, n, b[1].b.buf, b[2].b.buf);
    ret = Py_None;
    Py_INCREF(ret);
done:
    release_bufs(b, 3);
    return ret;
}

/* spd_solve(H, b, x) -> bool: x = H⁻¹ b by an unblocked Cholesky factorisation of the symmetric
   positive definite H (n x n; its lower triangle is read) and two triangular solves, for the
   small systems of the joint snapshot (up to ~60 unknowns it beats LAPACK through numpy, whose
   call overhead dominates there). False (x untouched) if H is not numerically positive definite. */
static PyObject *spd_solve(PyObject *self, PyObject *args) {
    static const char *names[3] = {"H", "b", "x"};
    buf_t b[3];
    PyObject *ret = NULL;
    if (get_bufs(args, b, 3, "ddd", names, 2, "spd_solve") < 0) return NULL;
    Py_ssize_t n = b[1].b.len / 8;
    if (n > MAX_UNKNOWNS) {
        PyErr_SetString(PyExc_ValueError, "spd_solve: system too large");
        goto done;
    }
    if (b[0].b.len != n * n * 8 || b[2].b.len != n * 8) {
        PyErr_SetString(PyExc_ValueError, "spd_solve: inconsistent array sizes");
        goto done;
    }
    const double *H = b[0].b.buf, *rhs = b[1].b.buf;
    double *x = b[2].b.buf;
    double *L = PyMem_Malloc((size_t)(n * n + n) * sizeof(double));
    if (L == NULL) {
        PyErr_NoMemory();
        goto done;
    }
    double *y = L + n * n;
    int ok = 1;
    for (Py_ssize_t j = 0; j < n && ok; j++) {  /* L Lᵀ = H, row-oriented (Cholesky–Banachiewicz) */
        for (Py_ssize_t i = j; i < n; i++) {
            double s = H[i * n + j];
            const double *Li = L + i * n, *Lj = L + j * n;
            for (Py_ssize_t k = 0; k < j; k++) s -= Li[k] * Lj[k];
            if (i == j) {
                if (!(s > 0.0) || !isfinite(s)) { ok = 0; break; }
                L[j * n + j] = sqrt(s);
            } else {
                L[i * n + j] = s / L[j * n + j];
            }
        }
    }
    if (ok) {
        triangular_solves(L, n, rhs, y);
        memcpy(x, y, (size_t)n * sizeof(double));
    }
    PyMem_Free(L);
    ret = PyBool_FromLong(ok);
done:
    release_bufs(b, 3);
    return ret;
}

/* joint_step(x, prior_mean, prior_info, ia, ib, d, a, obs, tgt, z, c, dx) -> bool: the joint
   snapshot's Gauss-Newton step dx (n, 3) = H⁻¹g of the system joint_system builds at x, solved by a
   block-sparse Cholesky factorisation that never forms the dense 3n x 3n H.

   A neighbourhood's system is sparse at the level of 3 x 3 node blocks: node i and j are coupled
   only by a range or an az/el observation between them (median on configs/scale.toml: 52 nodes, 13
   at most left coupled to a node when it is eliminated; ~12x fewer multiply-adds than a dense
   factorisation). Symbolic phase: the node coupling pattern from the factor lists, an elimination
   order by minimum degree (the node with the fewest uneliminated neighbours next, ties by index:
   deterministic), the fill it creates, one 3 x 3 slot per coupled node pair. Numeric phase: the
   blocks filled as joint_system fills H (same factor models, joint_factors), then a right-looking
   block Cholesky L Lᵀ = H in that order and the two block triangular solves. Exact: the same H⁻¹g
   as a dense solve up to rounding. False (dx untouched) if H is not numerically positive definite,
   if the step is not finite (a NaN or inf in g: x, μ, d, z) or if n > JOINT_STEP_MAX_NODES (its
   O(n²) bookkeeping: 9n² bytes of slot, R and nz tables, ~150 MB at the limit); the caller then
   takes the dense path (numpy's Cholesky of the dense H, LU where that fails). Cost: O(n²) for the
   tables and the minimum-degree search plus the fill; a fully coupled set (every pair ranged) is
   O(n³) like the dense factorisation but without BLAS (~1.4x the dense path's time at n = 100,
   ~2.2x at n = 200; equal at ~50). */
#define JOINT_STEP_MAX_NODES 4096

typedef struct {
    Py_ssize_t n;
    const int *slot; /* n*n: index of the pair's 3 x 3 block in pool (-1: uncoupled); (i, i): the diagonal */
    double *pool; /* blocks: the diagonal one full and symmetric; an off-diagonal pair {i, j} holds
                     the rows of max(i, j) and the columns of min(i, j) until one of them is
                     eliminated, then L_ik (rows i, columns k of the eliminated k) */
    double *g;    /* 3n right-hand side, then the forward solve's y */
} blocks_t;

static void sparse_add(void *vctx, Py_ssize_t A, Py_ssize_t Bn, const double *Bm, const double *v) {
    blocks_t *ctx = vctx;
    Py_ssize_t n = ctx->n;
    /* A != Bn (joint_factors skips a factor between a node and itself; here it would add +B) */
    double *DA = ctx->pool + 9 * (Py_ssize_t)ctx->slot[A * n + A], *DB = ctx->pool + 9 * (Py_ssize_t)ctx->slot[Bn * n + Bn];
    double *O = ctx->pool + 9 * (Py_ssize_t)ctx->slot[A * n + Bn];
    for (int p = 0; p < 3; p++) {
        ctx->g[3 * A + p] += v[p];
        ctx->g[3 * Bn + p] -= v[p];
        for (int s = 0; s < 3; s++) {
            double bb = Bm[3 * p + s];
            DA[3 * p + s] += bb;
            DB[3 * p + s] += bb;
            O[3 * p + s] -= bb; /* Bm symmetric: the same in either orientation */
        }
    }
}

/* 3 x 3 lower Cholesky factor of the symmetric D; 0 if not positive definite */
static int chol3(const double *D, double *L) {
    double l00 = D[0];
    if (!(l00 > 0.0) || !isfinite(l00)) return 0;
    l00 = sqrt(l00);
    double l10 = D[3] / l00, l20 = D[6] / l00;
    double l11 = D[4] - l10 * l10;
    if (!(l11 > 0.0) || !isfinite(l11)) return 0;
    l11 = sqrt(l11);
    double l21 = (D[7] - l20 * l10) / l11;
    double l22 = D[8] - l20 * l20 - l21 * l21;
    if (!(l22 > 0.0) || !isfinite(l22)) return 0;
    l22 = sqrt(l22);
    L[0] = l00; L[1] = 0.0; L[2] = 0.0;
    L[3] = l10; L[4] = l11; L[5] = 0.0;
    L[6] = l20; L[7] = l21; L[8] = l22;
    return 1;
}

/* y = L⁻¹ b and y = L⁻ᵀ b for a 3 x 3 lower triangular L (y may be b) */
static void lsolve3(const double *L, const double *b, double *y) {
    double y0 = b[0] / L[0];
    double y1 = (b[1] - L[3] * y0) / L[4];
    double y2 = (b[2] - L[6] * y0 - L[7] * y1) / L[8];
    y[0] = y0; y[1] = y1; y[2] = y2;
}

static void ltsolve3(const double *L, const double *b, double *y) {
    double y2 = b[2] / L[8];
    double y1 = (b[1] - L[7] * y2) / L[4];
    double y0 = (b[0] - L[3] * y1 - L[6] * y2) / L[0];
    y[0] = y0; y[1] = y1; y[2] = y2;
}

/* The symbolic phase: elimination order (order[n]), per eliminated node its uneliminated neighbours
   then (R, rstart[n + 1]) and a slot per coupled pair; returns the number of blocks. nz: n*n bytes. */
static Py_ssize_t joint_symbolic(Py_ssize_t n, const long long *ia, const long long *ib, Py_ssize_t m,
                                 const long long *obs, const long long *tgt, Py_ssize_t M, unsigned char *nz,
                                 int *deg, unsigned char *done, int *order, int *R, Py_ssize_t *rstart, int *slot) {
    memset(nz, 0, (size_t)(n * n));
    memset(deg, 0, (size_t)n * sizeof(int));
    memset(done, 0, (size_t)n);
    for (Py_ssize_t i = 0; i < n * n; i++) slot[i] = -1;
    Py_ssize_t nb = 0;
    for (Py_ssize_t i = 0; i < n; i++) slot[i * n + i] = (int)nb++;
    for (Py_ssize_t k = 0; k < m + M; k++) {
        Py_ssize_t A = k < m ? ia[k] : obs[k - m], B = k < m ? ib[k] : tgt[k - m];
        if (A == B || nz[A * n + B]) continue;
        nz[A * n + B] = nz[B * n + A] = 1;
        deg[A]++; deg[B]++;
        slot[A * n + B] = slot[B * n + A] = (int)nb++;
    }
    Py_ssize_t r = 0;
    for (Py_ssize_t s = 0; s < n; s++) {
        Py_ssize_t k = -1;
        for (Py_ssize_t i = 0; i < n; i++)
            if (!done[i] && (k < 0 || deg[i] < deg[k])) k = i;
        order[s] = (int)k;
        done[k] = 1;
        rstart[s] = r;
        for (Py_ssize_t i = 0; i < n; i++)
            if (!done[i] && nz[k * n + i]) R[r++] = (int)i;
        for (Py_ssize_t p = rstart[s]; p < r; p++) {
            Py_ssize_t i = R[p];
            deg[i]--; /* k leaves */
            for (Py_ssize_t q = rstart[s]; q < p; q++) {
                Py_ssize_t j = R[q];
                if (!nz[i * n + j]) { /* fill */
                    nz[i * n + j] = nz[j * n + i] = 1;
                    deg[i]++; deg[j]++;
                    slot[i * n + j] = slot[j * n + i] = (int)nb++;
                }
            }
        }
    }
    rstart[n] = r;
    return nb;
}

static int joint_numeric(Py_ssize_t n, const int *order, const int *R, const Py_ssize_t *rstart, const int *slot,
                         double *pool, double *g, double *dx) {
    double Lkk[9];
    for (Py_ssize_t s = 0; s < n; s++) {
        Py_ssize_t k = order[s];
        double *D = pool + 9 * (Py_ssize_t)slot[k * n + k];
        if (!chol3(D, Lkk)) return 0;
        memcpy(D, Lkk, sizeof Lkk);
        for (Py_ssize_t p = rstart[s]; p < rstart[s + 1]; p++) { /* L_ik = W_ik L_kk⁻ᵀ, rows i */
            Py_ssize_t i = R[p];
            double *O = pool + 9 * (Py_ssize_t)slot[i * n + k], W[9];
            for (int a = 0; a < 3; a++)
                for (int b2 = 0; b2 < 3; b2++) W[3 * a + b2] = i > k ? O[3 * a + b2] : O[3 * b2 + a];
            for (int a = 0; a < 3; a++) lsolve3(Lkk, W + 3 * a, O + 3 * a);
        }
        for (Py_ssize_t p = rstart[s]; p < rstart[s + 1]; p++) { /* W_ij -= L_ik L_jkᵀ, i >= j */
            Py_ssize_t i = R[p];
            double li[9], lj[9], u[9]; /* local copies: the blocks share the pool, so the compiler would reload */
            memcpy(li, pool + 9 * (Py_ssize_t)slot[i * n + k], sizeof li);
            const int *srow = slot + i * n;
            for (Py_ssize_t q = rstart[s]; q <= p; q++) { /* R ascending: j <= i */
                Py_ssize_t j = R[q];
                memcpy(lj, pool + 9 * (Py_ssize_t)slot[j * n + k], sizeof lj);
                for (int a = 0; a < 3; a++)
                    for (int b2 = 0; b2 < 3; b2++)
                        u[3 * a + b2] = li[3 * a] * lj[3 * b2] + li[3 * a + 1] * lj[3 * b2 + 1] + li[3 * a + 2] * lj[3 * b2 + 2];
                double *T = pool + 9 * (Py_ssize_t)srow[j];
                for (int e = 0; e < 9; e++) T[e] -= u[e];
            }
        }
        lsolve3(Lkk, g + 3 * k, g + 3 * k); /* forward: y_k, then b_i -= L_ik y_k */
        for (Py_ssize_t p = rstart[s]; p < rstart[s + 1]; p++) {
            Py_ssize_t i = R[p];
            const double *Li = pool + 9 * (Py_ssize_t)slot[i * n + k], *y = g + 3 * k;
            for (int a = 0; a < 3; a++) g[3 * i + a] -= Li[3 * a] * y[0] + Li[3 * a + 1] * y[1] + Li[3 * a + 2] * y[2];
        }
    }
    for (Py_ssize_t s = n - 1; s >= 0; s--) { /* back: x_k = L_kk⁻ᵀ (y_k - Σ L_ikᵀ x_i) */
        Py_ssize_t k = order[s];
        double t[3] = {g[3 * k], g[3 * k + 1], g[3 * k + 2]};
        for (Py_ssize_t p = rstart[s]; p < rstart[s + 1]; p++) {
            Py_ssize_t i = R[p];
            const double *Li = pool + 9 * (Py_ssize_t)slot[i * n + k], *xi = dx + 3 * i;
            for (int a = 0; a < 3; a++) t[a] -= Li[a] * xi[0] + Li[3 + a] * xi[1] + Li[6 + a] * xi[2];
        }
        ltsolve3(pool + 9 * (Py_ssize_t)slot[k * n + k], t, dx + 3 * k);
    }
    for (Py_ssize_t i = 0; i < 3 * n; i++)
        if (!isfinite(dx[i])) return 0;
    return 1;
}

/* A snapshot's symbolic phase, done once for all its joint_step calls (its ranged pairs and az/el rows
   stay; x, weights and values change): the checked index copies (ia, ib, obs, tgt), the elimination
   order and the block slots. One PyMem block: this header, then the arrays; freed with the capsule
   (joint_plan) or by joint_step (a call without a plan). */
typedef struct {
    Py_ssize_t n, m, M, nb;
    long long *idx;          /* 2m + 2M: ia, ib, obs, tgt */
    Py_ssize_t *rstart;      /* n + 1 */
    double *scratch;         /* the caller's doubles (joint_step without a plan: g, 3n) */
    int *slot, *R, *order, *deg; /* n*n, n*n, n, n */
    unsigned char *nz, *done; /* n*n, n: the symbolic phase's work space */
} plan_t;

#define PLAN_NAME "swarmnav._kernels.joint_plan"

/* Allocate a plan for n nodes, m ranges, M az/el rows and n_scratch doubles (n*n products are safe:
   3n <= MAX_UNKNOWNS is checked first); NULL with MemoryError set. */
static void *plan_alloc(Py_ssize_t n, Py_ssize_t m, Py_ssize_t M, Py_ssize_t n_scratch, plan_t **out) {
    size_t nn = (size_t)(n * n);
    size_t o_idx = (sizeof(plan_t) + 7) & ~(size_t)7;
    size_t o_rstart = o_idx + (size_t)(2 * m + 2 * M) * sizeof(long long);
    size_t o_scratch = o_rstart + (size_t)(n + 1) * sizeof(Py_ssize_t);
    size_t o_int = o_scratch + (size_t)n_scratch * sizeof(double);
    size_t o_bytes = o_int + (2 * nn + 2 * (size_t)n) * sizeof(int);
    char *mem = PyMem_Malloc(o_bytes + nn + (size_t)n + 1);
    if (mem == NULL) {
        PyErr_NoMemory();
        return NULL;
    }
    plan_t *p = (plan_t *)mem;
    p->n = n, p->m = m, p->M = M, p->nb = 0;
    p->idx = (long long *)(mem + o_idx);
    p->rstart = (Py_ssize_t *)(mem + o_rstart);
    p->scratch = (double *)(mem + o_scratch);
    p->slot = (int *)(mem + o_int), p->R = p->slot + nn, p->order = p->R + nn, p->deg = p->order + n;
    p->nz = (unsigned char *)(mem + o_bytes), p->done = p->nz + nn;
    *out = p;
    return mem;
}

/* The symbolic phase of p's nodes over the checked indices ia, ib (m), obs, tgt (M). */
static void joint_plan_fill(plan_t *p, const long long *ia, const long long *ib, const long long *obs,
                            const long long *tgt) {
    p->nb = joint_symbolic(p->n, ia, ib, p->m, obs, tgt, p->M, p->nz, p->deg, p->done, p->order, p->R, p->rstart,
                           p->slot);
}

static void plan_capsule_free(PyObject *cap) {
    PyMem_Free(PyCapsule_GetPointer(cap, PLAN_NAME));
}

static PyObject *joint_plan(PyObject *self, PyObject *args) {
    static const char *names[4] = {"ia", "ib", "obs", "tgt"};
    Py_ssize_t n;
    PyObject *rest;
    buf_t b[4];
    if (!PyTuple_Check(args) || PyTuple_GET_SIZE(args) != 5) {
        PyErr_SetString(PyExc_TypeError, "joint_plan takes n and 4 arrays");
        return NULL;
    }
    n = PyLong_AsSsize_t(PyTuple_GET_ITEM(args, 0));
    if (n == -1 && PyErr_Occurred()) return NULL;
    if (n < 1 || n > MAX_UNKNOWNS / 3) {
        PyErr_SetString(PyExc_ValueError, "joint_plan: n out of range");
        return NULL;
    }
    if ((rest = PyTuple_GetSlice(args, 1, 5)) == NULL) return NULL;
    int got = get_bufs(rest, b, 4, "qqqq", names, 4, "joint_plan");
    Py_DECREF(rest);
    if (got < 0) return NULL;
    PyObject *ret = NULL;
    Py_ssize_t m = b[0].b.len / 8, M = b[2].b.len / 8;
    if (b[1].b.len != m * 8 || b[3].b.len != M * 8) {
        PyErr_SetString(PyExc_ValueError, "joint_plan: inconsistent array sizes");
        goto done;
    }
    if (n > JOINT_STEP_MAX_NODES) { /* joint_step takes no plan there: the dense path */
        ret = Py_None;
        Py_INCREF(ret);
        goto done;
    }
    plan_t *p;
    void *mem = plan_alloc(n, m, M, 0, &p);
    if (mem == NULL) goto done;
    if (copy_indices(p->idx, b[0].b.buf, b[1].b.buf, m, b[2].b.buf, b[3].b.buf, M, n, "joint_plan") < 0) {
        PyMem_Free(mem);
        goto done;
    }
    joint_plan_fill(p, p->idx, p->idx + m, p->idx + 2 * m, p->idx + 2 * m + M);
    if ((ret = PyCapsule_New(mem, PLAN_NAME, plan_capsule_free)) == NULL) PyMem_Free(mem);
done:
    release_bufs(b, 4);
    return ret;
}

static PyObject *joint_step(PyObject *self, PyObject *args) {
    static const char *names[12] = {"x", "prior_mean", "prior_info", "ia", "ib", "d", "a", "obs", "tgt",
                                    "z", "c", "dx"};
    buf_t b[12];
    PyObject *ret = NULL, *arrays = args;
    void *mem = NULL;
    const plan_t *plan = NULL;
    if (PyTuple_Check(args) && PyTuple_GET_SIZE(args) == 13) { /* the 13th: a joint_plan of these factors */
        plan = PyCapsule_GetPointer(PyTuple_GET_ITEM(args, 12), PLAN_NAME);
        if (plan == NULL) return NULL;
        if ((arrays = PyTuple_GetSlice(args, 0, 12)) == NULL) return NULL;
    }
    int got = get_bufs(arrays, b, 12, "dddqqddqqddd", names, 11, "joint_step");
    if (arrays != args) Py_DECREF(arrays);
    if (got < 0) return NULL;
    Py_ssize_t n = b[0].b.len / (3 * 8), m = b[3].b.len / 8, M = b[7].b.len / 8;
    long long *idx = NULL;
    if (b[11].b.len != n * 24) {
        PyErr_SetString(PyExc_ValueError, "joint_step: inconsistent array sizes");
        goto done;
    }
    if ((idx = joint_check(b, n, m, M, "joint_step")) == NULL) goto done;
    if (plan != NULL && (plan->n != n || plan->m != m || plan->M != M ||
                         memcmp(plan->idx, idx, (size_t)(2 * m + 2 * M) * sizeof(long long)) != 0)) {
        PyErr_SetString(PyExc_ValueError, "joint_step: the plan is not of these factors");
        goto done;
    }
    if (n > JOINT_STEP_MAX_NODES) {
        ret = Py_False;
        Py_INCREF(ret);
        goto done;
    }
    const double *x = b[0].b.buf, *pm = b[1].b.buf, *pi = b[2].b.buf, *d = b[5].b.buf, *a = b[6].b.buf,
                 *z = b[9].b.buf, *c = b[10].b.buf;
    const long long *ia = idx, *ib = idx + m, *obs = idx + 2 * m, *tgt = idx + 2 * m + M;
    double *dx = b[11].b.buf;
    const int *slot, *R, *order;
    const Py_ssize_t *rstart;
    Py_ssize_t nb;
    double *g;
    if (plan != NULL) { /* the symbolic phase done once for the snapshot's steps */
        if ((mem = PyMem_Malloc((size_t)(3 * n + 1) * sizeof(double))) == NULL) {
            PyErr_NoMemory();
            goto done;
        }
        g = mem;
        slot = plan->slot, R = plan->R, order = plan->order, rstart = plan->rstart, nb = plan->nb;
    } else {
        plan_t *own = NULL;
        if ((mem = plan_alloc(n, m, M, 3 * n, &own)) == NULL) goto done;
        g = own->scratch;
        joint_plan_fill(own, ia, ib, obs, tgt);
        slot = own->slot, R = own->R, order = own->order, rstart = own->rstart, nb = own->nb;
    }
    double *pool = PyMem_Calloc((size_t)nb * 9 + 1, sizeof(double));
    if (pool == NULL) {
        PyErr_NoMemory();
        goto done;
    }
    for (Py_ssize_t q = 0; q < n; q++) { /* priors: H_qq = Λ_q, g_q = Λ_q (μ_q - x_q) */
        const double *L = pi + 9 * q;
        double r[3] = {pm[3 * q] - x[3 * q], pm[3 * q + 1] - x[3 * q + 1], pm[3 * q + 2] - x[3 * q + 2]};
        double *D = pool + 9 * (Py_ssize_t)slot[q * n + q];
        for (int p = 0; p < 3; p++) {
            g[3 * q + p] = L[3 * p] * r[0] + L[3 * p + 1] * r[1] + L[3 * p + 2] * r[2];
            for (int s = 0; s < 3; s++) D[3 * p + s] = L[3 * p + s];
        }
    }
    blocks_t ctx = {n, slot, pool, g};
    joint_factors(x, ia, ib, d, a, m, obs, tgt, z, c, M, sparse_add, &ctx);
    double *out = PyMem_Malloc((size_t)(3 * n + 1) * sizeof(double));
    int ok = out != NULL && joint_numeric(n, order, R, rstart, slot, pool, g, out);
    if (ok) memcpy(dx, out, (size_t)(3 * n) * sizeof(double));
    PyMem_Free(out);
    PyMem_Free(pool);
    if (out == NULL) {
        PyErr_NoMemory();
        goto done;
    }
    ret = PyBool_FromLong(ok);
done:
    PyMem_Free(mem);
    PyMem_Free(idx);
    release_bufs(b, 12);
    return ret;
}

/* detect(res, pool, delta_l, floor_factor, ceil_factor, cap_h1, cls, w) -> delta_h: the double-threshold
   test of detection.py (:func:`detect` with the "exact" 2-means backend) in one call, the same
   operations in the same order (bit-identical results; tests/test_detection.py): Δh from the
   2-means boundary of the sorted ``pool`` (every split of the sorted values; the first minimum),
   descended while above ceil_factor·Δl (ceil_factor ≤ 0: no ceiling) and clamped to
   [floor_factor·Δl, ceiling]; then per residual of ``res`` its class (H2 2, H1 1, H0 0) into cls
   (int64) and its eq. 24 weight, capped at (Δl/∂)² with cap_h1, into w. Every value finite (the
   caller checks). */
static int two_means(const double *x, Py_ssize_t n, double *c1, double *c2, double *b) {
    if (n < 2 || x[n - 1] - x[0] <= 1e-12) return 0;
    double s1 = 0.0, s2 = 0.0;
    for (Py_ssize_t i = 0; i < n; i++) {
        s1 += x[i];
        s2 += x[i] * x[i];
        c1[i] = s1;
        c2[i] = s2;
    }
    Py_ssize_t best_i = 0;
    double best = 0.0;
    for (Py_ssize_t s = 1; s < n; s++) {
        double lo1 = c1[s - 1], lo2 = c2[s - 1], ds = (double)s;
        double sse_lo = lo2 - lo1 * lo1 / ds;
        double hi1 = c1[n - 1] - lo1;
        double sse_hi = (c2[n - 1] - lo2) - hi1 * hi1 / ((double)n - ds);
        double v = sse_lo + sse_hi;
        /* np.argmin: the first minimum, or the first NaN if any (an overflowed sum: |x| > ~1e154) */
        if (s == 1 || v < best || (isnan(v) && !isnan(best))) {
            best = v;
            best_i = s - 1;
        }
    }
    *b = 0.5 * (x[best_i] + x[best_i + 1]);
    return 1;
}

static int cmp_double(const void *a, const void *b) {
    double x = *(const double *)a, y = *(const double *)b;
    return (x > y) - (x < y);
}

static PyObject *detect_kernel(PyObject *self, PyObject *args) {
    PyObject *res_o, *pool_o, *cls_o, *w_o;
    double dl, floor_factor, ceil_factor;
    int cap;
    if (!PyArg_ParseTuple(args, "OOdddpOO", &res_o, &pool_o, &dl, &floor_factor, &ceil_factor, &cap, &cls_o, &w_o))
        return NULL;
    static const char *names[4] = {"res", "pool", "cls", "w"};
    buf_t b[4];
    PyObject *tuple = PyTuple_Pack(4, res_o, pool_o, cls_o, w_o), *ret = NULL;
    if (tuple == NULL) return NULL;
    int got = get_bufs(tuple, b, 4, "ddqd", names, 2, "detect");
    Py_DECREF(tuple);
    if (got < 0) return NULL;
    Py_ssize_t m = b[0].b.len / 8, P = b[1].b.len / 8;
    double *x = NULL;
    if (b[2].b.len != m * 8 || b[3].b.len != m * 8) {
        PyErr_SetString(PyExc_ValueError, "detect: cls and w must have res's length");
        goto done;
    }
    for (int a = 0; a < 2; a++) { /* the caller routes non-finite values to numpy; NaN would also break qsort's order */
        const double *v = b[a].b.buf;
        for (Py_ssize_t k = 0; k < b[a].b.len / 8; k++)
            if (!isfinite(v[k])) {
                PyErr_Format(PyExc_ValueError, "detect: %s has a non-finite value (detection.detect_numpy handles them)",
                             names[a]);
                goto done;
            }
    }
    x = PyMem_Malloc((size_t)(3 * P + 1) * sizeof(double));
    if (x == NULL) {
        PyErr_NoMemory();
        goto done;
    }
    memcpy(x, b[1].b.buf, (size_t)P * sizeof(double));
    qsort(x, (size_t)P, sizeof(double), cmp_double);
    double *c1 = x + P, *c2 = x + 2 * P;
    double floor_ = floor_factor * dl, bnd;
    int found = two_means(x, P, c1, c2, &bnd);
    if (ceil_factor > 0.0) {
        double ceil_ = ceil_factor * dl;
        if (floor_ > ceil_) ceil_ = floor_;
        Py_ssize_t n = P;
        while (found && bnd > ceil_) {
            while (n > 0 && !(x[n - 1] <= bnd)) n--; /* x[x <= b]: a prefix of the sorted values */
            double nb;
            if (!two_means(x, n, c1, c2, &nb) || nb >= bnd) break;
            bnd = nb;
        }
        if (found && ceil_ < bnd) bnd = ceil_;
    }
    double dh = !found ? floor_ : (bnd < floor_ ? floor_ : bnd);
    const double *r0 = b[0].b.buf;
    long long *cls = b[2].b.buf;
    double *w = b[3].b.buf;
    for (Py_ssize_t k = 0; k < m; k++) {
        double r = fabs(r0[k]), wk;
        long long c = 2;
        if (r > dl) c = 1;
        if (r > dh) c = 0;
        if (dh <= dl) {
            wk = r >= dl ? 0.0 : 1.0;
        } else if (r >= dl && r < dh) {
            double t = (dh - r) / (dh - dl);
            wk = dl / r * (t * t);
        } else {
            wk = r >= dh ? 0.0 : 1.0;
        }
        if (cap && r > dl && wk > 0.0) {
            double q = dl / r;
            q = q * q;
            if (q < wk) wk = q;
        }
        if (c == 0) wk = 0.0;
        cls[k] = c;
        w[k] = wk;
    }
    ret = PyFloat_FromDouble(dh);
done:
    PyMem_Free(x);
    release_bufs(b, 4);
    return ret;
}

/* The passive-listening (tdoa) links of a node's own solve (rounds.py :func:`normal_equations` and
   :func:`tdoa_residuals`), in the order of operations of the numpy code they replace (models.tdoa
   tdoa_h; gᵀ C g as (gᵀC)·g, column by column), so the results are bit for bit those of numpy.
   Row k has three ends (listener, initiator, responder) of kind 0 "self" (the own tag: position =
   own origin + off), 1 "peer" (a neighbour's tag) or 2 "fixed" (an anchor: position = off). */

/* pow(var, 2.0) as Python/numpy compute var ** 2 (libm's pow; GCC would fold a direct call to var * var,
   which differs in the last bit for ~0.1 % of values) */
static double (*volatile pow_fn)(double, double) = pow;

/* gᵀ C g as numpy's g @ C @ g: v = gᵀ C column by column, then v · g */
static double quad_np(const double *g, const double *C) {
    double v[3];
    for (int s = 0; s < 3; s++) v[s] = g[0] * C[s] + g[1] * C[3 + s] + g[2] * C[6 + s];
    return v[0] * g[0] + v[1] * g[1] + v[2] * g[2];
}

/* models.tdoa.tdoa_h: h and the gradients (listener, initiator, responder) of the points x (3 x 3) */
static double tdoa_h3(const double *x, double *gr) {
    double dr[3], di[3];
    for (int q = 0; q < 3; q++) {
        dr[q] = x[6 + q] - x[q];
        di[q] = x[3 + q] - x[q];
    }
    double rr = sqrt(dr[0] * dr[0] + dr[1] * dr[1] + dr[2] * dr[2]);
    double ri = sqrt(di[0] * di[0] + di[1] * di[1] + di[2] * di[2]);
    double mr = rr > 1e-9 ? rr : 1e-9, mi = ri > 1e-9 ? ri : 1e-9;
    for (int q = 0; q < 3; q++) {
        double ur = dr[q] / mr, ui = di[q] / mi;
        gr[q] = ui - ur;
        gr[3 + q] = -ui;
        gr[6 + q] = ur;
    }
    return rr - ri;
}

/* own_tdoa(p, kind, pos, cov, w, z, sig2, cov_true, H, g, meat): add the tdoa rows to H (3, 3), g (3,)
   and, with cov_true (n, 3, 3, 3) non-empty, to meat (3, 3). Per row k (kinds (n, 3) int64; pos (n, 3, 3):
   the own tag's offset from p, the neighbour's tag position or the anchor's; cov (n, 3, 3, 3): the
   neighbour ends' covariances (ignored for the others); w, z, sig2 (n,)):
     j = Σ_self g_e, var = σ² + Σ_peer g_eᵀ C_e g_e, H += (w/var) j jᵀ, g += (w (z − h)/var) j,
     meat += (w² var_true / var²) j jᵀ with var_true from cov_true. */
static PyObject *own_tdoa(PyObject *self, PyObject *args) {
    static const char *names[11] = {"p", "kind", "pos", "cov", "w", "z", "sig2", "cov_true", "H", "g", "meat"};
    buf_t b[11];
    PyObject *ret = NULL;
    if (get_bufs(args, b, 11, "dqddddddddd", names, 8, "own_tdoa") < 0) return NULL;
    Py_ssize_t n = b[4].b.len / 8;
    int with_meat = b[10].b.len > 0;
    if (b[0].b.len != 24 || b[1].b.len != n * 24 || b[2].b.len != n * 72 || b[3].b.len != n * 216 ||
        b[5].b.len != n * 8 || b[6].b.len != n * 8 || b[8].b.len != 72 || b[9].b.len != 24 ||
        (with_meat ? (b[7].b.len != n * 216 || b[10].b.len != 72) : b[7].b.len != 0)) {
        PyErr_SetString(PyExc_ValueError, "own_tdoa: inconsistent array sizes");
        goto done;
    }
    const double *p = b[0].b.buf, *pos = b[2].b.buf, *cov = b[3].b.buf, *w = b[4].b.buf, *z = b[5].b.buf,
                 *sig2 = b[6].b.buf, *cov_t = b[7].b.buf;
    const long long *kind = b[1].b.buf;
    double *H = b[8].b.buf, *g = b[9].b.buf, *meat = b[10].b.buf;
    for (Py_ssize_t k = 0; k < n; k++) {
        double x[9], gr[9], j[3] = {0.0, 0.0, 0.0};
        long long kd[3];
        for (int e = 0; e < 3; e++) {
            kd[e] = kind[3 * k + e];
            for (int q = 0; q < 3; q++) x[3 * e + q] = kd[e] == 0 ? p[q] + pos[9 * k + 3 * e + q] : pos[9 * k + 3 * e + q];
        }
        double h = tdoa_h3(x, gr);
        double sp = 0.0, st = 0.0;
        for (int e = 0; e < 3; e++) {
            if (kd[e] == 0)
                for (int q = 0; q < 3; q++) j[q] += gr[3 * e + q];
            else if (kd[e] == 1) {
                sp += quad_np(gr + 3 * e, cov + 27 * k + 9 * e);
                if (with_meat) st += quad_np(gr + 3 * e, cov_t + 27 * k + 9 * e);
            }
        }
        double var = sig2[k] + sp;
        double a = w[k] / var, c = w[k] * (z[k] - h) / var;
        for (int q = 0; q < 3; q++) {
            for (int s = 0; s < 3; s++) H[3 * q + s] += a * (j[q] * j[s]);
            g[q] += c * j[q];
        }
        if (with_meat) {
            double m = w[k] * w[k] * (sig2[k] + st) / pow_fn(var, 2.0);
            for (int q = 0; q < 3; q++)
                for (int s = 0; s < 3; s++) meat[3 * q + s] += m * (j[q] * j[s]);
        }
    }
    ret = Py_None;
    Py_INCREF(ret);
done:
    release_bufs(b, 11);
    return ret;
}

/* tdoa_res(me, kind, idx, off, z, sig2, P, C, P_own, absres, var): per row k, |z − h| into absres and
   the innovation variance into var: σ² + Σ over the bodies of its ends (the own body, each neighbour
   by node index; anchors none) of gᵀ Cov g with g the summed gradients of the body's ends, Cov =
   P_own or C[idx] (C (N, 3, 3) empty: var = σ²). Positions: self me + off, peer P[idx] + off,
   fixed off. idx (n, 3) int64 < N = len(P) for peer ends. */
static PyObject *tdoa_res(PyObject *self, PyObject *args) {
    static const char *names[11] = {"me", "kind", "idx", "off", "z", "sig2", "P", "C", "P_own", "absres", "var"};
    buf_t b[11];
    PyObject *ret = NULL;
    long long *ki = NULL;
    if (get_bufs(args, b, 11, "dqqdddddddd", names, 9, "tdoa_res") < 0) return NULL;
    Py_ssize_t n = b[4].b.len / 8, N = b[6].b.len / 24;
    int with_cov = b[7].b.len > 0;
    if (b[0].b.len != 24 || b[1].b.len != n * 24 || b[2].b.len != n * 24 || b[3].b.len != n * 72 ||
        b[5].b.len != n * 8 || b[6].b.len != N * 24 || b[9].b.len != n * 8 || b[10].b.len != n * 8 ||
        (with_cov ? (b[7].b.len != N * 72 || b[8].b.len != 72) : b[8].b.len != 0)) {
        PyErr_SetString(PyExc_ValueError, "tdoa_res: inconsistent array sizes");
        goto done;
    }
    ki = PyMem_Malloc((size_t)(n > 0 ? n : 1) * 48);
    if (!ki) {
        PyErr_NoMemory();
        goto done;
    }
    memcpy(ki, b[1].b.buf, (size_t)n * 24);
    memcpy(ki + 3 * n, b[2].b.buf, (size_t)n * 24);
    for (Py_ssize_t k = 0; k < 3 * n; k++)
        if (ki[k] == 1 && (ki[3 * n + k] < 0 || ki[3 * n + k] >= N)) {
            PyErr_SetString(PyExc_ValueError, "tdoa_res: peer index out of range");
            goto done;
        }
    const double *me = b[0].b.buf, *off = b[3].b.buf, *z = b[4].b.buf, *sig2 = b[5].b.buf, *P = b[6].b.buf,
                 *C = b[7].b.buf, *Pown = b[8].b.buf;
    double *absres = b[9].b.buf, *var = b[10].b.buf;
    for (Py_ssize_t k = 0; k < n; k++) {
        double x[9], gr[9];
        const long long *kd = ki + 3 * k, *ix = ki + 3 * n + 3 * k;
        for (int e = 0; e < 3; e++)
            for (int q = 0; q < 3; q++) {
                double o = off[9 * k + 3 * e + q];
                x[3 * e + q] = kd[e] == 0 ? me[q] + o : (kd[e] == 1 ? P[3 * ix[e] + q] + o : o);
            }
        double h = tdoa_h3(x, gr);
        double v = sig2[k];
        if (with_cov) {
            /* bodies in order of first appearance: key -1 the own body, else the neighbour's node index */
            long long key[3];
            double bg[9];
            int nb = 0;
            for (int e = 0; e < 3; e++) {
                if (kd[e] != 0 && kd[e] != 1) continue;
                long long kk = kd[e] == 0 ? -1 : ix[e];
                int s = 0;
                while (s < nb && key[s] != kk) s++;
                if (s == nb) {
                    key[nb++] = kk;
                    for (int q = 0; q < 3; q++) bg[3 * s + q] = 0.0 + gr[3 * e + q];
                } else
                    for (int q = 0; q < 3; q++) bg[3 * s + q] += gr[3 * e + q];
            }
            double sum = 0.0;
            for (int s = 0; s < nb; s++) sum += quad_np(bg + 3 * s, key[s] < 0 ? Pown : C + 9 * key[s]);
            if (nb) v += sum;
        }
        absres[k] = fabs(z[k] - h);
        var[k] = v;
    }
    ret = Py_None;
    Py_INCREF(ret);
done:
    PyMem_Free(ki);
    release_bufs(b, 11);
    return ret;
}

static PyMethodDef methods[] = {
    {"own_tdoa", own_tdoa, METH_VARARGS,
     "own_tdoa(p, kind, pos, cov, w, z, sig2, cov_true, H, g, meat): add a node's tdoa links to H (3, 3), g (3,) "
     "and (cov_true, meat non-empty) the sandwich meat (rounds.py normal_equations). float64 / int64, C-contiguous."},
    {"tdoa_res", tdoa_res, METH_VARARGS,
     "tdoa_res(me, kind, idx, off, z, sig2, P, C, P_own, absres, var): |z - h| and innovation variance of a round "
     "cache's tdoa rows (rounds.py tdoa_residuals). float64 / int64, C-contiguous."},
    {"joint_system", joint_system, METH_VARARGS,
     "joint_system(x, prior_mean, prior_info, ia, ib, d, a, obs, tgt, z, c, H, g): fill H (3n, 3n) and g (3n,) "
     "of the joint snapshot's Gauss-Newton step at x (n, 3); a = range weight / sigma^2 (m,), c = az/el "
     "weight / sigma^2 (M,). float64 / int64, C-contiguous."},
    {"joint_step", joint_step, METH_VARARGS,
     "joint_step(x, prior_mean, prior_info, ia, ib, d, a, obs, tgt, z, c, dx[, plan]) -> bool: dx (n, 3) = H^-1 g of the "
     "joint snapshot's Gauss-Newton step at x by a block-sparse Cholesky (minimum-degree order); False (dx "
     "untouched) if H is not numerically positive definite, the step is not finite or n > 4096 nodes; plan: "
     "joint_plan of the same n and indices (ValueError if not). float64 / int64, C-contiguous."},
    {"joint_plan", joint_plan, METH_VARARGS,
     "joint_plan(n, ia, ib, obs, tgt) -> plan: the symbolic phase of joint_step (elimination order, fill) for "
     "these factors among n nodes, to pass as joint_step's 13th argument on every step of one snapshot; None "
     "above 4096 nodes (joint_step refuses those). int64, C-contiguous."},
    {"detect", detect_kernel, METH_VARARGS,
     "detect(res, pool, delta_l, floor_factor, ceil_factor, cap_h1, cls, w) -> delta_h: detection.detect's "
     "double-threshold test (exact 2-means on pool; ceil_factor <= 0: no ceiling), classes (int64) and eq. 24 "
     "weights of res into cls and w. float64, C-contiguous, finite (else ValueError)."},
    {"cho_solve", cho_solve, METH_VARARGS,
     "cho_solve(L, b, x): x = (L L^T)^-1 b, L lower triangular (n, n), b and x (n,). float64, C-contiguous."},
    {"spd_solve", spd_solve, METH_VARARGS,
     "spd_solve(H, b, x) -> bool: x = H^-1 b by Cholesky (H symmetric positive definite, lower triangle read); "
     "False if H is not numerically positive definite. float64, C-contiguous."},
    {"own_meat", own_meat, METH_VARARGS,
     "own_meat(p, pj, Pj, w, lev, sig2, Pj_true, group, pt, Pt, wt, st2, Pt_true, meat): add the sandwich meat of a node's links to meat (3, 3)"},
    {"own_system", own_system, METH_VARARGS,
     "own_system(p, pj, Pj, w, lev, sig2, z, pt, Pt, wt, st2, zt, H, g): add the range and az/el factors of "
     "one position p (3,) against its neighbours to H (3, 3) and g (3,). float64, C-contiguous."},
    {NULL, NULL, 0, NULL}};

static struct PyModuleDef module = {PyModuleDef_HEAD_INIT, "_kernels",
                                    "The cooperative solves' normal equations (joint.py, rounds.py).", -1, methods};

PyMODINIT_FUNC PyInit__kernels(void) { return PyModule_Create(&module); }
