/* services.model._polyline: a route's closest-point projection in C.

   Why (issue 14, profile-driven): with 200 cars in the harness, each car's planner
   projects the other cars' future paths onto its own route many times a step
   (`Polyline.project_many`, about 12 000 calls in 20 simulated seconds, 80 us each),
   most of it numpy's overhead on a few points against a few dozen segments.

   Optional by design, as protocol/_speedups.c and services/rsu/_scan.c: setup builds it
   when a C compiler is there, and services/model/geometry.py falls back to its numpy
   code, which stays the reference: both give the same numbers, to the bit
   (tests/model/test_polyline_kernel.py), the same arithmetic in the same order, compiled
   with -ffp-contract=off. Returns None for any argument it does not expect (a wrong
   dtype or shape, a non-finite point); the caller then takes the numpy path.

   project_many(a, unit, seglen, cumlen, p) -> (s, lateral) | None

   a (S, 2): the start of every segment; unit (S, 2): their unit directions; seglen (S,)
   and cumlen (S + 1,): their lengths and the arc length at each vertex; p (M, 2): the
   points. */

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

static PyMethodDef methods[] = {
    {"project_many", project_many, METH_VARARGS, "Polyline.project_many in C."},
    {NULL, NULL, 0, NULL},
};

static struct PyModuleDef module = {
    PyModuleDef_HEAD_INIT, "services.model._polyline",
    "A route's closest-point projection in C (see services/model/geometry.py).", -1, methods,
};

PyMODINIT_FUNC PyInit__polyline(void) {
    import_array(); /* numpy's C API; on failure the import fails and numpy is used */
    return PyModule_Create(&module);
}
