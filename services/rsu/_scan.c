/* services.rsu._scan: the reservation table's conflict query, in one pass in C.

   Why (issue 14, profile-driven): at 200 cars at one intersection a query pairs its
   points with about 6 000 stored points (25 000 at p99), and the numpy version of the
   same work (`ReservationTable._batch` with `_near`) paid most of its time in the fancy
   indexing of those pairs across some forty numpy calls. Here the blocks of the index
   (services/rsu/reservation.py, module docstring) are walked once: each live block
   against the query's own time-cell groups by box distance, then each query point
   against the block's box and time cell, then each stored point of the block with the
   exact predicate. No pair list is built.

   Optional by design, as protocol/_speedups.c: setup builds it when a C compiler is
   there (`optional=True`), and reservation.py falls back to its numpy path, which stays
   the reference: both give the same conflicts, to the bit (tests/rsu/test_scan.py, and
   `naive_conflicts`). The arithmetic of the exact predicate is the numpy path's, in the
   same order, compiled with -ffp-contract=off (no fused multiply-add). The prefilters
   only ever admit more pairs than they must (the slack of the numpy search), so they
   change no answer. Returns None for any argument it does not expect; the caller then
   takes the numpy path.

   scan(q, hq, dense, head, live, b_slot, b_k, b_start, b_box, rows, npts,
        d_slot, f_slot, lat_slot, rad_d, rad_f, params,
        out_time, out_self, out_other, out_first) -> int | None

   q (K, 3) and hq (K, 2): the query's points in the window and their headings;
   dense, head: the table's per-slot lists (a slot's stored points sorted by time, and its
   stored headings or None); live (cap + 1,) bool; the block columns; npts (cap,) int32;
   per slot the crossing margin, the follow distance, the lane reach and the two search
   radii (float64, cap); params = (headway, window, now, end, cell, same_way_cos,
   band_slack); out_* (cap,): per slot the earliest max(t_q, t_o), t_q, t_o and the
   first query index of a conflicting pair (out_first -1: none; the caller fills them
   with +inf and -1). Returns how many slots conflict. */

#define PY_SSIZE_T_CLEAN
#define NPY_NO_DEPRECATED_API NPY_1_7_API_VERSION
#include <Python.h>
#include <numpy/arrayobject.h>
#include <math.h>
#include <stdint.h>
#include <stdlib.h>

/* Time cells (and the band in cells) beyond this are refused, so that no cast or
   difference of them can overflow: only an absurdly small headway gets there. */
#define CELL_LIMIT 4503599627370496.0 /* 2**52 */
#define CELL_LIMIT_I ((int64_t)1 << 52)

typedef struct {
    const char *data;
    npy_intp s0, s1, n;
} view2;

/* `obj` as a view of an aligned, native float64 2-D array with `cols` columns. */
static int as_view(PyObject *obj, int cols, view2 *v) {
    if (!PyArray_Check(obj)) {
        return 0;
    }
    PyArrayObject *a = (PyArrayObject *)obj;
    if (PyArray_TYPE(a) != NPY_DOUBLE || PyArray_NDIM(a) != 2 || PyArray_DIM(a, 1) != cols ||
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

/* a 1-D, C-contiguous, aligned, native array of `type` with at least `n` items */
static void *column(PyObject *obj, int type, npy_intp n, int writable) {
    if (!PyArray_Check(obj)) {
        return NULL;
    }
    PyArrayObject *a = (PyArrayObject *)obj;
    if (PyArray_TYPE(a) != type || PyArray_NDIM(a) != 1 || PyArray_DIM(a, 0) < n ||
        !PyArray_IS_C_CONTIGUOUS(a) || !PyArray_ISNOTSWAPPED(a) || !PyArray_ISALIGNED(a) ||
        (writable && !PyArray_ISWRITEABLE(a))) {
        return NULL;
    }
    return PyArray_DATA(a);
}

static inline double dmax(double a, double b) { return a > b ? a : b; }

static PyObject *scan(PyObject *self, PyObject *args) {
    PyObject *q_o, *hq_o, *dense, *head, *live_o, *slot_o, *k_o, *start_o, *box_o, *npts_o;
    PyObject *d_o, *f_o, *lat_o, *rd_o, *rf_o, *time_o, *self_o, *other_o, *first_o;
    Py_ssize_t rows;
    double headway, window, now, end, cell, same_way_cos, band_slack;
    if (!PyArg_ParseTuple(args, "OOO!O!OOOOOnOOOOOO(ddddddd)OOOO", &q_o, &hq_o, &PyList_Type,
                          &dense, &PyList_Type, &head, &live_o, &slot_o, &k_o, &start_o,
                          &box_o, &rows, &npts_o, &d_o, &f_o, &lat_o, &rd_o, &rf_o, &headway,
                          &window, &now, &end, &cell, &same_way_cos, &band_slack, &time_o,
                          &self_o, &other_o, &first_o)) {
        return NULL;
    }
    view2 q, hq;
    if (!as_view(q_o, 3, &q) || !as_view(hq_o, 2, &hq) || hq.n != q.n || rows < 0) {
        Py_RETURN_NONE;
    }
    npy_intp cap = PyList_GET_SIZE(dense);
    if (PyList_GET_SIZE(head) != cap) {
        Py_RETURN_NONE;
    }
    const npy_bool *live = column(live_o, NPY_BOOL, cap + 1, 0);
    const int32_t *b_slot = column(slot_o, NPY_INT32, rows, 0);
    const int64_t *b_k = column(k_o, NPY_INT64, rows, 0);
    const int32_t *b_start = column(start_o, NPY_INT32, rows, 0);
    const int32_t *npts = column(npts_o, NPY_INT32, cap, 0);
    const double *d_slot = column(d_o, NPY_DOUBLE, cap, 0);
    const double *f_slot = column(f_o, NPY_DOUBLE, cap, 0);
    const double *lat_slot = column(lat_o, NPY_DOUBLE, cap, 0);
    const double *rad_d = column(rd_o, NPY_DOUBLE, cap, 0);
    const double *rad_f = column(rf_o, NPY_DOUBLE, cap, 0);
    double *o_time = column(time_o, NPY_DOUBLE, cap, 1);
    double *o_self = column(self_o, NPY_DOUBLE, cap, 1);
    double *o_other = column(other_o, NPY_DOUBLE, cap, 1);
    int64_t *o_first = column(first_o, NPY_INT64, cap, 1);
    if (!live || !b_slot || !b_k || !b_start || !npts || !d_slot || !f_slot || !lat_slot ||
        !rad_d || !rad_f || !o_time || !o_self || !o_other || !o_first) {
        Py_RETURN_NONE;
    }
    if (!PyArray_Check(box_o)) {
        Py_RETURN_NONE;
    }
    PyArrayObject *box_a = (PyArrayObject *)box_o;
    if (PyArray_TYPE(box_a) != NPY_FLOAT32 || PyArray_NDIM(box_a) != 2 ||
        PyArray_DIM(box_a, 1) != 4 || PyArray_DIM(box_a, 0) < rows ||
        !PyArray_IS_C_CONTIGUOUS(box_a) || !PyArray_ISNOTSWAPPED(box_a) ||
        !PyArray_ISALIGNED(box_a)) {
        Py_RETURN_NONE;
    }
    const float *b_box = (const float *)PyArray_DATA(box_a);
    npy_intp K = q.n;
    if (K == 0 || rows == 0) {
        return PyLong_FromLong(0);
    }
    if (!(cell > 0.0)) {
        Py_RETURN_NONE;
    }
    /* the query's points grouped by time cell (consecutive points of one cell; a path
       out of time order only makes more groups), each group's bounding box */
    npy_intp *g_start = malloc(sizeof(npy_intp) * (size_t)(K + 1));
    int64_t *g_k = malloc(sizeof(int64_t) * (size_t)K);
    double *g_box = malloc(sizeof(double) * 4 * (size_t)K);
    if (!g_start || !g_k || !g_box) {
        free(g_start);
        free(g_k);
        free(g_box);
        return PyErr_NoMemory();
    }
    npy_intp groups = 0;
    for (npy_intp i = 0; i < K; i++) {
        double x = at(&q, i, 0), y = at(&q, i, 1);
        double kd = floor(at(&q, i, 2) / cell);
        if (!(fabs(kd) < CELL_LIMIT)) { /* an absurd headway: no int64 cast of this */
            free(g_start);
            free(g_k);
            free(g_box);
            Py_RETURN_NONE;
        }
        int64_t k = (int64_t)kd;
        if (groups == 0 || g_k[groups - 1] != k) {
            g_start[groups] = i;
            g_k[groups] = k;
            double *b = g_box + 4 * groups;
            b[0] = b[1] = x;
            b[2] = b[3] = y;
            groups++;
        } else {
            double *b = g_box + 4 * (groups - 1);
            b[0] = x < b[0] ? x : b[0];
            b[1] = x > b[1] ? x : b[1];
            b[2] = y < b[2] ? y : b[2];
            b[3] = y > b[3] ? y : b[3];
        }
    }
    g_start[groups] = K;
    double band = headway > window ? headway : window;
    double rtd = ceil(band / cell);
    if (!(rtd < CELL_LIMIT)) {
        free(g_start);
        free(g_k);
        free(g_box);
        Py_RETURN_NONE;
    }
    int64_t rt = rtd < 1.0 ? 1 : (int64_t)rtd;
    long found = 0;
    int failed = 0;
    for (Py_ssize_t r = 0; r < rows && !failed; r++) {
        int32_t s = b_slot[r];
        if (s < 0 || s >= cap || !live[s]) {
            continue;
        }
        npy_intp first_pt = b_start[r];
        npy_intp stop = (r + 1 < rows && b_slot[r + 1] == s) ? b_start[r + 1] : npts[s];
        if (first_pt < 0 || first_pt > npts[s]) {
            failed = 1; /* never from the table: refuse, the numpy path answers */
            break;
        }
        if (stop <= first_pt) {
            continue;
        }
        const float *bx = b_box + 4 * r;
        double x0 = bx[0], x1 = bx[1], y0 = bx[2], y1 = bx[3];
        int64_t bk = b_k[r];
        if (bk <= -CELL_LIMIT_I || bk >= CELL_LIMIT_I) {
            failed = 1; /* never with a sane headway: the numpy path answers */
            break;
        }
        double t0 = (double)bk * cell, t1 = t0 + cell;
        double rd = rad_d[s], rf = rad_f[s], rmax = rd > rf ? rd : rf;
        view2 o;
        int have_o = 0;
        view2 ho;
        int stored_head = 0;
        double d = d_slot[s], d2 = d * d, f = f_slot[s], f2 = f * f, lat = lat_slot[s];
        for (npy_intp g = 0; g < groups && !failed; g++) {
            if (g_k[g] < bk - rt || g_k[g] > bk + rt) {
                continue;
            }
            const double *gb = g_box + 4 * g;
            double gx = dmax(dmax(x0 - gb[1], gb[0] - x1), 0.0);
            double gy = dmax(dmax(y0 - gb[3], gb[2] - y1), 0.0);
            if (!(gx * gx + gy * gy <= rmax * rmax)) {
                continue;
            }
            for (npy_intp i = g_start[g]; i < g_start[g + 1]; i++) {
                double px = at(&q, i, 0), py = at(&q, i, 1), pt = at(&q, i, 2);
                gx = dmax(dmax(x0 - px, px - x1), 0.0);
                gy = dmax(dmax(y0 - py, py - y1), 0.0);
                double g2 = gx * gx + gy * gy;
                double gt = dmax(dmax(t0 - pt, pt - t1), 0.0);
                double slack = 1e-9 * (fabs(pt) + cell);
                int near_d = g2 <= rd * rd && gt < headway * band_slack + slack;
                int near_f = g2 <= rf * rf && gt < window * band_slack + slack;
                if (!near_d && !near_f) {
                    continue;
                }
                if (!have_o) {
                    PyObject *item = PyList_GET_ITEM(dense, s);
                    PyObject *h = PyList_GET_ITEM(head, s);
                    if (!as_view(item, 3, &o) || o.n < stop ||
                        (h != Py_None && (!as_view(h, 2, &ho) || ho.n < stop)) ||
                        (h == Py_None && o.n < 2)) {
                        failed = 1;
                        break;
                    }
                    stored_head = h != Py_None;
                    have_o = 1;
                }
                double hq0 = at(&hq, i, 0), hq1 = at(&hq, i, 1);
                for (npy_intp j = first_pt; j < stop; j++) {
                    double ot = at(&o, j, 2);
                    if (!(ot >= now && ot <= end)) {
                        continue;
                    }
                    double gap_t = fabs(pt - ot);
                    if (!(gap_t < headway) && !(gap_t < window)) {
                        continue;
                    }
                    double dx = px - at(&o, j, 0);
                    double dy = py - at(&o, j, 1);
                    double dist2 = dx * dx + dy * dy;
                    int hit = dist2 <= d2 && gap_t < headway;
                    if (!hit && dist2 <= f2 && gap_t < window) {
                        double ho0, ho1;
                        if (stored_head) {
                            ho0 = at(&ho, j, 0);
                            ho1 = at(&ho, j, 1);
                        } else {
                            npy_intp seg = j < o.n - 2 ? j : o.n - 2;
                            double sx = at(&o, seg + 1, 0) - at(&o, seg, 0);
                            double sy = at(&o, seg + 1, 1) - at(&o, seg, 1);
                            double len = hypot(sx, sy);
                            ho0 = sx / len;
                            ho1 = sy / len;
                        }
                        double cs = hq0 * ho0 + hq1 * ho1;
                        int q_still = isnan(hq0), o_still = isnan(ho0);
                        int same_way = cs >= same_way_cos || (q_still != o_still);
                        double side_q = fabs(hq0 * dy - hq1 * dx);
                        double side_o = fabs(ho0 * dy - ho1 * dx);
                        hit = same_way && (side_q <= lat || side_o <= lat);
                    }
                    if (hit) {
                        if (o_first[s] < 0) {
                            found++;
                            o_first[s] = i;
                        } else if (i < o_first[s]) {
                            o_first[s] = i;
                        }
                        double tm = pt > ot ? pt : ot;
                        o_time[s] = tm < o_time[s] ? tm : o_time[s];
                        o_self[s] = pt < o_self[s] ? pt : o_self[s];
                        o_other[s] = ot < o_other[s] ? ot : o_other[s];
                    }
                }
            }
        }
    }
    free(g_start);
    free(g_k);
    free(g_box);
    if (failed) {
        Py_RETURN_NONE;
    }
    return PyLong_FromLong(found);
}

static PyMethodDef methods[] = {
    {"scan", scan, METH_VARARGS, "Conflicts of a query with the table's blocks, per slot."},
    {NULL, NULL, 0, NULL},
};

static struct PyModuleDef module = {
    PyModuleDef_HEAD_INIT, "services.rsu._scan",
    "The reservation table's conflict query in C (see services/rsu/reservation.py).", -1,
    methods,
};

PyMODINIT_FUNC PyInit__scan(void) {
    import_array(); /* numpy's C API; on failure the import fails and numpy is used */
    return PyModule_Create(&module);
}
