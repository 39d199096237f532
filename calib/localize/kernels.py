"""The localizer's compiled kernels (numba): packing the frames' bright bits, reading
labels of the virtual stack (:class:`calib.localize.volume.SweepVolume`), the exhaustive
search's label sums (§III-E-3) and the cap refinement's weights (§III-E-4).

Written by hand and compiled with numba: they are the localizer's whole cost. Each
touches a packed word once, where the obvious numpy scorer (``score_candidates_reference``
in ``tests/localize_reference.py``) is ≈ 24 000× slower on a sweep
(``benchmarks/localize.py``).
"""

from __future__ import annotations

import numba
import numpy as np

__all__ = [
    "block_intensity",
    "candidate_sums",
    "cap_weights",
    "column_tops",
    "grid_sums",
    "parabola_vertex",
]


@numba.njit(cache=True, nogil=True, boundscheck=False)
def _frame_sums(images):  # pragma: no cover - compiled
    """Integer grey-level sum of each frame (exact; no float copy of the frames)."""
    out = np.zeros(images.shape[0], np.int64)
    for j in range(images.shape[0]):
        acc = np.int64(0)
        for r in range(images.shape[1]):
            row = images[j, r]
            for c in range(images.shape[2]):
                acc += row[c]
        out[j] = acc
    return out


@numba.njit(cache=True, nogil=True, boundscheck=False)
def _pack_bits(images, thresholds, sc, out):  # pragma: no cover - compiled
    """out[j, d, r, w] bit b = pixel (r, d + (64 w + b)·sc) of frame j ≥ thresholds[j, r]."""
    H, W = images.shape[1], images.shape[2]
    for j in range(images.shape[0]):
        for r in range(H):
            t = thresholds[j, r]
            src = images[j, r]
            for d in range(sc):
                dst = out[j, d, r]
                n = (W - d + sc - 1) // sc
                for w in range((n + 63) // 64):
                    word = np.uint64(0)
                    for b in range(min(64, n - 64 * w)):
                        bright = np.uint64(src[d + (64 * w + b) * sc] >= t)
                        word |= bright << np.uint64(b)
                    dst[w] = word


@numba.njit(cache=True, nogil=True, boundscheck=False)
def _gather_labels(bits, nearest, frame_rows, frame_cols, H, W, k, r, c):  # pragma: no cover
    """Labels at voxel indices (flat arrays) of a virtual stack, 0 outside."""
    sc = bits.shape[1]
    K = nearest.shape[0]
    out = np.zeros(k.shape[0], np.int16)
    for i in range(k.shape[0]):
        ki = k[i]
        if ki < 0 or ki >= K:
            continue
        j = nearest[ki]
        fr = r[i] - frame_rows[j]
        fc = c[i] - frame_cols[j]
        if 0 <= fr < H and 0 <= fc < W:
            q = fc // sc
            bit = (bits[j, fc % sc, fr, q >> 6] >> np.uint64(q & 63)) & np.uint64(1)
            out[i] = 1 + 512 * np.int16(bit)
    return out


@numba.njit(cache=True, nogil=True, boundscheck=False)
def candidate_sums(
    bits, nearest, frame_rows, frame_cols, H, W, candidates, offsets
):  # pragma: no cover - compiled
    """Encoded label sums (valid + LABEL_UNIT · bright) of listed candidates (N, 3) as
    (k, r, c), each over the sample ``offsets`` (m, 3): :func:`_gather_labels` at every
    candidate + offset, summed as it goes. The numpy form built the (N, m) index blocks
    and gathered them (≈ 10 % of a quick run's CPU, profiled); the same sums."""
    sc = bits.shape[1]
    K = nearest.shape[0]
    out = np.zeros(candidates.shape[0], np.int64)
    one = np.uint64(1)
    for n in range(candidates.shape[0]):
        acc = 0
        for m in range(offsets.shape[0]):
            ki = candidates[n, 0] + offsets[m, 0]
            if ki < 0 or ki >= K:
                continue
            j = nearest[ki]
            fr = candidates[n, 1] + offsets[m, 1] - frame_rows[j]
            fc = candidates[n, 2] + offsets[m, 2] - frame_cols[j]
            if 0 <= fr < H and 0 <= fc < W:
                q = fc // sc
                bit = (bits[j, fc % sc, fr, q >> 6] >> np.uint64(q & 63)) & one
                acc += 1 + 512 * np.int64(bit)
        out[n] = acc
    return out


# The lowest set bit's index of a 64-bit word: its isolated bit times a de Bruijn sequence
# puts a unique 6-bit pattern in the top bits (Leiserson, Prokop & Randall 1998).
_DE_BRUIJN_64 = np.uint64(0x03F79D71B4CB0A89)
_DE_BRUIJN_INDEX = np.zeros(64, np.int64)
for _i in range(64):
    _DE_BRUIJN_INDEX[((1 << _i) * 0x03F79D71B4CB0A89 % (1 << 64)) >> 58] = _i


@numba.njit(cache=True, nogil=True, boundscheck=False)
def grid_sums(
    bits, nearest, frame_rows, frame_cols, H, W, start, step, count, offsets
):  # pragma: no cover - compiled
    """Encoded label sums (valid + LABEL_UNIT · bright) of every grid candidate.

    Per (slice, sample offset) the slice's frame and shift are fixed, so for each row of
    candidates the samples read one bit-row of one column phase of that frame, and the
    candidates whose sample lands inside the frame form one run, found once. The run's
    valid count goes into a difference array (two writes per run, summed once at the
    end) and only its set bits are visited for the bright count: most of a sweep is dark,
    and one step per candidate and sample was the localizer's largest cost (a quarter of
    a refined localization, profiled). Samples past the acquired volume count as
    outside. The grid's column step must be the bits' phase count
    (:meth:`~calib.localize.volume.SweepVolume.with_column_step` re-splits otherwise).
    """
    sc = bits.shape[1]
    K = nearest.shape[0]
    nk, nr, nc = count[0], count[1], count[2]
    out = np.zeros((nk, nr, nc), np.int32)
    runs = np.zeros((nr, nc + 1), np.int32)
    one = np.uint64(1)
    full = ~np.uint64(0)
    for i in range(nk):
        runs[:] = 0
        for m in range(offsets.shape[0]):
            k = start[0] + i * step[0] + offsets[m, 0]
            if k < 0 or k >= K:
                continue
            j = nearest[k]
            fc0 = start[2] + offsets[m, 2] - frame_cols[j]  # frame column of candidate 0
            d = fc0 % sc
            q0 = fc0 // sc
            n_cols = (W - d + sc - 1) // sc  # columns of phase d inside the frame
            lo = max(0, -q0)
            hi = min(nc, n_cols - q0)
            if hi <= lo:
                continue
            b_lo, b_hi = q0 + lo, q0 + hi  # the run's bits: [b_lo, b_hi)
            w_lo, w_hi = b_lo >> 6, (b_hi - 1) >> 6
            for jj in range(nr):
                fr = start[1] + jj * step[1] + offsets[m, 1] - frame_rows[j]
                if fr < 0 or fr >= H:
                    continue
                runs[jj, lo] += 1
                runs[jj, hi] -= 1
                row = bits[j, d, fr]
                dst = out[i, jj]
                for w in range(w_lo, w_hi + 1):
                    word = row[w]
                    if w == w_lo:
                        word &= full << np.uint64(b_lo & 63)
                    if w == w_hi and (b_hi & 63) != 0:
                        word &= ~(full << np.uint64(b_hi & 63))
                    base = (w << 6) - q0
                    while word != 0:
                        low = word & (~word + one)
                        dst[base + _DE_BRUIJN_INDEX[(low * _DE_BRUIJN_64) >> np.uint64(58)]] += 512
                        word ^= low
        for jj in range(nr):
            acc = 0
            dst = out[i, jj]
            for q in range(nc):
                acc += runs[jj, q]
                dst[q] += acc
    return out


@numba.njit(cache=True, nogil=True, boundscheck=False)
def cap_weights(
    frames, levels, nearest, frame_rows, frame_cols, ks, rs, cs, dz2, dy2, dx2, lo2, hi2
):  # pragma: no cover - compiled
    """Weights (len(ks), len(rs), len(cs)) of the cap refinement: grey level minus its
    brightness level (:func:`~calib.localize.volume.frame_levels`) where positive and the
    voxel lies in the shell band (squared distances ``lo2 ≤ dz2 + dy2 + dx2 ≤ hi2``), else
    0. Compiled: one pass
    instead of the several full-block NumPy passes it replaces (≈ 4× faster)."""
    H, W = frames.shape[1], frames.shape[2]
    out = np.zeros((ks.shape[0], rs.shape[0], cs.shape[0]))
    for a in range(ks.shape[0]):
        j = nearest[ks[a]]
        for b in range(rs.shape[0]):
            fr = rs[b] - frame_rows[j]
            if fr < 0 or fr >= H:
                continue
            row = frames[j, fr]
            level = levels[j, fr]
            dzy = dz2[a] + dy2[b]
            for c in range(cs.shape[0]):
                fc = cs[c] - frame_cols[j]
                if fc < 0 or fc >= W:
                    continue
                d2 = dzy + dx2[c]
                if d2 < lo2 or d2 > hi2:
                    continue
                v = row[fc] - level
                if v > 0:
                    out[a, b, c] = v
    return out


@numba.njit(cache=True, nogil=True, boundscheck=False)
def block_intensity(
    frames, levels, nearest, frame_rows, frame_cols, ks, r0, nr, c0, nc, level, one_level
):  # pragma: no cover - compiled
    """Grey level minus its brightness level of the virtual stack's voxel block ``ks`` ×
    rows ``r0 … r0 + nr − 1`` × columns ``c0 … c0 + nc − 1`` (0 outside the frames): the
    row's own level, or ``level`` everywhere with ``one_level``. Compiled: the cap
    refinement reads hundreds of such small blocks per sweep, and NumPy's per-slice
    windows cost more in call overhead than in arithmetic."""
    H, W = frames.shape[1], frames.shape[2]
    out = np.zeros((ks.shape[0], nr, nc))
    for a in range(ks.shape[0]):
        j = nearest[ks[a]]
        for b in range(nr):
            fr = r0 + b - frame_rows[j]
            if fr < 0 or fr >= H:
                continue
            sub = level if one_level else levels[j, fr]
            for c in range(nc):
                fc = c0 + c - frame_cols[j]
                if 0 <= fc < W:
                    out[a, b, c] = frames[j, fr, fc] - sub
    return out


@numba.njit(cache=True, nogil=True)
def parabola_vertex(u, y, wt):  # pragma: no cover - compiled
    """The weighted least-squares parabola y ≈ a u² + b u + c through (u, y), weights
    ``wt``: (status, vertex, its standard error). Status 0: fitted; 1: it does not open
    downwards; 2: the normal matrix is singular (the caller takes the pseudo-inverse).
    The standard error as :func:`calib.localize.refine._parabola_vertex` states it.
    Compiled: the elevation fit calls it thousands of times per calibration on a few
    points each, where NumPy's small-array overhead was 0.18 ms a call."""
    n = u.shape[0]
    # Normal matrix Vᵀ W V and Vᵀ W² V (V = [u², u, 1]), moments of u.
    m = np.zeros(5)
    m2 = np.zeros(5)
    r = np.zeros(3)
    for i in range(n):
        p = 1.0
        for k in range(5):
            m[k] += wt[i] * p
            m2[k] += wt[i] * wt[i] * p
            p *= u[i]
        r[0] += wt[i] * u[i] * u[i] * y[i]
        r[1] += wt[i] * u[i] * y[i]
        r[2] += wt[i] * y[i]
    M = np.empty((3, 3))
    S = np.empty((3, 3))
    for i in range(3):
        for j in range(3):
            M[i, j] = m[4 - i - j]
            S[i, j] = m2[4 - i - j]
    # Inverse by cofactors (symmetric 3 × 3).
    c00 = M[1, 1] * M[2, 2] - M[1, 2] * M[2, 1]
    c01 = M[1, 2] * M[2, 0] - M[1, 0] * M[2, 2]
    c02 = M[1, 0] * M[2, 1] - M[1, 1] * M[2, 0]
    det = M[0, 0] * c00 + M[0, 1] * c01 + M[0, 2] * c02
    if det == 0.0 or not np.isfinite(det):
        return 2, 0.0, 0.0
    Minv = np.empty((3, 3))
    Minv[0, 0] = c00 / det
    Minv[1, 0] = c01 / det
    Minv[2, 0] = c02 / det
    Minv[0, 1] = (M[0, 2] * M[2, 1] - M[0, 1] * M[2, 2]) / det
    Minv[1, 1] = (M[0, 0] * M[2, 2] - M[0, 2] * M[2, 0]) / det
    Minv[2, 1] = (M[0, 1] * M[2, 0] - M[0, 0] * M[2, 1]) / det
    Minv[0, 2] = (M[0, 1] * M[1, 2] - M[0, 2] * M[1, 1]) / det
    Minv[1, 2] = (M[0, 2] * M[1, 0] - M[0, 0] * M[1, 2]) / det
    Minv[2, 2] = (M[0, 0] * M[1, 1] - M[0, 1] * M[1, 0]) / det
    coef = np.zeros(3)
    for i in range(3):
        for j in range(3):
            coef[i] += Minv[i, j] * r[j]
    a, b = coef[0], coef[1]
    if a >= 0:
        return 1, 0.0, 0.0
    vertex = -b / (2 * a)
    sw, sw2 = m[0], m2[0]
    n_effective = sw * sw / sw2  # Kish's; n for equal weights
    if n_effective - 3 < 2:
        return 0, vertex, 0.0
    sse = 0.0
    for i in range(n):
        e = coef[0] * u[i] * u[i] + coef[1] * u[i] + coef[2] - y[i]
        sse += wt[i] * e * e
    s2 = sse / (sw * (1 - 3 / n_effective))
    cov = np.zeros((2, 2))  # (Minv S Minv)[:2, :2]
    for i in range(2):
        for j in range(2):
            for k in range(3):
                for q in range(3):
                    cov[i, j] += Minv[i, k] * S[k, q] * Minv[q, j]
    g0, g1 = b / (2 * a * a), -1 / (2 * a)
    var = s2 * (g0 * g0 * cov[0, 0] + 2 * g0 * g1 * cov[0, 1] + g1 * g1 * cov[1, 1])
    return 0, vertex, np.sqrt(max(var, 0.0))


@numba.njit(cache=True, nogil=True, boundscheck=False)
def column_tops(block, clip, ys):  # pragma: no cover - compiled
    """Depth of the cap's top echo in each slice of ``block`` (slices, rows, columns:
    grey levels less one level, saturated at ``clip``; rows at depths ``ys``), exactly
    as :func:`calib.localize.refine._axial_peak` reads one slice with its row sums
    (clipped at 0) as the weights; ``found`` False where the slice holds no echo.
    Compiled: the elevation's arc fit reads ten or so slices per refinement, each a
    handful of NumPy calls on a few dozen values."""
    F, R, C = block.shape
    depths = np.zeros(F)
    found = np.zeros(F, np.bool_)
    profile = np.empty(R)
    top = np.empty(R)
    for f in range(F):
        peak = -np.inf
        for r in range(R):
            acc = 0.0
            m = -np.inf
            for c in range(C):
                v = block[f, r, c]
                acc += v
                if v > m:
                    m = v
            profile[r] = acc
            top[r] = m
            if m > peak:
                peak = m
        if peak <= 0:
            continue
        total = 0.0
        for r in range(R):
            total += max(profile[r], 0.0)
        if total <= 0:
            continue
        found[f] = True
        i = 0
        for r in range(1, R):
            if profile[r] > profile[i]:
                i = r
        saturated = False
        for r in range(max(i - 1, 0), min(i + 2, R)):
            if top[r] >= clip - 0.5:
                saturated = True
        if saturated:
            k = 0
            while k < R and not top[k] >= clip - 0.5:
                k += 1
            if k == R:
                k = 0
            if k > 0 and top[k] > top[k - 1]:
                frac = (clip - 0.5 - top[k - 1]) / (top[k] - top[k - 1])
                depths[f] = ys[k - 1] + frac * (ys[k] - ys[k - 1])
            else:
                depths[f] = ys[k]
            continue
        if 0 < i < R - 1:
            curvature = profile[i - 1] - 2.0 * profile[i] + profile[i + 1]
            if curvature < 0:
                depths[f] = ys[i] + 0.5 * (profile[i - 1] - profile[i + 1]) / curvature * (
                    ys[1] - ys[0]
                )
                continue
        wsum = 0.0
        wy = 0.0
        for r in range(R):
            w = max(profile[r], 0.0)
            wsum += w
            wy += w * ys[r]
        depths[f] = wy / wsum
    return depths, found
