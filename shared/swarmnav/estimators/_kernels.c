/* The estimators' C kernels: the Gauss-Newton normal equations of the cooperative solves.

   joint_system  the joint snapshot's (joint.py :func:`solve`), every position of a neighbourhood;
   own_system    one node's own position against its neighbours' broadcasts (rounds.py
                 :func:`normal_equations`: the round solves, the commit, the reported solve);
   own_meat      the sandwich "meat" of those links (rounds.py :func:`link_meat`);
   cho_solve     the two triangular solves after numpy's Cholesky factorisation (joint.py);
   spd_solve     a whole Cholesky solve of a small system (joint.py, up to ~60 unknowns).

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
   ValueError (never a read or write outside the buffers). No I/O; spd_solve allocates its factor. */
#define PY_SSIZE_T_CLEAN
#include <Python.h>
#include <math.h>
#include <stdint.h>
#include <string.h>

static double wrap_angle(double a) {
    /* numpy's wrap_angle: pi - mod(pi - a, 2 pi), mod with the sign of the divisor */
    double y = 2.0 * M_PI, x = M_PI - a;
    double m = fmod(x, y);
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

static PyObject *joint_system(PyObject *self, PyObject *args) {
    static const char *names[13] = {"x", "prior_mean", "prior_info", "ia", "ib", "d", "a", "obs", "tgt",
                                    "z", "c", "H", "g"};
    buf_t b[13];
    PyObject *ret = NULL;
    if (get_bufs(args, b, 13, "dddqqddqqdddd", names, 11, "joint_system") < 0) return NULL;
    Py_ssize_t n = b[0].b.len / (3 * 8), m = b[3].b.len / 8, M = b[7].b.len / 8, N = 3 * n;
    if (N > MAX_UNKNOWNS) {
        PyErr_SetString(PyExc_ValueError, "joint_system: system too large");
        goto done;
    }
    if (b[0].b.len != n * 24 || b[1].b.len != n * 24 || b[2].b.len != n * 72 || b[4].b.len != m * 8 ||
        b[5].b.len != m * 8 || b[6].b.len != m * 8 || b[8].b.len != M * 8 || b[9].b.len != M * 16 ||
        b[10].b.len != M * 8 || b[11].b.len != N * N * 8 || b[12].b.len != N * 8) {
        PyErr_SetString(PyExc_ValueError, "joint_system: inconsistent array sizes");
        goto done;
    }
    const double *x = b[0].b.buf, *pm = b[1].b.buf, *pi = b[2].b.buf, *d = b[5].b.buf, *a = b[6].b.buf,
                 *z = b[9].b.buf, *c = b[10].b.buf;
    const long long *ia = b[3].b.buf, *ib = b[4].b.buf, *obs = b[7].b.buf, *tgt = b[8].b.buf;
    double *H = b[11].b.buf, *g = b[12].b.buf;
    for (Py_ssize_t k = 0; k < m; k++)
        if (ia[k] < 0 || ia[k] >= n || ib[k] < 0 || ib[k] >= n) {
            PyErr_SetString(PyExc_ValueError, "joint_system: range end out of range");
            goto done;
        }
    for (Py_ssize_t k = 0; k < M; k++)
        if (obs[k] < 0 || obs[k] >= n || tgt[k] < 0 || tgt[k] >= n) {
            PyErr_SetString(PyExc_ValueError, "joint_system: az/el end out of range");
            goto done;
        }
    memset(H, 0, (size_t)N * N * sizeof(double));
    for (Py_ssize_t q = 0; q < n; q++) {
        const double *L = pi + 9 * q;
        double r[3] = {pm[3 * q] - x[3 * q], pm[3 * q + 1] - x[3 * q + 1], pm[3 * q + 2] - x[3 * q + 2]};
        for (int p = 0; p < 3; p++) {
            g[3 * q + p] = L[3 * p] * r[0] + L[3 * p + 1] * r[1] + L[3 * p + 2] * r[2];
            for (int s = 0; s < 3; s++) H[(3 * q + p) * N + 3 * q + s] = L[3 * p + s];
        }
    }
#define ADD_FACTOR(A, Bn, Bm, v)                                                              \
    for (int p = 0; p < 3; p++) {                                                            \
        g[3 * (A) + p] += (v)[p];                                                            \
        g[3 * (Bn) + p] -= (v)[p];                                                           \
        for (int s = 0; s < 3; s++) {                                                        \
            double bb = (Bm)[3 * p + s];                                                     \
            H[(3 * (A) + p) * N + 3 * (A) + s] += bb;                                        \
            H[(3 * (Bn) + p) * N + 3 * (Bn) + s] += bb;                                      \
            H[(3 * (A) + p) * N + 3 * (Bn) + s] -= bb;                                       \
            H[(3 * (Bn) + p) * N + 3 * (A) + s] -= bb;                                       \
        }                                                                                    \
    }
    for (Py_ssize_t k = 0; k < m; k++) {
        Py_ssize_t ea = ia[k], eb = ib[k];
        double dv[3] = {x[3 * ea] - x[3 * eb], x[3 * ea + 1] - x[3 * eb + 1], x[3 * ea + 2] - x[3 * eb + 2]};
        double u[3], B[9], v[3];
        double h = unit_of(dv, u);
        double res = d[k] - h;
        for (int p = 0; p < 3; p++) {
            double up = u[p] * a[k];
            v[p] = up * res;
            for (int s = 0; s < 3; s++) B[3 * p + s] = u[s] * up;
        }
        ADD_FACTOR(ea, eb, B, v)
    }
    for (Py_ssize_t k = 0; k < M; k++) {
        Py_ssize_t t = tgt[k], ob = obs[k];
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
        ADD_FACTOR(t, ob, B, v)
    }
#undef ADD_FACTOR
    ret = Py_None;
    Py_INCREF(ret);
done:
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

static PyMethodDef methods[] = {
    {"joint_system", joint_system, METH_VARARGS,
     "joint_system(x, prior_mean, prior_info, ia, ib, d, a, obs, tgt, z, c, H, g): fill H (3n, 3n) and g (3n,) "
     "of the joint snapshot's Gauss-Newton step at x (n, 3); a = range weight / sigma^2 (m,), c = az/el "
     "weight / sigma^2 (M,). float64 / int64, C-contiguous."},
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
