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

/* `obj` as a view of an aligned, native float64 2-D array with `lo` to `hi` columns */
static int view_of(PyObject *obj, npy_intp lo, npy_intp hi, view2 *v) {
    if (!PyArray_Check(obj)) {
        return 0;
    }
    PyArrayObject *a = (PyArrayObject *)obj;
    if (PyArray_TYPE(a) != NPY_DOUBLE || PyArray_NDIM(a) != 2 || PyArray_DIM(a, 1) < lo ||
        PyArray_DIM(a, 1) > hi || !PyArray_ISNOTSWAPPED(a) || !PyArray_ISALIGNED(a)) {
        return 0;
    }
    v->data = (const char *)PyArray_DATA(a);
    v->s0 = PyArray_STRIDE(a, 0);
    v->s1 = PyArray_STRIDE(a, 1);
    v->n = PyArray_DIM(a, 0);
    return 1;
}

/* ... with exactly `cols` columns */
static int as_view(PyObject *obj, int cols, view2 *v) { return view_of(obj, cols, cols, v); }

/* ... with at least `cols` columns (a path's x, y and more) */
static int as_view_min(PyObject *obj, int cols, view2 *v) {
    return view_of(obj, cols, NPY_MAX_INTP, v);
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

/* -- the path projections (issue 14: after the query in C, paths.project_many and its
   prefilters were a quarter of an RSU update in a jam, numpy's per-call overhead on
   120-point paths) -------------------------------------------------------------------- */

#define SEG_EPS 1e-9 /* services/rsu/paths.py: _EPS */

static int all_finite(const view2 *v) {
    for (npy_intp i = 0; i < v->n; i++) {
        if (!isfinite(at(v, i, 0)) || !isfinite(at(v, i, 1))) {
            return 0;
        }
    }
    return 1;
}

/* segment_lengths(points) -> (N,) float64 | None: paths.segment_lengths */
static PyObject *segment_lengths(PyObject *self, PyObject *args) {
    PyObject *po;
    view2 p;
    if (!PyArg_ParseTuple(args, "O", &po)) {
        return NULL;
    }
    if (!as_view_min(po, 2, &p)) {
        Py_RETURN_NONE;
    }
    npy_intp dims[1] = {p.n};
    PyObject *out = PyArray_SimpleNew(1, dims, NPY_DOUBLE);
    if (out == NULL) {
        return NULL;
    }
    double *d = (double *)PyArray_DATA((PyArrayObject *)out);
    for (npy_intp i = 0; i < p.n; i++) {
        d[i] = i == 0 ? 0.0
                      : hypot(at(&p, i, 0) - at(&p, i - 1, 0), at(&p, i, 1) - at(&p, i - 1, 1));
    }
    return out;
}

/* farther_than(xy, x, y, reach) -> bool | None: paths.farther_than (None: an empty or
   non-finite polyline or point, which the numpy path answers) */
static PyObject *farther_than(PyObject *self, PyObject *args) {
    PyObject *po;
    double x, y, reach;
    view2 p;
    if (!PyArg_ParseTuple(args, "Oddd", &po, &x, &y, &reach)) {
        return NULL;
    }
    if (!as_view_min(po, 2, &p) || p.n < 1 || !isfinite(x) || !isfinite(y) ||
        !isfinite(reach) || !all_finite(&p)) {
        Py_RETURN_NONE;
    }
    double nearest = INFINITY, longest = 0.0;
    for (npy_intp i = 0; i < p.n; i++) {
        double px = at(&p, i, 0), py = at(&p, i, 1);
        double d = hypot(px - x, py - y);
        nearest = d < nearest ? d : nearest;
        if (i > 0) {
            double l = hypot(px - at(&p, i - 1, 0), py - at(&p, i - 1, 1));
            longest = l > longest ? l : longest;
        }
    }
    double half = 0.5 * longest;
    if (nearest - half > reach + 1e-6) {
        Py_RETURN_TRUE;
    }
    Py_RETURN_FALSE;
}

/* project_many(xy, q) -> (s, dist, index) | None: paths.project_many, the same
   arithmetic in the same order (None: an empty or non-finite polyline or query) */
static PyObject *project_many(PyObject *self, PyObject *args) {
    PyObject *po, *qo;
    view2 p, q;
    if (!PyArg_ParseTuple(args, "OO", &po, &qo)) {
        return NULL;
    }
    if (!as_view_min(po, 2, &p) || !as_view_min(qo, 2, &q) || p.n < 1 || !all_finite(&p) ||
        !all_finite(&q)) {
        Py_RETURN_NONE;
    }
    npy_intp k = q.n, segs = p.n - 1;
    npy_intp dims[1] = {k};
    PyObject *s_out = PyArray_SimpleNew(1, dims, NPY_DOUBLE);
    PyObject *d_out = PyArray_SimpleNew(1, dims, NPY_DOUBLE);
    PyObject *i_out = PyArray_SimpleNew(1, dims, NPY_INT64);
    double *seg = segs > 0 ? malloc(sizeof(double) * 5 * (size_t)segs) : NULL;
    if (s_out == NULL || d_out == NULL || i_out == NULL || (segs > 0 && seg == NULL)) {
        Py_XDECREF(s_out);
        Py_XDECREF(d_out);
        Py_XDECREF(i_out);
        free(seg);
        return PyErr_NoMemory();
    }
    double *s = (double *)PyArray_DATA((PyArrayObject *)s_out);
    double *dist = (double *)PyArray_DATA((PyArrayObject *)d_out);
    int64_t *index = (int64_t *)PyArray_DATA((PyArrayObject *)i_out);
    /* per segment: length, unit x, unit y, arc length at its start, moves (1/0) */
    int moves = 0;
    double start = 0.0;
    for (npy_intp i = 0; i < segs; i++) {
        double dx = at(&p, i + 1, 0) - at(&p, i, 0), dy = at(&p, i + 1, 1) - at(&p, i, 1);
        double len = hypot(dx, dy);
        double *g = seg + 5 * i;
        g[0] = len;
        g[4] = len > SEG_EPS ? 1.0 : 0.0;
        g[1] = g[4] != 0.0 ? dx / len : 0.0;
        g[2] = g[4] != 0.0 ? dy / len : 0.0;
        g[3] = start;
        start += len;
        moves |= g[4] != 0.0;
    }
    for (npy_intp j = 0; j < k; j++) {
        double qx = at(&q, j, 0), qy = at(&q, j, 1);
        if (!moves) {
            s[j] = 0.0;
            dist[j] = hypot(qx - at(&p, 0, 0), qy - at(&p, 0, 1));
            index[j] = 0;
            continue;
        }
        double best = INFINITY, best_along = 0.0;
        npy_intp best_i = -1;
        for (npy_intp i = 0; i < segs; i++) {
            const double *g = seg + 5 * i;
            if (g[4] == 0.0) {
                continue;
            }
            double px = at(&p, i, 0), py = at(&p, i, 1);
            double along = (qx - px) * g[1] + (qy - py) * g[2];
            along = along > 0.0 ? along : 0.0;
            along = along < g[0] ? along : g[0];
            double d = hypot(px + g[1] * along - qx, py + g[2] * along - qy);
            if (best_i < 0 || d < best) {
                best = d;
                best_i = i;
                best_along = along;
            }
        }
        s[j] = seg[5 * best_i + 3] + best_along;
        dist[j] = best;
        index[j] = best_i;
    }
    free(seg);
    return Py_BuildValue("(NNN)", s_out, d_out, i_out);
}

/* path_headings(points) -> (N, 2) float64 | None: reservation.path_headings */
static PyObject *path_headings(PyObject *self, PyObject *args) {
    PyObject *po;
    view2 p;
    if (!PyArg_ParseTuple(args, "O", &po)) {
        return NULL;
    }
    if (!as_view_min(po, 2, &p)) {
        Py_RETURN_NONE;
    }
    npy_intp n = p.n;
    npy_intp dims[2] = {n, 2};
    PyObject *out = PyArray_SimpleNew(2, dims, NPY_DOUBLE);
    if (out == NULL) {
        return NULL;
    }
    double *o = (double *)PyArray_DATA((PyArrayObject *)out);
    for (npy_intp i = 0; i < 2 * n; i++) {
        o[i] = NAN;
    }
    if (n < 2) {
        return out;
    }
    /* the unit of segment i (leaving point i) goes to row i; a segment that does not move
       takes the last moving one before it, or the first one when none is before it */
    npy_intp first = -1;
    double ux = NAN, uy = NAN;
    for (npy_intp i = 0; i < n - 1; i++) {
        double dx = at(&p, i + 1, 0) - at(&p, i, 0), dy = at(&p, i + 1, 1) - at(&p, i, 1);
        double len = hypot(dx, dy);
        if (len > 1e-6) {
            ux = dx / len;
            uy = dy / len;
            if (first < 0) {
                first = i;
                for (npy_intp j = 0; j < i; j++) {
                    o[2 * j] = ux;
                    o[2 * j + 1] = uy;
                }
            }
        }
        if (first >= 0) {
            o[2 * i] = ux;
            o[2 * i + 1] = uy;
        }
    }
    if (first < 0) {
        return out;
    }
    o[2 * (n - 1)] = o[2 * (n - 2)];
    o[2 * (n - 1) + 1] = o[2 * (n - 2) + 1];
    return out;
}

/* path_curvature(xy, s, base) -> (M,) float64 | None: paths.path_curvature, with
   `base` its CURVE_BASE_M (None: non-finite or unsorted arc lengths, or a shape it does
   not expect) */
static PyObject *path_curvature(PyObject *self, PyObject *args) {
    PyObject *po, *so;
    double base;
    view2 p;
    if (!PyArg_ParseTuple(args, "OOd", &po, &so, &base)) {
        return NULL;
    }
    if (!as_view_min(po, 2, &p) || !all_finite(&p) || !isfinite(base)) {
        Py_RETURN_NONE;
    }
    npy_intp n = p.n;
    const double *s = (const double *)column(so, NPY_DOUBLE, n, 0);
    if (s == NULL || PyArray_DIM((PyArrayObject *)so, 0) != n) {
        Py_RETURN_NONE;
    }
    for (npy_intp i = 0; i < n; i++) {
        if (!isfinite(s[i]) || (i > 0 && s[i] < s[i - 1])) {
            Py_RETURN_NONE;
        }
    }
    npy_intp dims[1] = {n};
    PyObject *out = PyArray_SimpleNew(1, dims, NPY_DOUBLE);
    double *kappa = n > 0 ? malloc(sizeof(double) * (size_t)n) : NULL;
    if (out == NULL || (n > 0 && kappa == NULL)) {
        Py_XDECREF(out);
        free(kappa);
        return PyErr_NoMemory();
    }
    double *spread = (double *)PyArray_DATA((PyArrayObject *)out);
    for (npy_intp i = 0; i < n; i++) {
        kappa[i] = 0.0;
        spread[i] = 0.0;
    }
    if (n < 3) {
        free(kappa);
        return out;
    }
    /* before: the last point with s <= s_i - base (searchsorted right, less one); after:
       the first with s >= s_i + base (searchsorted left); both move forward with i */
    npy_intp right = 0, left = 0;
    for (npy_intp i = 0; i < n; i++) {
        double lo = s[i] - base, hi = s[i] + base;
        while (right < n && s[right] <= lo) {
            right++;
        }
        while (left < n && s[left] < hi) {
            left++;
        }
        npy_intp before = right - 1, after = left;
        if (before < 0 || after >= n) {
            continue;
        }
        double px = at(&p, i, 0), py = at(&p, i, 1);
        double ax = at(&p, before, 0), ay = at(&p, before, 1);
        double bx = at(&p, after, 0), by = at(&p, after, 1);
        double u0 = px - ax, u1 = py - ay, w0 = bx - ax, w1 = by - ay;
        double cross2 = fabs(u0 * w1 - u1 * w0);
        double sides = hypot(u0, u1) * hypot(bx - px, by - py) * hypot(w0, w1);
        kappa[i] = sides > 0.0 ? 2.0 * cross2 / sides : 0.0;
    }
    /* the largest within 2 base of each point: a window over the sorted arc lengths */
    double reach = 2.0 * base;
    for (npy_intp i = 0; i < n; i++) {
        double m = 0.0;
        for (npy_intp j = i; j >= 0 && fabs(s[i] - s[j]) <= reach; j--) {
            m = kappa[j] > m ? kappa[j] : m;
        }
        for (npy_intp j = i + 1; j < n && fabs(s[i] - s[j]) <= reach; j++) {
            m = kappa[j] > m ? kappa[j] : m;
        }
        spread[i] = m;
    }
    free(kappa);
    return out;
}

/* convex_contains(xy, vertices, edges, tol) -> (M,) bool | None: paths.ConvexZone.contains
   (vertices and edges (K, 2), counter-clockwise; a point is in when every side test is at
   least -tol, NaN is not) */
static PyObject *convex_contains(PyObject *self, PyObject *args) {
    PyObject *po, *vo, *eo;
    double tol;
    view2 p, v, e;
    if (!PyArg_ParseTuple(args, "OOOd", &po, &vo, &eo, &tol)) {
        return NULL;
    }
    if (!as_view_min(po, 2, &p) || !as_view(vo, 2, &v) || !as_view(eo, 2, &e) || v.n != e.n) {
        Py_RETURN_NONE;
    }
    npy_intp dims[1] = {p.n};
    PyObject *out = PyArray_SimpleNew(1, dims, NPY_BOOL);
    if (out == NULL) {
        return NULL;
    }
    npy_bool *o = (npy_bool *)PyArray_DATA((PyArrayObject *)out);
    for (npy_intp i = 0; i < p.n; i++) {
        double x = at(&p, i, 0), y = at(&p, i, 1);
        npy_bool in = 1;
        for (npy_intp k = 0; k < v.n && in; k++) {
            double cross = at(&e, k, 0) * (y - at(&v, k, 1)) - at(&e, k, 1) * (x - at(&v, k, 0));
            in = cross >= -tol;
        }
        o[i] = in;
    }
    return out;
}

/* within_bounds(points, coord, t_max) -> bool | None: reservation.within_wire_bounds for
   an (N, 3) path: every value finite, |x| and |y| <= coord, |t| <= t_max */
static PyObject *within_bounds(PyObject *self, PyObject *args) {
    PyObject *po;
    double coord, t_max;
    view2 p;
    if (!PyArg_ParseTuple(args, "Odd", &po, &coord, &t_max)) {
        return NULL;
    }
    if (!as_view(po, 3, &p)) {
        Py_RETURN_NONE;
    }
    for (npy_intp i = 0; i < p.n; i++) {
        double x = at(&p, i, 0), y = at(&p, i, 1), t = at(&p, i, 2);
        if (!isfinite(x) || !isfinite(y) || !isfinite(t) || fabs(x) > coord ||
            fabs(y) > coord || fabs(t) > t_max) {
            Py_RETURN_FALSE;
        }
    }
    Py_RETURN_TRUE;
}

/* gap_over(points, max_dt) -> bool | None: whether two consecutive times of an (N, 3+)
   path are more than max_dt apart (reservation.densify's test: t[i+1] - t[i] > max_dt) */
static PyObject *gap_over(PyObject *self, PyObject *args) {
    PyObject *po;
    double max_dt;
    view2 p;
    if (!PyArg_ParseTuple(args, "Od", &po, &max_dt)) {
        return NULL;
    }
    if (!as_view_min(po, 3, &p)) {
        Py_RETURN_NONE;
    }
    for (npy_intp i = 0; i + 1 < p.n; i++) {
        if (at(&p, i + 1, 2) - at(&p, i, 2) > max_dt) {
            Py_RETURN_TRUE;
        }
    }
    Py_RETURN_FALSE;
}

static PyMethodDef methods[] = {
    {"scan", scan, METH_VARARGS, "Conflicts of a query with the table's blocks, per slot."},
    {"segment_lengths", segment_lengths, METH_VARARGS, "paths.segment_lengths in C."},
    {"farther_than", farther_than, METH_VARARGS, "paths.farther_than in C."},
    {"project_many", project_many, METH_VARARGS, "paths.project_many in C."},
    {"path_headings", path_headings, METH_VARARGS, "reservation.path_headings in C."},
    {"path_curvature", path_curvature, METH_VARARGS, "paths.path_curvature in C."},
    {"convex_contains", convex_contains, METH_VARARGS, "paths.ConvexZone.contains in C."},
    {"within_bounds", within_bounds, METH_VARARGS, "reservation.within_wire_bounds in C."},
    {"gap_over", gap_over, METH_VARARGS, "reservation.densify's gap test in C."},
    {NULL, NULL, 0, NULL},
};

static struct PyModuleDef module = {
    PyModuleDef_HEAD_INIT, "services.rsu._scan",
    "The reservation table's conflict query and the path projections in C (see services/rsu/reservation.py, paths.py).",
    -1,
    methods,
};

PyMODINIT_FUNC PyInit__scan(void) {
    import_array(); /* numpy's C API; on failure the import fails and numpy is used */
    return PyModule_Create(&module);
}
