"""The Triton kernels of `diffshadow.render.fused` (imported on first use: importing Triton takes a second)."""

import os

import triton
import triton.language as tl

# The launch kernels take n (points this launch) unspecialised: Triton otherwise compiles a kernel per property
# of n (n % 16 == 0 or not), and the renderer's n changes every iteration. On an H200 the first 512² frame after
# a 128² warm-up took 3.6 s instead of 0.03 s, compiling (bench render --kernel fused).


# π in three parts (Cody-Waite): k·PI_A is exact for |k| < 2^16, so the reduced argument keeps its bits
PI_A, PI_B, PI_C = tl.constexpr(3.140625), tl.constexpr(9.67502593994140625e-4), tl.constexpr(1.509957990978376432e-7)
# 1.5·2^23: adding it rounds a float below 2^22 to an integer in the last mantissa bits, in one full-rate add (a
# floor is a quarter-rate conversion on A100/H100), and leaves the integer's parity in the lowest bit
ROUND = tl.constexpr(12582912.0)
# Triton's interpreter (the CPU tests) runs no PTX: there the sine's last step is numpy's sin of the same reduced
# argument, so the tests check everything of the kernels but the special-function unit (tests/gpu checks that)
INTERPRETED = tl.constexpr(os.environ.get("TRITON_INTERPRET") == "1")


@triton.jit
def sine(x):
    """sin(x) as the SIRENs' activations need it: x = 2kπ + r (Cody-Waite, exact for the arguments SIRENs give),
    then the GPU's special-function unit (PTX sin.approx, within ~1e-6 on [-π, π]): 8 instructions on sm_90,
    one MUFU (bench kernels' one-sine row). On an H200 it gave the fastest frames of the three sines measured
    (a branch-free polynomial: 0.92-0.96x the fps at 512²-1024²; CUDA's sinf: 0.45x) with the same image
    (docs/performance.md)."""
    t = x * 0.15915494309189535 + ROUND
    k = t - ROUND
    r = x - k * (2 * PI_A)
    r = r - k * (2 * PI_B)
    r = r - k * (2 * PI_C)
    if INTERPRETED:
        y = tl.sin(r)
    else:
        y = tl.inline_asm_elementwise("sin.approx.f32 $0, $1;", "=f,f", [r], dtype=tl.float32, is_pure=True, pack=1)
    return y


@triton.jit(do_not_specialize=["n"])
def sine_kernel(x_ptr, y_ptr, n, COPY: tl.constexpr, BLOCK: tl.constexpr):
    """y = sine(x), elementwise; COPY copies x instead (bench kernels subtracts it to count one sine's cost)."""
    i = tl.program_id(0) * BLOCK + tl.arange(0, BLOCK)
    live = i < n
    x = tl.load(x_ptr + i, mask=live, other=0.0)
    if COPY:
        y = x
    else:
        y = sine(x)
    tl.store(y_ptr + i, y, mask=live)


# TF32 keeps the sign, the exponent and the top 10 of fp32's 23 mantissa bits: x & TF32_MASK is x as a tensor core
# reads it, x - (x & TF32_MASK) the rest
TF32_MASK = tl.constexpr(-8192)  # 0xFFFFE000


@triton.jit
def tf32_split(x):
    hi = (x.to(tl.int32, bitcast=True) & TF32_MASK).to(tl.float32, bitcast=True)
    return hi, x - hi


@triton.jit
def first_layer(x0, x1, x2, w0_ptr, b0_ptr, W: tl.constexpr):
    """The first layer's pre-activations (BLOCK, W) from the inputs x0, x1, x2 (BLOCK,), on tensor cores as three
    TF32 products of the operands split in high and low parts (hi·hi + hi·lo + lo·hi; K padded to 16, the least
    `tl.dot` takes). Why not three fp32 multiply-adds: the activations feed both the first hidden layer's `tl.dot`
    and the residual sum, in two register layouts, and Triton recomputes the multiply-adds and their sines in each
    layout instead of converting one, while a dot's result is converted: 48 of a whole-ray trip's 288 sines were
    repeats. With ω0 = 30 in the weights, one TF32 product would put 3e-2 into the sine's argument; the split,
    1.7e-5 against fp32's 3.9e-6 (`git show 716ff5a:scripts/tf32_first_layer.py`), well below the TF32 hidden
    layers' own rounding."""
    c = tl.arange(0, W)
    k = tl.arange(0, 16)
    x = tl.where(k[None, :] == 0, x0[:, None],
                 tl.where(k[None, :] == 1, x1[:, None], tl.where(k[None, :] == 2, x2[:, None], 0.0)))
    w = tl.load(w0_ptr + k[:, None] * W + c[None, :], mask=k[:, None] < 3, other=0.0)
    x_hi, x_lo = tf32_split(x)
    w_hi, w_lo = tf32_split(w)
    z = tl.dot(x_hi, w_hi, input_precision="tf32")
    z = tl.dot(x_hi, w_lo, z, input_precision="tf32")
    z = tl.dot(x_lo, w_hi, z, input_precision="tf32")
    return z + tl.load(b0_ptr + c)[None, :]


@triton.jit
def siren(x0, x1, x2, w0_ptr, b0_ptr, wh_ptr, bh_ptr, wl_ptr, bl_ptr, W: tl.constexpr, BLOCKS: tl.constexpr,
          RES: tl.constexpr):
    """A tile's SIREN outputs from its inputs x0, x1, x2 (BLOCK,), each in [-1, 1]."""
    c = tl.arange(0, W)
    h = sine(first_layer(x0, x1, x2, w0_ptr, b0_ptr, W))
    square = c[:, None] * W + c[None, :]  # (in, out) layout: h @ w
    for i in tl.static_range(BLOCKS):
        wa = tl.load(wh_ptr + (2 * i) * W * W + square)
        ba = tl.load(bh_ptr + (2 * i) * W + c)
        inner = sine(tl.dot(h, wa, input_precision="tf32") + ba[None, :])
        wb = tl.load(wh_ptr + (2 * i + 1) * W * W + square)
        bb = tl.load(bh_ptr + (2 * i + 1) * W + c)
        outer = sine(tl.dot(inner, wb, input_precision="tf32") + bb[None, :])
        h = RES * (h + outer)
    y = tl.sum(h * tl.load(wl_ptr + c)[None, :], axis=1) + tl.load(bl_ptr)
    return 0.5 * y + 0.5


@triton.jit(do_not_specialize=["n"])
def siren_kernel(x_ptr, w0_ptr, b0_ptr, wh_ptr, bh_ptr, wl_ptr, bl_ptr, out_ptr, n,
                 W: tl.constexpr, BLOCKS: tl.constexpr, BLOCK: tl.constexpr, RES: tl.constexpr):
    rows = tl.program_id(0) * BLOCK + tl.arange(0, BLOCK)
    live = rows < n
    x0 = tl.load(x_ptr + rows * 3, mask=live, other=0.0)
    x1 = tl.load(x_ptr + rows * 3 + 1, mask=live, other=0.0)
    x2 = tl.load(x_ptr + rows * 3 + 2, mask=live, other=0.0)
    y = siren(x0, x1, x2, w0_ptr, b0_ptr, wh_ptr, bh_ptr, wl_ptr, bl_ptr, W, BLOCKS, RES)
    tl.store(out_ptr + rows, y, mask=live)


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


@triton.jit
def lattice_t(m, rows, live, t0, dt, cum_ptr, off_ptr, J, BLOCK: tl.constexpr):
    """Each ray's occupied sample number m as its parameter t, as `render.Runs.samples` finds it: run j is the
    number of runs that end at or before m (searchsorted, right=True), lattice index k = m + offset[j]."""
    j = tl.zeros([BLOCK], dtype=tl.int32)
    # J, the runs per ray, is an argument and not a constant: a constant compiled a kernel per value (the README
    # run's benchmark compiled one for J=1 beside J=7); `while`, not `range`, which the interpreter cannot bound
    i = 0
    while i < J:
        j += (tl.load(cum_ptr + rows * J + i, mask=live, other=0) <= m).to(tl.int32)
        i += 1
    k = m + tl.load(off_ptr + rows * J + tl.minimum(j, J - 1), mask=live, other=0)
    return t0 + (k.to(tl.float32) + 0.5) * dt


@triton.jit(do_not_specialize=["J", "n"])
def march_kernel(order_ptr, o_ptr, d_ptr, t0_ptr, t1_ptr, cum_ptr, off_ptr, total_ptr, extent_ptr,
                 w0_ptr, b0_ptr, wh_ptr, bh_ptr, wl_ptr, bl_ptr,
                 sw0_ptr, sb0_ptr, swh_ptr, sbh_ptr, swl_ptr, sbl_ptr,
                 xs_ptr, ys_ptr, density, dt, stop, acc_ptr, rgb_ptr, count_ptr, trips_ptr, J, n,
                 W: tl.constexpr, BLOCKS: tl.constexpr, SW: tl.constexpr, SBLOCKS: tl.constexpr,
                 SHADOW: tl.constexpr, ABSORB: tl.constexpr, KNOTS: tl.constexpr, BLOCK: tl.constexpr,
                 RES: tl.constexpr):
    """Whole rays, one sample of every ray of the tile per trip, until none is left: a ray stops after its
    last occupied sample, at its exit, or when `stop` is crossed. ABSORB=False: primary rays composited front
    to back (`acc` transmittance, `rgb` colour; stop: transmittance below it), as the renderer's eager step
    shades each sample. ABSORB=True: a secondary ray's optical depth (`acc`; stop: depth at or above it), as
    `MarchedShadow` sums it. `count`: samples each ray took; `trips`: the tile's trips (lanes are busy
    trips x BLOCK). `order`: the rays in the order programs take them, BLOCK to a program."""
    at = tl.program_id(0) * BLOCK + tl.arange(0, BLOCK)
    live = at < n
    rows = tl.load(order_ptr + at, mask=live, other=0)
    ox = tl.load(o_ptr + rows * 3, mask=live, other=0.0)
    oy = tl.load(o_ptr + rows * 3 + 1, mask=live, other=0.0)
    oz = tl.load(o_ptr + rows * 3 + 2, mask=live, other=0.0)
    dx = tl.load(d_ptr + rows * 3, mask=live, other=0.0)
    dy = tl.load(d_ptr + rows * 3 + 1, mask=live, other=0.0)
    dz = tl.load(d_ptr + rows * 3 + 2, mask=live, other=0.0)
    t0 = tl.load(t0_ptr + rows, mask=live, other=0.0)
    t1 = tl.load(t1_ptr + rows, mask=live, other=0.0)
    total = tl.load(total_ptr + rows, mask=live, other=0)
    ex = tl.load(extent_ptr)
    ey = tl.load(extent_ptr + 1)
    ez = tl.load(extent_ptr + 2)
    acc = tl.zeros([BLOCK], dtype=tl.float32) + (0.0 if ABSORB else 1.0)
    r = tl.zeros([BLOCK], dtype=tl.float32)
    g = tl.zeros([BLOCK], dtype=tl.float32)
    b = tl.zeros([BLOCK], dtype=tl.float32)
    count = tl.zeros([BLOCK], dtype=tl.int32)
    active = live & (total > 0)
    m = 0
    while tl.max(active.to(tl.int32), axis=0) > 0:
        t = lattice_t(m, rows, live, t0, dt, cum_ptr, off_ptr, J, BLOCK)
        valid = active & (t < t1)
        # the box point o + t d, as SIREN input (`siren.box_to_siren`)
        x0 = (ox + t * dx) / ex * 2 - 1
        x1 = (oy + t * dy) / ey * 2 - 1
        x2 = (oz + t * dz) / ez * 2 - 1
        s = siren(x0, x1, x2, w0_ptr, b0_ptr, wh_ptr, bh_ptr, wl_ptr, bl_ptr, W, BLOCKS, RES)
        lo, hi, w = segment(s, xs_ptr, KNOTS, BLOCK)
        mu = density * channel(ys_ptr, lo, hi, w, 0)
        if ABSORB:
            acc += tl.where(valid, mu * dt, 0.0)
            keep = acc < stop
        else:
            alpha = tl.where(valid, 1 - tl.exp(-mu * dt), 0.0)
            shade = 1.0
            if SHADOW:
                gs = siren(x0, x1, x2, sw0_ptr, sb0_ptr, swh_ptr, sbh_ptr, swl_ptr, sbl_ptr, SW, SBLOCKS, RES)
                shade = 0.1 + 0.9 * tl.minimum(tl.maximum(gs, 0.0), 1.0)
            weight = acc * alpha
            r += weight * tl.minimum(tl.maximum(channel(ys_ptr, lo, hi, w, 1) * shade, 0.0), 1.0)
            g += weight * tl.minimum(tl.maximum(channel(ys_ptr, lo, hi, w, 2) * shade, 0.0), 1.0)
            b += weight * tl.minimum(tl.maximum(channel(ys_ptr, lo, hi, w, 3) * shade, 0.0), 1.0)
            acc = acc * (1 - alpha)
            keep = acc >= stop
        count += valid.to(tl.int32)
        m += 1
        active = valid & (m < total) & keep
    tl.store(acc_ptr + rows, acc, mask=live)
    tl.store(count_ptr + rows, count, mask=live)
    if not ABSORB:
        tl.store(rgb_ptr + rows * 3, r, mask=live)
        tl.store(rgb_ptr + rows * 3 + 1, g, mask=live)
        tl.store(rgb_ptr + rows * 3 + 2, b, mask=live)
    tl.store(trips_ptr + tl.program_id(0), m)
