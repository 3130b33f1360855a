import sys, numpy as np
a = np.load(sys.argv[1]); T = float(sys.argv[2])
t, w, tau = a[:, 0], a[:, 1], a[:, 2:]
dt = t[1] - t[0]
n = int(np.floor((t[-1] + dt) / T + 1e-9))
print("cycle work (mJ) by read-out 0 configured, 1 h=0, 2 no read-point gate, 3 exact hydrostatic")
for k in range(n):
    m = (t >= k * T - 1e-12) & (t < (k + 1) * T - 1e-12)
    W = (tau[m] * w[m, None]).sum(axis=0) * dt
    print(f"  cycle {k}: " + "  ".join(f"{x*1e3:+.3f}" for x in W))
