"""Scalar helpers for the numba kernels: a vectorisable float32 exp and an exact fused multiply-add.

Why: PyPI's llvmlite has no SVML, so ``math.exp`` stays a scalar libm call and blocks SIMD in the pixel loops.
``fexp`` is the Cephes single-precision scheme (Cody-Waite range reduction, degree-6 polynomial, exponent bits
built with an integer bitcast), as accurate as libm's ``expf`` (both measurements: docs/DECISIONS.md, "Numbers
behind code comments"). It is exact-rounding-insensitive where it matters: the kernels take their
alpha >= 1/255 decisions on sigma, never on the exp.

Importing this module imports numba (it is only imported by the cpu backend's kernels).

numba's on-disk cache (``cache=True``) is keyed on each kernel's own source file: after editing this module or
``_constants.py``, delete ``pipeline/splat/__pycache__/*.nb*`` so the kernels that inline them recompile.
"""

from __future__ import annotations

import numpy as np
from llvmlite import ir
from numba import njit, types
from numba.core import cgutils
from numba.extending import intrinsic

# fastmath flags for kernels whose float results need not be bit-reproducible against torch (no nnan/ninf:
# inputs may legitimately hold inf, e.g. culled depth keys).
FASTMATH = {"nsz", "arcp", "contract", "afn", "reassoc"}


@intrinsic
def _bits_to_f32(typingctx, x):
    """Reinterpret the low 32 bits of an integer as float32 (LLVM trunc + bitcast; vectorises)."""
    if not isinstance(x, types.Integer):
        return None

    def codegen(context, builder, signature, args):
        v = args[0]
        if v.type.width != 32:
            v = builder.trunc(v, ir.IntType(32))
        return builder.bitcast(v, ir.FloatType())

    return types.float32(x), codegen


@intrinsic
def fma32(typingctx, a, b, c):
    """a * b + c rounded once (llvm.fma.f32): exact by IEEE definition, so usable in bit-reproducible code."""
    if not (a == types.float32 and b == types.float32 and c == types.float32):
        return None

    def codegen(context, builder, signature, args):
        f32 = ir.FloatType()
        fn = cgutils.get_or_insert_function(builder.module, ir.FunctionType(f32, [f32, f32, f32]), "llvm.fma.f32")
        return builder.call(fn, args)

    return types.float32(types.float32, types.float32, types.float32), codegen


_LOG2E = np.float32(1.4426950408889634)
_LN2_HI = np.float32(0.693359375)
_LN2_LO = np.float32(-2.12194440e-4)
_P0 = np.float32(1.9875691500e-4)
_P1 = np.float32(1.3981999507e-3)
_P2 = np.float32(8.3334519073e-3)
_P3 = np.float32(4.1665795894e-2)
_P4 = np.float32(1.6666665459e-1)
_P5 = np.float32(5.0000001201e-1)
_ONE = np.float32(1.0)
_HALF = np.float32(0.5)
_XMIN = np.float32(-87.0)


@njit(inline="always")
def fexp(x):
    """exp(x) for float32 x <= 0 (inputs below -87 give exp(-87) ~ 1.6e-38)."""
    x = max(x, _XMIN)
    n = np.floor(fma32(x, _LOG2E, _HALF))
    r = fma32(n, -_LN2_HI, x)
    r = fma32(n, -_LN2_LO, r)
    p = fma32(_P0, r, _P1)
    p = fma32(p, r, _P2)
    p = fma32(p, r, _P3)
    p = fma32(p, r, _P4)
    p = fma32(p, r, _P5)
    p = fma32(p * r, r, r) + _ONE
    return p * _bits_to_f32((np.int32(n) + 127) << 23)
