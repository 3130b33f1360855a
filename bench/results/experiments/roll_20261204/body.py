import sys, numpy as np
a = np.load(sys.argv[1]); th0 = float(sys.argv[2]) if len(sys.argv) > 2 else 20.0
t, w, v, tau, F, c = a[:, 0], a[:, 1:4], a[:, 4:7], a[:, 7:10], a[:, 10:13], a[:, 13:16]
dt = t[1] - t[0]
th = th0 + np.degrees(np.cumsum(w[:, 0]) * dt)
dw = np.diff(w[:, 0]); dv = np.diff(v[:, 2])
def lag1(x):
    x = x - x.mean(); return float((x[1:] * x[:-1]).sum() / (x * x).sum())
print(f"substeps {len(t)}, dt {dt*1e3:.4f} ms")
step = int(round(0.1 / dt))
print("  t s   theta(deg) min..max  z_c mm min..max  |w_x| max  lag-1 corr of d w_x, d v_z (-1: substep alternation)")
for k in range(0, len(t) - 1, step):
    s = slice(k, k + step)
    print(f"  {t[k]:.2f}  {th[s].min():6.1f} {th[s].max():6.1f}  {c[s,2].min()*1e3:6.2f} {c[s,2].max()*1e3:6.2f}  "
          f"{np.abs(w[s,0]).max():6.2f}  {lag1(dw[k:k+step-1]):+.2f} {lag1(dv[k:k+step-1]):+.2f}")
