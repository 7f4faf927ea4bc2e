import sys, numpy as np
from refsim.io import read_results
for f in sys.argv[1:]:
    r = read_results(f)
    o = r.constraint_offsets
    best = (0, 0)
    # inserted length from the puncture step: the tip's travel along the needle since then
    punct = [e.step for e in r.events if e.name == 'puncture'][0]
    axis = r.needle_positions[:, -1] - r.needle_positions[:, 0]; axis /= np.linalg.norm(axis, axis=1)[:, None]
    tip = r.needle_positions[:, -1]
    ins = r.source_names.index('insertion'); bil = r.kind_names.index('bilateral')
    for i in range(punct, r.step_count):
        sl = slice(o[i], o[i + 1])
        m = (r.constraint_source[sl] == ins) & (r.constraint_kind[sl] == bil)
        idx = np.flatnonzero(m)[2:]
        F = (r.constraint_directions[sl][idx] * r.constraint_forces[sl][idx, None]).sum(0)
        L = float((tip[i] - tip[punct - 1]) @ axis[i])
        if L > 0.01 and np.linalg.norm(F) / L > best[0]:
            best = (np.linalg.norm(F) / L, i + 1)
    print(f, 'max shaft lateral force per inserted length %.1f N/m at step %d' % best)
