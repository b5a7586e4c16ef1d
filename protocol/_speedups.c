/* protocol._speedups: the point columns of a vehicle path, packed and unpacked in C.

   Why: a future path is encoded by every car and decoded by the RSU and every other car
   ten times a second, and the numpy version of the same work (protocol/codec.py, `_points`
   and `_decode_vehicle_path_fast`) pays about 0.3-0.9 µs per numpy call over a dozen calls
   each way: 20-23 µs for one encode + decode of a 120-point path against issue 14's 8 µs.
   Here each direction is one pass over at most MAX_POINTS rows (aioquic keeps its packet
   buffer in C, `_buffer.c`, for the same reason).

   Optional by design: setup builds it when a C compiler is there (`optional=True`), and
   protocol/codec.py falls back to its numpy path, which stays the reference: both give the
   same bytes and bit-identical arrays (tests/protocol/test_fast_points.py). Neither
   function raises for bad input: each returns None, and the caller takes the general
   Python path, which refuses with its own explanation (DecodeError / EncodeError).

   Wire layout (protocol/SPEC.md 2.4): first point as three int32 (x [cm], y [cm],
   t [ms after the header's ms]), then for each column whose width code is not 0 the n-1
   deltas, column after column, little-endian: x and y int8 (code 1) or int16 (code 2),
   t uint8 or uint16. Rounding is round-half-even (as numpy's `rint`), every
   sum is of whole numbers far below 2**53, so results are exact and equal to numpy's. */

#define PY_SSIZE_T_CLEAN
#define NPY_NO_DEPRECATED_API NPY_1_7_API_VERSION
#include <Python.h>
#include <numpy/arrayobject.h>
#include <math.h>
#include <stdint.h>
#include <string.h>

#define MAX_POINTS 1024      /* far above any kind's max_points (216): bounds the stack */

static const double SCALE[3] = {100.0, 100.0, 1000.0}; /* m, m, s -> cm, cm, ms */

/* Round half to even, as numpy's rint, without a libm call per value (nearbyint costs
   4-5 ns here, saving and restoring the floating-point environment): below 2**51 in
   magnitude, adding and subtracting 1.5 * 2**52 leaves the nearest integer, ties to even,
   exactly (IEEE binary64, default rounding; no -ffast-math, which would fold it away). */
static double round_even(double v) {
    if (fabs(v) < 2251799813685248.0) {
        return (v + 6755399441055744.0) - 6755399441055744.0;
    }
    return rint(v); /* huge, infinite or NaN: rint keeps it so */
}

static void put_le16(unsigned char *p, int v) {
    p[0] = (unsigned char)(v & 0xFF);
    p[1] = (unsigned char)((v >> 8) & 0xFF);
}

static void put_le32(unsigned char *p, int32_t v) {
    uint32_t u = (uint32_t)v;
    p[0] = (unsigned char)(u & 0xFF);
    p[1] = (unsigned char)((u >> 8) & 0xFF);
    p[2] = (unsigned char)((u >> 16) & 0xFF);
    p[3] = (unsigned char)((u >> 24) & 0xFF);
}

static int32_t get_le32(const unsigned char *p) {
    uint32_t u = (uint32_t)p[0] | ((uint32_t)p[1] << 8) | ((uint32_t)p[2] << 16) |
                 ((uint32_t)p[3] << 24);
    return (int32_t)u;
}

/* pack(points, t_base_ms, max_coord_cm) -> (widths, bytes) | None

   points: C-contiguous float64 buffer of n rows (x [m], y [m], t [s]), 2 <= n <= 1024;
   t_base_ms: the header time in whole ms (time_us // 1000). None when anything is outside
   what the wire carries (NaN, infinity, a first point out of range, a delta too wide, time
   going back): the caller's checked path then explains the refusal. */
static PyObject *pack_points(PyObject *obj, long long t_base_ms, double max_coord,
                             int *widths) {
    if (!PyArray_Check(obj)) {
        Py_RETURN_NONE;
    }
    PyArrayObject *arr = (PyArrayObject *)obj;
    if (PyArray_TYPE(arr) != NPY_DOUBLE || PyArray_NDIM(arr) != 2 ||
        PyArray_DIM(arr, 1) != 3 || !PyArray_IS_C_CONTIGUOUS(arr) || !PyArray_ISNOTSWAPPED(arr) ||
        !PyArray_ISALIGNED(arr)) {
        Py_RETURN_NONE; /* the numpy path handles every other array */
    }
    npy_intp n = PyArray_DIM(arr, 0);
    if (n < 2 || n > MAX_POINTS) {
        Py_RETURN_NONE;
    }
    const double *p = (const double *)PyArray_DATA(arr);
    /* one pass: quantise each value, difference it with the one before (both whole
       numbers, so the difference is exact, as numpy's), bound it, keep it as an int */
    double prev[3];
    for (int c = 0; c < 3; c++) {
        prev[c] = round_even(p[c] * SCALE[c]);
    }
    double x0 = prev[0], y0 = prev[1], t0 = prev[2] - (double)t_base_ms;
    if (!(-max_coord <= x0 && x0 <= max_coord && -max_coord <= y0 && y0 <= max_coord &&
          -2147483648.0 <= t0 && t0 <= 2147483647.0)) {
        Py_RETURN_NONE; /* NaN fails here too */
    }
    int32_t deltas[3][MAX_POINTS];
    int32_t lo[3] = {0, 0, 0}, hi[3] = {0, 0, 0};
    for (npy_intp i = 1; i < n; i++) {
        for (int c = 0; c < 3; c++) {
            double r = round_even(p[3 * i + c] * SCALE[c]);
            double d = r - prev[c];
            if (!(d >= -32768.0 && d <= 65535.0)) {
                Py_RETURN_NONE; /* NaN, infinity or a step too wide */
            }
            int32_t v = (int32_t)d;
            deltas[c][i - 1] = v;
            lo[c] = v < lo[c] ? v : lo[c];
            hi[c] = v > hi[c] ? v : hi[c];
            prev[c] = r;
        }
    }
    int codes[3];
    for (int c = 0; c < 3; c++) {
        if (lo[c] == 0 && hi[c] == 0) {
            codes[c] = 0;
        } else if (c == 2) {
            if (lo[c] < 0) {
                Py_RETURN_NONE; /* time goes back */
            }
            codes[c] = hi[c] <= 255 ? 1 : 2;
        } else if (lo[c] >= -128 && hi[c] <= 127) {
            codes[c] = 1;
        } else if (hi[c] <= 32767) {
            codes[c] = 2;
        } else {
            Py_RETURN_NONE;
        }
    }
    Py_ssize_t size = 12 + (n - 1) * (codes[0] + codes[1] + codes[2]);
    PyObject *result = PyBytes_FromStringAndSize(NULL, size);
    if (result == NULL) {
        return NULL;
    }
    unsigned char *out = (unsigned char *)PyBytes_AS_STRING(result);
    put_le32(out, (int32_t)x0);
    put_le32(out + 4, (int32_t)y0);
    put_le32(out + 8, (int32_t)t0);
    out += 12;
    for (int c = 0; c < 3; c++) {
        const int32_t *col = deltas[c];
        if (codes[c] == 1) {
            for (npy_intp i = 0; i < n - 1; i++) {
                *out++ = (unsigned char)(col[i] & 0xFF);
            }
        } else if (codes[c] == 2) {
            for (npy_intp i = 0; i < n - 1; i++) {
                put_le16(out, col[i]);
                out += 2;
            }
        }
    }
    *widths = codes[0] | (codes[1] << 2) | (codes[2] << 4);
    return result;
}

static PyObject *pack(PyObject *self, PyObject *args) {
    PyObject *points;
    long long t_base_ms;
    double max_coord;
    if (!PyArg_ParseTuple(args, "OLd", &points, &t_base_ms, &max_coord)) {
        return NULL;
    }
    int widths = 0;
    PyObject *packed = pack_points(points, t_base_ms, max_coord, &widths);
    if (packed == NULL || packed == Py_None) {
        return packed;
    }
    return Py_BuildValue("(iN)", widths, packed);
}

/* Python's round(v * scale) for a finite result below 2**62 in magnitude, else 0 with
   *ok cleared (the caller's Python path then explains the refusal). */
static long long quantize(double v, double scale, int *ok) {
    double r = round_even(v * scale);
    if (!(r > -4.6e18 && r < 4.6e18)) {
        *ok = 0;
        return 0;
    }
    return (long long)r;
}

/* vehicle_path(points, t_base_ms, max_coord_cm, x, y, speed, heading, length, width)
       -> (x, y, speed, heading, length, width, widths, packed) | None

   A vehicle path's state in wire units (cm, cm, cm/s, 1e-4 rad, cm, cm: Python's
   round(float(value) * scale), unchecked: the caller checks the fields' ranges) and its
   packed points, in one call; None when either is outside what `pack` takes. */
static PyObject *vehicle_path(PyObject *self, PyObject *args) {
    PyObject *points;
    long long t_base_ms;
    double max_coord, x, y, speed, heading, length, width;
    if (!PyArg_ParseTuple(args, "OLddddddd", &points, &t_base_ms, &max_coord, &x, &y, &speed,
                          &heading, &length, &width)) {
        PyErr_Clear(); /* a field that is not a number: the Python path explains it */
        Py_RETURN_NONE;
    }
    int ok = 1;
    long long q[6] = {
        quantize(x, 100.0, &ok),      quantize(y, 100.0, &ok),   quantize(speed, 100.0, &ok),
        quantize(heading, 1e4, &ok),  quantize(length, 100.0, &ok), quantize(width, 100.0, &ok),
    };
    if (!ok) {
        Py_RETURN_NONE;
    }
    int widths = 0;
    PyObject *packed = pack_points(points, t_base_ms, max_coord, &widths);
    if (packed == NULL || packed == Py_None) {
        return packed;
    }
    return Py_BuildValue("(LLLLLLiN)", q[0], q[1], q[2], q[3], q[4], q[5], widths, packed);
}

/* unpack(buf, off, n, widths, t_base_ms, max_coord_cm) -> (rows, end) | None

   Reads the first point at `off` and the delta columns `widths` names; returns the points
   as a new read-only (n, 3) float64 array (x [m], y [m], t [s]) and the offset after the
   last column. None for anything the general decoder must look at: a reserved width code,
   bits beyond the three columns, a first point out of range, too few bytes. Never reads
   past `buf`. */
static PyObject *unpack(PyObject *self, PyObject *args) {
    Py_buffer view;
    Py_ssize_t off, n;
    int widths;
    long long t_base_ms;
    double max_coord;
    if (!PyArg_ParseTuple(args, "y*nniLd", &view, &off, &n, &widths, &t_base_ms,
                          &max_coord)) {
        return NULL;
    }
    int codes[3] = {widths & 3, (widths >> 2) & 3, (widths >> 4) & 3};
    Py_ssize_t len = view.len;
    if (n < 2 || n > MAX_POINTS || (widths & ~0x3F) || codes[0] == 3 || codes[1] == 3 ||
        codes[2] == 3 || off < 0 || off > len || len - off < 12 ||
        (len - off - 12) / (n - 1) < codes[0] + codes[1] + codes[2]) {
        PyBuffer_Release(&view);
        Py_RETURN_NONE;
    }
    const unsigned char *in = (const unsigned char *)view.buf + off;
    int64_t first[3] = {get_le32(in), get_le32(in + 4), (int64_t)get_le32(in + 8)};
    if (!(-max_coord <= (double)first[0] && (double)first[0] <= max_coord &&
          -max_coord <= (double)first[1] && (double)first[1] <= max_coord)) {
        PyBuffer_Release(&view);
        Py_RETURN_NONE;
    }
    first[2] += t_base_ms; /* |t_base_ms| <= 2**53 / 1000: no overflow */
    npy_intp dims[2] = {n, 3};
    PyObject *arr = PyArray_SimpleNew(2, dims, NPY_DOUBLE);
    if (arr == NULL) {
        PyBuffer_Release(&view);
        return NULL;
    }
    double *rows = (double *)PyArray_DATA((PyArrayObject *)arr);
    in += 12;
    for (int c = 0; c < 3; c++) {
        int64_t acc = first[c];
        double scale = SCALE[c];
        rows[c] = (double)acc / scale;
        if (codes[c] == 0) {
            for (Py_ssize_t i = 1; i < n; i++) {
                rows[3 * i + c] = rows[c];
            }
        } else if (codes[c] == 1) {
            for (Py_ssize_t i = 1; i < n; i++) {
                acc += c == 2 ? (int64_t)in[i - 1] : (int64_t)(int8_t)in[i - 1];
                rows[3 * i + c] = (double)acc / scale;
            }
        } else {
            for (Py_ssize_t i = 1; i < n; i++) {
                unsigned v = (unsigned)in[2 * (i - 1)] | ((unsigned)in[2 * (i - 1) + 1] << 8);
                acc += c == 2 ? (int64_t)v : (int64_t)(int16_t)v;
                rows[3 * i + c] = (double)acc / scale;
            }
        }
        in += (n - 1) * codes[c];
    }
    Py_ssize_t end = (Py_ssize_t)(in - (const unsigned char *)view.buf);
    PyBuffer_Release(&view);
    PyArray_CLEARFLAGS((PyArrayObject *)arr, NPY_ARRAY_WRITEABLE);
    return Py_BuildValue("(Nn)", arr, end);
}

/* build(spec, *values) -> obj

   spec = (cls, descriptors): a new `cls` (a slotted dataclass) whose slots are set, in
   order, through their member descriptors, without __init__ or __post_init__: what
   protocol/codec.py's `_constructor` does in Python (11 descriptor calls from Python cost
   about 1.2 µs for a future path, most of a decode's object making), for values the decoder
   has validated. TypeError if the counts differ or a descriptor refuses. */
static PyObject *build(PyObject *self, PyObject *const *args, Py_ssize_t nargs) {
    if (nargs < 1 || !PyTuple_CheckExact(args[0]) || PyTuple_GET_SIZE(args[0]) != 2) {
        PyErr_SetString(PyExc_TypeError, "build(spec, *values): spec is (cls, descriptors)");
        return NULL;
    }
    PyObject *cls = PyTuple_GET_ITEM(args[0], 0);
    PyObject *descrs = PyTuple_GET_ITEM(args[0], 1);
    if (!PyType_Check(cls) || !PyTuple_CheckExact(descrs) ||
        PyTuple_GET_SIZE(descrs) != nargs - 1) {
        PyErr_SetString(PyExc_TypeError, "build: one value per descriptor of the class");
        return NULL;
    }
    PyTypeObject *type = (PyTypeObject *)cls;
    PyObject *obj = type->tp_alloc(type, 0);
    if (obj == NULL) {
        return NULL;
    }
    for (Py_ssize_t i = 1; i < nargs; i++) {
        PyObject *descr = PyTuple_GET_ITEM(descrs, i - 1);
        descrsetfunc set = Py_TYPE(descr)->tp_descr_set;
        if (set == NULL || set(descr, obj, args[i]) < 0) {
            if (!PyErr_Occurred()) {
                PyErr_SetString(PyExc_TypeError, "build: not a settable descriptor");
            }
            Py_DECREF(obj);
            return NULL;
        }
    }
    return obj;
}

static PyMethodDef methods[] = {
    {"build", (PyCFunction)(void (*)(void))build, METH_FASTCALL,
     "A slotted object from its class, slot descriptors and values, without __init__."},
    {"pack", pack, METH_VARARGS, "Point columns of a vehicle path -> (widths, bytes) or None."},
    {"vehicle_path", vehicle_path, METH_VARARGS,
     "A vehicle path's state in wire units and its packed points, or None."},
    {"unpack", unpack, METH_VARARGS, "Point columns -> (read-only (n, 3) rows, end) or None."},
    {NULL, NULL, 0, NULL},
};

static struct PyModuleDef module = {
    PyModuleDef_HEAD_INIT, "protocol._speedups",
    "Vehicle path points packed and unpacked in C (see protocol/codec.py).", -1, methods,
};

PyMODINIT_FUNC PyInit__speedups(void) {
    import_array(); /* numpy's C API; on failure the import fails and codec.py uses numpy */
    return PyModule_Create(&module);
}
