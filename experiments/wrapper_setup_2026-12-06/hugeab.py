import sys, time, torch, mmap, os
HARNESS = __import__("pathlib").Path(__file__).resolve().parent.parent / "setup_simd_2026-12-06" / "harness.py"
import numpy as np
from pipeline import heap; heap.keep_freed_memory()
sys.argv = ["x", "none"]
exec(open(HARNESS).read().split("mode = sys.argv[1]")[0])
from pipeline.rasterizer import cpu
ROLES = set(os.environ.get("ROLES", "simd-surf,simd-forward,backward").split(","))
class HugePool(cpu.ScratchPool):
    def take(self, role, nbytes):
        with self._lock:
            idle = self._idle.setdefault(role, [])
            fits = [b for b in idle if b.nbytes >= nbytes]
            if fits:
                buf = min(fits, key=lambda b: b.nbytes); idle[:] = [b for b in idle if b is not buf]; return buf
        n = int(nbytes * 1.25) + 64
        if role not in ROLES:
            return np.empty(n, np.uint8)
        m = mmap.mmap(-1, n + (2 << 20))
        m.madvise(mmap.MADV_HUGEPAGE)
        a = np.frombuffer(m, np.uint8)
        off = (-a.ctypes.data) % (2 << 20)
        return a[off: off + n]
normal, huge = cpu.ScratchPool(), HugePool()
s, cam = case(800, 600, 200000, 3)
_, cot = run(s, cam, "auto")
res = {"normal": [], "huge": []}
for pool, name in [(normal, "normal"), (huge, "huge")]:
    cpu.SCRATCH = pool; run(s, cam, "auto", cot)
reps = int(os.environ.get("REPS", "10"))
for i in range(reps):
    for pool, name in ([(normal, "normal"), (huge, "huge")] if i % 2 == 0 else [(huge, "huge"), (normal, "normal")]):
        cpu.SCRATCH = pool
        t0 = time.perf_counter(); run(s, cam, "auto", cot); res[name].append(time.perf_counter() - t0)
import statistics
m = {k: statistics.median(v) for k, v in res.items()}
print(m, "ratio huge/normal", m["huge"] / m["normal"])
