/* The peer-state frame's checks and parse in C: the fast path of swarmnav.wire.frames.decode_state.
 *
 * A node of a 100-UAV swarm decodes ~100 peer states per epoch in its state pump thread; in Python
 * the checks alone took ~20 us of the ~35 us per state (about a fifth of the node's CPU). This
 * module does the same checks and returns the frame's values as Python objects, or None when ANY
 * check fails: the caller then runs the Python decoder, which names the error (WireError kind and
 * text). So this code decides only "valid or not", and tests/test_frames_c.py compares that
 * verdict and the values with the Python decoder on real and mutated frames.
 *
 * Frame layout (frames.py docstring): "SNS", version byte, int32 LE uav, k, r, uint32 LE n, m, w,
 * float64 LE [t, pos 3, cov 9, vel 3, delta_m, n_links, quat 4, ranges n, bearings 3m, window 3w],
 * int64 LE [range peer ids n, bearing target ids m, window epochs w]. Little-endian hosts only (a
 * big-endian host always gets None: the Python decoder). Built with -fno-fast-math
 * -ffp-contract=off, so every comparison and product is the IEEE double arithmetic Python does.
 */
#define PY_SSIZE_T_CLEAN
#include <Python.h>
#include <math.h>
#include <stdint.h>
#include <stdlib.h>
#include <string.h>

#define HDR 28 /* struct "<3sBiiiIII" */
#define NF 22  /* t, pos 3, cov 9, vel 3, delta_m, n_links, quat 4 */

#if defined(__BYTE_ORDER__) && __BYTE_ORDER__ == __ORDER_LITTLE_ENDIAN__
#define FRAMES_LITTLE 1
#else
#define FRAMES_LITTLE 0
#endif

static double f64(const unsigned char *p, int64_t i) {
    double v;
    memcpy(&v, p + 8 * i, 8);
    return v;
}

static long long i64(const unsigned char *p, int64_t i) {
    int64_t v;
    memcpy(&v, p + 8 * i, 8);
    return (long long)v;
}

static int cmp_ll(const void *a, const void *b) {
    long long x = *(const long long *)a, y = *(const long long *)b;
    return (x > y) - (x < y);
}

static double max3(double a, double b, double c) {
    double m = a > b ? a : b;
    return m > c ? m : c;
}

/* 1 when every check of frames.decode_state (before its scope check) passes, else 0. */
static int frame_ok(const unsigned char *fx, const unsigned char *ids, int32_t u, int32_t k, int32_t r, int64_t n,
                    int64_t m, int64_t w, double env, double vel_env, double max_var) {
    const int64_t nf = NF + n + 3 * m + 3 * w, o_b = NF + n, o_w = NF + n + 3 * m;
    if (u < 1 || k < 0 || r < 0)
        return 0;
    for (int64_t i = 0; i < nf; i++)  /* every value finite but delta_m (may be inf) and n_links */
        if (i != 16 && i != 17 && !isfinite(f64(fx, i)))
            return 0;
    /* codec.check_position_cov: inside the envelope, symmetric, variances plausible, Sylvester */
    if (max3(fabs(f64(fx, 1)), fabs(f64(fx, 2)), fabs(f64(fx, 3))) > env)
        return 0;
    const double a = f64(fx, 4), b = f64(fx, 5), c = f64(fx, 6), d = f64(fx, 7), e = f64(fx, 8), f = f64(fx, 9),
                 g = f64(fx, 10), h = f64(fx, 11), i = f64(fx, 12);
    double tol = max3(fabs(a), fabs(e), fabs(i));
    tol = 1e-9 * (tol > 1e-300 ? tol : 1e-300);
    if (fabs(b - d) > tol || fabs(c - g) > tol || fabs(f - h) > tol)
        return 0;
    if (max3(a, e, i) > max_var)
        return 0;
    const double det = a * (e * i - f * h) - b * (d * i - f * g) + c * (d * h - e * g);
    if (!(a > 0 && a * e - b * d > 0 && det > 0))
        return 0;
    if (max3(fabs(f64(fx, 13)), fabs(f64(fx, 14)), fabs(f64(fx, 15))) > vel_env)
        return 0;
    for (int64_t j = o_w; j < nf; j++)
        if (fabs(f64(fx, j)) > env)
            return 0;
    const double q0 = f64(fx, 18), q1 = f64(fx, 19), q2 = f64(fx, 20), q3 = f64(fx, 21);
    if ((q0 != 0 || q1 != 0 || q2 != 0 || q3 != 0) && fabs(sqrt(q0 * q0 + q1 * q1 + q2 * q2 + q3 * q3) - 1.0) > 1e-6)
        return 0;
    if (w) { /* window epochs: >= 0, <= k, distinct */
        long long *kids = malloc((size_t)w * sizeof(long long));
        if (kids == NULL)
            return 0; /* the Python decoder decides */
        for (int64_t j = 0; j < w; j++)
            kids[j] = i64(ids, n + m + j);
        qsort(kids, (size_t)w, sizeof(long long), cmp_ll);
        int ok = kids[0] >= 0 && kids[w - 1] <= k;
        for (int64_t j = 1; ok && j < w; j++)
            ok = kids[j] != kids[j - 1];
        free(kids);
        if (!ok)
            return 0;
    }
    const double delta = f64(fx, 16), links = f64(fx, 17);
    if (isnan(delta) || delta < 0)
        return 0;
    for (int64_t j = 0; j < n + m; j++)
        if (i64(ids, j) < 0)
            return 0;
    for (int64_t j = 0; j < n; j++)
        if (f64(fx, NF + j) < 0)
            return 0;
    if (!(links >= 0 && links <= 1e6 && links == floor(links)))
        return 0;
    for (int64_t j = 0; j < m; j++)
        if (!(fabs(f64(fx, o_b + 3 * j)) <= M_PI && fabs(f64(fx, o_b + 3 * j + 1)) <= M_PI / 2 &&
              f64(fx, o_b + 3 * j + 2) > 0))
            return 0;
    return 1;
}

static PyObject *floats(const unsigned char *fx, int64_t from, int64_t count) {
    PyObject *t = PyTuple_New((Py_ssize_t)count);
    if (t == NULL)
        return NULL;
    for (int64_t j = 0; j < count; j++) {
        PyObject *v = PyFloat_FromDouble(f64(fx, from + j));
        if (v == NULL) {
            Py_DECREF(t);
            return NULL;
        }
        PyTuple_SET_ITEM(t, (Py_ssize_t)j, v);
    }
    return t;
}

/* {id: value} (value = a float, or the tuple of `width` floats), in frame order: a repeated id
 * keeps its last value, as dict(zip(...)) does. */
static PyObject *by_id(const unsigned char *fx, int64_t from, const unsigned char *ids, int64_t id_from, int64_t count,
                       int width) {
    PyObject *dict = PyDict_New();
    if (dict == NULL)
        return NULL;
    for (int64_t j = 0; j < count; j++) {
        PyObject *key = PyLong_FromLongLong(i64(ids, id_from + j));
        PyObject *val = width == 1 ? PyFloat_FromDouble(f64(fx, from + j)) : floats(fx, from + width * j, width);
        if (key == NULL || val == NULL || PyDict_SetItem(dict, key, val) < 0) {
            Py_XDECREF(key);
            Py_XDECREF(val);
            Py_DECREF(dict);
            return NULL;
        }
        Py_DECREF(key);
        Py_DECREF(val);
    }
    return dict;
}

static PyObject *state_frame(PyObject *self, PyObject *args) {
    PyObject *payload;
    int version;
    double env, vel_env, max_var;
    if (!PyArg_ParseTuple(args, "Oiddd", &payload, &version, &env, &vel_env, &max_var))
        return NULL;
    if (!FRAMES_LITTLE || !PyBytes_CheckExact(payload))
        Py_RETURN_NONE;
    const unsigned char *buf = (const unsigned char *)PyBytes_AS_STRING(payload);
    const Py_ssize_t len = PyBytes_GET_SIZE(payload);
    if (len < HDR || memcmp(buf, "SNS", 3) != 0 || buf[3] != version)
        Py_RETURN_NONE;
    int32_t u, k, r;
    uint32_t n32, m32, w32;
    memcpy(&u, buf + 4, 4);
    memcpy(&k, buf + 8, 4);
    memcpy(&r, buf + 12, 4);
    memcpy(&n32, buf + 16, 4);
    memcpy(&m32, buf + 20, 4);
    memcpy(&w32, buf + 24, 4);
    const int64_t n = n32, m = m32, w = w32;
    const int64_t nf = NF + n + 3 * m + 3 * w;
    if ((int64_t)len != HDR + 8 * nf + 8 * (n + m + w))
        Py_RETURN_NONE;
    const unsigned char *fx = buf + HDR, *ids = buf + HDR + 8 * nf;
    if (!frame_ok(fx, ids, u, k, r, n, m, w, env, vel_env, max_var))
        Py_RETURN_NONE;
    const int64_t o_b = NF + n, o_w = NF + n + 3 * m;
    int ascending = 1; /* bearing targets in the encoder's order (by id, no repeats) */
    for (int64_t j = 1; j < m; j++)
        ascending = ascending && i64(ids, n + j - 1) < i64(ids, n + j);
    const int has_quat = f64(fx, 18) != 0 || f64(fx, 19) != 0 || f64(fx, 20) != 0 || f64(fx, 21) != 0;
    PyObject *kids = PyTuple_New((Py_ssize_t)w);
    if (kids == NULL)
        return NULL;
    for (int64_t j = 0; j < w; j++) {
        PyObject *v = PyLong_FromLongLong(i64(ids, n + m + j));
        if (v == NULL) {
            Py_DECREF(kids);
            return NULL;
        }
        PyTuple_SET_ITEM(kids, (Py_ssize_t)j, v);
    }
    PyObject *quat = has_quat ? floats(fx, 18, 4) : (Py_INCREF(Py_None), Py_None);
    /* N: the reference is handed over (Py_BuildValue releases every one if it fails, not on NULL
     * arguments: those are checked first) */
    PyObject *parts[8] = {floats(fx, 1, 3), floats(fx, 4, 9), floats(fx, 13, 3), quat,
                          by_id(fx, NF, ids, 0, n, 1), by_id(fx, o_b, ids, n, m, 3), kids, floats(fx, o_w, 3 * w)};
    for (int j = 0; j < 8; j++) {
        if (parts[j] == NULL) {
            for (int i = 0; i < 8; i++)
                Py_XDECREF(parts[i]);
            return NULL;
        }
    }
    return Py_BuildValue("(iiidNNNdLNNNNNN)", (int)u, (int)k, (int)r, f64(fx, 0), parts[0], parts[1], parts[2],
                         f64(fx, 16), (long long)f64(fx, 17), parts[3], parts[4], parts[5], parts[6], parts[7],
                         PyBool_FromLong(ascending));
}

static PyMethodDef methods[] = {
    {"state_frame", state_frame, METH_VARARGS,
     "state_frame(payload: bytes, version, envelope_m, velocity_envelope_m, max_var_m2) -> None (a check "
     "failed: decode in Python for the error) or (uav, k, r, t, pos (3), cov (9, row-major), vel (3), "
     "delta_m, n_links, quat (4) or None, {peer: range m}, {target: (az, el, sigma)}, window epochs, "
     "window positions (3w), bearing targets ascending)"},
    {NULL, NULL, 0, NULL}};

static struct PyModuleDef module = {PyModuleDef_HEAD_INIT, "_frames",
                                    "The peer-state frame's checks and parse (frames.decode_state's fast path).",
                                    -1, methods};

PyMODINIT_FUNC PyInit__frames(void) { return PyModule_Create(&module); }
