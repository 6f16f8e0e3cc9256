import numba, numpy as np
_SORT_PARTS = 8

@numba.njit(parallel=True, cache=True)
def depth_order_par(depth, radii):
    P = radii.shape[0]
    parts = _SORT_PARTS
    plen = -(-P // parts)
    drawn = np.zeros(parts + 1, np.int64)
    for b in numba.prange(parts):
        c = 0
        for s in range(b * plen, min(P, (b + 1) * plen)):
            c += radii[s] > 0
        drawn[b + 1] = c
    for b in range(parts):
        drawn[b + 1] += drawn[b]
    n = drawn[parts]
    ids = np.empty(n, np.int64)
    key32 = np.empty(n, np.float32)
    for b in numba.prange(parts):
        k = drawn[b]
        for s in range(b * plen, min(P, (b + 1) * plen)):
            if radii[s] > 0:
                ids[k] = s
                key32[k] = depth[s]
                k += 1
    bits = key32.view(np.uint32)
    keys = np.empty(n, np.uint32)
    nlen = -(-n // parts)
    for b in numba.prange(parts):
        for i in range(b * nlen, min(n, (b + 1) * nlen)):
            keys[i] = ~bits[i] if bits[i] >> 31 else bits[i] | np.uint32(0x80000000)
    tmp_k = np.empty_like(keys)
    tmp_i = np.empty_like(ids)
    count = np.empty((parts, 2048), np.int64)
    for shift in (0, 11, 22):
        for b in numba.prange(parts):
            count[b, :] = 0
            for i in range(b * nlen, min(n, (b + 1) * nlen)):
                count[b, (keys[i] >> shift) & 2047] += 1
        at = 0
        for d in range(2048):
            for b in range(parts):
                c = count[b, d]
                count[b, d] = at
                at += c
        for b in numba.prange(parts):
            for i in range(b * nlen, min(n, (b + 1) * nlen)):
                d = (keys[i] >> shift) & 2047
                j = count[b, d]
                tmp_k[j] = keys[i]
                tmp_i[j] = ids[i]
                count[b, d] = j + 1
        keys, tmp_k = tmp_k, keys
        ids, tmp_i = tmp_i, ids
    a = 0
    while a < n:
        e = a + 1
        while e < n and keys[e] == keys[a]:
            e += 1
        if e - a > 32:
            run = ids[a:e].copy()
            ids[a:e] = run[np.argsort(depth[run], kind="mergesort")]
        else:
            for i in range(a + 1, e):
                s = ids[i]
                m = i - 1
                while m >= a and (depth[ids[m]] > depth[s] or (depth[ids[m]] == depth[s] and ids[m] > s)):
                    ids[m + 1] = ids[m]
                    m -= 1
                ids[m + 1] = s
        a = e
    return ids
