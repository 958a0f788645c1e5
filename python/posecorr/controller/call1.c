/* posecorr.controller._call1: the Python shim's single-pose call without ctypes' per-call argument
 * conversion (about 1 us of the shim's 3). Not part of libposecorr: it calls the
 * library's pc_run through the address the shim passes, converts float64 <-> float32
 * itself, and needs only Python.h. Built when the interpreter's headers are present; the
 * shim falls back to ctypes otherwise (runtime.py). */
#define PY_SSIZE_T_CLEAN
#include <Python.h>

#include <float.h>
#include <math.h>
#include <string.h>

#define POSE_WIDTH 7

typedef int (*pc_run_fn)(void *model, const float *in, size_t n, float *out);

/* A C-contiguous buffer of exactly 7 float64 values (or float32 where allow_f32), or 0
 * (no exception set); *f32 says which. */
static int pose_buffer(PyObject *obj, Py_buffer *view, int writable, int allow_f32, int *f32)
{
    if (PyObject_GetBuffer(obj, view, PyBUF_C_CONTIGUOUS | PyBUF_FORMAT |
                                          (writable ? PyBUF_WRITABLE : 0)) < 0) {
        PyErr_Clear();
        return 0;
    }
    *f32 = view->format && strcmp(view->format, "f") == 0;
    if (!view->format || !(strcmp(view->format, "d") == 0 || (allow_f32 && *f32)) ||
        view->len != POSE_WIDTH * (Py_ssize_t)(*f32 ? sizeof(float) : sizeof(double))) {
        PyBuffer_Release(view);
        return 0;
    }
    return 1;
}

/* run1(run_address, model_address, pose, out) -> status of pc_run, or -1 when pose is
 * not a float64 or float32 contiguous (7,) buffer or out not a float64 one (the caller
 * then takes the general path). */
static PyObject *run1(PyObject *self, PyObject *const *args, Py_ssize_t nargs)
{
    Py_buffer in, out;
    pc_run_fn run;
    void *model, *address;
    float a[POSE_WIDTH], b[POSE_WIDTH];
    double *y;
    int k, status, in_f32, out_f32;
    if (nargs != 4) {
        PyErr_SetString(PyExc_TypeError, "run1(run_address, model_address, pose, out)");
        return NULL;
    }
    address = PyLong_AsVoidPtr(args[0]);
    model = PyLong_AsVoidPtr(args[1]);
    if (PyErr_Occurred())
        return NULL;
    if (!address || !model) {
        PyErr_SetString(PyExc_ValueError, "run1: null address");
        return NULL;
    }
    memcpy(&run, &address, sizeof run); /* object pointer -> function pointer */
    if (!pose_buffer(args[2], &in, 0, 1, &in_f32))
        return PyLong_FromLong(-1);
    if (!pose_buffer(args[3], &out, 1, 0, &out_f32)) {
        PyBuffer_Release(&in);
        return PyLong_FromLong(-1);
    }
    y = (double *)out.buf;
    if (in_f32)
        memcpy(a, in.buf, sizeof a);
    else
        for (k = 0; k < POSE_WIDTH; k++) {
            const double v = ((const double *)in.buf)[k];
            /* a finite value beyond float's range has no float (C99 6.3.1.5: undefined); the
             * general path names it (checks.check_wide_input) */
            if (isfinite(v) && fabs(v) > FLT_MAX) {
                PyBuffer_Release(&in);
                PyBuffer_Release(&out);
                return PyLong_FromLong(-1);
            }
            a[k] = (float)v;
        }
    /* the GIL stays held: releasing it would cost a fifth of the call */
    status = run(model, a, 1, b);
    if (status == 0)
        for (k = 0; k < POSE_WIDTH; k++)
            y[k] = (double)b[k];
    PyBuffer_Release(&in);
    PyBuffer_Release(&out);
    return PyLong_FromLong(status);
}

static PyMethodDef methods[] = {
    {"run1", (PyCFunction)(void (*)(void))run1, METH_FASTCALL,
     "run1(run_address, model_address, pose, out) -> pc_run status, -1 for other buffers"},
    {NULL, NULL, 0, NULL}};

static struct PyModuleDef module_def = {PyModuleDef_HEAD_INIT, "_call1",
                                        "Single-pose calls into libposecorr.", -1, methods,
                                        NULL, NULL, NULL, NULL};

PyMODINIT_FUNC PyInit__call1(void)
{
    return PyModule_Create(&module_def);
}
