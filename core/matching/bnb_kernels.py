"""The numba kernels of the multi-resolution scan matcher (:mod:`.m3rsm`, whose docstring says
what they compute and why): the scan's cells per angle, the level-0 score, the per-level merged
entries and the two admissible bounds, the array max-heap, the branch and bound itself, the
exhaustive search it is checked against, and the bound grids built from the pyramid. All run
without the GIL."""

from __future__ import annotations

import numba as nb
import numpy as np


@nb.njit(cache=True, nogil=True)
def _angle_cells(B, cos_a, sin_a, ax, ay, inv_d):
    """L0 cell (relative to the grid origin) of every point under every angle at translation 0.
    ax, ay: anchor minus grid origin (m)."""
    R = cos_a.shape[0]
    K = B.shape[0]
    cx = np.empty((R, K), np.int64)
    cy = np.empty((R, K), np.int64)
    for r in range(R):
        c = cos_a[r]
        s = sin_a[r]
        for j in range(K):
            wx = c * B[j, 0] - s * B[j, 1] + ax
            wy = s * B[j, 0] + c * B[j, 1] + ay
            cx[r, j] = np.int64(np.floor(wx * inv_d))
            cy[r, j] = np.int64(np.floor(wy * inv_d))
    return cx, cy


@nb.njit(cache=True, nogil=True)
def score_l0(L0, cxr, cyr, kx, ky):
    """Exact score at L0 of one angle (cells cxr, cyr at k = 0) shifted by (kx, ky) cells."""
    nx, ny = L0.shape
    s = 0.0
    for j in range(cxr.shape[0]):
        x = cxr[j] + kx
        y = cyr[j] + ky
        if x >= 0 and x < nx and y >= 0 and y < ny:
            s += L0[x, y]
    return s


@nb.njit(cache=True, nogil=True)
def level_entries(cx, cy, first, top):
    """Per level l = first..top and angle r, the merged entries (X, Y, code, weight): X = c >> l,
    code = straddles_x + 2·straddles_y (straddles: c is not a multiple of 2^l, so the 2^l cells
    from c span two level-l cells), weight = number of points merged.

    Level ``first`` comes from the points; each next level from the previous one's entries:
    X_l = X_{l−1} >> 1 and straddles_l = straddles_{l−1} | (X_{l−1} & 1). Equal entries are merged
    through a scratch grid (slot → entry index). Returns flat arrays and offsets such that level l,
    angle r is [off[l, r], off[l, r + 1])."""
    R, K = cx.shape
    n_lv = top + 1
    counts = np.zeros((n_lv, R), np.int64)
    n_used = max(top - first + 1, 0)
    cap = R * K * n_used + 1
    ex = np.empty(cap, np.int32)
    ey = np.empty(cap, np.int32)
    ec = np.empty(cap, np.int8)
    ew = np.empty(cap, np.float64)
    off = np.zeros((n_lv, R + 1), np.int64)
    if n_used == 0 or K == 0:
        return ex[:0], ey[:0], ec[:0], ew[:0], off
    xmin, xmax, ymin, ymax = cx.min(), cx.max(), cy.min(), cy.max()
    # the scratch is sized for level `first` (the finest used); coarser levels use a prefix of it
    W = (xmax >> first) - (xmin >> first) + 1
    H = (ymax >> first) - (ymin >> first) + 1
    scratch = np.full(W * H * 4, -1, np.int64)
    mask = (np.int64(1) << first) - 1
    # previous level's entries of the angle being processed
    px = np.empty(K, np.int64)
    py = np.empty(K, np.int64)
    pc = np.empty(K, np.int64)
    pw = np.empty(K, np.float64)
    n = 0
    for r in range(R):
        for l in range(first, top + 1):
            x0 = xmin >> l
            y0 = ymin >> l
            Hl = (ymax >> l) - y0 + 1
            start = n
            m = K if l == first else counts[l - 1, r]
            for i in range(m):
                if l == first:
                    c_x = cx[r, i]
                    c_y = cy[r, i]
                    X = c_x >> first
                    Y = c_y >> first
                    code = (1 if (c_x & mask) != 0 else 0) + (2 if (c_y & mask) != 0 else 0)
                    w = 1.0
                else:
                    X = px[i] >> 1
                    Y = py[i] >> 1
                    code = ((pc[i] & 1) | (px[i] & 1)) + 2 * (((pc[i] >> 1) & 1) | (py[i] & 1))
                    w = pw[i]
                slot = ((X - x0) * Hl + (Y - y0)) * 4 + code
                e = scratch[slot]
                if e < 0:
                    scratch[slot] = n
                    ex[n] = X
                    ey[n] = Y
                    ec[n] = code
                    ew[n] = w
                    n += 1
                else:
                    ew[e] += w
            # clear the slots used, and hand this level's entries to the next level
            counts[l, r] = n - start
            for i in range(n - start):
                e = start + i
                scratch[((ex[e] - x0) * Hl + (ey[e] - y0)) * 4 + ec[e]] = -1
                px[i] = ex[e]
                py[i] = ey[e]
                pc[i] = ec[e]
                pw[i] = ew[e]
    # entries were appended angle-major; reorder level-major so each (l, r) slice is contiguous
    pos = 0
    for l in range(first, n_lv):
        off[l, 0] = pos
        for r in range(R):
            pos += counts[l, r]
            off[l, r + 1] = pos
    oxs = np.empty(n, np.int32)
    oys = np.empty(n, np.int32)
    ocs = np.empty(n, np.int8)
    ows = np.empty(n, np.float64)
    src = 0
    for r in range(R):
        for l in range(first, n_lv):
            dst = off[l, r]
            for i in range(counts[l, r]):
                oxs[dst + i] = ex[src + i]
                oys[dst + i] = ey[src + i]
                ocs[dst + i] = ec[src + i]
                ows[dst + i] = ew[src + i]
            src += counts[l, r]
    return oxs, oys, ocs, ows, off


@nb.njit(cache=True, nogil=True)
def bound(G, gnx, gny, goff, l, ex, ey, ec, ew, a, b, mx, my):
    """Upper bound of level l for block (mx·2^l, my·2^l): Σ w · G_l[code][X + mx, Y + my]. The bound
    grid G_l[code] is padded by one cell on the low side (index X + 1), since a straddling entry
    at X = −1 still sees cell 0."""
    nx = gnx[l]
    ny = gny[l]
    plane = (nx + 1) * (ny + 1)
    base = goff[l]
    s = 0.0
    for e in range(a, b):
        X = ex[e] + mx + 1
        Y = ey[e] + my + 1
        if X >= 0 and X <= nx and Y >= 0 and Y <= ny:
            s += ew[e] * G[base + ec[e] * plane + X * (ny + 1) + Y]
    return s


@nb.njit(cache=True, nogil=True)
def bound_dense(S, snx, sny, soff, l, cxr, cyr, kx, ky):
    """Tight bound of level l for block (kx, ky): Σ_j S_l[c_j + k], S_l[x, y] = max of L0 over
    [x, x + 2^l) × [y, y + 2^l), stored with a low-side pad of 2^l − 1 cells."""
    pad = (np.int64(1) << l) - 1
    nx = snx[l]
    ny = sny[l]
    base = soff[l]
    s = 0.0
    for j in range(cxr.shape[0]):
        x = cxr[j] + kx + pad
        y = cyr[j] + ky + pad
        if x >= 0 and x < nx and y >= 0 and y < ny:
            s += S[base + x * ny + y]
    return s


@nb.njit(cache=True, nogil=True)
def _heap_push(hs, hl, hr, hx, hy, n, s, l, r, x, y):
    """Push into the max-heap (ties: deeper level first, so leaves surface sooner).

    A block takes 21 bytes: its bound in float64 (the sums the search compares exactly), its level
    in int8, its angle in int32 and its lattice corner in int32 (a city's grid is thousands of
    cells a side). A global search over a 16 km² city holds up to ~34 M blocks at once: 0.7 GB
    at 21 bytes, 1.1 GB with int32 levels and int64 corners."""
    if n == hs.shape[0]:
        cap = 2 * n
        hs2 = np.empty(cap, np.float64)
        hl2 = np.empty(cap, np.int8)
        hr2 = np.empty(cap, np.int32)
        hx2 = np.empty(cap, np.int32)
        hy2 = np.empty(cap, np.int32)
        hs2[:n] = hs
        hl2[:n] = hl
        hr2[:n] = hr
        hx2[:n] = hx
        hy2[:n] = hy
        hs, hl, hr, hx, hy = hs2, hl2, hr2, hx2, hy2
    i = n
    while i > 0:
        p = (i - 1) >> 1
        if hs[p] > s or (hs[p] == s and hl[p] <= l):
            break
        hs[i] = hs[p]
        hl[i] = hl[p]
        hr[i] = hr[p]
        hx[i] = hx[p]
        hy[i] = hy[p]
        i = p
    hs[i] = s
    hl[i] = l
    hr[i] = r
    hx[i] = x
    hy[i] = y
    return hs, hl, hr, hx, hy, n + 1


@nb.njit(cache=True, nogil=True)
def _heap_pop(hs, hl, hr, hx, hy, n):
    """Remove the top (read it before calling); returns the new size."""
    n -= 1
    s = hs[n]
    l = hl[n]
    r = hr[n]
    x = hx[n]
    y = hy[n]
    i = 0
    while True:
        c = 2 * i + 1
        if c >= n:
            break
        if c + 1 < n and (hs[c + 1] > hs[c] or (hs[c + 1] == hs[c] and hl[c + 1] < hl[c])):
            c += 1
        if hs[c] < s or (hs[c] == s and hl[c] >= l):
            break
        hs[i] = hs[c]
        hl[i] = hl[c]
        hr[i] = hr[c]
        hx[i] = hx[c]
        hy[i] = hy[c]
        i = c
    if n > 0:
        hs[i] = s
        hl[i] = l
        hr[i] = r
        hx[i] = x
        hy[i] = y
    return n


@nb.njit(cache=True, nogil=True)
def _keep_best(ts, tr, tx, ty, m, s, r, kx, ky):
    """Insert leaf (s, r, kx, ky) into the list ts[:m], best first; an equal score goes after the
    entries already there, so the first of equal scores stays first, as it does for the search's
    own optimum (only a strictly better leaf replaces it). A full list drops its last entry.
    Returns the new length."""
    K = ts.shape[0]
    if m == K:
        if s <= ts[K - 1]:
            return m
        i = K - 1
    else:
        i = m
        m += 1
    while i > 0 and ts[i - 1] < s:
        ts[i] = ts[i - 1]
        tr[i] = tr[i - 1]
        tx[i] = tx[i - 1]
        ty[i] = ty[i - 1]
        i -= 1
    ts[i] = s
    tr[i] = r
    tx[i] = kx
    ty[i] = ky
    return m


@nb.njit(cache=True, nogil=True)
def _bnb_roots(
    L0, G, gnx, gny, goff, S, snx, sny, soff, dense_upto, cx, cy, ex, ey, ec, ew, eoff, top,
    kx_lo, kx_hi, ky_lo, ky_hi, best, keep,
):  # fmt: skip
    """Start a best-first search (see :func:`_branch_and_bound`): the root blocks of level ``top``
    tiling [kx_lo, kx_hi] × [ky_lo, ky_hi] from an aligned corner, every angle, pushed on a new heap
    if their bound beats ``best`` (scored directly when ``top`` is 0). Returns the search's state:
    (best, r, kx, ky, heap arrays, heap size, kept leaves, their count, nodes per level)."""
    R = cx.shape[0]
    best_r = -1
    best_kx = 0
    best_ky = 0
    per_level = np.zeros(top + 1, np.int64)
    ts = np.empty(keep, np.float64)
    tr = np.empty(keep, np.int64)
    tx = np.empty(keep, np.int64)
    ty = np.empty(keep, np.int64)
    m = 0
    cap = 1024
    hs = np.empty(cap, np.float64)
    hl = np.empty(cap, np.int8)
    hr = np.empty(cap, np.int32)
    hx = np.empty(cap, np.int32)
    hy = np.empty(cap, np.int32)
    n = 0
    step = np.int64(1) << top
    x_start = (kx_lo >> top) << top  # aligned root tiling (floor to a multiple of 2^top)
    y_start = (ky_lo >> top) << top
    for r in range(R):
        kx = x_start
        while kx <= kx_hi:
            ky = y_start
            while ky <= ky_hi:
                if top == 0:
                    if kx >= kx_lo and ky >= ky_lo:
                        s = score_l0(L0, cx[r], cy[r], kx, ky)
                        if keep > 0 and (m < keep or s > ts[keep - 1]):
                            m = _keep_best(ts, tr, tx, ty, m, s, r, kx, ky)
                        if s > best:
                            best, best_r, best_kx, best_ky = s, r, kx, ky
                else:
                    if top <= dense_upto:
                        s = bound_dense(S, snx, sny, soff, top, cx[r], cy[r], kx, ky)
                    else:
                        s = bound(
                            G, gnx, gny, goff, top, ex, ey, ec, ew, eoff[top, r], eoff[top, r + 1], kx >> top, ky >> top
                        )
                    if s > best:
                        hs, hl, hr, hx, hy, n = _heap_push(hs, hl, hr, hx, hy, n, s, top, r, kx, ky)
                ky += step
            kx += step
    return best, best_r, best_kx, best_ky, hs, hl, hr, hx, hy, n, ts, tr, tx, ty, m, per_level


@nb.njit(cache=True, nogil=True)
def _bnb_expand(
    L0, G, gnx, gny, goff, S, snx, sny, soff, dense_upto, cx, cy, ex, ey, ec, ew, eoff,
    kx_lo, kx_hi, ky_lo, ky_hi, best, hs, hl, hr, hx, hy, n, ts, tr, tx, ty, m, per_level, above,
):  # fmt: skip
    """Go on with a best-first search from its state: pop and split blocks while the heap's best
    bound beats both ``best`` and ``above``. A block whose bound does not beat ``above`` stays on
    the heap, so a later call with a lower ``above`` resumes the search where it stopped (−inf:
    to the end). Returns (best, r, kx, ky of a leaf strictly better than the ``best`` passed in,
    r = −1 if none; the heap arrays, its size, the kept leaves' count, nodes expanded)."""
    keep = ts.shape[0]
    best_r = -1
    best_kx = 0
    best_ky = 0
    nodes = 0
    while n > 0:
        s = hs[0]
        if s <= best or s <= above:
            break  # no block left beats the best leaf found (or this call's threshold)
        l = hl[0]
        r = hr[0]
        kx = hx[0]
        ky = hy[0]
        n = _heap_pop(hs, hl, hr, hx, hy, n)
        nodes += 1
        per_level[l] += 1
        h = l - 1
        half = np.int64(1) << h
        for q in range(4):
            ckx = kx + (q & 1) * half
            cky = ky + (q >> 1) * half
            if ckx > kx_hi or cky > ky_hi or ckx + half - 1 < kx_lo or cky + half - 1 < ky_lo:
                continue  # quadrant entirely outside the search region
            # scored here, not through a helper shared with _bnb_roots: passing the kernels'
            # sixteen arrays through one more call cost 17 % of a 16 km² city's search
            if h == 0:
                cs = score_l0(L0, cx[r], cy[r], ckx, cky)
                if keep > 0 and (m < keep or cs > ts[keep - 1]):
                    m = _keep_best(ts, tr, tx, ty, m, cs, r, ckx, cky)
                if cs > best:
                    best, best_r, best_kx, best_ky = cs, r, ckx, cky
            else:
                if h <= dense_upto:
                    cs = bound_dense(S, snx, sny, soff, h, cx[r], cy[r], ckx, cky)
                else:
                    cs = bound(G, gnx, gny, goff, h, ex, ey, ec, ew, eoff[h, r], eoff[h, r + 1], ckx >> h, cky >> h)
                if cs > best:
                    hs, hl, hr, hx, hy, n = _heap_push(hs, hl, hr, hx, hy, n, cs, h, r, ckx, cky)
    return best, best_r, best_kx, best_ky, hs, hl, hr, hx, hy, n, m, nodes


@nb.njit(cache=True, nogil=True)
def _branch_and_bound(
    L0, G, gnx, gny, goff, S, snx, sny, soff, dense_upto, cx, cy, ex, ey, ec, ew, eoff, top,
    kx_lo, kx_hi, ky_lo, ky_hi, best_in, keep,
):  # fmt: skip
    """Best-first search over angles r and lattice translations k ∈ [kx_lo, kx_hi] × [ky_lo, ky_hi].
    Returns (best score, r, kx, ky, nodes expanded, nodes expanded per level, the ``keep`` best
    leaves scored as (scores, r, kx, ky, count)). ``best_in`` is a score to beat (−1 for none):
    only strictly better optima are reported (r = −1 if none). Keeping the leaves costs one
    comparison per leaf scored; it changes neither the order of the search nor its result."""
    best, best_r, best_kx, best_ky, hs, hl, hr, hx, hy, n, ts, tr, tx, ty, m, per_level = _bnb_roots(
        L0, G, gnx, gny, goff, S, snx, sny, soff, dense_upto, cx, cy, ex, ey, ec, ew, eoff, top,
        kx_lo, kx_hi, ky_lo, ky_hi, best_in, keep,
    )  # fmt: skip
    out = _bnb_expand(
        L0, G, gnx, gny, goff, S, snx, sny, soff, dense_upto, cx, cy, ex, ey, ec, ew, eoff,
        kx_lo, kx_hi, ky_lo, ky_hi, best, hs, hl, hr, hx, hy, n, ts, tr, tx, ty, m, per_level, -np.inf,
    )  # fmt: skip
    if out[1] >= 0:  # a leaf of the expansion beat the roots' best
        best, best_r, best_kx, best_ky = out[0], out[1], out[2], out[3]
    nodes = out[11]
    m = out[10]
    return best, best_r, best_kx, best_ky, nodes, per_level, ts, tr, tx, ty, m


@nb.njit(cache=True, nogil=True)
def _exhaustive(L0, cx, cy, kx_lo, kx_hi, ky_lo, ky_hi, keep):
    """Every angle and lattice translation at L0; first maximum in (r, kx, ky) order. Also the
    ``keep`` best poses as (scores, r, kx, ky, count), as :func:`_branch_and_bound` keeps them."""
    best = -1.0
    best_r = 0
    best_kx = kx_lo
    best_ky = ky_lo
    ts = np.empty(keep, np.float64)
    tr = np.empty(keep, np.int64)
    tx = np.empty(keep, np.int64)
    ty = np.empty(keep, np.int64)
    m = 0
    for r in range(cx.shape[0]):
        for kx in range(kx_lo, kx_hi + 1):
            for ky in range(ky_lo, ky_hi + 1):
                s = score_l0(L0, cx[r], cy[r], kx, ky)
                if keep > 0 and (m < keep or s > ts[keep - 1]):
                    m = _keep_best(ts, tr, tx, ty, m, s, r, kx, ky)
                if s > best:
                    best, best_r, best_kx, best_ky = s, r, kx, ky
    return best, best_r, best_kx, best_ky, ts, tr, tx, ty, m


@nb.njit(cache=True, nogil=True)
def _bound_grid(Ll):
    """For one level, the four (nx+1, ny+1) grids of max over L_l[X..X+fx, Y..Y+fy], fx, fy ∈ {0, 1},
    stored at index (X + 1, Y + 1) for X ∈ [−1, nx − 1]; cells outside L_l count as 0."""
    nx, ny = Ll.shape
    out = np.zeros((4, nx + 1, ny + 1), np.float32)
    for X in range(-1, nx):
        for Y in range(-1, ny):
            for code in range(4):
                fx = code & 1
                fy = code >> 1
                m = np.float32(0.0)
                for ix in range(X, X + fx + 1):
                    for iy in range(Y, Y + fy + 1):
                        if ix >= 0 and ix < nx and iy >= 0 and iy < ny and Ll[ix, iy] > m:
                            m = Ll[ix, iy]
                out[code, X + 1, Y + 1] = m
    return out


@nb.njit(cache=True, nogil=True)
def _sliding_max(prev, l):
    """S_l from S_{l-1}: S_l[x] = max(S_{l−1}[x], S_{l−1}[x + 2^{l−1}]) per axis. Index x of S_l is
    stored at x + 2^l − 1 (S_{l−1} at x + 2^{l−1} − 1)."""
    half = np.int64(1) << (l - 1)
    pad_prev = half - 1
    pad = 2 * half - 1
    px, py = prev.shape
    nx = px + half
    ny = py + half
    out = np.zeros((nx, ny), np.float32)
    for X in range(nx):
        x = X - pad  # world-cell index
        for Y in range(ny):
            y = Y - pad
            m = np.float32(0.0)
            for ddx in range(2):
                xi = x + ddx * half + pad_prev
                if xi < 0 or xi >= px:
                    continue
                for ddy in range(2):
                    yi = y + ddy * half + pad_prev
                    if yi >= 0 and yi < py and prev[xi, yi] > m:
                        m = prev[xi, yi]
            out[X, Y] = m
    return out
