/* The joint snapshot's normal equations in C (joint.py :func:`solve`).

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

   Units: m, rad. Inputs are C-contiguous float64 (indices int64); the caller (joint.py) owns the
   shapes; they are checked here anyway, and a mismatch raises ValueError. No I/O, no allocation
   beyond the buffers' views. */
#define PY_SSIZE_T_CLEAN
#include <Python.h>
#include <math.h>
#include <string.h>

static double wrap_angle(double a) {
    /* numpy's wrap_angle: pi - mod(pi - a, 2 pi), mod with the sign of the divisor */
    double y = 2.0 * M_PI, x = M_PI - a;
    double m = fmod(x, y);
    if (m != 0.0 && ((y < 0) != (m < 0))) m += y;
    return M_PI - m;
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
    return 0;
}

static PyObject *joint_system(PyObject *self, PyObject *args) {
    PyObject *o[13];
    static const char *names[13] = {"x", "prior_mean", "prior_info", "ia", "ib", "d", "a", "obs", "tgt",
                                    "z", "c", "H", "g"};
    static const char *fmts[13] = {"d", "d", "d", "q", "q", "d", "d", "q", "q", "d", "d", "d", "d"};
    if (!PyArg_ParseTuple(args, "OOOOOOOOOOOOO", &o[0], &o[1], &o[2], &o[3], &o[4], &o[5], &o[6], &o[7],
                          &o[8], &o[9], &o[10], &o[11], &o[12]))
        return NULL;
    buf_t b[13];
    int i;
    PyObject *ret = NULL;
    for (i = 0; i < 13; i++) b[i].held = 0;
    for (i = 0; i < 13; i++)
        if (get_buf(o[i], &b[i], fmts[i], i >= 11, names[i]) < 0) goto done;
    Py_ssize_t n = b[0].b.len / (3 * 8), m = b[3].b.len / 8, M = b[7].b.len / 8, N = 3 * n;
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
        double h = sqrt(dv[0] * dv[0] + dv[1] * dv[1] + dv[2] * dv[2]);
        double hh = h > 1e-9 ? h : 1e-9;
        double u[3] = {dv[0] / hh, dv[1] / hh, dv[2] / hh}, B[9], v[3];
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
        double h2 = e * e + nn * nn;
        if (h2 < 1e-12) h2 = 1e-12;
        double h = sqrt(h2), r2 = h2 + uu * uu, hr2 = h * r2;
        double J[6] = {-nn / h2, e / h2, 0.0, -e * uu / hr2, -nn * uu / hr2, h / r2};
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
    for (i = 0; i < 13; i++)
        if (b[i].held) PyBuffer_Release(&b[i].b);
    return ret;
}

static PyMethodDef methods[] = {
    {"joint_system", joint_system, METH_VARARGS,
     "joint_system(x, prior_mean, prior_info, ia, ib, d, a, obs, tgt, z, c, H, g): fill H (3n, 3n) and g (3n,) "
     "of the joint snapshot's Gauss-Newton step at x (n, 3); a = range weight / sigma^2 (m,), c = az/el "
     "weight / sigma^2 (M,). float64 / int64, C-contiguous."},
    {NULL, NULL, 0, NULL}};

static struct PyModuleDef module = {PyModuleDef_HEAD_INIT, "_joint_kernel",
                                    "The joint snapshot's normal equations (joint.py).", -1, methods};

PyMODINIT_FUNC PyInit__joint_kernel(void) { return PyModule_Create(&module); }
