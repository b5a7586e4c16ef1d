/* services.model._geometry: a route's closest-point projection and the bodies'
   overlap test in C.

   Why (issue 14, profile-driven): with 200 cars in the harness, each car's planner
   projects the other cars' future paths onto its own route many times a step
   (`Polyline.project_many`, about 12 000 calls in 20 simulated seconds, 80 us each),
   most of it numpy's overhead on a few points against a few dozen segments; and the
   RSU's slowest updates (its p99) test two swept bodies against each other
   (`any_rects_overlap`, thousands of footprint pairs by the separating axis theorem,
   about half a millisecond in numpy), where the first overlapping pair answers.

   Optional by design, as protocol/_speedups.c and services/rsu/_scan.c: setup builds it
   when a C compiler is there, and services/model/geometry.py falls back to its numpy
   code, which stays the reference: both give the same numbers, to the bit
   (tests/model/test_geometry_kernel.py), the same arithmetic in the same order, compiled
   with -ffp-contract=off. Returns None for any argument it does not expect (a wrong
   dtype or shape, a non-finite point); the caller then takes the numpy path.

   project_many(a, unit, seglen, cumlen, p) -> (s, lateral) | None

   a (S, 2): the start of every segment; unit (S, 2): their unit directions; seglen (S,)
   and cumlen (S + 1,): their lengths and the arc length at each vertex; p (M, 2): the
   points.

   any_quads_overlap(a, b) -> bool | None

   a (M, 4, 2) and b (K, 4, 2): footprints (convex quads); whether any of the M x K
   pairs overlaps by the separating axis theorem (touching overlaps), each pair's
   projections computed as geometry._quads_separated computes them. */

#define PY_SSIZE_T_CLEAN
#define NPY_NO_DEPRECATED_API NPY_1_7_API_VERSION
#include <Python.h>
#include <numpy/arrayobject.h>
#include <math.h>

typedef struct {
    const char *data;
    npy_intp s0, s1, n;
} view2;

/* `obj` as a view of an aligned, native float64 (N, 2) array */
static int as_view(PyObject *obj, view2 *v) {
    if (!PyArray_Check(obj)) {
        return 0;
    }
    PyArrayObject *a = (PyArrayObject *)obj;
    if (PyArray_TYPE(a) != NPY_DOUBLE || PyArray_NDIM(a) != 2 || PyArray_DIM(a, 1) != 2 ||
        !PyArray_ISNOTSWAPPED(a) || !PyArray_ISALIGNED(a)) {
        return 0;
    }
    v->data = (const char *)PyArray_DATA(a);
    v->s0 = PyArray_STRIDE(a, 0);
    v->s1 = PyArray_STRIDE(a, 1);
    v->n = PyArray_DIM(a, 0);
    return 1;
}

static inline double at(const view2 *v, npy_intp i, int c) {
    return *(const double *)(v->data + i * v->s0 + c * v->s1);
}

/* a 1-D, C-contiguous, aligned, native float64 array of exactly `n` items */
static const double *column(PyObject *obj, npy_intp n) {
    if (!PyArray_Check(obj)) {
        return NULL;
    }
    PyArrayObject *a = (PyArrayObject *)obj;
    if (PyArray_TYPE(a) != NPY_DOUBLE || PyArray_NDIM(a) != 1 || PyArray_DIM(a, 0) != n ||
        !PyArray_IS_C_CONTIGUOUS(a) || !PyArray_ISNOTSWAPPED(a) || !PyArray_ISALIGNED(a)) {
        return NULL;
    }
    return (const double *)PyArray_DATA(a);
}

static PyObject *project_many(PyObject *self, PyObject *args) {
    PyObject *a_o, *u_o, *len_o, *cum_o, *p_o;
    view2 a, u, p;
    if (!PyArg_ParseTuple(args, "OOOOO", &a_o, &u_o, &len_o, &cum_o, &p_o)) {
        return NULL;
    }
    if (!as_view(a_o, &a) || !as_view(u_o, &u) || !as_view(p_o, &p) || a.n < 1 ||
        u.n != a.n) {
        Py_RETURN_NONE;
    }
    npy_intp segs = a.n, m = p.n;
    const double *seglen = column(len_o, segs);
    const double *cumlen = column(cum_o, segs + 1);
    if (seglen == NULL || cumlen == NULL) {
        Py_RETURN_NONE;
    }
    for (npy_intp j = 0; j < m; j++) {
        if (!isfinite(at(&p, j, 0)) || !isfinite(at(&p, j, 1))) {
            Py_RETURN_NONE;
        }
    }
    npy_intp dims[1] = {m};
    PyObject *s_out = PyArray_SimpleNew(1, dims, NPY_DOUBLE);
    PyObject *l_out = PyArray_SimpleNew(1, dims, NPY_DOUBLE);
    if (s_out == NULL || l_out == NULL) {
        Py_XDECREF(s_out);
        Py_XDECREF(l_out);
        return NULL;
    }
    double *s = (double *)PyArray_DATA((PyArrayObject *)s_out);
    double *lateral = (double *)PyArray_DATA((PyArrayObject *)l_out);
    for (npy_intp j = 0; j < m; j++) {
        double px = at(&p, j, 0), py = at(&p, j, 1);
        double best = INFINITY, best_t = 0.0, best_r0 = 0.0, best_r1 = 0.0;
        npy_intp best_i = -1;
        for (npy_intp i = 0; i < segs; i++) {
            double r0 = px - at(&a, i, 0), r1 = py - at(&a, i, 1);
            double u0 = at(&u, i, 0), u1 = at(&u, i, 1);
            double t = r0 * u0 + r1 * u1;
            t = t > 0.0 ? t : 0.0;
            t = t < seglen[i] ? t : seglen[i];
            double d0 = r0 - t * u0, d1 = r1 - t * u1;
            double d2 = d0 * d0 + d1 * d1;
            if (best_i < 0 || d2 < best) {
                best = d2;
                best_i = i;
                best_t = t;
                best_r0 = r0;
                best_r1 = r1;
            }
        }
        s[j] = cumlen[best_i] + best_t;
        double cross = at(&u, best_i, 0) * best_r1 - at(&u, best_i, 1) * best_r0;
        lateral[j] = (cross >= 0.0 ? 1.0 : -1.0) * sqrt(best);
    }
    return Py_BuildValue("(NN)", s_out, l_out);
}

/* `obj` as an aligned, native float64 (N, 4, 2) array; its data and strides */
static int as_quads(PyObject *obj, const char **data, npy_intp st[3], npy_intp *n) {
    if (!PyArray_Check(obj)) {
        return 0;
    }
    PyArrayObject *a = (PyArrayObject *)obj;
    if (PyArray_TYPE(a) != NPY_DOUBLE || PyArray_NDIM(a) != 3 || PyArray_DIM(a, 1) != 4 ||
        PyArray_DIM(a, 2) != 2 || !PyArray_ISNOTSWAPPED(a) || !PyArray_ISALIGNED(a)) {
        return 0;
    }
    *data = (const char *)PyArray_DATA(a);
    for (int d = 0; d < 3; d++) {
        st[d] = PyArray_STRIDE(a, d);
    }
    *n = PyArray_DIM(a, 0);
    return 1;
}

static inline double q_at(const char *data, const npy_intp st[3], npy_intp p, int i, int k) {
    return *(const double *)(data + p * st[0] + i * st[1] + k * st[2]);
}

/* separated along one of the pair's eight edge normals (-e_y, e_x), e = next - this;
   the projections as numpy's einsum gives them: x * axis_x + y * axis_y */
static int quads_separated(const double qa[8], const double qb[8]) {
    for (int side = 0; side < 2; side++) {
        const double *q = side == 0 ? qa : qb;
        for (int e = 0; e < 4; e++) {
            int n = (e + 1) & 3;
            double ex = q[2 * n] - q[2 * e], ey = q[2 * n + 1] - q[2 * e + 1];
            double ax = -ey, ay = ex;
            double amin = INFINITY, amax = -INFINITY, bmin = INFINITY, bmax = -INFINITY;
            for (int v = 0; v < 4; v++) {
                double pa = qa[2 * v] * ax + qa[2 * v + 1] * ay;
                double pb = qb[2 * v] * ax + qb[2 * v + 1] * ay;
                amin = pa < amin ? pa : amin;
                amax = pa > amax ? pa : amax;
                bmin = pb < bmin ? pb : bmin;
                bmax = pb > bmax ? pb : bmax;
            }
            double lo = amin > bmin ? amin : bmin, hi = amax < bmax ? amax : bmax;
            if (lo > hi) {
                return 1;
            }
        }
    }
    return 0;
}

static PyObject *any_quads_overlap(PyObject *self, PyObject *args) {
    PyObject *a_o, *b_o;
    const char *ad, *bd;
    npy_intp ast[3], bst[3], m, k;
    if (!PyArg_ParseTuple(args, "OO", &a_o, &b_o)) {
        return NULL;
    }
    if (!as_quads(a_o, &ad, ast, &m) || !as_quads(b_o, &bd, bst, &k)) {
        Py_RETURN_NONE;
    }
    /* NaN corners make numpy's min and max NaN and no axis separate: numpy answers */
    for (npy_intp p = 0; p < m; p++) {
        for (int i = 0; i < 8; i++) {
            if (!isfinite(q_at(ad, ast, p, i >> 1, i & 1))) {
                Py_RETURN_NONE;
            }
        }
    }
    for (npy_intp p = 0; p < k; p++) {
        for (int i = 0; i < 8; i++) {
            if (!isfinite(q_at(bd, bst, p, i >> 1, i & 1))) {
                Py_RETURN_NONE;
            }
        }
    }
    double qa[8], qb[8];
    for (npy_intp i = 0; i < m; i++) {
        for (int c = 0; c < 8; c++) {
            qa[c] = q_at(ad, ast, i, c >> 1, c & 1);
        }
        for (npy_intp j = 0; j < k; j++) {
            for (int c = 0; c < 8; c++) {
                qb[c] = q_at(bd, bst, j, c >> 1, c & 1);
            }
            if (!quads_separated(qa, qb)) {
                Py_RETURN_TRUE;
            }
        }
    }
    Py_RETURN_FALSE;
}

static PyMethodDef methods[] = {
    {"project_many", project_many, METH_VARARGS, "Polyline.project_many in C."},
    {"any_quads_overlap", any_quads_overlap, METH_VARARGS, "any_rects_overlap in C."},
    {NULL, NULL, 0, NULL},
};

static struct PyModuleDef module = {
    PyModuleDef_HEAD_INIT, "services.model._geometry",
    "A route's projection and the bodies' overlap test in C (services/model/geometry.py).",
    -1, methods,
};

PyMODINIT_FUNC PyInit__geometry(void) {
    import_array(); /* numpy's C API; on failure the import fails and numpy is used */
    return PyModule_Create(&module);
}
