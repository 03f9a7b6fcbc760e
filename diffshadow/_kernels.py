"""The Triton kernels of `diffshadow.fused` (imported on first use: importing Triton takes a second)."""

import triton
import triton.language as tl

# The launch kernels take n (points this launch) unspecialised: Triton otherwise compiles a kernel per property
# of n (n % 16 == 0 or not), and the renderer's n changes every iteration. On an H200 the first 512² frame after
# a 128² warm-up took 3.6 s instead of 0.03 s, compiling (bench render, DIFFSHADOW_FUSED_SIREN=tf32).


@triton.jit
def siren(x0, x1, x2, w0_ptr, b0_ptr, wh_ptr, bh_ptr, wl_ptr, bl_ptr, W: tl.constexpr, BLOCKS: tl.constexpr,
          PRECISION: tl.constexpr, RES: tl.constexpr):
    """A tile's SIREN outputs from its inputs x0, x1, x2 (BLOCK,), each in [-1, 1]."""
    c = tl.arange(0, W)
    h = (x0[:, None] * tl.load(w0_ptr + c)[None, :] + x1[:, None] * tl.load(w0_ptr + W + c)[None, :]
         + x2[:, None] * tl.load(w0_ptr + 2 * W + c)[None, :] + tl.load(b0_ptr + c)[None, :])
    h = tl.sin(h)
    square = c[:, None] * W + c[None, :]  # (in, out) layout: h @ w
    for i in tl.static_range(BLOCKS):
        wa = tl.load(wh_ptr + (2 * i) * W * W + square)
        ba = tl.load(bh_ptr + (2 * i) * W + c)
        inner = tl.sin(tl.dot(h, wa, input_precision=PRECISION) + ba[None, :])
        wb = tl.load(wh_ptr + (2 * i + 1) * W * W + square)
        bb = tl.load(bh_ptr + (2 * i + 1) * W + c)
        outer = tl.sin(tl.dot(inner, wb, input_precision=PRECISION) + bb[None, :])
        h = RES * (h + outer)
    y = tl.sum(h * tl.load(wl_ptr + c)[None, :], axis=1) + tl.load(bl_ptr)
    return 0.5 * y + 0.5


@triton.jit(do_not_specialize=["n"])
def siren_kernel(x_ptr, w0_ptr, b0_ptr, wh_ptr, bh_ptr, wl_ptr, bl_ptr, out_ptr, n,
                 W: tl.constexpr, BLOCKS: tl.constexpr, BLOCK: tl.constexpr, PRECISION: tl.constexpr,
                 RES: tl.constexpr):
    rows = tl.program_id(0) * BLOCK + tl.arange(0, BLOCK)
    live = rows < n
    x0 = tl.load(x_ptr + rows * 3, mask=live, other=0.0)
    x1 = tl.load(x_ptr + rows * 3 + 1, mask=live, other=0.0)
    x2 = tl.load(x_ptr + rows * 3 + 2, mask=live, other=0.0)
    y = siren(x0, x1, x2, w0_ptr, b0_ptr, wh_ptr, bh_ptr, wl_ptr, bl_ptr, W, BLOCKS, PRECISION, RES)
    tl.store(out_ptr + rows, y, mask=live)


@triton.jit
def box_inputs(p_ptr, extent_ptr, rows, live):
    """A tile's box points as SIREN inputs, as `siren.box_to_siren`: points / extent * 2 - 1."""
    x0 = tl.load(p_ptr + rows * 3, mask=live, other=0.0) / tl.load(extent_ptr) * 2 - 1
    x1 = tl.load(p_ptr + rows * 3 + 1, mask=live, other=0.0) / tl.load(extent_ptr + 1) * 2 - 1
    x2 = tl.load(p_ptr + rows * 3 + 2, mask=live, other=0.0) / tl.load(extent_ptr + 2) * 2 - 1
    return x0, x1, x2


@triton.jit
def segment(s, xs_ptr, KNOTS: tl.constexpr, BLOCK: tl.constexpr):
    """The transfer function's segment (lo, hi) and weight w at s, as `transfer._piecewise_linear` finds them on
    the optics knots: s clamped to the ends, the segment after the last knot at or below s (bucketize with
    right=True)."""
    s = tl.minimum(tl.maximum(s, tl.load(xs_ptr)), tl.load(xs_ptr + KNOTS - 1))
    hi = tl.zeros([BLOCK], dtype=tl.int32)
    for k in tl.static_range(KNOTS):
        hi += (s >= tl.load(xs_ptr + k)).to(tl.int32)
    hi = tl.minimum(tl.maximum(hi, 1), KNOTS - 1)
    lo = hi - 1
    xa = tl.load(xs_ptr + lo)
    xb = tl.load(xs_ptr + hi)
    w = tl.minimum(tl.maximum((s - xa) / tl.maximum(xb - xa, 1e-12), 0.0), 1.0)
    return lo, hi, w


@triton.jit
def channel(ys_ptr, lo, hi, w, CH: tl.constexpr):
    """Channel CH of the optics table (0 opacity, 1-3 RGB) on the segment."""
    ya = tl.load(ys_ptr + lo * 4 + CH)
    return ya + w * (tl.load(ys_ptr + hi * 4 + CH) - ya)


@triton.jit(do_not_specialize=["n"])
def samples_kernel(p_ptr, extent_ptr,
                   w0_ptr, b0_ptr, wh_ptr, bh_ptr, wl_ptr, bl_ptr,
                   sw0_ptr, sb0_ptr, swh_ptr, sbh_ptr, swl_ptr, sbl_ptr,
                   xs_ptr, ys_ptr, density, dt, alpha_ptr, rgb_ptr, n,
                   W: tl.constexpr, BLOCKS: tl.constexpr, SW: tl.constexpr, SBLOCKS: tl.constexpr,
                   SHADOW: tl.constexpr, KNOTS: tl.constexpr, BLOCK: tl.constexpr, PRECISION: tl.constexpr,
                   RES: tl.constexpr):
    rows = tl.program_id(0) * BLOCK + tl.arange(0, BLOCK)
    live = rows < n
    x0, x1, x2 = box_inputs(p_ptr, extent_ptr, rows, live)
    s = siren(x0, x1, x2, w0_ptr, b0_ptr, wh_ptr, bh_ptr, wl_ptr, bl_ptr, W, BLOCKS, PRECISION, RES)
    lo, hi, w = segment(s, xs_ptr, KNOTS, BLOCK)
    opacity = channel(ys_ptr, lo, hi, w, 0)
    tl.store(alpha_ptr + rows, 1 - tl.exp(-(density * opacity) * dt), mask=live)
    shade = 1.0
    if SHADOW:
        g = siren(x0, x1, x2, sw0_ptr, sb0_ptr, swh_ptr, sbh_ptr, swl_ptr, sbl_ptr, SW, SBLOCKS, PRECISION, RES)
        shade = 0.1 + 0.9 * tl.minimum(tl.maximum(g, 0.0), 1.0)
    for ch in tl.static_range(1, 4):
        c = channel(ys_ptr, lo, hi, w, ch) * shade
        tl.store(rgb_ptr + rows * 3 + (ch - 1), tl.minimum(tl.maximum(c, 0.0), 1.0), mask=live)


@triton.jit(do_not_specialize=["n"])
def extinction_kernel(p_ptr, extent_ptr, w0_ptr, b0_ptr, wh_ptr, bh_ptr, wl_ptr, bl_ptr, xs_ptr, ys_ptr, density,
                      out_ptr, n, W: tl.constexpr, BLOCKS: tl.constexpr, KNOTS: tl.constexpr, BLOCK: tl.constexpr,
                      PRECISION: tl.constexpr, RES: tl.constexpr):
    """μ = density · opacity(data INR) at box points: a secondary ray's samples (the naive baseline)."""
    rows = tl.program_id(0) * BLOCK + tl.arange(0, BLOCK)
    live = rows < n
    x0, x1, x2 = box_inputs(p_ptr, extent_ptr, rows, live)
    s = siren(x0, x1, x2, w0_ptr, b0_ptr, wh_ptr, bh_ptr, wl_ptr, bl_ptr, W, BLOCKS, PRECISION, RES)
    lo, hi, w = segment(s, xs_ptr, KNOTS, BLOCK)
    tl.store(out_ptr + rows, density * channel(ys_ptr, lo, hi, w, 0), mask=live)
