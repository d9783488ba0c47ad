"""Triangular solves with a Cholesky factor stored as packed rows, without unpacking it.

The live posterior appends one row of its factor L per reading. Stored as packed rows (row
i at offset i(i+1)/2), the factor takes half the memory of a square buffer and grows at the
end. BLAS ``dtpsv`` solves with packed storage directly. scipy does not wrap it for Python,
so it is called through the function pointer scipy exports for Cython (``cython_blas``),
the same OpenBLAS that scipy uses everywhere else. (A square buffer with spare capacity
would need ``solve_triangular(L[:n, :n])``, which copies the strided block on every call:
five times the cost of the solve itself at n ≈ 1,400.)

Fortran reads row-major packed lower rows as column-major packed *upper* columns of Lᵀ, so
``L x = b`` is the transposed upper solve ``uplo='U', trans='T'``.
"""

from __future__ import annotations

import ctypes
from collections.abc import Callable

import numpy as np
from scipy.linalg import cython_blas, solve_triangular

__all__ = ["solve_packed_lower"]

_P_INT = ctypes.POINTER(ctypes.c_int)
# dtpsv(uplo, trans, diag, n, ap, x, incx). The arrays go as plain addresses
# (``ndarray.ctypes.data``): ``data_as`` builds a pointer object per call, which cost more
# than the solve itself at small n.
_DTPSV = ctypes.CFUNCTYPE(None, ctypes.c_char_p, ctypes.c_char_p, ctypes.c_char_p,
                          _P_INT, ctypes.c_void_p, ctypes.c_void_p, _P_INT)
_INC = ctypes.c_int(1)  # read only by BLAS


def _load_dtpsv() -> Callable[..., None] | None:
    try:
        capsule = cython_blas.__pyx_capi__["dtpsv"]
        get_name = ctypes.pythonapi.PyCapsule_GetName
        get_name.restype, get_name.argtypes = ctypes.c_char_p, [ctypes.py_object]
        get_pointer = ctypes.pythonapi.PyCapsule_GetPointer
        get_pointer.restype = ctypes.c_void_p
        get_pointer.argtypes = [ctypes.py_object, ctypes.c_char_p]
        address = get_pointer(capsule, get_name(capsule))
    except (AttributeError, KeyError, ValueError):  # another scipy build: unpack and solve
        return None
    return _DTPSV(address) if address else None


_dtpsv = _load_dtpsv()


def _unpacked(packed: np.ndarray, n: int) -> np.ndarray:
    L = np.zeros((n, n))
    L[np.tril_indices(n)] = packed[: n * (n + 1) // 2]
    return L


def solve_packed_lower(packed: np.ndarray, n: int, b: np.ndarray) -> np.ndarray:
    """x = L⁻¹ b for the n×n lower-triangular L whose rows are packed in ``packed``.

    packed: [≥ n(n+1)/2] float64, contiguous; b: [n]. Returns a new array [n].
    """
    if n == 0:
        return np.zeros(0)
    # BLAS reads and writes without bounds: check what it will touch.
    if b.shape != (n,) or packed.ndim != 1 or packed.size < n * (n + 1) // 2:
        raise ValueError(f"solve_packed_lower: b {b.shape} and packed {packed.shape} do not "
                         f"fit n = {n}")
    if _dtpsv is None or not packed.flags.c_contiguous or packed.dtype != np.float64:
        return solve_triangular(_unpacked(packed, n), b, lower=True, check_finite=False)
    x = np.array(b, dtype=np.float64, copy=True)
    _dtpsv(b"U", b"T", b"N", ctypes.byref(ctypes.c_int(n)), packed.ctypes.data,
           x.ctypes.data, ctypes.byref(_INC))
    return x
