// numpy's 64-bit argsort for one x86-64 level, as numpy 2.4.6 builds it
// (numpy/_core/src/npysort/x86_simd_argsort.dispatch.cpp): the vendored
// x86-simd-sort compiled with that level's flags, `hasnan` true, the index array
// filled 0..n by the caller. build.rs compiles this file once per level with
// SWARMREC_LEVEL set to its suffix; each copy's templates are static, so the two
// levels never share a symbol.
#include <cstddef>
#include <cstdint>

#include "x86simdsort-static-incl.h"

#define SWARMREC_CAT2(a, b) a##b
#define SWARMREC_CAT(a, b) SWARMREC_CAT2(a, b)

extern "C" void SWARMREC_CAT(swarmrec_argsort_f64_, SWARMREC_LEVEL)(double *arr, size_t *arg, size_t n)
{
    x86simdsortStatic::argsort(arr, arg, n, true);
}

extern "C" void SWARMREC_CAT(swarmrec_argsort_i64_, SWARMREC_LEVEL)(int64_t *arr, size_t *arg, size_t n)
{
    x86simdsortStatic::argsort(arr, arg, n, true);
}
