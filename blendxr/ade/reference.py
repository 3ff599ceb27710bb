"""Pure-NumPy reference twins of the ADE kernels (:mod:`blendxr.ade.kernels` and the
semi-Lagrangian scheme's in :mod:`blendxr.ade.schemes.semi_lagrangian`).

Slow and written for reading, not speed: whole-array expressions, one formula per line,
no scratch-buffer juggling. Used only by the tests, which check that each numba kernel
gives the same numbers. Signatures mirror the kernels except that the twins return their
result (the output arguments are filled too) and :func:`lw_step_2d`/:func:`lw_step_3d`
take ``clip`` so the tests can look at the unclipped update.
"""

import itertools

import numpy as np

from .kernels import FV_M_TINY, FV_MASS_MARGIN

__all__ = [
    "concentration",
    "extend_into_empty",
    "fv_step_2d",
    "fv_step_3d",
    "fv_transport_velocity",
    "lw_free_surface_2d",
    "lw_free_surface_3d",
    "lw_step_2d",
    "lw_step_3d",
    "sl_advect",
    "sl_core",
    "sl_diffuse",
]


def _shift(a, axis, s):
    """``b[p] = a[p + s]`` along ``axis``, zero where ``p + s`` is outside the array."""
    b = np.zeros_like(a)
    n = a.shape[axis]
    dst = [slice(None)] * a.ndim
    src = [slice(None)] * a.ndim
    if s >= 0:
        dst[axis] = slice(0, n - s)
        src[axis] = slice(s, n)
    else:
        dst[axis] = slice(-s, n)
        src[axis] = slice(0, n + s)
    b[tuple(dst)] = a[tuple(src)]
    return b


def _inner(shape):
    """True away from the outermost layer of cells."""
    mask = np.zeros(shape, dtype=bool)
    mask[tuple(slice(1, n - 1) for n in shape)] = True
    return mask


def _position(shape, axis):
    """Index along ``axis`` of every cell."""
    idx = np.arange(shape[axis]).reshape([-1 if a == axis else 1 for a in range(len(shape))])
    return np.broadcast_to(idx, shape)


def _interior_material(material):
    """Cells whose whole 3x3(x3) box is material."""
    mat = np.asarray(material) != 0
    out = _inner(mat.shape) & mat
    for offset in itertools.product((-1, 0, 1), repeat=mat.ndim):
        shifted = mat
        for axis, s in enumerate(offset):
            if s:
                shifted = _shift(shifted, axis, s)
        out &= shifted
    return out


# ---------------------------------------------------------------------------------------
# Lax-Wendroff
# ---------------------------------------------------------------------------------------


def _lw_step(c, out, vels, difs, material, dt, spacing, clip):
    ndim = c.ndim
    w = []  # effective velocity of eq. (4)
    for axis in range(ndim):
        h = spacing[axis]
        w.append(
            vels[axis] - (_shift(difs[axis], axis, 1) - _shift(difs[axis], axis, -1)) / (2 * h)
        )

    def grad(a, axis):
        return (_shift(a, axis, 1) - _shift(a, axis, -1)) / (2.0 * spacing[axis])

    nu = []  # the first-order (and cross) Courant numbers, with the (w . grad) v term
    nu2 = []  # the second-order ones, w dt / h
    mu = []
    d0 = []
    for axis in range(ndim):
        h = spacing[axis]
        advective = sum(w[b] * grad(vels[axis], b) for b in range(ndim))
        nu.append((w[axis] - 0.5 * dt * advective) * dt / h)
        nu2.append(w[axis] * dt / h)
        mu.append(difs[axis] * dt / (h * h))
        d0.append(0.5 * (_shift(c, axis, 1) - _shift(c, axis, -1)))
    new = c.copy()
    for axis in range(ndim):
        d2 = _shift(c, axis, 1) - 2.0 * c + _shift(c, axis, -1)
        new = new - (nu[axis] * d0[axis] - (0.5 * nu2[axis] ** 2 + mu[axis]) * d2)
    # cross terms nu_x nu_y, nu_y nu_z, nu_z nu_x
    pairs = [(0, 1)] if ndim == 2 else [(0, 1), (1, 2), (2, 0)]
    for a, b in pairs:
        cross = 0.5 * (_shift(d0[b], a, 1) - _shift(d0[b], a, -1))
        new = new + nu[a] * nu[b] * cross
    if clip:
        new = np.clip(new, 0.0, 1.0)
    interior = _interior_material(material)
    out[...] = np.where(interior, new, c)
    return out


def lw_step_2d(c, out, vx, vy, dxx, dyy, material, dt, dx, dy, clip=True):
    """Twin of :func:`blendxr.ade.kernels.lw_step_2d` (``clip=False`` skips the clipping)."""
    return _lw_step(c, out, (vx, vy), (dxx, dyy), material, dt, (dx, dy), clip)


def lw_step_3d(c, out, vx, vy, vz, dxx, dyy, dzz, material, dt, dx, dy, dz, clip=True):
    """Twin of :func:`blendxr.ade.kernels.lw_step_3d` (``clip=False`` skips the clipping)."""
    return _lw_step(c, out, (vx, vy, vz), (dxx, dyy, dzz), material, dt, (dx, dy, dz), clip)


def _lw_free_surface(out, material, fill):
    mat = np.asarray(material) != 0
    interior = _interior_material(material)
    surface = mat & ~interior & _inner(mat.shape)
    before = out.copy()
    for cell in zip(*np.nonzero(surface), strict=True):
        normal = [
            0.5 * (fill[tuple(p + (a == ax) for a, p in enumerate(cell))] - fill[
                tuple(p - (a == ax) for a, p in enumerate(cell))
            ])
            for ax in range(mat.ndim)
        ]  # fmt: skip
        nmax = max(abs(n) for n in normal)
        step = [int(np.sign(n)) if (abs(n) >= 0.5 * nmax and n != 0.0) else 0 for n in normal]
        target = tuple(p + s for p, s in zip(cell, step, strict=True))
        if interior[target]:
            out[cell] = before[target]
            continue
        values = [
            before[tuple(p + s for p, s in zip(cell, off, strict=True))]
            for off in itertools.product((-1, 0, 1), repeat=mat.ndim)
            if interior[tuple(p + s for p, s in zip(cell, off, strict=True))]
        ]
        if values:
            out[cell] = sum(values) / len(values)
    return out


def lw_free_surface_2d(out, material, fill):
    """Twin of :func:`blendxr.ade.kernels.lw_free_surface_2d`."""
    return _lw_free_surface(out, material, fill)


def lw_free_surface_3d(out, material, fill):
    """Twin of :func:`blendxr.ade.kernels.lw_free_surface_3d`."""
    return _lw_free_surface(out, material, fill)


# ---------------------------------------------------------------------------------------
# Finite volume
# ---------------------------------------------------------------------------------------


def _ratio(g, p):
    with np.errstate(divide="ignore", invalid="ignore"):
        r = np.clip(g / p, 0.0, 1.0)
    return np.where(p > 0.0, r, 1.0)


def _fv_sweep(m, q, vel, dif, vessel, dt, h, axis, n_diff_sub):
    na = m.shape[axis]
    inner = _inner(m.shape)
    pos = _position(m.shape, axis)
    ves = np.asarray(vessel) != 0

    def up(a):
        return _shift(a, axis, 1)

    def down(a):
        return _shift(a, axis, -1)

    # faces, stored at their lower cell p (face p + 1/2); flux positive towards +axis
    open_face = inner & (pos <= na - 3) & ves & up(ves)
    sgm = np.where(open_face, 0.5 * (vel + up(vel)) * (dt / h), 0.0)
    m_up = np.where(sgm > 0.0, m, up(m))
    m_dn = np.where(sgm > 0.0, up(m), m)
    moving = (sgm != 0.0) & (m_up > FV_M_TINY)
    sgm = np.where(moving, sgm, 0.0)
    anti = np.where(moving, 0.5 * sgm * (1.0 - np.abs(sgm)) * (m_dn - m_up), 0.0)
    f_low = sgm * m_up

    # Zalesak ratios of m per cell: the lower face (l) brings flux in, the upper (r) out
    m_l, m_r = down(m), up(m)
    s_l, s_r = down(sgm), sgm
    a_l, a_r = down(anti), anti
    m_low = m + down(f_low) - f_low
    m_top = np.maximum(np.maximum(m_l, m), np.maximum(m_r, m_low))
    m_bot = np.minimum(np.minimum(m_l, m), np.minimum(m_r, m_low))
    out_low = np.where(s_r > 0.0, s_r * m, 0.0) - np.where(s_l < 0.0, s_l * m, 0.0)
    gain = np.where(a_l > 0.0, a_l, 0.0) - np.where(a_r < 0.0, a_r, 0.0)
    loss = -np.where(a_l < 0.0, a_l, 0.0) + np.where(a_r > 0.0, a_r, 0.0)
    loss_up = -np.where((a_l < 0.0) & (s_l < 0.0), a_l, 0.0) + np.where(
        (a_r > 0.0) & (s_r > 0.0), a_r, 0.0
    )
    r_gain = _ratio(m_top - m_low, gain)
    r_loss = _ratio(m_low - m_bot, loss)
    r_out = _ratio(np.maximum(0.0, (1.0 - FV_MASS_MARGIN) * m - out_low), loss_up)
    r_lup = np.minimum(r_loss, r_out)

    # one coefficient per face; the losing side uses its upwind ratio if it is upwind
    lose_lo = np.where(sgm > 0.0, r_lup, r_loss)
    lose_hi = np.where(sgm < 0.0, up(r_lup), up(r_loss))
    coef = np.where(anti > 0.0, np.minimum(up(r_gain), lose_lo), 0.0)
    coef = np.where(anti < 0.0, np.minimum(r_gain, lose_hi), coef)
    f_m = np.where(moving, f_low + coef * anti, 0.0)
    m_new = np.where(inner, m + down(f_m) - f_m, m)

    # colour of the leaving slabs: MC slope, scaled so the staying material stays in range
    with np.errstate(divide="ignore", invalid="ignore"):
        c = np.where(m > 0.0, q / m, 0.0)
        c_l, c_r = down(c), up(c)
        has_l, has_r = m_l > FV_M_TINY, m_r > FV_M_TINY
        d_lo = np.where(has_l, c - c_l, 0.0)
        d_hi = np.where(has_r, c_r - c, 0.0)
        cmax = np.maximum(c, np.where(has_l, c_l, c))
        cmax = np.maximum(cmax, np.where(has_r, c_r, c))
        cmin = np.minimum(c, np.where(has_l, c_l, c))
        cmin = np.minimum(cmin, np.where(has_r, c_r, c))
        mag = np.minimum(2.0 * np.minimum(np.abs(d_lo), np.abs(d_hi)), 0.5 * np.abs(d_lo + d_hi))
        slope = np.where(d_lo * d_hi <= 0.0, 0.0, np.where(d_lo > 0.0, mag, -mag))
        f_l, f_r = down(f_m), f_m
        o_r = np.where(s_r > 0.0, f_r, 0.0)
        o_l = np.where(s_l < 0.0, -f_l, 0.0)
        h_r = 0.5 * (1.0 - o_r / m)
        h_l = 0.5 * (1.0 - o_l / m)
        x = slope * (o_r * h_r - o_l * h_l)
        stay = m - o_r - o_l
        alpha = np.where(x > 0.0, np.minimum(1.0, stay * (c - cmin) / x), 1.0)
        alpha = np.where(x < 0.0, np.minimum(1.0, stay * (cmax - c) / -x), alpha)
        alpha = np.maximum(0.0, alpha)
        col_l = c - h_l * alpha * slope
        col_r = c + h_r * alpha * slope
    f_q = np.where(sgm > 0.0, f_m * col_r, 0.0)
    f_q = np.where(sgm < 0.0, f_m * up(col_l), f_q)
    q_new = np.where(inner, q + down(f_q) - f_q, q)

    # species diffusion, flux D_f m_f (c_R - c_L) through open faces
    if n_diff_sub > 0:
        kdiff = dt / n_diff_sub / (h * h)
        m_face = np.minimum(m_new, up(m_new))
        d_face = 0.5 * (dif + up(dif))
        conducting = open_face & (m_face > FV_M_TINY)
        active = inner & (m_new > 0.0)
        for _ in range(n_diff_sub):
            with np.errstate(divide="ignore", invalid="ignore"):
                c = np.where(m_new > 0.0, q_new / m_new, 0.0)
            flux = np.where(conducting, d_face * m_face * (up(c) - c), 0.0)
            q_new = np.where(active, q_new + kdiff * (flux - down(flux)), q_new)
    return m_new, q_new


def _fv_step(m, q, m_out, q_out, vels, difs, vessel, dt, spacing, reverse, n_diff_sub):
    axes = list(range(m.ndim))
    if reverse:
        axes.reverse()
    mm, qq = m.copy(), q.copy()
    for axis in axes:
        mm, qq = _fv_sweep(
            mm, qq, vels[axis], difs[axis], vessel, dt, spacing[axis], axis, n_diff_sub
        )
    m_out[...] = mm
    q_out[...] = qq
    return m_out, q_out


def fv_step_2d(m, q, m_out, q_out, work, vx, vy, dxx, dyy, vessel, dt, dx, dy, reverse, n_diff_sub):
    """Twin of :func:`blendxr.ade.kernels.fv_step_2d` (``work`` is ignored)."""
    return _fv_step(
        m, q, m_out, q_out, (vx, vy), (dxx, dyy), vessel, dt, (dx, dy), reverse, n_diff_sub
    )


def fv_step_3d(
    m, q, m_out, q_out, work, vx, vy, vz, dxx, dyy, dzz, vessel, dt, dx, dy, dz, reverse, n_diff_sub
):
    """Twin of :func:`blendxr.ade.kernels.fv_step_3d` (``work`` is ignored)."""
    return _fv_step(
        m,
        q,
        m_out,
        q_out,
        (vx, vy, vz),
        (dxx, dyy, dzz),
        vessel,
        dt,
        (dx, dy, dz),
        reverse,
        n_diff_sub,
    )


def concentration(m, q, out, m_min):
    """Twin of :func:`blendxr.ade.kernels.concentration`."""
    with np.errstate(divide="ignore", invalid="ignore"):
        out[...] = np.where(m > m_min, q / m, np.nan)
    return out


def fv_transport_velocity(v, axis, dt, h, cap):
    """NumPy twin of :func:`blendxr.ade.kernels.fv_transport_velocity`."""
    grad = np.gradient(v, h, axis=axis)  # central inside, one-sided at the ends
    return v * np.clip(1.0 - 0.5 * dt * grad, 0.0, cap)


def extend_into_empty(field, known, allowed, layers=2):
    """NumPy twin of :func:`blendxr.ade.grid.extend_into_empty`."""
    out = np.where(known, field, 0.0)
    known = known.copy()
    for _ in range(layers):
        total = np.zeros_like(out)
        count = np.zeros(out.shape)
        for axis in range(out.ndim):
            for shift in (1, -1):
                rolled_v = np.roll(out, shift, axis=axis)
                rolled_k = np.roll(known, shift, axis=axis)
                # no wrap-around: the rolled-in edge slice is not a neighbour
                edge = [slice(None)] * out.ndim
                edge[axis] = 0 if shift == 1 else -1
                rolled_k[tuple(edge)] = False
                total += np.where(rolled_k, rolled_v, 0.0)
                count += rolled_k
        new = (~known) & allowed & (count > 0)
        if not new.any():
            break
        out[new] = total[new] / count[new]
        known = known | new
    return out


# ---------------------------------------------------------------------------------------
# semi-Lagrangian
# ---------------------------------------------------------------------------------------


def _sl_bracket(p, n):
    """Lower and upper index and the upper weight for positions ``p`` (cells, clamped)."""
    if n == 1:
        zero = np.zeros(p.shape, dtype=np.int64)
        return zero, zero, np.zeros(p.shape)
    i0 = np.clip(np.floor(p).astype(np.int64), 0, n - 2)
    return i0, i0 + 1, p - i0


def _sl_trilinear(field, lower, upper, frac, weight=None):
    """Sum over the eight bracketing cells of the trilinear weight (times ``weight``)
    times ``field``; returns (sum, sum of the weights)."""
    num = np.zeros(lower[0].shape)
    den = np.zeros(lower[0].shape)
    for corner in itertools.product((0, 1), repeat=3):
        index = tuple(up if o else lo for o, lo, up in zip(corner, lower, upper, strict=True))
        w = np.ones(lower[0].shape)
        for o, f in zip(corner, frac, strict=True):
            w = w * (f if o else 1.0 - f)
        if weight is not None:
            w = w * weight[index]
        num += w * field[index]
        den += w
    return num, den


def _sl_cubic_weights(f, n):
    """Lagrange weights of the points -1, 0, 1, 2 at fraction ``f`` (one point on an axis
    of one cell)."""
    if n == 1:
        return [np.ones(f.shape)]
    return [
        -f * (f - 1.0) * (f - 2.0) / 6.0,
        (f + 1.0) * (f - 1.0) * (f - 2.0) / 2.0,
        -(f + 1.0) * f * (f - 2.0) / 2.0,
        (f + 1.0) * f * (f - 1.0) / 6.0,
    ]


def sl_core(material):
    """Twin of :func:`blendxr.ade.schemes.semi_lagrangian.sl_core`: every cell of the
    stencil (offsets -1..2 on each axis longer than one cell, clamped) is material."""
    mat = np.asarray(material) != 0
    out = mat.copy()
    ranges = [(-1, 0, 1, 2) if n > 1 else (0,) for n in mat.shape]
    for offset in itertools.product(*ranges):
        index = tuple(
            np.clip(_position(mat.shape, axis) + s, 0, n - 1)
            for axis, (s, n) in enumerate(zip(offset, mat.shape, strict=True))
        )
        out &= mat[index]
    return out.astype(np.uint8)


def sl_advect(c, out, vx, vy, vz, material, core, dt, hx, hy, hz):
    """Twin of :func:`blendxr.ade.schemes.semi_lagrangian.sl_advect` (arrays of shape
    (nx, ny, nz), a 2-D grid as nz = 1)."""
    shape = c.shape
    mat = material != 0
    vel = (vx, vy, vz)
    here = [_position(shape, axis).astype(float) for axis in range(3)]
    steps = [dt / h for h in (hx, hy, hz)]

    def clamp(p, n):
        return np.clip(p, 0.0, n - 1.0)

    def velocity_at(points):
        brackets = [_sl_bracket(p, n) for p, n in zip(points, shape, strict=True)]
        lower, upper, frac = zip(*brackets, strict=True)
        return [_sl_trilinear(v, lower, upper, frac)[0] for v in vel]

    u = [np.asarray(v, float) for v in vel]
    for _ in range(2):  # the midpoint rule, two fixed-point iterations
        mid = [clamp(x - 0.5 * s * w, n) for x, s, w, n in zip(here, steps, u, shape, strict=True)]
        u = velocity_at(mid)
    departure = [clamp(x - s * w, n) for x, s, w, n in zip(here, steps, u, shape, strict=True)]
    brackets = [_sl_bracket(p, n) for p, n in zip(departure, shape, strict=True)]
    lower, upper, frac = zip(*brackets, strict=True)

    # the clipped cubic
    cubic = np.zeros(shape)
    weights = [_sl_cubic_weights(f, n) for f, n in zip(frac, shape, strict=True)]
    for offset in itertools.product(*[range(len(w)) for w in weights]):
        w = np.ones(shape)
        index = []
        for axis, o in enumerate(offset):
            w = w * weights[axis][o]
            base = lower[axis] - 1 if len(weights[axis]) == 4 else lower[axis]
            index.append(np.clip(base + o, 0, shape[axis] - 1))
        cubic += w * c[tuple(index)]
    corners = [
        c[tuple(up if o else lo for o, lo, up in zip(corner, lower, upper, strict=True))]
        for corner in itertools.product((0, 1), repeat=3)
    ]
    cubic = np.clip(cubic, np.min(corners, axis=0), np.max(corners, axis=0))

    # the material-weighted trilinear mean, or c itself without a material corner
    num, den = _sl_trilinear(c, lower, upper, frac, weight=mat.astype(float))
    with np.errstate(divide="ignore", invalid="ignore"):
        linear = np.where(den > 1e-12, num / den, c)

    uses_cubic = (core != 0)[tuple(lower)]
    out[...] = np.where(mat, np.where(uses_cubic, cubic, linear), c)
    return out


def sl_diffuse(c, out, dxx, dyy, dzz, material, rx, ry, rz):
    """Twin of :func:`blendxr.ade.schemes.semi_lagrangian.sl_diffuse`."""
    mat = material != 0
    acc = np.zeros(c.shape)
    for axis, (d, r) in enumerate(zip((dxx, dyy, dzz), (rx, ry, rz), strict=True)):
        for s in (-1, 1):
            neighbour = _shift(mat.astype(np.uint8), axis, s) != 0
            face = 0.5 * (d + _shift(d, axis, s))
            acc += np.where(neighbour, r * face * (_shift(c, axis, s) - c), 0.0)
    out[...] = np.where(mat, c + acc, c)
    return out
