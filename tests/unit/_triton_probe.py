"""Tiny kernels over the Triton path's helpers, for the compile test (imported only where Triton compiles)."""

import triton
import triton.language as tl

from ctsplat.splat._triton_kernels import _finite


@triton.jit
def finite_of_product(a_ptr, b_ptr, out_ptr):
    """``out = isfinite(a * b)`` (int8): the form of the projection's pixel-box check ``hx = cutoff * sqrt(f)``."""
    tl.store(out_ptr, _finite(tl.load(a_ptr) * tl.load(b_ptr)).to(tl.int8))
