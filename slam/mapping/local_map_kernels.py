"""Compiled kernels of the voxel-hash local map (``slam.mapping.local_map``).

Two levels of open-addressing hash tables (linear probing, keys packed 21 bits per axis):
voxels of ``voxel`` metres hold the point rows (at most ``cap`` each); coarse cells of
``B`` x ``B`` x ``B`` voxels hold a doubly linked list of their voxels. Every id space is
kept dense by swap-removal (the last row / voxel / cell moves into the hole), so that
insertion and eviction cost what they touch, never the map size, and the point arrays
stay contiguous without a compaction pass.

``state`` (int64[9]): n points, n voxels, n cells, then the bounding box of the occupied
coarse cells (x0, y0, z0, x1, y1, z1; may be larger than needed after removals: the
queries only use it to stop searching, a superset is exact).
"""

from __future__ import annotations

import numpy as np
from numba import njit, prange

OFF = 1 << 20  # voxel coordinates are offset by this into [0, 2^21)
MASK21 = (1 << 21) - 1
N, NV, NC, BOX = 0, 1, 2, 3  # indices into ``state``


@njit(cache=True, nogil=True)
def _home(tkeys, key):
    """Home slot of ``key``: splitmix64's finaliser, whose low bits depend on every bit of
    the key. (Masking bits 17.. of key * golden ratio ignored x, the top 21 bits of the key:
    the voxels of a row along x shared a home slot, and lookups on an outdoor map probed 16
    slots on average, absent keys far more.)"""
    mask = np.uint64(len(tkeys) - 1)
    h = np.uint64(key)
    h = (h ^ (h >> np.uint64(30))) * np.uint64(0xBF58476D1CE4E5B9)
    h = (h ^ (h >> np.uint64(27))) * np.uint64(0x94D049BB133111EB)
    return (h ^ (h >> np.uint64(31))) & mask


@njit(cache=True, nogil=True)
def slot(tkeys, key):
    """Slot of ``key`` in the table (its own, or the empty slot where it would go)."""
    mask = np.uint64(len(tkeys) - 1)
    h = _home(tkeys, key)
    while tkeys[h] != key and tkeys[h] != -1:
        h = (h + np.uint64(1)) & mask
    return h


@njit(cache=True, nogil=True)
def _delete(tkeys, tvals, key):
    """Remove ``key`` (present) by backward shifting, so that no probe chain breaks."""
    mask = np.uint64(len(tkeys) - 1)
    i = slot(tkeys, key)
    j = i
    while True:
        j = (j + np.uint64(1)) & mask
        if tkeys[j] == -1:
            break
        h = _home(tkeys, tkeys[j])
        # the entry at j may fill the hole at i unless its home lies cyclically in (i, j]
        if i <= j:
            stays = i < h and h <= j
        else:
            stays = h > i or h <= j
        if not stays:
            tkeys[i] = tkeys[j]
            tvals[i] = tvals[j]
            i = j
    tkeys[i] = -1


@njit(cache=True, nogil=True)
def rehash(keys, n, tkeys, tvals):
    """Insert ids 0..n-1 with keys ``keys`` into the empty table."""
    for v in range(n):
        h = slot(tkeys, keys[v])
        tkeys[h] = keys[v]
        tvals[h] = v


@njit(cache=True, nogil=True)
def _axis(key, a):
    """Coordinate a (0, 1, 2) of a packed key."""
    return (key >> (42 - 21 * a)) & MASK21


@njit(cache=True, nogil=True)
def _grow_box(state, ck, first):
    """Widen the box of occupied cells (``state[BOX:]``) to cell ``ck`` (reset if first)."""
    for a in range(3):
        x = _axis(ck, a)
        if first or x < state[BOX + a]:
            state[BOX + a] = x
        if first or x > state[BOX + 3 + a]:
            state[BOX + 3 + a] = x


@njit(cache=True, nogil=True)
def _coarse_key(key, b):
    x = (key >> 42) // b
    y = ((key >> 21) & MASK21) // b
    z = (key & MASK21) // b
    return (x << 42) | (y << 21) | z


@njit(cache=True, nogil=True)
def insert(
    keys,
    points,
    b,
    tkeys,
    tvals,
    vkey,
    vcount,
    vslots,
    vpts,
    vcell,
    vprev,
    vnext,
    ctkeys,
    ctvals,
    ckey,
    chead,
    cnvox,
    pkeys,
    pvox,
    pslot,
    state,
    accepted,
):
    """Append-insert: point i of ``keys`` is accepted when its voxel holds < cap points;
    accepted[:m] = their input indices (in order), given rows n..n+m-1. Returns m."""
    cap = vslots.shape[1]
    n0 = state[N]
    n_acc = 0
    for i in range(len(keys)):
        key = keys[i]
        h = slot(tkeys, key)
        if tkeys[h] == -1:  # a new voxel, linked into its coarse cell
            v = state[NV]
            state[NV] += 1
            tkeys[h] = key
            tvals[h] = v
            vkey[v] = key
            vcount[v] = 0
            ck = _coarse_key(key, b)
            hc = slot(ctkeys, ck)
            if ctkeys[hc] == -1:
                c = state[NC]
                state[NC] += 1
                ctkeys[hc] = ck
                ctvals[hc] = c
                ckey[c] = ck
                chead[c] = -1
                cnvox[c] = 0
                _grow_box(state, ck, c == 0)
            c = ctvals[hc]
            vcell[v] = c
            vprev[v] = -1
            vnext[v] = chead[c]
            if chead[c] != -1:
                vprev[chead[c]] = v
            chead[c] = v
            cnvox[c] += 1
        v = tvals[h]
        cnt = vcount[v]
        if cnt < cap:
            r = n0 + n_acc
            vslots[v, cnt] = r
            for a in range(3):
                vpts[v, cnt, a] = points[i, a]
            vcount[v] = cnt + 1
            pkeys[r] = key
            pvox[r] = v
            pslot[r] = cnt
            accepted[n_acc] = i
            n_acc += 1
    state[N] = n0 + n_acc
    return n_acc


@njit(cache=True, nogil=True)
def _box_d2(lo, hi, q):
    """(min, max) squared distance from point q to the axis-aligned box [lo, hi]."""
    dmin = 0.0
    dmax = 0.0
    for a in range(3):
        g = max(lo[a] - q[a], q[a] - hi[a], 0.0)
        f = max(q[a] - lo[a], hi[a] - q[a])
        dmin += g * g
        dmax += f * f
    return dmin, dmax


@njit(cache=True, nogil=True)
def _remove_cell(c, ctkeys, ctvals, ckey, chead, cnvox, vcell, vnext, state):
    _delete(ctkeys, ctvals, ckey[c])
    u = state[NC] - 1
    if c != u:  # the last cell takes the id
        ckey[c] = ckey[u]
        chead[c] = chead[u]
        cnvox[c] = cnvox[u]
        ctvals[slot(ctkeys, ckey[c])] = c
        v = chead[c]
        while v != -1:
            vcell[v] = c
            v = vnext[v]
    state[NC] = u


@njit(cache=True, nogil=True)
def _remove_voxel(
    v,
    tkeys,
    tvals,
    vkey,
    vcount,
    vslots,
    vpts,
    vcell,
    vprev,
    vnext,
    ctkeys,
    ctvals,
    ckey,
    chead,
    cnvox,
    pvox,
    state,
):
    _delete(tkeys, tvals, vkey[v])
    c = vcell[v]
    if vprev[v] != -1:
        vnext[vprev[v]] = vnext[v]
    else:
        chead[c] = vnext[v]
    if vnext[v] != -1:
        vprev[vnext[v]] = vprev[v]
    cnvox[c] -= 1
    if cnvox[c] == 0:
        _remove_cell(c, ctkeys, ctvals, ckey, chead, cnvox, vcell, vnext, state)
    w = state[NV] - 1
    if v != w:  # the last voxel takes the id
        vkey[v] = vkey[w]
        vcount[v] = vcount[w]
        for s in range(vcount[w]):
            vslots[v, s] = vslots[w, s]
            for a in range(3):
                vpts[v, s, a] = vpts[w, s, a]
            pvox[vslots[v, s]] = v
        vcell[v] = vcell[w]
        vprev[v] = vprev[w]
        vnext[v] = vnext[w]
        if vprev[v] != -1:
            vnext[vprev[v]] = v
        else:
            chead[vcell[v]] = v
        if vnext[v] != -1:
            vprev[vnext[v]] = v
        tvals[slot(tkeys, vkey[v])] = v
    state[NV] = w


@njit(cache=True, nogil=True)
def remove_far(
    origin,
    radius,
    voxel,
    b,
    tkeys,
    tvals,
    vkey,
    vcount,
    vslots,
    vpts,
    vcell,
    vprev,
    vnext,
    ctkeys,
    ctvals,
    ckey,
    chead,
    cnvox,
    pts,
    covs,
    pkeys,
    pvox,
    pslot,
    state,
):
    """Remove every point farther than ``radius`` from ``origin``; returns how many.

    Coarse cells wholly inside the radius are skipped, voxels wholly outside go whole, and
    only points of the voxels the sphere cuts are tested one by one. The removed rows are
    filled with the surviving rows of the end (rows, voxels and cells keep dense ids).
    covs: (n, 3, 3) or (0, 3, 3).
    """
    r2 = radius * radius
    nc = state[NC]
    size = b * voxel
    lo = np.empty(3)
    hi = np.empty(3)
    rows = np.empty(state[N], dtype=np.int64)
    m = 0
    for c in range(nc):
        ck = ckey[c]
        for a in range(3):
            lo[a] = (_axis(ck, a) * b - OFF) * voxel
            hi[a] = lo[a] + size
        dmin, dmax = _box_d2(lo, hi, origin)
        if dmax <= r2:
            continue
        v = chead[c]
        while v != -1:
            key = vkey[v]
            for a in range(3):
                lo[a] = (_axis(key, a) - OFF) * voxel
                hi[a] = lo[a] + voxel
            vmin, vmax = _box_d2(lo, hi, origin)
            if vmax > r2:
                for s in range(vcount[v]):
                    j = vslots[v, s]
                    if vmin > r2:
                        rows[m] = j
                        m += 1
                    else:
                        ex = pts[j, 0] - origin[0]
                        ey = pts[j, 1] - origin[1]
                        ez = pts[j, 2] - origin[2]
                        if ex * ex + ey * ey + ez * ez > r2:
                            rows[m] = j
                            m += 1
            v = vnext[v]
    with_covs = covs.shape[0] > 0
    for t in range(m):  # out of their voxels (rows stay where they are)
        r = rows[t]
        v = pvox[r]
        p = pslot[r]
        last = vcount[v] - 1
        moved = vslots[v, last]
        vslots[v, p] = moved
        for a in range(3):
            vpts[v, p, a] = vpts[v, last, a]
        pslot[moved] = p
        vcount[v] = last
        if last == 0:
            _remove_voxel(
                v,
                tkeys,
                tvals,
                vkey,
                vcount,
                vslots,
                vpts,
                vcell,
                vprev,
                vnext,
                ctkeys,
                ctvals,
                ckey,
                chead,
                cnvox,
                pvox,
                state,
            )
    # the surviving rows of the last m fill the removed rows below n - m (no sort needed)
    n1 = state[N] - m
    gone = np.zeros(m, dtype=np.bool_)
    for t in range(m):
        if rows[t] >= n1:
            gone[rows[t] - n1] = True
    t = 0
    for L in range(n1, state[N]):
        if gone[L - n1]:
            continue
        while rows[t] >= n1:
            t += 1
        r = rows[t]
        t += 1
        for a in range(3):  # (scalar copies: slice assignments compile slowly)
            pts[r, a] = pts[L, a]
            if with_covs:
                for c in range(3):
                    covs[r, a, c] = covs[L, a, c]
        pkeys[r] = pkeys[L]
        pvox[r] = pvox[L]
        pslot[r] = pslot[L]
        vslots[pvox[r], pslot[r]] = r
    state[N] = n1
    if m and state[NC]:  # shrink the box of occupied cells
        for a in range(6):
            state[BOX + a] = -1
        for c in range(state[NC]):
            _grow_box(state, ckey[c], c == 0)
    return m


# --------------------------------------------------------------------------- queries


@njit(cache=True, nogil=True)
def _push(bd, bi, d2, j):
    """Insert (d2, j) into the ascending k-best lists (strictly closer than the last)."""
    m = len(bd) - 1
    while m > 0 and bd[m - 1] > d2:
        bd[m] = bd[m - 1]
        bi[m] = bi[m - 1]
        m -= 1
    bd[m] = d2
    bi[m] = j


@njit(cache=True, nogil=True)
def _scan_voxel(v, vcount, vslots, vpts, qx, qy, qz, max_d2, bd, bi):
    """Offer the points of voxel v (their copies in ``vpts``: contiguous, no row gathers)."""
    last = len(bd) - 1
    for c in range(vcount[v]):
        ex = vpts[v, c, 0] - qx
        ey = vpts[v, c, 1] - qy
        ez = vpts[v, c, 2] - qz
        d2 = ex * ex + ey * ey + ez * ez
        if d2 < bd[last] and d2 <= max_d2:
            _push(bd, bi, d2, vslots[v, c])


@njit(cache=True, nogil=True)
def _gap(lo, q, size):
    """Distance (m) along one axis from q to the interval [lo, lo + size]."""
    return max(lo - q, q - (lo + size), 0.0)


@njit(cache=True, nogil=True)
def _coarse_search(
    qx,
    qy,
    qz,
    cxo,
    cyo,
    czo,
    fine_s,
    max_d2,
    voxel,
    b,
    ctkeys,
    ctvals,
    chead,
    vnext,
    vkey,
    vcount,
    vslots,
    vpts,
    state,
    bd,
    bi,
):
    """Continue a k-NN that the voxel shells (within ``fine_s`` of voxel cxo, cyo, czo) did
    not settle: shells of coarse cells, each cell's voxels pruned by their box distance,
    until the k-th neighbour is closer than every unvisited cell or the box of occupied
    cells is exhausted (then the answer is complete)."""
    last = len(bd) - 1
    size = b * voxel
    X, Y, Z = cxo // b, cyo // b, czo // b
    x0, y0, z0 = state[BOX], state[BOX + 1], state[BOX + 2]
    x1, y1, z1 = state[BOX + 3], state[BOX + 4], state[BOX + 5]
    smax = max(X - x0, x1 - X, Y - y0, y1 - Y, Z - z0, z1 - Z, 0)
    for s in range(smax + 1):
        for dx in range(-s, s + 1):
            xx = X + dx
            if xx < x0 or xx > x1:
                continue
            gx = _gap((xx * b - OFF) * voxel, qx, size)
            gx2 = gx * gx
            if gx2 > max_d2 or gx2 >= bd[last]:
                continue
            for dy in range(-s, s + 1):
                yy = Y + dy
                if yy < y0 or yy > y1:
                    continue
                gy = _gap((yy * b - OFF) * voxel, qy, size)
                gxy2 = gx2 + gy * gy
                if gxy2 > max_d2 or gxy2 >= bd[last]:
                    continue
                edge = abs(dx) == s or abs(dy) == s
                step = 1 if edge else max(2 * s, 1)
                for dz in range(-s, s + 1, step):
                    zz = Z + dz
                    if zz < z0 or zz > z1:
                        continue
                    gz = _gap((zz * b - OFF) * voxel, qz, size)
                    g2 = gxy2 + gz * gz
                    if g2 > max_d2 or g2 >= bd[last]:
                        continue
                    hc = slot(ctkeys, (xx << 42) | (yy << 21) | zz)
                    if ctkeys[hc] == -1:
                        continue
                    v = chead[ctvals[hc]]
                    while v != -1:
                        key = vkey[v]
                        vx = key >> 42
                        vy = (key >> 21) & MASK21
                        vz = key & MASK21
                        near = max(abs(vx - cxo), abs(vy - cyo), abs(vz - czo)) <= fine_s
                        if not near:  # (the voxel shells have seen the near ones)
                            ex = _gap((vx - OFF) * voxel, qx, voxel)
                            ey = _gap((vy - OFF) * voxel, qy, voxel)
                            ez = _gap((vz - OFF) * voxel, qz, voxel)
                            e2 = ex * ex + ey * ey + ez * ez
                            if e2 <= max_d2 and e2 < bd[last]:
                                _scan_voxel(v, vcount, vslots, vpts, qx, qy, qz, max_d2, bd, bi)
                        v = vnext[v]
        # every point closer than r lies in the coarse cells visited so far
        r = min(
            qx - ((X - s) * b - OFF) * voxel,
            ((X + s + 1) * b - OFF) * voxel - qx,
            qy - ((Y - s) * b - OFF) * voxel,
            ((Y + s + 1) * b - OFF) * voxel - qy,
            qz - ((Z - s) * b - OFF) * voxel,
            ((Z + s + 1) * b - OFF) * voxel - qz,
        )
        if bd[last] <= r * r or max_d2 <= r * r:
            return


def shell_offsets(max_shells: int) -> tuple[np.ndarray, np.ndarray]:
    """Voxel offsets (u, v, w) of the shells 0..max_shells (Chebyshev distance s) and the
    start of each shell in them (max_shells + 2 entries). Positive components point to the
    side of each axis nearer to the query; within a shell the offsets come in the order of
    their gap to a typical query (a quarter voxel from its near faces), so that the k best
    fill with near points first and more of the farther voxels are pruned unopened."""
    rows, start = [], [0]
    for s in range(max_shells + 1):
        r = np.arange(-s, s + 1)
        g = np.stack(np.meshgrid(r, r, r, indexing="ij"), -1).reshape(-1, 3)
        g = g[np.abs(g).max(axis=1) == s]
        gap = np.where(g > 0, g - 0.75, np.where(g < 0, -g - 0.25, 0.0))
        g = g[np.lexsort((g[:, 2], g[:, 1], g[:, 0], (gap**2).sum(axis=1)))]
        rows.append(g)
        start.append(start[-1] + len(g))
    return np.concatenate(rows).astype(np.int64), np.array(start, dtype=np.int64)


@njit(cache=True, nogil=True)
def _query_one(
    i,
    q,
    k,
    max_d2,
    voxel,
    max_shells,
    offsets,
    shell_start,
    tkeys,
    tvals,
    vcount,
    vslots,
    vpts,
    state,
    od,
    oi,
):
    """Query i (see ``query``) over the voxel shells into od[i], oi[i]; False if unsettled.
    Voxels are opened in the order of ``offsets`` (``shell_offsets``), mirrored per axis
    towards the query's nearer face."""
    n = state[N]
    lim = 2 * OFF
    last = k - 1
    bd = od[i]
    bi = oi[i]
    for m in range(k):
        bd[m] = np.inf
        bi[m] = n
    if n == 0:
        return True
    qx, qy, qz = q[i, 0], q[i, 1], q[i, 2]
    cx = np.int64(np.floor(qx / voxel))
    cy = np.int64(np.floor(qy / voxel))
    cz = np.int64(np.floor(qz / voxel))
    fx0, fx1 = qx - cx * voxel, (cx + 1) * voxel - qx
    fy0, fy1 = qy - cy * voxel, (cy + 1) * voxel - qy
    fz0, fz1 = qz - cz * voxel, (cz + 1) * voxel - qz
    face = min(fx0, fx1, fy0, fy1, fz0, fz1)
    sx = 1 if fx1 < fx0 else -1  # +1: the high face is the nearer one
    sy = 1 if fy1 < fy0 else -1
    sz = 1 if fz1 < fz0 else -1
    cxo, cyo, czo = cx + OFF, cy + OFF, cz + OFF
    for s in range(max_shells + 1):
        for o in range(shell_start[s], shell_start[s + 1]):
            dx = offsets[o, 0] * sx
            dy = offsets[o, 1] * sy
            dz = offsets[o, 2] * sz
            x = cxo + dx
            y = cyo + dy
            z = czo + dz
            if x < 0 or x >= lim or y < 0 or y >= lim or z < 0 or z >= lim:
                continue
            gx = _gap((cx + dx) * voxel, qx, voxel)
            gy = _gap((cy + dy) * voxel, qy, voxel)
            gz = _gap((cz + dz) * voxel, qz, voxel)
            g2 = gx * gx + gy * gy + gz * gz
            if g2 > max_d2 or g2 >= bd[last]:
                continue
            h = slot(tkeys, (x << 42) | (y << 21) | z)
            if tkeys[h] == -1:
                continue
            _scan_voxel(tvals[h], vcount, vslots, vpts, qx, qy, qz, max_d2, bd, bi)
        r = face + s * voxel  # every point closer than r has been seen
        if bd[last] <= r * r or max_d2 <= r * r:
            return True
    return False


@njit(cache=True, nogil=True)
def query(
    q,
    k,
    max_d2,
    voxel,
    max_shells,
    offsets,
    shell_start,
    tkeys,
    tvals,
    vcount,
    vslots,
    vpts,
    state,
    od,
    oi,
    unresolved,
):
    """Exact k-NN (squared distances) of each query among the map points, over the voxel
    shells outwards from the query's voxel (a voxel whose box is farther than the current
    k-th neighbour, or the bound, is not opened). A query not settled within ``max_shells``
    shells (an isolated point: sparse far returns) is flagged in ``unresolved`` with its
    partial answer, for ``query_coarse``. Missing neighbours: inf / n. ``offsets``,
    ``shell_start``: ``shell_offsets(>= max_shells)``.
    """
    for i in range(len(q)):
        settled = _query_one(
            i,
            q,
            k,
            max_d2,
            voxel,
            max_shells,
            offsets,
            shell_start,
            tkeys,
            tvals,
            vcount,
            vslots,
            vpts,
            state,
            od,
            oi,
        )
        unresolved[i] = not settled


@njit(cache=True, nogil=True, parallel=True)
def query_parallel(
    q,
    k,
    max_d2,
    voxel,
    max_shells,
    offsets,
    shell_start,
    tkeys,
    tvals,
    vcount,
    vslots,
    vpts,
    state,
    od,
    oi,
    unresolved,
):
    """``query`` with the queries split over numba's threads: each query reads the map and
    writes its own rows only, so the answers equal the serial kernel's bit for bit."""
    for i in prange(len(q)):
        settled = _query_one(
            i,
            q,
            k,
            max_d2,
            voxel,
            max_shells,
            offsets,
            shell_start,
            tkeys,
            tvals,
            vcount,
            vslots,
            vpts,
            state,
            od,
            oi,
        )
        unresolved[i] = not settled


@njit(cache=True, nogil=True)
def query_coarse(
    q,
    rows,
    max_d2,
    voxel,
    max_shells,
    b,
    ctkeys,
    ctvals,
    chead,
    vnext,
    vkey,
    vcount,
    vslots,
    vpts,
    state,
    od,
    oi,
):
    """Finish the queries ``rows`` that ``query`` left unsettled, over coarse cells (a
    separate pass: inside the shell loop the rarely taken branch slowed every query)."""
    for t in range(len(rows)):
        i = rows[t]
        qx, qy, qz = q[i, 0], q[i, 1], q[i, 2]
        cxo = np.int64(np.floor(qx / voxel)) + OFF
        cyo = np.int64(np.floor(qy / voxel)) + OFF
        czo = np.int64(np.floor(qz / voxel)) + OFF
        _coarse_search(
            qx,
            qy,
            qz,
            cxo,
            cyo,
            czo,
            max_shells,
            max_d2,
            voxel,
            b,
            ctkeys,
            ctvals,
            chead,
            vnext,
            vkey,
            vcount,
            vslots,
            vpts,
            state,
            od[i],
            oi[i],
        )
