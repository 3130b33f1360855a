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

Fractional faces (`weighted=True`, the gas solver's tools by face fractions): (L y)_c = Σ_f w_f (y_c − y_n(f)) with
w_f ∈ [0, 1] each face's open share (w6, per cell and face), L = D W Dᵀ; a cell is an unknown when any face is
open. The fine level uses these weights; the coarse levels keep whole cells, which only the preconditioner sees.

Preconditioner: one V-cycle of geometric multigrid (McAdams, Sifakis & Teran 2010, "A parallel multigrid Poisson
solver for fluids simulation on large grids"): levels of half the resolution (a coarse cell is fluid when any
of its children is), red-black Gauss-Seidel smoothing (pre-smoothing red then black, post-smoothing black then
red, so the V-cycle is a symmetric operator), restriction r_2h = ½ Σ_children r_h (the stencil of level l is the
Laplacian times (2^l Δx)², hence ½ = 4/8), prolongation by injection, and smoothing sweeps as the coarsest
solve. Conjugate gradients corrects what the coarse levels get wrong near irregular solids.

Cost: each level's down leg (smoothing, residual, restriction) and up leg (prolongation, smoothing) is one kernel
launch, the coarsest solve one more, a CG iteration four more; the kernels close over their level's fields, so a
call costs no template dispatch (a V-cycle of ~30 template-kernel calls cost more in Python than in arithmetic).

Small grids: on the CPU each parallel loop of a kernel is dispatched to the thread pool, which costs tens of
microseconds whatever the loop's size; a V-cycle leg holds about eight such loops, and a CG iteration of a small
grid was mostly that (AirCirculation's small house, 40 × 27 × 3 cells: 4 ms an iteration, 380 µs a down leg).
So on the CPU the loops of every level with at most SERIAL_CELLS cells run serially, in the calling thread
(`ti.loop_config(serialize=True)`; FLUIDLAB_POISSON_SERIAL_CELLS overrides the threshold, 0 turns it off). The
arithmetic is the same and so are the bits: a colour's Gauss-Seidel updates do not read each other, and the sums
keep their fixed order (`bench/gas_poisson_serial.py`).

Stopping: ‖r_k‖₂ ≤ tol ‖b‖₂ (relative residual, b the compatible right-hand side), or the iteration cap; the
caller decides whether missing the tolerance raises or warns (gas.py). All solver vectors are float64 whatever
the working precision, so that a relative residual of 1e-6 is reachable on large grids.

Determinism: every sum the solve takes (CG's dot products, the closed regions' sums) adds its terms in one fixed
order, whatever the threads do: each column of cells is summed by one thread into `part` (on the CPU the (i, j)
columns along k, the memory's fastest axis; on a GPU the (j, k) columns along i, so that neighbouring threads read
neighbouring cells), each row of those by one thread into `part_row`, and those serially. A parallel reduction (Taichi's thread-local sums,
or atomic adds) adds them in the order the threads happen to take their blocks, which changes with the machine's
load; the last bits of a dot product then differ from run to run, and a solve whose residual lands near the
tolerance stops one iteration earlier or later. A flow over hundreds of steps carries that: AirCirculation's loss
came out as 7.551720 or 7.551713 on the same input under load (two iteration counts at some step), and its window
gradient as 0.015033 or 0.015102 (tests/test_air_circulation.py, 2026-12-06), so that two runs of the same
rollout did not agree.
"""

import os

import numpy as np
import taichi as ti

SOLID, FLUID = 0, 1
SERIAL_CELLS = 32768  # on the CPU, levels of at most this many cells run their loops serially ("Small grids")


def _on_cpu() -> bool:
    """Whether Taichi runs on the CPU (the defaults below differ between the CPU and a GPU)."""
    return ti.lang.impl.current_cfg().arch in (ti.x64, ti.arm64)


def _default_serial_cells() -> int:
    """SERIAL_CELLS, or FLUIDLAB_POISSON_SERIAL_CELLS, on the CPU; 0 (parallel loops everywhere) on a GPU."""
    if not _on_cpu():
        return 0
    text = os.environ.get("FLUIDLAB_POISSON_SERIAL_CELLS", "").strip()
    if not text:
        return SERIAL_CELLS
    if not text.isdigit():
        raise ValueError(f"FLUIDLAB_POISSON_SERIAL_CELLS must be a number of cells (0 turns the serial loops off), "
                         f"got {text!r}")
    return int(text)


def level_shapes(shape, min_cells: int = 4) -> list[tuple[int, int, int]]:
    """Grid shapes of the multigrid levels: halve (rounding up) until the largest side is at most `min_cells`."""
    shapes = [tuple(int(n) for n in shape)]
    while max(shapes[-1]) > min_cells:
        shapes.append(tuple(max(1, -(-n // 2)) for n in shapes[-1]))
    return shapes


def _operator(masks, diags):
    """The ti.func (diag, Σ y over gas neighbours) of gas cell I on one level: `masks` holds per cell a bit per
    neighbour (2d + s: axis d, side s) that is a gas cell, `diags` the number of open faces (gas neighbours and
    open walls), both made from the flags by `_make_masks`."""

    shape = tuple(masks.shape)

    @ti.func
    def diag_off(y: ti.template(), I):
        m = ti.cast(masks[I], ti.i32)
        off = ti.f64(0.0)
        for d in ti.static(range(3)):
            for s in ti.static((0, 1)):
                J = I + (2 * s - 1) * ti.Vector.unit(3, d, ti.i32)
                J[d] = ti.min(ti.max(J[d], 0), shape[d] - 1)  # clamped: the backend may load before the branch
                if (m >> (2 * d + s)) & 1:
                    off += y[J]
        return ti.cast(diags[I], ti.f64), off

    return diag_off


def _weighted_operator(w6):
    """The ti.func (diag, Σ w y over neighbours) of cell I with fractional faces (the fine level when the gas
    solver's tools enter by face fractions): w6[I][2d + s] is the open share of cell I's face on axis d, side s
    (0 for a face to a solid or a closed wall; an open wall's share counts in the diagonal only, y = 0 beyond it).
    L = D W Dᵀ stays symmetric: the gas solver writes the same share into both cells of a face."""

    shape = tuple(w6.shape)

    @ti.func
    def diag_off(y: ti.template(), I):
        diag = ti.f64(0.0)
        off = ti.f64(0.0)
        for d in ti.static(range(3)):
            for s in ti.static((0, 1)):
                wf = w6[I][2 * d + s]
                J = I + (2 * s - 1) * ti.Vector.unit(3, d, ti.i32)
                inside = J[d] >= 0 and J[d] < shape[d]
                J[d] = ti.min(ti.max(J[d], 0), shape[d] - 1)
                diag += wf
                if inside:
                    off += wf * y[J]
        return diag, off

    return diag_off


def _smoother(flags, r, z, diag_off, serial: bool = False):
    shape = tuple(z.shape)
    half = (shape[0], shape[1], -(-shape[2] // 2))

    @ti.func
    def half_sweep(color: ti.template()):
        """One Gauss-Seidel half-sweep of L z = r over the cells of one colour ((i + j + k) % 2): the loop visits
        only that colour's cells (which do not read each other: any order gives the same bits)."""
        ti.loop_config(serialize=serial)
        for i, j, kk in ti.ndrange(*half):
            k = 2 * kk + (i + j + color) % 2
            if k < shape[2]:
                I = ti.Vector([i, j, k])
                if flags[I] == FLUID:
                    diag, off = diag_off(z, I)
                    if diag > 0.0:
                        z[I] = (r[I] + off) / diag

    return half_sweep


def _make_masks(flags, masks, diags, open_walls):
    shape = tuple(flags.shape)

    @ti.kernel
    def make():
        for I in ti.grouped(flags):
            m = 0
            n = 0
            if flags[I] == FLUID:
                for d in ti.static(range(3)):
                    for s in ti.static((0, 1)):
                        J = I + (2 * s - 1) * ti.Vector.unit(3, d, ti.i32)
                        outside = J[d] < 0 or J[d] >= shape[d]
                        J[d] = ti.min(ti.max(J[d], 0), shape[d] - 1)  # never read outside the field
                        if outside:
                            if ti.static(open_walls[2 * d + s]):
                                n += 1
                        elif flags[J] == FLUID:
                            n += 1
                            m |= 1 << (2 * d + s)
            masks[I] = ti.cast(m, ti.i8)
            diags[I] = ti.cast(n, ti.i8)

    return make


def _label_linked(fluid: np.ndarray, links) -> tuple[np.ndarray, int]:
    """Connected fluid regions (labels 1..n, 0 outside the fluid) where neighbours connect only through open faces
    (ndimage.label's labelling, with the links as the graph's edges)."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    index = np.full(fluid.shape, -1, dtype=np.int64)
    index[fluid] = np.arange(int(fluid.sum()))
    rows, cols = [], []
    for d in range(3):
        lo = [slice(None)] * 3
        hi = [slice(None)] * 3
        lo[d], hi[d] = slice(0, -1), slice(1, None)
        a, b = index[tuple(lo)], index[tuple(hi)]
        ok = links[d] & (a >= 0) & (b >= 0)
        rows.append(a[ok])
        cols.append(b[ok])
    n_cells = int(fluid.sum())
    r, c = np.concatenate(rows), np.concatenate(cols)
    graph = coo_matrix((np.ones(len(r), dtype=np.int8), (r, c)), shape=(n_cells, n_cells))
    n, comp = connected_components(graph, directed=False)
    labels = np.zeros(fluid.shape, dtype=np.int32)
    labels[fluid] = comp + 1
    return labels, int(n)


@ti.data_oriented
class PoissonSolver:
    """MGPCG for L y = r on a grid of `shape` cells (see the module docstring).

    open_walls: 6 bools, (x−, x+, y−, y+, z−, z+): which domain walls are Dirichlet (y = 0 outside).
    The fine level's cell flags (`flags[0]`, FLUID or SOLID) are written by the gas solver before `solve`.
    columns_along_i: the order of the sums (module docstring, "Determinism"); None: along i on a GPU, else along k.
    serial_cells: the levels of at most this many cells run their loops serially (module docstring, "Small grids");
    None: SERIAL_CELLS on the CPU (or FLUIDLAB_POISSON_SERIAL_CELLS), 0 on a GPU."""

    def __init__(self, shape, open_walls, pre_sweeps: int = 2, post_sweeps: int = 2, bottom_sweeps: int = 30,
                 weighted: bool = False, columns_along_i: bool | None = None, serial_cells: int | None = None):
        self.shape = tuple(int(n) for n in shape)
        self.serial_cells = int(serial_cells) if serial_cells is not None else _default_serial_cells()
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
        self.region_mean = ti.field(f64, shape=self.max_regions)  # a closed region's mean (summed on the host)
        self._region_cells_at = None  # flat indices of the cells in closed regions (update_flags)
        self._region_of = None  # their closed regions
        self._region_cells = None  # (n_closed,) float: cells per closed region
        self._region_means = np.zeros(self.max_regions)  # the host's copy of region_mean
        # the sums' columns (module docstring, "Determinism"): along i on a GPU, along k on the CPU
        self.columns_along_i = not _on_cpu() if columns_along_i is None else bool(columns_along_i)
        nx, ny, nz = self.shape
        outer = (ny, nz) if self.columns_along_i else (nx, ny)
        self.part = ti.field(f64, shape=outer)  # a sum's partial over each column of cells
        self.part_row = ti.field(f64, shape=outer[0])  # and over each row of columns
        self.n_closed = 0
        self._regions_for = None  # the flags the regions were labelled for (bytes), to relabel only on change
        self.last = {"iterations": 0, "residual": 0.0, "removed": 0.0}
        self.res = [ti.field(f64, shape=sh) for sh in self.shapes[:-1]]  # the level's residual r − L z
        self.masks = [ti.field(ti.i8, shape=sh) for sh in self.shapes]  # gas neighbours, a bit per face
        self.diags = [ti.field(ti.i8, shape=sh) for sh in self.shapes]  # open faces per cell
        # weighted: the fine level's faces open by fractions (w6, written by the gas solver with the flags); the
        # coarser levels keep whole cells (a coarse cell is fluid when any child is), an approximation that only
        # the preconditioner sees, so CG still solves the fine operator
        self.weighted = bool(weighted)
        self.w6 = ti.Vector.field(6, f64, shape=self.shape) if self.weighted else None
        self._ops = [_weighted_operator(self.w6) if lv == 0 and self.weighted else
                     _operator(self.masks[lv], self.diags[lv]) for lv in range(self.n_levels)]
        self._make_masks = [_make_masks(self.flags[lv], self.masks[lv], self.diags[lv], self.open_walls)
                            for lv in range(self.n_levels)]
        self._down = [self._make_down(lv) for lv in range(self.n_levels - 1)]
        self._up = [self._make_up(lv) for lv in range(self.n_levels - 1)]
        self._coarsen = [self._make_coarsen(lv) for lv in range(self.n_levels - 1)]
        self._bottom = self._make_bottom()
        self._make_cg()

    def _serial(self, lv: int) -> bool:
        """Whether level lv's loops run serially (module docstring, "Small grids")."""
        return self.serial_cells > 0 and int(np.prod(self.shapes[lv])) <= self.serial_cells

    # --- multigrid legs, one kernel each ----------------------------------------------------------------------
    def _restriction_factor(self, lv: int) -> float:
        """r_2h = f Σ_children r_h with f = 4 / children: the coarse stencil is the Laplacian times (2h)², the
        children's mean residual times h² (8 children in 3-D, 4 where one axis is a single cell thick)."""
        fine, coarse = self.shapes[lv], self.shapes[lv + 1]
        children = int(np.prod([2 if f > c else 1 for f, c in zip(fine, coarse)]))
        return 4.0 / children

    def _make_down(self, lv: int):
        flags, r, z, rc, res = self.flags[lv], self.r[lv], self.z[lv], self.r[lv + 1], self.res[lv]
        op = self._ops[lv]
        serial = self._serial(lv)
        sweep = _smoother(flags, r, z, op, serial)
        sweeps, factor = self.pre_sweeps, self._restriction_factor(lv)
        fine, coarse = self.shapes[lv], self.shapes[lv + 1]

        @ti.kernel
        def down():
            """z = 0; pre-smoothing (red then black); the residual r − L z; the coarse level's right-hand side
            f Σ_children (r − L z), gathered per coarse cell (no atomics)."""
            ti.loop_config(serialize=serial)
            for I in ti.grouped(ti.ndrange(*fine)):
                z[I] = 0.0
            for _ in ti.static(range(sweeps)):
                sweep(0)
                sweep(1)
            ti.loop_config(serialize=serial)
            for I in ti.grouped(ti.ndrange(*fine)):
                v = ti.f64(0.0)
                if flags[I] == FLUID:
                    diag, off = op(z, I)
                    v = r[I] - (diag * z[I] - off)
                res[I] = v
            ti.loop_config(serialize=serial)
            for J in ti.grouped(ti.ndrange(*coarse)):
                acc = ti.f64(0.0)
                for a, b, c in ti.static(ti.ndrange(2, 2, 2)):
                    I = 2 * J + ti.Vector([a, b, c])
                    inside = I[0] < fine[0] and I[1] < fine[1] and I[2] < fine[2]
                    I = ti.min(I, ti.Vector([fine[0] - 1, fine[1] - 1, fine[2] - 1]))
                    if inside:
                        acc += res[I]
                rc[J] = factor * acc

        return down

    def _make_up(self, lv: int):
        flags, r, z, zc = self.flags[lv], self.r[lv], self.z[lv], self.z[lv + 1]
        serial = self._serial(lv)
        sweep = _smoother(flags, r, z, self._ops[lv], serial)
        sweeps, fine = self.post_sweeps, self.shapes[lv]

        @ti.kernel
        def up():
            """z += the coarse correction (injection); post-smoothing (black then red)."""
            ti.loop_config(serialize=serial)
            for I in ti.grouped(ti.ndrange(*fine)):
                z[I] += zc[I // 2]
            for _ in ti.static(range(sweeps)):
                sweep(1)
                sweep(0)

        return up

    def _make_coarsen(self, lv: int):
        fine, coarse = self.flags[lv], self.flags[lv + 1]

        @ti.kernel
        def coarsen():
            for I in ti.grouped(coarse):
                coarse[I] = ti.cast(SOLID, ti.i8)
            for I in ti.grouped(fine):
                if fine[I] == FLUID:
                    coarse[I // 2] = ti.cast(FLUID, ti.i8)

        return coarsen

    def _make_bottom(self):
        lv = self.n_levels - 1
        flags, r, z, op = self.flags[lv], self.r[lv], self.z[lv], self._ops[lv]
        nx, ny, nz = self.shapes[lv]
        n = nx * ny * nz
        sweeps = self.bottom_sweeps

        @ti.kernel
        def bottom():
            """The coarsest level's solve: z = 0, then symmetric Gauss-Seidel sweeps (forward, then backward in
            lexicographic order), serially in one launch (the level has a few dozen cells)."""
            ti.loop_config(serialize=True)
            for _ in range(1):
                for i, j, k in ti.ndrange(nx, ny, nz):
                    z[i, j, k] = 0.0
                for _s in range(sweeps):
                    for m2 in range(2 * n):
                        m = m2 if m2 < n else 2 * n - 1 - m2
                        I = ti.Vector([m // (ny * nz), (m // nz) % ny, m % nz])
                        if flags[I] == FLUID:
                            diag, off = op(z, I)
                            if diag > 0.0:
                                z[I] = (r[I] + off) / diag

        return bottom

    def _vcycle(self):
        """z[0] = M⁻¹ r[0]: one symmetric V-cycle."""
        for lv in range(self.n_levels - 1):
            self._down[lv]()
        self._bottom()
        for lv in reversed(range(self.n_levels - 1)):
            self._up[lv]()

    # --- CG, fused vector operations ----------------------------------------------------------------------------
    def _make_cg(self):
        flags, x, b, p, Ap, r0, z0 = self.flags[0], self.x, self.b, self.p, self.Ap, self.r[0], self.z[0]
        op = self._ops[0]
        part, part_row = self.part, self.part_row
        nx, ny, nz = self.shape
        along_i = self.columns_along_i
        n1, n2, n3 = (ny, nz, nx) if along_i else (nx, ny, nz)  # columns (i1, i2), each summed along i3
        serial = self._serial(0)

        @ti.func
        def cell(i1, i2, i3):
            I = ti.Vector([i1, i2, i3])
            if ti.static(along_i):
                I = ti.Vector([i3, i1, i2])
            return I

        def fixed_order_sum(term):
            """A kernel (α) -> Σ_I term(I, α) over the cells, the sum in a fixed order (the module docstring's
            "Determinism"): each column by one thread, the columns' sums row by row in parallel, the rows serially.
            term may also write the cell's vector entries."""

            @ti.kernel
            def kernel(alpha: ti.f64) -> ti.f64:
                ti.loop_config(serialize=serial)
                for i1, i2 in ti.ndrange(n1, n2):
                    s = ti.f64(0.0)
                    for i3 in range(n3):
                        s += term(cell(i1, i2, i3), alpha)
                    part[i1, i2] = s
                ti.loop_config(serialize=serial)
                for i1 in range(n1):
                    s = ti.f64(0.0)
                    for i2 in range(n2):
                        s += part[i1, i2]
                    part_row[i1] = s
                t = ti.f64(0.0)
                ti.loop_config(serialize=True)
                for i1 in range(n1):
                    t += part_row[i1]
                return t

            return kernel

        @ti.func
        def start_term(I, alpha):
            """x = 0, r = b; b·b (the pressure is not warm-started: the forward and the adjoint solve take the same
            path)."""
            x[I] = 0.0
            r0[I] = b[I]
            return b[I] * b[I]

        @ti.func
        def first_direction_term(I, alpha):
            """p = z; r·z."""
            p[I] = z0[I]
            return r0[I] * z0[I]

        @ti.func
        def apply_dot_term(I, alpha):
            """Ap = L p (0 on solid cells); p·Ap."""
            v = ti.f64(0.0)
            if flags[I] == FLUID:
                diag, off = op(p, I)
                v = diag * p[I] - off
            Ap[I] = v
            return p[I] * v

        @ti.func
        def update_term(I, alpha):
            """x += α p, r −= α Ap; r·r."""
            x[I] += alpha * p[I]
            r0[I] -= alpha * Ap[I]
            return r0[I] * r0[I]

        @ti.func
        def rz_term(I, alpha):
            return r0[I] * z0[I]

        start, first_direction = fixed_order_sum(start_term), fixed_order_sum(first_direction_term)
        apply_dot, update, rz_dot = (fixed_order_sum(apply_dot_term), fixed_order_sum(update_term),
                                     fixed_order_sum(rz_term))

        @ti.kernel
        def next_direction(beta: ti.f64):
            ti.loop_config(serialize=serial)
            for I in ti.grouped(ti.ndrange(nx, ny, nz)):
                p[I] = z0[I] + beta * p[I]

        @ti.kernel
        def apply_to(y: ti.template(), out: ti.template()):
            """out = L y (0 on solid cells), for checks."""
            for I in ti.grouped(y):
                v = ti.f64(0.0)
                if flags[I] == FLUID:
                    diag, off = op(y, I)
                    v = diag * y[I] - off
                out[I] = v

        self._start, self._first_direction = (lambda: start(0.0)), (lambda: first_direction(0.0))
        self._apply_dot, self._rz_dot = (lambda: apply_dot(0.0)), (lambda: rz_dot(0.0))
        self._update, self._next_direction, self.apply = update, next_direction, apply_to

    # --- compatibility on closed regions ----------------------------------------------------------------------
    def update_flags(self, flags: np.ndarray | None = None, links=None):
        """After flags[0] changed: coarsen them and label the closed fluid regions (those touching no open
        wall), whose right-hand sides must sum to zero. links: with fractional faces, three boolean arrays
        ((nx−1, ny, nz), (nx, ny−1, nz), (nx, ny, nz−1)) saying which faces between neighbouring cells are open at
        all; two fluid cells whose shared face is shut are not connected through it."""
        from scipy import ndimage

        for lv in range(self.n_levels - 1):
            self._coarsen[lv]()
        for lv in range(1 if self.weighted else 0, self.n_levels):  # a weighted fine level reads w6, not masks
            self._make_masks[lv]()
        if flags is None:
            flags = self.flags[0].to_numpy()
        key = flags.tobytes() + (b"" if links is None else b"".join(np.packbits(k).tobytes() for k in links))
        if key == self._regions_for:
            return
        self._regions_for = key
        if links is None:
            labels, n = ndimage.label(flags == FLUID)
        else:
            labels, n = _label_linked(flags == FLUID, links)
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
        ids = remap[labels]
        self.region.from_numpy(ids)
        self.n_closed = len(closed)
        flat = ids.ravel()
        self._region_cells_at = np.flatnonzero(flat >= 0)  # the cells in closed regions (flat, C order)
        self._region_of = flat[self._region_cells_at].astype(np.int64)  # and their regions
        self._region_cells = np.bincount(self._region_of, minlength=self.n_closed).astype(np.float64)

    @ti.kernel
    def _subtract_region_means(self, f: ti.template()):
        for I in ti.grouped(f):
            g = self.region[I]
            if g >= 0:
                f[I] -= self.region_mean[g]

    def _remove_region_means(self, f) -> float:
        """Subtract each closed region's mean from f; returns ‖the removed part‖₂. The sums are numpy's bincount
        over the cells in their order, so they do not depend on the threads (module docstring, "Determinism")."""
        if self.n_closed == 0:
            return 0.0
        values = f.to_numpy().ravel()[self._region_cells_at]
        means = np.bincount(self._region_of, weights=values, minlength=self.n_closed) / self._region_cells
        self._region_means[: self.n_closed] = means
        self.region_mean.from_numpy(self._region_means)
        self._subtract_region_means(f)
        return float(np.sqrt(np.dot(self._region_cells, means * means)))

    def make_compatible(self) -> float:
        """Subtract each closed region's mean from b (L y = b is then solvable); returns ‖removed part‖₂."""
        return self._remove_region_means(self.b)

    def remove_solution_means(self):
        """Subtract each closed region's mean from the solution x (the Π after L⁺ of the projection's adjoint)."""
        self._remove_region_means(self.x)

    # --- the solve ------------------------------------------------------------------------------------------
    def solve(self, tol: float, max_iterations: int) -> dict:
        """Solve L x = b (b in `self.b`, flags up to date) to ‖r‖ ≤ tol ‖b‖. Returns {"iterations", "residual"
        (relative, last), "converged", "rhs_norm" ‖b‖₂ (after the compatibility), "removed_norm" (‖b's incompatible
        part‖₂, in closed regions) and "removed" (the same over ‖b‖)}."""
        removed = self.make_compatible()
        bnorm = float(np.sqrt(max(self._start(), 0.0)))
        out = {"iterations": 0, "residual": 0.0, "converged": True, "rhs_norm": bnorm, "removed_norm": removed,
               "removed": removed / bnorm if bnorm > 0 else 0.0}
        if bnorm == 0.0:
            self.last = out
            return out
        self._vcycle()
        rz = self._first_direction()
        rel = 1.0
        for it in range(1, int(max_iterations) + 1):
            pAp = self._apply_dot()
            if pAp <= 0.0:  # the residual lies in the null space: nothing more to remove
                break
            rel = float(np.sqrt(max(self._update(rz / pAp), 0.0))) / bnorm
            out["iterations"] = it
            if rel <= tol:
                break
            self._vcycle()
            rz_new = self._rz_dot()
            self._next_direction(rz_new / rz)
            rz = rz_new
        out["residual"] = rel
        out["converged"] = bool(rel <= tol)
        self.last = out
        return out
