import numba, numpy as np

@numba.njit(cache=True)
def depth_order2(depth, radii):
    n = 0
    for s in range(radii.shape[0]):
        n += radii[s] > 0
    ids = np.empty(n, np.int64)
    key32 = np.empty(n, np.float32)
    k = 0
    for s in range(radii.shape[0]):
        if radii[s] > 0:
            ids[k] = s
            key32[k] = depth[s]
            k += 1
    keys = key32.view(np.uint32).copy()
    lo, hi = np.uint32(0xFFFFFFFF), np.uint32(0)
    for i in range(n):  # float bits -> unsigned keys in the floats' order
        keys[i] = ~keys[i] if keys[i] >> 31 else keys[i] | np.uint32(0x80000000)
        lo = min(lo, keys[i])
        hi = max(hi, keys[i])
    # Sort by the keys' offsets from the smallest: two passes of 11 bits when they span at
    # most 24 bits (the lowest one or two dropped: equal sort keys are sorted below), else three.
    span = np.uint32(hi - lo) if n else np.uint32(0)
    bits = 0
    while bits < 32 and (span >> bits) != 0:
        bits += 1
    drop = bits - 22 if 22 < bits <= 24 else 0
    for i in range(n):
        keys[i] = (keys[i] - lo) >> drop
    tmp_k = np.empty_like(keys)
    tmp_i = np.empty_like(ids)
    for shift in (0, 11, 22):
        if shift >= bits - drop and shift > 0:
            break
        count = np.zeros(2049, np.int64)
        for i in range(n):
            count[((keys[i] >> shift) & 2047) + 1] += 1
        for b in range(2048):
            count[b + 1] += count[b]
        for i in range(n):
            b = (keys[i] >> shift) & 2047
            tmp_k[count[b]] = keys[i]
            tmp_i[count[b]] = ids[i]
            count[b] += 1
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
