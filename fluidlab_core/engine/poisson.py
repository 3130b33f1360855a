"""The pressure Poisson solve of the gas solver: multigrid-preconditioned conjugate gradients (MGPCG).

The math (cell-centred unknowns y on the gas grid, unit-free stencil: the 1/Δx² is folded into y):

    (L y)_c = Σ_{f ∈ faces(c), f open} (y_c − y_n(f))                        for every fluid cell c

where a face is open when the cell n(f) across it is fluid, or when f lies on a domain wall declared open
(n(f) is then a Dirichlet cell with y = 0). Faces to solid cells (statics, tools, particles, closed walls,
inflow walls) are Neumann: they drop out. L = D M Dᵀ with D the face-to-cell divergence and M the open-face
mask, so L is symmetric positive semi-definite; it is singular on every connected fluid region that touches no
open wall (y + const solves as well), and L y = r is then solvable only if Σ_region r = 0. `solve` makes the
right-hand side compatible region by region (subtracting each closed region's mean; the amount is reported)
and returns the solution of least... any solution: the pressure's constant does not change the velocity.

Preconditioner: one V-cycle of geometric multigrid (McAdams, Sifakis & Teran 2010, "A parallel multigrid Poisson
solver for fluids simulation on large grids"): levels of half the resolution (a coarse cell is fluid when any
of its children is), red-black Gauss-Seidel smoothing (pre-smoothing red then black, post-smoothing black then
red, so the V-cycle is a symmetric operator), restriction r_2h = ½ Σ_children r_h (the stencil of level l is the
Laplacian times (2^l Δx)², hence ½ = 4/8), prolongation by injection, and smoothing sweeps as the coarsest
solve. Conjugate gradients corrects what the coarse levels get wrong near irregular solids.

Stopping: ‖r_k‖₂ ≤ tol ‖b‖₂ (relative residual, b the compatible right-hand side), or the iteration cap; the
caller decides whether missing the tolerance raises or warns (gas.py). All solver vectors are float64 whatever
the working precision, so that a relative residual of 1e-6 is reachable on large grids.
"""

import numpy as np
import taichi as ti

SOLID, FLUID = 0, 1


def level_shapes(shape, min_cells: int = 4) -> list[tuple[int, int, int]]:
    """Grid shapes of the multigrid levels: halve (rounding up) until the largest side is at most `min_cells`."""
    shapes = [tuple(int(n) for n in shape)]
    while max(shapes[-1]) > min_cells:
        shapes.append(tuple(max(1, -(-n // 2)) for n in shapes[-1]))
    return shapes


@ti.data_oriented
class PoissonSolver:
    """MGPCG for L y = r on a grid of `shape` cells (see the module docstring).

    open_walls: 6 bools, (x−, x+, y−, y+, z−, z+): which domain walls are Dirichlet (y = 0 outside).
    The fine level's cell flags (`flags[0]`, FLUID or SOLID) are written by the gas solver before `solve`."""

    def __init__(self, shape, open_walls, pre_sweeps: int = 2, post_sweeps: int = 2, bottom_sweeps: int = 30):
        self.shape = tuple(int(n) for n in shape)
        self.open_walls = tuple(bool(b) for b in open_walls)
        self.shapes = level_shapes(self.shape)
        self.n_levels = len(self.shapes)
        self.pre_sweeps, self.post_sweeps, self.bottom_sweeps = int(pre_sweeps), int(post_sweeps), int(bottom_sweeps)
        f64 = ti.f64
        self.flags = [ti.field(ti.i8, shape=s) for s in self.shapes]  # FLUID / SOLID per cell and level
        self.r = [ti.field(f64, shape=s) for s in self.shapes]  # residual (level 0: of the CG iteration)
        self.z = [ti.field(f64, shape=s) for s in self.shapes]  # preconditioned residual / level correction
        self.x = ti.field(f64, shape=self.shape)  # the solution y
        self.b = ti.field(f64, shape=self.shape)  # right-hand side (made compatible in place)
        self.p = ti.field(f64, shape=self.shape)  # CG search direction
        self.Ap = ti.field(f64, shape=self.shape)  # L p
        self.region = ti.field(ti.i32, shape=self.shape)  # closed fluid region id (−1: open or solid)
        self.max_regions = 4096
        self.region_sum = ti.field(f64, shape=self.max_regions)
        self.region_count = ti.field(f64, shape=self.max_regions)
        self.n_closed = 0
        self._regions_for = None  # the flags the regions were labelled for (bytes), to relabel only on change
        self.sums = ti.field(f64, shape=4)  # reductions
        self.last = {"iterations": 0, "residual": 0.0, "removed": 0.0}

    # --- the operator, one level ---------------------------------------------------------------------------
    @ti.func
    def _diag_off(self, flags: ti.template(), y: ti.template(), I):
        """(number of open faces, Σ y over fluid neighbours) of cell I."""
        shape = flags.shape
        diag = ti.f64(0.0)
        off = ti.f64(0.0)
        for d in ti.static(range(3)):
            for s in ti.static((0, 1)):
                J = I + (2 * s - 1) * ti.Vector.unit(3, d, ti.i32)
                if J[d] < 0 or J[d] >= shape[d]:
                    if ti.static(self.open_walls[2 * d + s]):
                        diag += 1.0
                elif flags[J] == FLUID:
                    diag += 1.0
                    off += y[J]
        return diag, off

    @ti.kernel
    def _apply(self, flags: ti.template(), y: ti.template(), out: ti.template()):
        """out = L y (zero on solid cells)."""
        for I in ti.grouped(y):
            v = ti.f64(0.0)
            if flags[I] == FLUID:
                diag, off = self._diag_off(flags, y, I)
                v = diag * y[I] - off
            out[I] = v

    @ti.kernel
    def _smooth(self, flags: ti.template(), r: ti.template(), z: ti.template(), color: ti.i32):
        """One Gauss-Seidel half-sweep of L z = r over the cells of one colour ((i + j + k) % 2)."""
        for I in ti.grouped(z):
            if (I[0] + I[1] + I[2]) % 2 == color and flags[I] == FLUID:
                diag, off = self._diag_off(flags, z, I)
                if diag > 0.0:
                    z[I] = (r[I] + off) / diag

    @ti.kernel
    def _bottom(self, flags: ti.template(), r: ti.template(), z: ti.template(), sweeps: ti.i32):
        """The coarsest level's solve: z = 0, then `sweeps` symmetric Gauss-Seidel sweeps (forward then backward
        in lexicographic order), serially in one launch (the level has a few dozen cells)."""
        nx, ny, nz = ti.static(z.shape)
        ti.loop_config(serialize=True)
        for _ in range(1):
            for i, j, k in ti.ndrange(nx, ny, nz):
                z[i, j, k] = 0.0
            for _s in range(sweeps):
                for n in range(2 * nx * ny * nz):
                    m = n if n < nx * ny * nz else 2 * nx * ny * nz - 1 - n
                    I = ti.Vector([m // (ny * nz), (m // nz) % ny, m % nz])
                    if flags[I] == FLUID:
                        diag, off = self._diag_off(flags, z, I)
                        if diag > 0.0:
                            z[I] = (r[I] + off) / diag

    @ti.kernel
    def _residual_restrict(self, flags: ti.template(), r: ti.template(), z: ti.template(), coarse: ti.template()):
        """coarse = ½ Σ_children (r − L z) (the next level's right-hand side)."""
        for I in ti.grouped(coarse):
            coarse[I] = 0.0
        for I in ti.grouped(z):
            if flags[I] == FLUID:
                diag, off = self._diag_off(flags, z, I)
                coarse[I // 2] += 0.5 * (r[I] - (diag * z[I] - off))

    @ti.kernel
    def _prolong(self, z: ti.template(), coarse: ti.template()):
        for I in ti.grouped(z):
            z[I] += coarse[I // 2]

    @ti.kernel
    def _coarsen_flags(self, fine: ti.template(), coarse: ti.template()):
        for I in ti.grouped(coarse):
            coarse[I] = ti.cast(SOLID, ti.i8)
        for I in ti.grouped(fine):
            if fine[I] == FLUID:
                coarse[I // 2] = ti.cast(FLUID, ti.i8)

    @ti.kernel
    def _clear(self, f: ti.template()):
        for I in ti.grouped(f):
            f[I] = 0.0

    def _vcycle(self):
        """z[0] = M⁻¹ r[0]: one symmetric V-cycle."""
        L = self.n_levels
        for lv in range(L - 1):
            self._clear(self.z[lv])
            for _ in range(self.pre_sweeps):
                self._smooth(self.flags[lv], self.r[lv], self.z[lv], 0)
                self._smooth(self.flags[lv], self.r[lv], self.z[lv], 1)
            self._residual_restrict(self.flags[lv], self.r[lv], self.z[lv], self.r[lv + 1])
        self._bottom(self.flags[L - 1], self.r[L - 1], self.z[L - 1], self.bottom_sweeps)
        for lv in reversed(range(L - 1)):
            self._prolong(self.z[lv], self.z[lv + 1])
            for _ in range(self.post_sweeps):
                self._smooth(self.flags[lv], self.r[lv], self.z[lv], 1)
                self._smooth(self.flags[lv], self.r[lv], self.z[lv], 0)

    # --- CG vector operations -----------------------------------------------------------------------------
    @ti.kernel
    def _dot(self, a: ti.template(), b: ti.template(), slot: ti.i32):
        self.sums[slot] = 0.0
        for I in ti.grouped(a):
            self.sums[slot] += a[I] * b[I]

    @ti.kernel
    def _start(self):
        """x = 0, r = b (the initial guess is zero: the pressure is not warm-started, so the adjoint solve and
        the forward solve see the same iteration)."""
        for I in ti.grouped(self.x):
            self.x[I] = 0.0
            self.r[0][I] = self.b[I]

    @ti.kernel
    def _update_xr(self, alpha: ti.f64):
        for I in ti.grouped(self.x):
            self.x[I] += alpha * self.p[I]
            self.r[0][I] -= alpha * self.Ap[I]

    @ti.kernel
    def _update_p(self, beta: ti.f64):
        for I in ti.grouped(self.p):
            self.p[I] = self.z[0][I] + beta * self.p[I]

    @ti.kernel
    def _copy(self, src: ti.template(), dst: ti.template()):
        for I in ti.grouped(src):
            dst[I] = src[I]

    # --- compatibility on closed regions ----------------------------------------------------------------------
    def update_flags(self, flags: np.ndarray | None = None):
        """After flags[0] changed: coarsen them and label the closed fluid regions (those touching no open
        wall), whose right-hand sides must sum to zero."""
        from scipy import ndimage

        if flags is None:
            flags = self.flags[0].to_numpy()
        for lv in range(self.n_levels - 1):
            self._coarsen_flags(self.flags[lv], self.flags[lv + 1])
        key = flags.tobytes()
        if key == self._regions_for:
            return
        self._regions_for = key
        labels, n = ndimage.label(flags == FLUID)
        open_ids = set()
        for d in range(3):
            for s in range(2):
                if self.open_walls[2 * d + s]:
                    face = np.take(labels, -1 if s else 0, axis=d)
                    open_ids.update(np.unique(face[face > 0]).tolist())
        closed = np.array([i for i in range(1, n + 1) if i not in open_ids], dtype=np.int64)
        if len(closed) > self.max_regions:
            raise ValueError(f"the gas domain has {len(closed)} enclosed fluid pockets (at most {self.max_regions}); "
                             f"the solids leave too many isolated cells: refine the gas grid")
        remap = np.full(n + 1, -1, dtype=np.int32)
        remap[closed] = np.arange(len(closed), dtype=np.int32)
        self.region.from_numpy(remap[labels])
        self.n_closed = len(closed)

    @ti.kernel
    def _region_sums(self, f: ti.template(), n: ti.i32):
        for i in range(n):
            self.region_sum[i] = 0.0
            self.region_count[i] = 0.0
        for I in ti.grouped(f):
            g = self.region[I]
            if g >= 0:
                self.region_sum[g] += f[I]
                self.region_count[g] += 1.0

    @ti.kernel
    def _remove_means(self, f: ti.template()) -> ti.f64:
        removed = ti.f64(0.0)
        for I in ti.grouped(f):
            g = self.region[I]
            if g >= 0:
                m = self.region_sum[g] / self.region_count[g]
                f[I] -= m
                removed += m * m
        return removed

    def _remove_region_means(self, f) -> float:
        if self.n_closed == 0:
            return 0.0
        self._region_sums(f, self.n_closed)
        return float(np.sqrt(max(self._remove_means(f), 0.0)))

    def make_compatible(self) -> float:
        """Subtract each closed region's mean from b (L y = b is then solvable); returns ‖removed part‖₂."""
        return self._remove_region_means(self.b)

    def remove_solution_means(self):
        """Subtract each closed region's mean from the solution x (the Π after L⁺ of the projection's adjoint)."""
        self._remove_region_means(self.x)

    # --- the solve ------------------------------------------------------------------------------------------
    def solve(self, tol: float, max_iterations: int) -> dict:
        """Solve L x = b (b in `self.b`, flags up to date) to ‖r‖ ≤ tol ‖b‖. Returns {"iterations", "residual"
        (relative, last), "converged", "removed" (‖b's incompatible part‖ / ‖b‖)}."""
        removed = self.make_compatible()
        self._start()
        self._dot(self.b, self.b, 0)
        bnorm = float(np.sqrt(self.sums[0]))
        out = {"iterations": 0, "residual": 0.0, "converged": True,
               "removed": removed / bnorm if bnorm > 0 else 0.0}
        if bnorm == 0.0:
            self.last = out
            return out
        self._vcycle()
        self._copy(self.z[0], self.p)
        self._dot(self.r[0], self.z[0], 1)
        rz = float(self.sums[1])
        rel = 1.0
        for it in range(1, int(max_iterations) + 1):
            self._apply(self.flags[0], self.p, self.Ap)
            self._dot(self.p, self.Ap, 2)
            pAp = float(self.sums[2])
            if pAp <= 0.0:  # the residual lies in the null space: nothing more to remove
                break
            alpha = rz / pAp
            self._update_xr(alpha)
            self._dot(self.r[0], self.r[0], 0)
            rel = float(np.sqrt(self.sums[0])) / bnorm
            out["iterations"] = it
            if rel <= tol:
                break
            self._vcycle()
            self._dot(self.r[0], self.z[0], 1)
            rz_new = float(self.sums[1])
            self._update_p(rz_new / rz)
            rz = rz_new
        out["residual"] = rel
        out["converged"] = bool(rel <= tol)
        self.last = out
        return out
