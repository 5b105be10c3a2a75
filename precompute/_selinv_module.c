/* Makes _selected_inverse.c a loadable module of the package, so that the build backend compiles it
 * and the wheel ships it.  Python never calls into it as a module: precompute/native.py loads the
 * same shared object with ctypes and calls the pmask_* functions of _selected_inverse.c. */
#define PY_SSIZE_T_CLEAN
#include <Python.h>

static struct PyModuleDef selinv_module = {
    PyModuleDef_HEAD_INIT, "_selinv",
    "Selected inversion over CHOLMOD (C); called through ctypes by pmask.precompute.native.", -1, NULL,
    NULL, NULL, NULL, NULL};

PyMODINIT_FUNC PyInit__selinv(void) { return PyModule_Create(&selinv_module); }
