"""The liquids' pressure by a projection on the grid, solved together with a rigid body's motion where the scene has
one, or with its deformable solids' nodes, beside its statics and tools (`Scene(pressure="projection")`; forward
solver only). Issue 19; docs/engine.md, "Floating bodies: the projection".

Why. With the default weakly compressible liquid (pressure from J by an equation of state) a rigid body and the
liquid share one velocity field where they touch, and the liquid's push reaches the body only as the liquid
compresses the body's bottom layers: a slow, history-dependent route, so that light bodies floated 0.1 of their
side too high, then crept (docs/engine.md, "Open problems"). Here the liquid is incompressible, its pressure p (Pa)
is the unknown of a Poisson problem on the MPM grid, and the body's rigid velocity q = (V, ω) is an unknown of the
same solve (monolithic, after Batty, Bertails & Bridson 2007, "A fast variational framework for accurate
solid-fluid coupling"): the body's push is the adjoint of its wall's flux, so that the coupling does no net work.

Per substep (FastSolver.projected_substep):
    P2G           the liquid's F stays I (its stress keeps only its deviatoric, viscous part); the body carries no
                  stress (and keeps J = 1: rigid.py); the liquid field's v* = mv/m + Δt g at every node (no walls yet), and v⁰ = mv/m (AFLIP)
    classify      node kinds: LIQ (an unknown: liquid fill ≥ ½ of the room the walls and body leave it), AIR
                  (p = 0), WALL (beyond the walls' rows), BSOLID (inside the body, deeper than a cell; moving with it)
    enclose_air   an air pocket the body borders that no path of air joins to the top is liquid (below)
    solve         (A_a + Δx B M⁻¹ Bᵀ) p = −(D u*)/Δt  by preconditioned CG (float64, warm-started; over a list of
                  the unknowns in lexicographic order). On the CPU MIC(0) and the whole CG in one serial launch (each
                  launch costs the host 50-80 µs there, as much as an iteration's arithmetic at the tasks' sizes); on
                  a GPU the diagonal (Jacobi; MIC(0)'s sweeps are serial) and one parallel launch an iteration, its
                  sums in a fixed order of chunks (`preconditioner`, `serial_cg`; bench/projection_preconditioners.py)
    correct       u = u* − Δt/ρ ∇p on the faces; q = q* + Δt M⁻¹ Q
    G2P           the liquid's particles gather u and C from the faces (a staggered grid), with AFLIP
    position      particles of a packed liquid move down the gradient of a second potential (below)
    rigid         the body's projection to one rigid motion, with the walls' contact (rigid.py), then its push Δq

Emitters. A pool particle adds nothing to the grid until its emitter has emitted it (emitters.py); the particles
born in a substep leave their nozzles in G2P, after the solve, as in the default solver, and the position
correction moves only emitted ones. A jet into water adds its volume to the layer (tests/test_projection.py).

Density. The liquids may differ in density: ρ_I at node I is the liquids' mass there over their particles'
volume (ρ of the densest liquid where none has volume), and a face between unknowns I and J has 1/ρ = 2/(ρ_I + ρ_J)
(below written ρ), so that the pressure rises by each layer's own ρ g (tests/test_projection.py: brine under water).
A domain without air is pinned (p = 0 half a cell above its highest liquid node) and skips the position correction.

Statics and tools (solids of prescribed velocity: 0, or the tool's rigid motion at the substep's start pose; beside a
rigid body too, which meets them through rigid.py's contact). Each face f has their share σ_k (the statics' once, the tools' each substep, by the same sub-box rule as
the body's σ_f, the tools' in what the statics leave), the liquid's open share becomes a_f = 1 − σ_f − σ_k (the body's
σ_f capped at 1 − σ_k), and the divergence gains the tools' flux Σ_t σ_t u_t·e_d:
    (D u)_I = Σ_f s w_f [a_f u_f + σ_f K_f·q + Σ_t σ_t u_t·e_d] / Δx
A node over a cell inside one (φ ≤ −Δx) is a wall moving with it; so is a node over half a cell inside that is not
liquid (as air, p = 0 there drew the liquid into the solid), and a liquid node inside one whose faces are open by
less than KIN_OPEN_MIN in all. The room a node's liquid fills is what the walls', statics' and tools' share of its
B-spline stencil leaves, from a quadrature of their SDF over the stencil's 6³ half-cell boxes (stencil_share_func;
from φ at the node alone a tank's inner corner counted ½ where ⅞ is wall, and its liquid drained through the walls).
After the solve a face partly theirs carries the liquid's (and the body's) velocity, not a blend with theirs; a face
they close, theirs. The deformable solids' nodes take the statics' and tools' contact laws (grid.boundary), and the
liquid's particles are put out of every tool after the substep (tools.Tool.keep_out). docs/engine.md, "Statics and
tools in the projection", has the measurements.

Deformable solids (elastic, plastic; in a scene without a rigid body). They keep the solids' velocity field and
their own stress; each of its nodes' velocities v_K (mass m_K) is an unknown of the same solve, as the rigid body's
q is: a face between I and J has the solids' share σ_f of its Δx³ box, from their particles' boxes (soft_faces; 1
where a node is SOFT: the solids' volume share s of its cell at least FILL and no liquid),
their velocity u_f = Σ_K c_fK v_K·e_d with c_fK = m_K/(m_I + m_J) over its two nodes, and the pressure's force on
v_K is Q_K = Δx² G_K, G_K = Σ_f c_fK σ_f w_f s (p_K − p_J) e_d. So (A p)_I gains Δx Σ_f s σ_f w_f Σ_K c_fK (G_K/m_K)·e_d (matrix-free,
symmetric; the MIC(0) factor leaves it to the CG) and v_K = v*_K + Δt Δx² G_K/m_K after the solve. Taken into the
liquid's field instead, as a mixture, an elastic cube stood on the water instead of entering it
(docs/experiments/elastic_mixture_projection.patch).

Discretisation. Node I at x_I = origin + I Δx; the face f from I to J = I + s e_d (s = ±1) has the midpoint
x_f, the body's solid share σ_f (the share of the face's Δx³ box inside the body, from the body's SDF φ:
clamp(½ − φ(x_f)/Δx, 0, 1), from 4³ sub-boxes where |φ(x_f)| < Δx, so that a box holding an edge of the body
counts it), its open share a_f = 1 − σ_f, and the walls' weight w_f (½ per wall the face's square lies on, after
Batty et al. 2007's variational weights for a wall through the nodes; 0 beyond it). With K_f = (e_d, r_f × e_d),
r_f = x_f − c:
    (D u)_I = Σ_f s w_f [a_f u_f + σ_f K_f·q] / Δx
    u_f = ½ (u*_I + u*_J)·e_d − Δt (p_J − p_I)/(ρ Δx)      (liquid–liquid)
    u_f = u*_I·e_d − Δt (0 − p_I)/(ρ θ Δx)                 (liquid–air: p = 0 at θ of the way, θ from the fills'
                                                             B-spline inverse, θ ≥ 0.1, THETA_RULE; ghost fluid)
    u_f = the nodes' mean, after and before the substep      (outside the solve: air; AFLIP's u_f − u⁰_f there is
                                                             gravity, as for a free particle)
    u_f = u⁰_f                                              (outside the solve with a node in a wall, static or
                                                             tool: the particles beside it gather no gravity that
                                                             the pressure does not balance)
    Q = Δx² Σ_I p_I b_I,   b_I = Σ_f s w_f σ_f K_f          (the pressure's force and torque on the body)
    q = q* + Δt M⁻¹ Q,    M = diag(m 1, I_c),   q* = the body's velocity after the last push, plus g Δt
Each solid face's weight whose segment the body's surface crosses (t cells beyond I, from φ at the two nodes) is
moved from I to the crossing by linear extrapolation from I and I' = I − s e_d, b_I += (1 + t) w, b_I' += −t w,
so that a linear pressure gives the surface's pressure, not the node's (held still at Archimedes' depth, a 4 cm cube
gets 1.020 of its weight at 16 cells and 1.004 at 32; 1.055 and 1.009 without). A shell node inside the body but
within a cell of its surface is liquid if it borders the liquid, unless its faces are open by less than half a
face in all (its pressure would be ill-determined: such nodes threw the liquid out at 2-7 m/s): then it is the
body's. An air pocket that
no path of air nodes joins to the air at the top and that the body borders (a node within a cell of its surface)
is a vacuum, not air: its nodes are liquid unknowns, their u* the body's velocity when they join the pocket and
their own after the last solve from then on. The body's particles keep the liquid
out of the gap under a body on the floor, and with p = 0 there a buoyant cube stood on the floor stayed there (the
liquid's pressure pressed its top and never reached its bottom); now it lifts off (tests/test_projection.py).
The work the wall does on the liquid, −Δt Q·q, and the push's, Δt Q·q* + ½ Δq·M Δq, sum to
−½ Δq·M Δq ≤ 0.

Position correction (after Kugelstadt et al. 2019's density projection on positions): a FLIP liquid under a
velocity projection packs (8-14 % of its volume in 2 s): with ψ = 0 at the free surface, Neumann at the walls, and
the pressure solve's own matrix (so the body's faces count by their open share, and the body's rank-6 term treats
it as free to give way; it is not moved), −∇²ψ = φ − 1.005 at liquid nodes packed beyond 1.005, or φ − 0.995 where
loosened below 0.995 away from the surface (solved to a relative residual of 1e-3), and each liquid particle moves by ½ Σ_i w_ip (−∇ψ)_i per substep. It moves particles,
adds no velocity.

Units: p in Pa, velocities in m/s, ψ in m², q's angular part in rad/s. Float64 in the solve whatever the state's
precision. The measurements behind each rule (and the rules tried and dropped) are in docs/engine.md and
docs/experiments/README.md.
"""
import numpy as np
import taichi as ti

from fluidlab_core import runtime
from fluidlab_core.engine import grid, statics, transfer
from fluidlab_core.engine.emitters import takes_part

AIR, LIQ, WALL, BSOLID = 0, 1, 3, 4
SOFT = 9  # a node of a deformable solid without liquid (no unknown; its faces to the liquid are closed)
# A face's share σ inside the deformable solids: the share of the face's Δx³ box that their particles' boxes cover
# (soft_faces). Before (2026-12-05 to 12-07) σ came from the mean s̄ of its two nodes' B-spline volume shares,
# clamp(½ + (s̄ − ½)·4/3) (4/3 the inverse of the smearing's slope at a plane surface): a share along one axis, where
# at a body's edges and corners the node's share is a product of two or three (s = Φ(d_x) Φ(d_z)) and the rule
# read the faces under an edge column as open. The pressure's force on a 0.8 ρ_w elastic cube then fell 5 % short
# of ρ_w g × its volume under the pressure's own zero level (the rows of node columns beside its sides 0.58 and 0.63 of theirs), and it
# floated 1.5 mm (0.2 Δx) deep at 16 cells (0.829 for 0.80). docs/engine.md, "Elastic bodies in the projection".
SHELL, LIQ_SHELL, AIR_SHELL, ENC_SHELL = 5, 6, 7, 8  # the classification's passes over the body's shell

TOL = 1e-7  # the pressure CG's relative residual
# the position correction's relative residual: it moves particles by a share of a packing error of a few per cent, so
# 1e-3 is ample. Measured at 16 cells (bench/buoyancy_3d.py, 10 s, dropped 500 and 800 kg/m³ cubes): the per-second
# means and the liquid's surface as at 1e-7 within the runs' own scatter (0.475-0.501 against 0.476-0.502, 0.775-0.792
# against 0.774-0.791; the far field's surface 0.08 mm lower), and the runs took 290 s instead of 585 s.
CORRECTION_TOL = 1e-3
MAX_IT = 400  # the CG's iteration cap
FILL = 0.5  # a node with this much of its room filled by liquid is liquid (an unknown)
THETA_MIN = 0.1  # the least share θ of the way from a liquid node to an air node at which p = 0 is placed
# Where between a liquid node I and an air node J the free surface (p = 0) lies. A node's fill is its B-spline
# stencil's share of liquid, so across a flat surface at height H the fills are C((H − x)/Δx), C the quadratic
# B-spline's cumulative distribution (a cubic by pieces), and the surface is where each fill's inverse puts it:
# θ = u_I or 1 + u_J, u = C⁻¹(fill) (cells), averaged with the weights C'(u) (the fill nearer ½ measures it better).
# "linear" (before 2026-12-08): θ = (φ_I − ½)/(φ_I − φ_J), exact only where the surface lies on a node or halfway
# between two; a quarter cell above a node it put p = 0 0.048 Δx too high (0.36 mm at 16 cells), and a quarter cell
# below one as much too low, so a floating body's depth against the liquid's volume moved with where the surface met
# the grid (bench/free_surface_level.py; docs/engine.md, "The free surface's height"). The ghost-fluid boundary
# itself: Gibou, Fedkiw, Cheng & Kang 2002.
THETA_RULE = "spline"  # or "linear"; read when the kernels compile
OPEN_MIN = 0.5  # a shell node whose faces are open by less than this (faces, all six together) is the body's
KIN_OPEN_MIN = 0.5  # a liquid node inside a static or tool whose faces are open by less than this is theirs
SUB_BOXES = 4  # sub-boxes per axis for a face's solid share where the body's surface may cross its box
POSITION_CORRECTION = 0.5  # the share of the position correction's displacement applied per substep
# no position correction within 1 ± this fill. 0.02 until a zero right-hand side gave ψ = 0 instead of re-applying
# the last ψ (b6f60d7): the liquid could then pack by up to 2 % unchecked, and a dropped 800 kg/m³ cube sank to 0.835
# of its volume under (Archimedes 0.80) by its eighth second at 16 cells. At 0.005: 0.788-0.808, and 0.476-0.511 for
# a 500 kg/m³ cube, over seconds 1-10 (bench/results/buoyancy_3d.txt, 2026-12-05).
PACKING_BAND = 0.005
MIC_TAU, MIC_SIGMA = 0.97, 0.25  # MIC(0) (Bridson, "Fluid Simulation for Computer Graphics", 2nd ed., §5.4)
# The parallel path's sums (a GPU's): each thread sums CHUNK consecutive unknowns of the list, the chunks' sums are
# added serially, so that the order of every sum is fixed (atomic adds follow the hardware's scheduling)
CHUNK = 256
# the CG's iteration cap with the Jacobi preconditioner (the GPU's): it needs 3.3-5.4x MIC(0)'s iterations, more as the
# cell shrinks (55, 71, 86, 122 a solve at 12, 16, 24, 32 cells: bench/results/projection_preconditioners_cpu.txt)
MAX_IT_JACOBI = 2000


def face_share_func(sdf, dx: float):
    """A Taichi function share(x_f, R, o) -> the share of the Δx³ box centred on x_f inside the solid whose SDF in its
    own frame is `sdf` (negative inside), at pose (R, o): local x = Rᵀ(x − o). clamp(½ − φ(x_f)/Δx, 0, 1) where the
    surface is over a cell away; from SUB_BOXES³ sub-boxes where |φ(x_f)| < Δx, so that a box holding an edge of the
    solid counts it (module docstring)."""

    @ti.func
    def share(xm, R, o):
        sd = ti.cast(sdf(R.transpose() @ (xm - o)), ti.f64)
        out = ti.min(ti.max(0.5 - sd / dx, 0.0), 1.0)
        if ti.abs(sd) < dx:
            n = ti.static(SUB_BOXES)
            h = dx / n
            acc = ti.f64(0.0)
            for a, b, c in ti.ndrange(n, n, n):
                xs = xm + (ti.Vector([a, b, c]) + 0.5) * h - 0.5 * dx
                acc += ti.min(ti.max(0.5 - ti.cast(sdf(R.transpose() @ (xs - o)), ti.f64) / h, 0.0), 1.0)
            out = acc / (n * n * n)
        return out

    return share


# A node's stencil share inside a solid is Σ W_a W_b W_c × (the sub-box's share inside) over the 6³ half-cell
# sub-boxes of the quadratic B-spline's support [−3/2, 3/2] (cells): W = 1/48, 7/48, 1/3 for the halves whose
# midpoints are 5/4, 3/4, 1/4 cells from the node (the spline's integral over each). Exact for a plane through the
# nodes and for the corners and edges where such planes meet (statics.bspline_cdf, from φ alone, counts ½ at a
# tank's inner corner, whose share is ⅞).


def stencil_share_func(sdf, dx: float):
    """A Taichi function share(x_I, R, o) -> the share of the quadratic B-spline stencil of the node at x_I inside the
    solid whose SDF in its own frame is `sdf`, at pose (R, o) (local x = Rᵀ(x − o)): 6³ half-cell sub-boxes, each
    counted by clamp(½ − φ/h, 0, 1) at its centre (h = Δx/2). 0 without evaluating them where φ(x_I) > 2.7 Δx."""

    @ti.func
    def share(xn, R, o):
        out = ti.f64(0.0)
        if ti.cast(sdf(R.transpose() @ (xn - o)), ti.f64) < 2.7 * dx:
            h = 0.5 * dx
            for a, b, c in ti.ndrange(6, 6, 6):
                s = 0.5 * (ti.Vector([a, b, c]) - 2.5)  # the sub-box's midpoint, in cells from the node
                w = ti.f64(1.0)
                for e in ti.static(range(3)):
                    w *= ti.select(ti.abs(s[e]) > 1.0, 1.0 / 48.0, ti.select(ti.abs(s[e]) > 0.5, 7.0 / 48.0, 1.0 / 3.0))
                sd = ti.cast(sdf(R.transpose() @ (xn + dx * s - o)), ti.f64)
                out += w * ti.min(ti.max(0.5 - sd / h, 0.0), 1.0)
        return out

    return share


@ti.func
def _spline_cdf_inverse(c):
    """u (cells) with statics.bspline_cdf(u) = c (the quadratic B-spline's cumulative distribution: (u + 3/2)³/6 for
    u ≤ −½, ½ + ¾u − u³/3 for |u| ≤ ½, 1 − (3/2 − u)³/6 for u ≥ ½); c clamped into (0, 1)."""
    c = ti.min(ti.max(c, 1e-9), 1.0 - 1e-9)
    u = ti.f64(0.0)
    if c <= 1.0 / 6.0:
        u = ti.pow(6.0 * c, 1.0 / 3.0) - 1.5
    elif c >= 5.0 / 6.0:
        u = 1.5 - ti.pow(6.0 * (1.0 - c), 1.0 / 3.0)
    else:  # Newton on the middle cubic (its slope ¾ − u² ≥ ½ there)
        u = (c - 0.5) / 0.75
        for _ in ti.static(range(4)):
            u -= (statics.bspline_cdf(u) - c) / (0.75 - u * u)
    return u


@ti.func
def _spline_density(u):
    """C'(u): the quadratic B-spline at u (cells)."""
    au = ti.abs(u)
    out = ti.f64(0.0)
    if au <= 0.5:
        out = 0.75 - au * au
    elif au < 1.5:
        out = 0.5 * (1.5 - au) * (1.5 - au)
    return out


@ti.data_oriented
class LiquidProjection:
    """The projection of a FastSolver whose model has `projection` (liquids, and one rigid body or none)."""

    def __init__(self, solver):
        self.solver = solver
        model = solver.model
        self.model = model
        self.rho_w = float(model.liquid_density)
        self.rho = ti.field(ti.f64, shape=())  # ρ_w in float64 (a Python constant would take the default precision)
        self.has_body = model.has_rigid  # the rigid body, if the scene has one (else only the mixture and walls)
        # deformable solids (elastic, plastic): the solids' field's nodes, each an unknown velocity of the solve
        self.has_soft = model.projection_soft
        shape = model.grid_shape
        f64, real = ti.f64, model.real
        self.kind = ti.field(ti.i8, shape=shape)
        self.phi = ti.field(f64, shape=shape)  # the mixture's fill of the room its node has (free surface)
        self.rho_n = ti.field(f64, shape=shape)  # the mixture's density at the node (kg/m³): its mass over its volume
        self.phi_all = ti.field(f64, shape=shape)  # all particles' and the walls' fill (the packing)
        self.sdf = ti.field(f64, shape=shape)  # the body's SDF at the node (m)
        self.vs = ti.Vector.field(3, f64, shape=shape)  # u* per node, or the wall's or the body's velocity
        self.b = ti.field(f64, shape=shape)  # right-hand side
        self.p = ti.field(f64, shape=shape)  # the solution (Pa; ψ in m² during the position correction)
        self.psi = ti.field(f64, shape=shape)  # the position correction's potential (m²), warm start
        self.p_keep = ti.field(f64, shape=shape)
        self.r = ti.field(f64, shape=shape)  # CG: residual, preconditioned residual, direction, A d
        self.z = ti.field(f64, shape=shape)
        self.d = ti.field(f64, shape=shape)
        self.Ad = ti.field(f64, shape=shape)
        self.diag = ti.field(f64, shape=shape)  # the liquid Laplacian's diagonal
        self.pdiag = ti.field(f64, shape=shape)  # with the body's rank-6 term
        self.aoff = ti.Vector.field(6, f64, shape=shape)  # off-diagonal face weights a_f w_f/ρ to −x, +x, …, +z
        self.sig_p = ti.Vector.field(3, f64, shape=shape)  # σ of the face from I to I + e_d
        self.bf = ti.Vector.field(3, f64, shape=shape)  # b_I's force part (1)
        self.bt = ti.Vector.field(3, f64, shape=shape)  # and torque part (m)
        self.mic = ti.field(f64, shape=shape)  # 1/√e of the MIC(0) factor's diagonal
        self.mic_q = ti.field(f64, shape=shape)  # and the forward sweep's result
        # the unknowns in lexicographic order (mic0 lists them once per projection, for both solves): the CG's
        # kernels run over these alone, not over the whole grid (the liquid fills a quarter of GatheringEasy's grid)
        self.unk = ti.Vector.field(3, ti.i32, shape=int(np.prod(shape)))
        self.n_unk = ti.field(ti.i32, shape=())
        self.cg_rz = ti.field(f64, shape=())  # the CG's r·z and next β, kept on the device between its launches
        self.cg_beta = ti.field(f64, shape=())
        self.cg_its = ti.field(ti.i32, shape=())  # _solve_serial's iterations, and its |b|²
        self.cg_bn2 = ti.field(f64, shape=())
        # the CG as one serial launch (_solve_serial) on the CPU, one parallel launch an iteration (_iterate) on a GPU,
        # whose threads a serial loop would idle; set before the first substep to choose (read when compiling)
        self.serial_cg = runtime.ensure_init().backend == "cpu"
        # the preconditioner: MIC(0) (incomplete Cholesky, Bridson §5.4; its two sweeps are serial) with the serial CG
        # on the CPU, where it needs 3.3-5.4x fewer iterations; the diagonal (Jacobi, every node in parallel) on a GPU,
        # where MIC(0)'s sweeps would run the whole grid on one thread and the listing of the unknowns in one serial
        # loop (mic0); there they are listed by columns in parallel (_list_unknowns). Set before the first substep
        # (read when compiling): "mic" or "jacobi".
        self.preconditioner = "mic" if self.serial_cg else "jacobi"
        # a shell node whose faces are open by less than this is the body's (OPEN_MIN; the benches that study the rule
        # set it per run before the first substep: read when compiling)
        self.open_min = OPEN_MIN
        self.part = ti.field(f64, shape=-(-int(np.prod(shape)) // CHUNK))  # the chunks' sums (_ordered_sum)
        self.part_v = ti.Vector.field(6, f64, shape=-(-int(np.prod(shape)) // CHUNK))  # and of the body's sums
        self.col_start = ti.Vector.field(2, ti.i32, shape=shape[:2])  # a column's first unknown, and solids' node
        self.disp = ti.Vector.field(3, real, shape=shape)  # the position correction's −∇ψ at liquid nodes (m)
        self.uf = ti.Vector.field(3, real, shape=shape)  # face I + ½e_d's velocity after the solve (m/s)
        self.uf0 = ti.Vector.field(3, real, shape=shape)  # and before gravity and the solve (AFLIP's v⁰)
        self.bx_f = ti.Vector.field(3, f64, shape=())  # Σ_I x_I b_I (force, torque parts)
        self.bx_t = ti.Vector.field(3, f64, shape=())
        self.q_lin = ti.Vector.field(3, f64, shape=())  # q*: the body's velocity the solve starts from (m/s)
        self.q_ang = ti.Vector.field(3, f64, shape=())  # (rad/s)
        self.dq_lin = ti.Vector.field(3, f64, shape=())  # the last push's velocity change
        self.dq_ang = ti.Vector.field(3, f64, shape=())
        self.body_dP = ti.Vector.field(3, f64, shape=())  # the solve's impulse on the body (N s)
        self.body_dL = ti.Vector.field(3, f64, shape=())  # its angular impulse about the centre of mass (N m s)
        self.minv_I = ti.Matrix.field(3, 3, f64, shape=())  # I_c⁻¹ (world)
        self.minv_m = ti.field(f64, shape=())  # 1/m
        self.force = ti.Vector.field(3, real, shape=())  # the push's force (N) and torque (N m), from the host
        self.torque = ti.Vector.field(3, real, shape=())
        self.enclosed = ti.field(ti.i8, shape=shape)  # 1 at an enclosed air node beside the body (enclose_air)
        if self.has_soft:
            self.soft_s = ti.field(f64, shape=shape)  # the solids' volume share of the node's cell
            self.soft_m = ti.field(f64, shape=shape)  # the solids' node mass (kg)
            self.soft_v = ti.Vector.field(3, f64, shape=shape)  # their velocity v* before the solve (m/s)
            self.soft_dv = ti.Vector.field(3, f64, shape=shape)  # G_K/m_K of the CG's x (soft_of; 1/(m s))
            self.soft_nodes = ti.Vector.field(3, ti.i32, shape=int(np.prod(shape)))  # the nodes with solids' mass
            self.n_soft = ti.field(ti.i32, shape=())  # (not walls'), listed by mic0 for the CG's soft_of
            self.soft_face = ti.Vector.field(3, f64, shape=shape)  # their share of the face box I + ½e_d (soft_faces)
            self.serial_faces = runtime.ensure_init().backend == "cpu"  # soft_faces' sums in a fixed order
        dx = float(model.dx)
        if self.has_body:
            self._body_share = face_share_func(model.rigid.sdfs[0], dx)
        # statics and tools: solids of prescribed velocity (0, or the tool's rigid motion) that close faces
        self.has_kin = bool(model.colliders) or model.n_tools > 0
        if self.has_kin:
            self._static_share = [face_share_func(c.sdf, dx) for c in model.colliders]
            self._tool_share = [face_share_func(t.sdf_local, dx) for t in model.tools]
            self._tool_stencil = [stencil_share_func(t.sdf_local, dx) for t in model.tools]
            lower, upper = tuple(model.lower), tuple(model.upper)

            @ti.func
            def outside(x):  # the SDF of the walls' outside and the statics together (m): the distance to the
                solid = ti.f64(1e9)  # nearest wall inside the domain, negative beyond a wall
                for e in ti.static(range(3)):
                    solid = ti.min(solid, ti.min(x[e] - lower[e], upper[e] - x[e]))
                for k in ti.static(range(len(model.colliders))):
                    solid = ti.min(solid, ti.cast(model.colliders[k].sdf(x), ti.f64))
                return solid
            self._walls_stencil = stencil_share_func(outside, dx)
            self.st_share = ti.field(f64, shape=shape)  # the walls' and the statics' share of the node's stencil
            self.sig_s = ti.Vector.field(3, f64, shape=shape)  # the statics' share of face I + ½e_d (once)
            self.sig_k = ti.Vector.field(3, f64, shape=shape)  # the statics' and tools' share of it (≤ 1)
            self.k_flux = ti.Vector.field(3, f64, shape=shape)  # the tools' flux through it, Σ σ_t u_t·e_d (m/s)
            self.k_phi = ti.field(f64, shape=shape)  # the least SDF of a static or tool at the node (m)
            self.k_v = ti.Vector.field(3, f64, shape=shape)  # that solid's velocity at the node (m/s)
            self.k_share = ti.field(f64, shape=shape)  # the tools' share of the node's stencil
        self._statics_done = False
        self.was_enclosed = ti.field(ti.i8, shape=shape)  # and in the last substep
        self.pocket_v = ti.Vector.field(3, f64, shape=shape)  # a pocket node's velocity after the last solve (m/s)
        self._pockets = False  # whether `enclosed` holds any node
        g = np.asarray(model.gravity, dtype=float)  # "up": against gravity, along its largest component (z without)
        self._up_axis = int(np.argmax(np.abs(g))) if np.any(g) else 2
        self._up = -1 if g[self._up_axis] > 0 else 1
        self._top_row = None  # the highest row of nodes inside the walls (fixed: found from the first kinds)
        self._pinned = False  # whether pin holds a node (the host's copy: position_correction reads it every substep)
        self.pin = ti.field(ti.i32, shape=())  # the flat index of the node pinned to p = 0 without air, or −1
        self.iterations = []  # the pressure solve's CG iterations per substep
        self.correction_iterations = []  # the position correction's
        self.primed = False

    def reset(self):
        """Forget the last push and the warm starts (a new state was written): the next substep primes the body's
        pose again."""
        for f in (self.dq_lin, self.dq_ang):
            f.from_numpy(np.zeros(3))
        self.p.fill(0.0)
        self.psi.fill(0.0)
        self.enclosed.fill(0)
        self.was_enclosed.fill(0)
        self._pockets = False
        self.primed = False

    # --- helpers ------------------------------------------------------------------------------------------
    @ti.func
    def _unknown(self, I):
        return self.kind[I] == LIQ

    @ti.func
    def _inside(self, J):
        ok = True
        for d in ti.static(range(3)):
            if J[d] < 0 or J[d] >= self.model.grid_shape[d]:
                ok = False
        return ok

    @ti.func
    def _on_wall(self, I, e: ti.template()):
        tol = 0.01 * self.model.dx
        xe = self.model.origin[e] + I[e] * self.model.dx
        return ti.abs(xe - self.model.lower[e]) < tol or ti.abs(xe - self.model.upper[e]) < tol

    @ti.func
    def _cellw(self, I):
        """Share of node I's cell inside the domain: ½ per wall whose row it is on."""
        w = ti.f64(1.0)
        for e in ti.static(range(3)):
            if self._on_wall(I, e):
                w *= 0.5
        return w

    @ti.func
    def _facew(self, I, d: ti.template()):
        """Share of the face between I and I ± e_d inside the domain: the cell's, less the wall across d."""
        w = self._cellw(I)
        if self._on_wall(I, d):
            w *= 2.0
        return w

    @ti.func
    def _beta(self, I, J):
        """1/ρ on a face between two unknowns, ρ the mean of the nodes' densities."""
        return 2.0 / (self.rho_n[I] + self.rho_n[J])

    @ti.func
    def _body(self):
        """The body's (R, c, valid): valid is False before its first rigid projection (R still zero), and in a
        scene without a rigid body."""
        R = ti.Matrix.identity(self.model.real, 3)
        c = ti.Vector.zero(self.model.real, 3)
        valid = False
        if ti.static(self.has_body):
            rp = self.solver.rigid
            R = rp.R[0]
            c = rp.com_sum[0] / self.model.rigid.body_mass[0]
            valid = R.determinant() > 0.5
        return R, c, valid

    @ti.func
    def _t_cross(self, I, J):
        """Where the body's surface crosses the segment from node I to J, in cells from I (linear in the SDF at the
        two nodes); 0 where it does not cross."""
        a, b = self.sdf[I], self.sdf[J]
        t = ti.f64(0.0)
        if a > 0.0 and b < 0.0:
            t = ti.min(a / (a - b), 1.0)
        return t

    @ti.func
    def _solid(self, I, J):
        """The body's share σ of the face between node I and its neighbour J (module docstring)."""
        out = ti.f64(0.0)
        if self.kind[I] == BSOLID or self.kind[J] == BSOLID:
            out = 1.0
        elif ti.static(self.has_soft):
            if self.kind[I] == SOFT or self.kind[J] == SOFT:
                out = 1.0
            else:  # (J is I ± e_d: the face box of the lower node)
                L = ti.min(I, J)
                e = ti.abs(J - I)
                out = ti.min(self.soft_face[L][0] * e[0] + self.soft_face[L][1] * e[1] + self.soft_face[L][2] * e[2],
                             1.0)
        elif ti.static(self.has_body):
            rig = self.model.rigid
            R, c, valid = self._body()
            xm = ti.Vector(self.model.origin) + 0.5 * (I + J) * self.model.dx
            if valid:  # the body's frame: x_local = Rᵀ(x − c) + c⁰ = Rᵀ(x − (c − R c⁰))
                out = self._body_share(xm, R, c - R @ rig.rest_com[0])
        return out

    @ti.func
    def _K(self, I, d: ti.template(), sgn: ti.template()):
        """K_f's torque part, r_f × e_d (m), at the midpoint of the face from I along sgn e_d."""
        _, cb, _ = self._body()
        c = ti.cast(cb, ti.f64)
        xf = ti.cast(ti.Vector(self.model.origin) + I * self.model.dx, ti.f64) \
            + 0.5 * sgn * self.model.dx * ti.Vector.unit(3, d, ti.f64)
        return (xf - c).cross(ti.Vector.unit(3, d, ti.f64))

    @ti.func
    def _theta(self, I, J):
        """Share θ of the way from liquid node I to air node J at which the free surface lies (THETA_RULE)."""
        a, b = self.phi[I], self.phi[J]
        th = ti.f64(1.0)
        if a - b > 1e-9:
            th = (a - FILL) / (a - b)
            if ti.static(THETA_RULE == "spline"):
                ua, ub = _spline_cdf_inverse(a), _spline_cdf_inverse(b)
                wa, wb = _spline_density(ua), _spline_density(ub)
                if wa + wb > 1e-6:
                    th = (wa * ua + wb * (1.0 + ub)) / (wa + wb)
        return ti.min(ti.max(th, THETA_MIN), 1.0)

    @ti.func
    def _face(self, f: ti.template(), I, d: ti.template(), sgn: ti.template()):
        """A per-face quantity f (a Vector field of the faces I + ½e_d) on the face from node I to I + sgn e_d."""
        out = ti.f64(0.0)
        if ti.static(sgn > 0):
            out = f[I][d]
        else:
            out = f[I - ti.Vector.unit(3, d, ti.i32)][d]
        return out

    @ti.func
    def _sig(self, I, d: ti.template(), sgn: ti.template()):
        """σ of the face from node I to I + sgn e_d (sig_p, set by rhs for this projection)."""
        return self._face(self.sig_p, I, d, sgn)

    @ti.func
    def _kin(self, I, d: ti.template(), sgn: ti.template()):
        """The statics' and tools' share of the face from node I to I + sgn e_d, and the tools' flux Σ σ_t u_t·e_d
        through it (m/s); both 0 without statics or tools."""
        share, flux = ti.f64(0.0), ti.f64(0.0)
        if ti.static(self.has_kin):
            share, flux = self._face(self.sig_k, I, d, sgn), self._face(self.k_flux, I, d, sgn)
        return share, flux

    @ti.func
    def _open(self, I, d: ti.template(), sgn: ti.template()):
        """The liquid's open share a_f of the face from I to I + sgn e_d: what the body, the deformable solids,
        the statics and the tools leave of it."""
        sk, _ = self._kin(I, d, sgn)
        return ti.max(1.0 - self._sig(I, d, sgn) - sk, 0.0)

    @ti.func
    def _soft_face(self, I, J, d: ti.template(), v: ti.template()):
        """The solids' velocity component d on the face between I and J: Σ_K c_K v_K, c_K = m_K/(m_I + m_J)."""
        mi, mj = self.soft_m[I], self.soft_m[J]
        out = ti.f64(0.0)
        if mi + mj > 0.0:
            out = (mi * v[I][d] + mj * v[J][d]) / (mi + mj)
        return out

    @ti.func
    def _soft_weight(self, I, d: ti.template(), sgn: ti.template()):
        """σ_f w_f of the face from I to I + sgn e_d, 0 where that node is outside the domain or a wall's."""
        out = ti.f64(0.0)
        J = I + sgn * ti.Vector.unit(3, d, ti.i32)
        if self._inside(J):
            if self.kind[J] != WALL:
                out = self._sig(I, d, sgn) * self._facew(I, d)
        return out

    @ti.func
    def _soft_of(self, x: ti.template()):
        """soft_dv_K = G_K/m_K, G_K = Σ_f c_fK σ_f w_f s (x_K − x_J) e_d over the faces f from K to J = K + s e_d
        (x = 0 off the unknowns): the solids' generalised force of the pressure x, over Δx², by node."""
        for n in range(self.n_soft[None]):  # soft_dv is 0 elsewhere (classify)
            K = self.soft_nodes[n]
            G = ti.Vector.zero(ti.f64, 3)
            mk = self.soft_m[K]
            if mk > 0.0 and self.kind[K] != WALL:
                xk = ti.f64(0.0)
                if self._unknown(K):
                    xk = x[K]
                for d in ti.static(range(3)):
                    for sgn in ti.static((-1, 1)):
                        wgt = self._soft_weight(K, d, sgn)
                        if wgt > 0.0:
                            J = K + sgn * ti.Vector.unit(3, d, ti.i32)
                            xj = ti.f64(0.0)
                            if self._unknown(J):
                                xj = x[J]
                            G[d] += mk / (mk + self.soft_m[J]) * wgt * sgn * (xk - xj)
                G /= mk
            self.soft_dv[K] = G

    @ti.func
    def _soft_A(self, I):
        """The solids' part of (A x)_I: Δx Σ_f s σ_f w_f Σ_K c_fK soft_dv_K·e_d (soft_of(x) beforehand)."""
        out = ti.f64(0.0)
        for d in ti.static(range(3)):
            for sgn in ti.static((-1, 1)):
                wgt = self._soft_weight(I, d, sgn)
                if wgt > 0.0:
                    out += sgn * wgt * self._soft_face(I, I + sgn * ti.Vector.unit(3, d, ti.i32), d, self.soft_dv)
        return self.model.dx * out

    # --- statics and tools --------------------------------------------------------------------------------
    @ti.kernel
    def _static_faces(self):
        """sig_s: the statics' share of each face I + ½e_d, and st_share: the walls' and the statics' share of each
        node's stencil (they do not move: once). model.solid_share takes a static's share from φ at the node alone
        (a plane), ½ at a tank's inner corner and edges, where ⅞ and ¾ of the stencil are in the walls: the corners'
        liquid read as loosened and as air, and the solve drained it into the corners at 0.3 m/s."""
        model = self.model
        R0 = ti.Matrix.identity(model.real, 3)
        o0 = ti.Vector.zero(model.real, 3)
        for I in ti.grouped(self.kind):
            xn = ti.Vector(model.origin) + I * model.dx
            self.st_share[I] = ti.min(self._walls_stencil(xn, R0, o0), 1.0)
            for d in ti.static(range(3)):
                xf = xn + 0.5 * model.dx * ti.Vector.unit(3, d, model.real)
                share = ti.f64(0.0)
                for k in ti.static(range(len(model.colliders))):
                    share += self._static_share[k](xf, R0, o0)
                self.sig_s[I][d] = ti.min(share, 1.0)

    @ti.kernel
    def kinematic(self, state: ti.template()):
        """The statics and the tools at the substep's start pose: at each node the least SDF, that solid's
        velocity and the tools' stencil share; at each face the solids' share sig_k (statics first, the tools in
        what they leave) and the tools' flux."""
        model = self.model
        dx = model.dx
        for I in ti.grouped(self.kind):
            xn = ti.Vector(model.origin) + I * dx
            phi = ti.f64(1e3 * dx)
            v = ti.Vector.zero(ti.f64, 3)
            share = ti.f64(0.0)
            for k in ti.static(range(len(model.colliders))):
                sd = ti.cast(model.colliders[k].sdf(xn), ti.f64)
                if sd < phi:
                    phi = sd
                    v = ti.Vector.zero(ti.f64, 3)
            for k in ti.static(range(model.n_tools)):
                p, R = state.tool_p_real[k, 0], state.tool_R_real[k, 0]
                lin, ang = state.tool_v_real[k, 0], state.tool_w_real[k, 0]
                sd = ti.cast(model.tools[k].sdf_local(R.transpose() @ (xn - p)), ti.f64)
                if self.solver.grid_vol[I] > 0.0:  # read by classify only where particles are (fill, packing)
                    share += self._tool_stencil[k](xn, R, p)
                if sd < phi:
                    phi = sd
                    v = ti.cast(lin + ang.cross(xn - p), ti.f64)
            self.k_phi[I] = phi
            self.k_v[I] = v
            self.k_share[I] = ti.min(share, 1.0)
            for d in ti.static(range(3)):
                xf = xn + 0.5 * dx * ti.Vector.unit(3, d, model.real)
                st, flux = ti.f64(0.0), ti.f64(0.0)
                for k in ti.static(range(model.n_tools)):
                    p, R = state.tool_p_real[k, 0], state.tool_R_real[k, 0]
                    lin, ang = state.tool_v_real[k, 0], state.tool_w_real[k, 0]
                    sh = self._tool_share[k](xf, R, p)
                    st += sh
                    flux += sh * ti.cast((lin + ang.cross(xf - p))[d], ti.f64)
                room = ti.max(1.0 - self.sig_s[I][d], 0.0)
                if st > room:
                    flux *= room / st
                    st = room
                self.sig_k[I][d] = self.sig_s[I][d] + st
                self.k_flux[I][d] = flux

    # --- the pressure solve -------------------------------------------------------------------------------
    @ti.kernel
    def classify(self):
        """Node kinds, fills, u*, the body's SDF at the nodes; q* and M⁻¹."""
        s = self.solver
        model = self.model
        R, c, valid = self._body()
        vb, wb = ti.Vector.zero(model.real, 3), ti.Vector.zero(model.real, 3)
        tol = 0.01 * model.dx
        g = ti.Vector(model.gravity)
        self.minv_I[None] = ti.Matrix.zero(ti.f64, 3, 3)
        self.minv_m[None] = 0.0
        if ti.static(self.has_body):
            rp = s.rigid
            rig = model.rigid
            vb, wb = rp.momentum[0] / rig.body_mass[0], rp.omega[0]
            vb = vb + ti.cast(self.dq_lin[None], model.real) + g * model.dt  # q*
            wb = wb + ti.cast(self.dq_ang[None], model.real)
            Ic = ti.cast(rp.inertia[0], ti.f64)
            self.minv_m[None] = 1.0 / ti.cast(rig.body_mass[0], ti.f64)
            if ti.abs(Ic.determinant()) > 0.0:
                self.minv_I[None] = Ic.inverse()
        self.q_lin[None] = ti.cast(vb, ti.f64)
        self.q_ang[None] = ti.cast(wb, ti.f64)
        for I in ti.grouped(self.kind):
            xn = ti.Vector(model.origin) + I * model.dx
            wall = False
            for d in ti.static(range(3)):
                if xn[d] < model.lower[d] - tol or xn[d] > model.upper[d] + tol:  # beyond the wall rows
                    wall = True
            sd = ti.cast(1e3 * model.dx, model.real)  # no body: every node far outside it
            if ti.static(self.has_body):
                rig = model.rigid
                xl = R.transpose() @ (xn - c) + rig.rest_com[0]
                sd = rig.sdfs[0](xl)
            self.sdf[I] = ti.cast(sd, ti.f64)
            deep = valid and sd <= -model.dx  # the body's own node
            wall_share = ti.cast(model.solid_share[I], ti.f64)  # the walls', the statics' and the tools' stencil share
            kin = False  # inside a static or a tool, deeper than a cell: a wall moving with it
            if ti.static(self.has_kin):
                wall_share = ti.min(self.st_share[I] + self.k_share[I], 1.0)
                kin = self.k_phi[I] <= -0.999 * model.dx  # (a node a cell deep, whatever the rounding)
            fill = ti.cast(s.grid_vol[I] * model.inv_dx ** 3, ti.f64) + wall_share
            self.phi_all[I] = fill
            vol_f = ti.cast(s.grid_vol_f[I], ti.f64)
            rho = self.rho[None]  # the mixture's density: its mass over its particles' volume (ρ_w where empty)
            if vol_f > 1e-9 * model.dx ** 3:
                rho = ti.cast(s.grid_m_f[I], ti.f64) / vol_f
            self.rho_n[I] = rho
            if not deep:  # the mixture's share of the room the walls and the body leave at the node
                liq = vol_f * model.inv_dx ** 3
                body = ti.max(ti.cast(s.grid_vol[I] * model.inv_dx ** 3, ti.f64) - liq, 0.0)
                fill = liq / ti.max(1.0 - wall_share - body, 0.05)
            self.phi[I] = fill
            v_body = ti.cast(vb + wb.cross(xn - c), ti.f64)
            k = AIR
            v = ti.Vector.zero(ti.f64, 3)
            if wall or kin:
                k = WALL
                if ti.static(self.has_kin):
                    if kin and not wall:
                        v = self.k_v[I]
            elif deep:
                k = BSOLID
                v = v_body
            elif valid and sd < 0.0:
                k = SHELL  # decided below, from its neighbours
                v = v_body
                if s.grid_m_f[I] > model.mass_floor:
                    v = ti.cast(s.grid_v_f[I], ti.f64)
            elif s.grid_m_f[I] > model.mass_floor and fill >= FILL:
                k = LIQ
                v = ti.cast(grid.walls(model, xn, s.grid_v_f[I]), ti.f64)  # the wall's velocity normal to it
            if ti.static(self.has_kin):  # a node over half a cell inside a static or tool that is not liquid is
                if k == AIR and self.k_phi[I] < -0.5 * model.dx:  # the solid's, not air: p = 0 there drained the
                    k = WALL  # liquid into the solid (a node on its surface stays air: the waterline's free surface)
                    v = self.k_v[I]
            if ti.static(self.has_soft):
                share = ti.max(ti.cast(s.grid_vol[I] - s.grid_vol_f[I], ti.f64) * model.inv_dx ** 3, 0.0)
                self.soft_s[I] = ti.min(share, 1.0)
                self.soft_m[I] = ti.cast(s.grid_m[I], ti.f64)
                self.soft_v[I] = ti.cast(s.grid_v[I], ti.f64)
                self.soft_dv[I] = ti.Vector.zero(ti.f64, 3)
                if k == AIR and not wall and share >= FILL and s.grid_m[I] > model.mass_floor:
                    k = SOFT
            self.kind[I] = ti.cast(k, ti.i8)
            self.vs[I] = v
        # a shell node is liquid where a neighbour outside the body is, whatever liquid mass the exclusion's gap
        # leaves it (its fill would call it air, and the bottom face's push would lose the shell's part), unless
        # the body nearly encloses it
        for I in ti.grouped(self.kind):
            if self.kind[I] == SHELL:
                wet = False
                for d in ti.static(range(3)):
                    for sgn in ti.static((-1, 1)):
                        J = I + sgn * ti.Vector.unit(3, d, ti.i32)
                        if self._inside(J):
                            if self.kind[J] == LIQ and self.sdf[J] >= 0.0:
                                wet = True
                k = LIQ_SHELL if wet else AIR_SHELL
                open_share = ti.f64(0.0)
                for d in ti.static(range(3)):
                    for sgn in ti.static((-1, 1)):
                        J = I + sgn * ti.Vector.unit(3, d, ti.i32)
                        if self._inside(J):
                            open_share += 1.0 - self._solid(I, J)
                if open_share < ti.static(self.open_min):
                    k = ENC_SHELL
                self.kind[I] = ti.cast(k, ti.i8)
        for I in ti.grouped(self.kind):
            if self.kind[I] == LIQ_SHELL:
                self.kind[I] = ti.cast(LIQ, ti.i8)
            elif self.kind[I] == AIR_SHELL:
                self.kind[I] = ti.cast(AIR, ti.i8)
            elif self.kind[I] == ENC_SHELL:
                self.kind[I] = ti.cast(BSOLID, ti.i8)
                xn = ti.Vector(model.origin) + I * model.dx
                self.vs[I] = ti.cast(vb + wb.cross(xn - c), ti.f64)
        if ti.static(self.has_kin):
            # a liquid node inside a static or tool whose faces they close but for less than KIN_OPEN_MIN (six faces
            # together) is theirs, as the body's shell nodes are: a stray particle's mass in a wall made such a
            # node an unknown whose pressure the few open hundredths of its faces barely fixed, and the position
            # correction's gradient through them threw the liquid 14 m in a substep (the Gathering tank)
            for I in ti.grouped(self.kind):
                if self.kind[I] == LIQ and self.k_phi[I] < 0.0:
                    open_share = ti.f64(0.0)
                    for d in ti.static(range(3)):
                        for sgn in ti.static((-1, 1)):
                            if self._inside(I + sgn * ti.Vector.unit(3, d, ti.i32)):
                                sk, _ = self._kin(I, d, sgn)
                                open_share += 1.0 - sk
                    if open_share < KIN_OPEN_MIN:
                        self.kind[I] = ti.cast(WALL, ti.i8)
                        self.vs[I] = self.k_v[I]

    def enclose_air(self):
        """Air nodes that no path of air nodes joins to the air at the top of the domain, in a pocket beside the
        body (a node of it within a cell of the body's surface), become liquid unknowns moving with the body (the
        liquid field's velocity where it has mass). Such a pocket is a vacuum, not air: the body's particles
        exclude the liquid from the gap under a body on the floor, and with p = 0 there the liquid's pressure
        never reached the body's bottom while the pressure on its top held it down, so that a buoyant body never
        lifted off the floor; a real one lifts off as water seeps under it. Pockets away from the body (a splash's
        void in the liquid) stay air and close. Nothing is changed where no air reaches the top (a full tank).
        A pocket node without liquid mass has no particles to carry its velocity from one substep to the next: it
        starts from its velocity after the last solve (pocket_v, plus g Δt), or the body's where it was not a
        pocket node then. Starting from the body's each substep, the liquid flowing into the gap under a lifting
        body stopped every substep, and the solve's pressure, re-accelerating it, held a cube stood on the floor
        at 24 cells down (0.15 mm up, then back; docs/engine.md)."""
        if not self.has_body or not np.any(self.model.gravity):  # no pockets (_pocket_mask): the kinds stay here
            n_liq, n_air = self._counts()
            if (n_liq > 0 and n_air == 0) or self._pinned:
                self._pin_node(self.kind.to_numpy())
            return
        kind = self.kind.to_numpy()
        self._pin_node(kind)
        mask = self._pocket_mask(kind)
        if mask is None:
            if self._pockets:
                self.enclosed.fill(0)
                self._pockets = False
            return
        self.enclosed.from_numpy(mask)
        self._pockets = True
        self._wet_enclosed()

    @ti.kernel
    def _counts(self) -> ti.types.vector(2, ti.i32):
        """The liquid and air nodes' counts."""
        n_liq, n_air = 0, 0
        for I in ti.grouped(self.kind):
            if self.kind[I] == LIQ:
                n_liq += 1
            elif self.kind[I] == AIR:
                n_air += 1
        return ti.Vector([n_liq, n_air])

    def _pin_node(self, kind):
        """With no air node the liquid fills the domain and both solves are pure Neumann problems, singular (p up
        to a constant) and, by the rounding of the right-hand side's sum, inconsistent: a full closed box threw its
        liquid across the domain in two steps. Then the highest liquid node gets p = 0 half a cell above it, as if
        air were there (pin, read by rhs); −1 otherwise."""
        liquid = kind == LIQ
        pinned = bool(liquid.any() and not (kind == AIR).any())
        if pinned or self._pinned:
            pin = -1
            if pinned:
                idx = np.argwhere(liquid)
                top = idx[np.argmax(self._up * idx[:, self._up_axis])]
                pin = int(np.ravel_multi_index(tuple(top), kind.shape))
            self.pin[None] = pin
        self._pinned = pinned

    def _pocket_mask(self, kind):
        """int8 mask of the air nodes enclose_air makes liquid, or None where there are none."""
        from scipy import ndimage

        air = kind == AIR
        if not self.has_body or not np.any(self.model.gravity) or not air.any():  # pockets are the body's
            return None
        labels, n = ndimage.label(air)  # face-connected components (6-connectivity)
        if n < 2:
            return None
        axis = self._up_axis
        if self._top_row is None:
            open_rows = np.nonzero(np.any(np.moveaxis(kind != WALL, axis, 0), axis=tuple(range(1, kind.ndim))))[0]
            self._top_row = int(open_rows.max() if self._up > 0 else open_rows.min())
        top_labels = np.unique(np.take(labels, self._top_row, axis=axis))
        top_labels = top_labels[top_labels > 0]
        if top_labels.size == 0:
            return None
        near = air & (self.sdf.to_numpy() < self.model.dx)
        pockets = np.setdiff1d(np.unique(labels[near]), top_labels)
        if pockets.size == 0:
            return None
        return np.isin(labels, pockets).astype(np.int8)

    @ti.kernel
    def _wet_enclosed(self):
        s = self.solver
        model = self.model
        R, c, valid = self._body()
        g = ti.cast(ti.Vector(model.gravity), ti.f64)
        for I in ti.grouped(self.kind):
            if self.enclosed[I] == 1:
                xn = ti.Vector(model.origin) + I * model.dx
                v = self.q_lin[None] + self.q_ang[None].cross(ti.cast(xn - c, ti.f64))  # q* at the node
                if self.was_enclosed[I] == 1:
                    v = self.pocket_v[I] + g * model.dt
                if s.grid_m_f[I] > model.mass_floor:
                    v = ti.cast(grid.walls(model, xn, s.grid_v_f[I]), ti.f64)
                self.kind[I] = ti.cast(LIQ, ti.i8)
                self.vs[I] = v

    @ti.kernel
    def soft_faces(self, state: ti.template()):
        """soft_face[I][d]: the share of the face box (Δx³ about the midpoint of the face from I to I + e_d) that
        the deformable solids' particles cover, each particle an axis-aligned box of its volume V = V⁰ det F
        (side h = V^⅓, at most Δx), split between the (at most two) face boxes its extent meets along each axis:
        σ = Σ_p (V_p/Δx³) Π_a ℓ_a/h, ℓ_a the particle box's overlap with the face box along axis a. A body that
        its particles' boxes tile (at rest, or stretched evenly) gets its faces' shares exactly."""
        model = self.model
        for I in ti.grouped(self.soft_face):
            self.soft_face[I] = ti.Vector.zero(ti.f64, 3)
        ti.loop_config(serialize=self.serial_faces)
        for p in range(model.n_particles):
            if takes_part(model, state, 0, p) and not transfer.is_fluid(model, p):
                vol = ti.cast(model.rest_volume[p] * state.F[0, p].determinant(), ti.f64)
                hc = ti.min(ti.max(ti.pow(ti.max(vol, 0.0), 1.0 / 3.0) * model.inv_dx, 1e-6), 1.0)  # h, cells
                u = ti.cast((state.x[0, p] - ti.Vector(model.origin)) * model.inv_dx, ti.f64)
                for d in ti.static(range(3)):
                    k0 = ti.Vector.zero(ti.i32, 3)  # the first face box the particle meets along each axis
                    w0 = ti.Vector.zero(ti.f64, 3)  # the share of its extent in that box
                    for a in ti.static(range(3)):
                        ua = u[a] - (0.5 if a == d else 0.0)  # face box k spans [k − ½, k + ½] in these units
                        lo = ua - 0.5 * hc
                        k = ti.cast(ti.floor(lo + 0.5), ti.i32)
                        k0[a] = k
                        w0[a] = ti.min((ti.min(ua + 0.5 * hc, k + 0.5) - lo) / hc, 1.0)
                    for o in ti.static(ti.grouped(ti.ndrange(2, 2, 2))):
                        wgt = vol * model.inv_dx ** 3
                        for a in ti.static(range(3)):
                            wgt *= w0[a] if o[a] == 0 else 1.0 - w0[a]
                        K = k0 + o
                        if self._inside(K):
                            self.soft_face[K][d] += wgt

    @ti.kernel
    def rhs(self):
        """σ and the matrix's weights; b = −(D u*)/Δt, the diagonal, and the body's b_I at the unknowns."""
        dx = self.model.dx
        for I in ti.grouped(self.kind):
            for d in ti.static(range(3)):
                J = I + ti.Vector.unit(3, d, ti.i32)
                self.sig_p[I][d] = 0.0
                if self._inside(J):
                    sig = self._solid(I, J)
                    if ti.static(self.has_kin):  # the statics and tools first: they do not give way
                        sig = ti.min(sig, 1.0 - self.sig_k[I][d])
                    self.sig_p[I][d] = sig
        for I in ti.grouped(self.kind):
            self.aoff[I] = ti.Vector.zero(ti.f64, 6)
            if self._unknown(I):
                for d in ti.static(range(3)):
                    for sgn in ti.static((-1, 1)):
                        J = I + sgn * ti.Vector.unit(3, d, ti.i32)
                        if self._inside(J):
                            if self._unknown(J):
                                a = self._open(I, d, sgn)
                                self.aoff[I][ti.static(2 * d + (sgn + 1) // 2)] = \
                                    self._facew(I, d) * a * self._beta(I, J)
        for I in ti.grouped(self.kind):
            self.b[I] = 0.0
            self.diag[I] = 0.0
            self.pdiag[I] = 0.0
            self.bf[I] = ti.Vector.zero(ti.f64, 3)
            self.bt[I] = ti.Vector.zero(ti.f64, 3)
            if self._unknown(I):
                div = ti.f64(0.0)
                dg = ti.f64(0.0)
                for d in ti.static(range(3)):
                    fw = self._facew(I, d)
                    for sgn in ti.static((-1, 1)):
                        J = I + sgn * ti.Vector.unit(3, d, ti.i32)
                        if self._inside(J):
                            kj = self.kind[J]
                            if kj == WALL:
                                div += sgn * fw * self.vs[J][d]
                            else:
                                sig = self._sig(I, d, sgn)
                                a = self._open(I, d, sgn)
                                uf = ti.f64(0.0)
                                if kj == AIR:
                                    uf = self.vs[I][d]
                                    dg += fw * a / (self.rho_n[I] * self._theta(I, J))
                                elif kj != BSOLID and kj != SOFT:
                                    uf = 0.5 * (self.vs[I][d] + self.vs[J][d])
                                    dg += fw * a * self._beta(I, J)
                                Kt = self._K(I, d, sgn)
                                _, kflux = self._kin(I, d, sgn)
                                div += sgn * fw * (a * uf + kflux)
                                if ti.static(self.has_soft):  # the solids' flux through the face's share σ
                                    div += sgn * fw * sig * self._soft_face(I, J, d, self.soft_v)
                                wgt = ti.f64(1.0)  # a solid face's weight moved to the surface's crossing
                                Ip = I - sgn * ti.Vector.unit(3, d, ti.i32)
                                if self._inside(Ip) and kj == BSOLID:
                                    if self._unknown(Ip):
                                        wgt = 1.0 + self._t_cross(I, J)
                                self.bf[I][d] += sgn * fw * sig * wgt
                                self.bt[I] += sgn * fw * sig * wgt * Kt
                    # −t w_f of the faces of the neighbours N = I + s e_d whose face beyond them is solid
                    for sgn in ti.static((-1, 1)):
                        N = I + sgn * ti.Vector.unit(3, d, ti.i32)
                        K2 = N + sgn * ti.Vector.unit(3, d, ti.i32)
                        if self._inside(N) and self._inside(K2):
                            if self._unknown(N) and self.kind[K2] == BSOLID:
                                sig2 = self._sig(N, d, sgn)
                                if sig2 > 0.0:
                                    fw2 = self._facew(N, d)
                                    t2 = self._t_cross(N, K2)
                                    self.bf[I][d] += -t2 * sgn * fw2 * sig2
                                    self.bt[I] += -t2 * sgn * fw2 * sig2 * self._K(N, d, sgn)
                div += self.bf[I].dot(self.q_lin[None]) + self.bt[I].dot(self.q_ang[None])
                self.b[I] = -div / (dx * self.model.dt)
                if dg < 1e-6 / self.rho_w:  # no open face (a node the body encloses): a small diagonal fixes p
                    dg = 1e-3 / self.rho_w
                flat = (I[0] * self.model.grid_shape[1] + I[1]) * self.model.grid_shape[2] + I[2]
                if flat == self.pin[None]:  # no air anywhere: p = 0 half a cell above this node (_pin_node)
                    dg += self._cellw(I) / (self.rho_n[I] * 0.5)
                self.diag[I] = dg / (dx * dx)
                bf, bt = self.bf[I], self.bt[I]
                self.pdiag[I] = self.diag[I] + dx * (bf.dot(bf) * self.minv_m[None] + bt.dot(self.minv_I[None] @ bt))

    @ti.func
    def _A(self, x: ti.template(), I):
        return self._A_with(x, I, self.bx_f[None], self.bx_t[None])

    @ti.func
    def _A_with(self, x: ti.template(), I, bxf, bxt):
        """(A x)_I, with Σ_J x_J b_J = (bxf, bxt) (the body's force and torque parts; _bx_of)."""
        dx = self.model.dx
        out = self.diag[I] * x[I]
        for d in ti.static(range(3)):
            for sgn in ti.static((-1, 1)):
                k = ti.static(2 * d + (sgn + 1) // 2)
                w = self.aoff[I][k]
                if w != 0.0:
                    out -= w * x[I + sgn * ti.Vector.unit(3, d, ti.i32)] / (dx * dx)
        if ti.static(self.has_body):  # Δx b_I · M⁻¹ Σ_J x_J b_J (bx set by _bx_of beforehand)
            out += dx * (self.bf[I].dot(bxf) * self.minv_m[None] + self.bt[I].dot(self.minv_I[None] @ bxt))
        if ti.static(self.has_soft):
            out += self._soft_A(I)
        return out

    @ti.func
    def _bx_of(self, x: ti.template()):
        """(bx_f, bx_t) = Σ_I x_I b_I over the unknowns, summed in a fixed order (CHUNK), at a kernel's top level."""
        if ti.static(self.has_soft):
            self._soft_of(x)
        self.bx_f[None] = ti.Vector.zero(ti.f64, 3)
        self.bx_t[None] = ti.Vector.zero(ti.f64, 3)
        if ti.static(self.has_body):  # b_I is the body's: 0 without one
            total = self._ordered_sum(self._bx_term, x, self.part_v, ti.Vector.zero(ti.f64, 6))
            self.bx_f[None] = ti.Vector([total[0], total[1], total[2]])
            self.bx_t[None] = ti.Vector([total[3], total[4], total[5]])

    @ti.func
    def _ordered_sum(self, term: ti.template(), a: ti.template(), part: ti.template(), zero: ti.template()):
        """Σ term(I, a) over the unknowns in the list's order of chunks: each thread sums CHUNK consecutive ones into
        part[c], the chunks' sums are added serially, so the result does not depend on the threads' scheduling
        (Taichi's parallel reductions and a GPU's atomic adds do). zero is the sum's zero (a scalar or a vector, of
        part's type). At a kernel's top level; term may write the node's entries."""
        n = self.n_unk[None]
        for c in range((n + CHUNK - 1) // CHUNK):
            acc = zero
            for m in range(c * CHUNK, ti.min((c + 1) * CHUNK, n)):
                acc += term(self.unk[m], a)
            part[c] = acc
        total = zero
        ti.loop_config(serialize=True)
        for c in range((n + CHUNK - 1) // CHUNK):
            total += part[c]
        return total

    @ti.func
    def _sum(self, term: ti.template(), a: ti.template()):
        """_ordered_sum of a scalar term."""
        return self._ordered_sum(term, a, self.part, ti.f64(0.0))

    @ti.func
    def _bx_term(self, I, x: ti.template()):
        """x_I b_I, the body's force and torque parts as one 6-vector."""
        bf, bt = self.bf[I], self.bt[I]
        return x[I] * ti.Vector([bf[0], bf[1], bf[2], bt[0], bt[1], bt[2]])

    @ti.func
    def _bb_term(self, I, a):
        return self.b[I] * self.b[I]

    @ti.func
    def _rz_term(self, I, a):
        return self.r[I] * self.z[I]

    @ti.func
    def _apply_term(self, I, a):
        """A d at I (the body's sums from _bx_of beforehand); d·A d."""
        self.Ad[I] = self._A(self.d, I)
        return self.d[I] * self.Ad[I]

    @ti.func
    def _advance_term(self, I, alpha):
        """p += α d, r −= α A d; r·r."""
        self.p[I] += alpha * self.d[I]
        self.r[I] -= alpha * self.Ad[I]
        return self.r[I] * self.r[I]

    @ti.func
    def _bx_of_serial(self, x: ti.template()):
        """_bx_of inside a serial loop, returning the sums (bx_f, bx_t) as local vectors for _A_with. Written into
        the fields and read back by _A inside _solve_serial's loop, they came out wrong at Taichi 1.7.4's
        opt_level 0 (the test suite's fast compilation): the CG took 400 iterations where the parallel path took 16
        (tests/test_projection.py)."""
        if ti.static(self.has_soft):
            self._soft_of(x)
        bxf = ti.Vector.zero(ti.f64, 3)
        bxt = ti.Vector.zero(ti.f64, 3)
        if ti.static(self.has_body):
            for n in range(self.n_unk[None]):
                I = self.unk[n]
                bxf += x[I] * self.bf[I]
                bxt += x[I] * self.bt[I]
        return bxf, bxt

    @ti.kernel
    def body_impulse(self, state: ti.template()):
        """The solve's impulse on the body, Δt Q = Δt Δx² Σ p b, and q's change Δq."""
        self._bx_of(self.p)
        dx, dt = self.model.dx, self.model.dt
        self.body_dP[None] = dt * dx * dx * self.bx_f[None]
        self.body_dL[None] = dt * dx * dx * self.bx_t[None]
        self.dq_lin[None] = self.body_dP[None] * self.minv_m[None]
        self.dq_ang[None] = self.minv_I[None] @ self.body_dL[None]
        if ti.static(self.has_soft):  # the solids' nodes: v = v* + Δt Δx² M⁻¹ G (soft_of(p) above), then the
            for K in ti.grouped(self.kind):  # statics', the tools' and the walls' conditions
                if self.soft_m[K] > 0.0:
                    v = self.soft_v[K] + dt * dx * dx * self.soft_dv[K]
                    self.solver.grid_v[K] = grid.boundary(self.model, K, ti.cast(v, self.model.real), state, 0)

    @ti.kernel
    def _start(self):
        self._start_f()

    @ti.func
    def _start_f(self):
        """r = b − A p from the warm start p (0 off the unknowns), and the first z = r/diag."""
        self._bx_of(self.p)
        for I in ti.grouped(self.kind):
            self.r[I] = 0.0
            self.z[I] = 0.0
            if self._unknown(I):
                self.r[I] = self.b[I] - self._A(self.p, I)
            else:
                self.p[I] = 0.0
        for I in ti.grouped(self.kind):
            if self._unknown(I):
                self.z[I] = self.r[I] / self.pdiag[I]
                self.d[I] = self.z[I]
            else:
                self.d[I] = 0.0

    @ti.kernel
    def _b_norm2(self) -> ti.f64:
        """|b|² over the unknowns."""
        return self._sum(self._bb_term, 0.0)

    @ti.kernel
    def _iterate(self) -> ti.types.vector(2, ti.f64):
        """One CG iteration in one launch, its loops parallel (a GPU's path; the CPU's is _solve_serial): d = z + β d,
        A d, α = r·z/(d·A d), p += α d, r −= α A d, z = M⁻¹ r, and β for the next. Returns (r·r, d·A d); with
        d·A d ≤ 0 (breakdown) α is 0 and p stays. Loops over the unknowns only (d, z are 0 elsewhere, from _start);
        its sums in a fixed order (_ordered_sum)."""
        beta = self.cg_beta[None]
        for n in range(self.n_unk[None]):
            I = self.unk[n]
            self.d[I] = self.z[I] + beta * self.d[I]
        self._bx_of(self.d)
        pAp = self._sum(self._apply_term, 0.0)
        alpha = ti.select(pAp > 0.0, self.cg_rz[None] / ti.max(pAp, 1e-300), 0.0)
        rr = self._sum(self._advance_term, alpha)
        self._precondition(True)
        rz = self._sum(self._rz_term, 0.0)
        self.cg_beta[None] = ti.select(self.cg_rz[None] > 0.0, rz / ti.max(self.cg_rz[None], 1e-300), 0.0)
        self.cg_rz[None] = rz
        return ti.Vector([rr, pAp])

    @ti.func
    def _advance(self, alpha):
        """p += α d, r −= α A d over the unknowns in the list's order; returns r·r (the serial path's; the parallel
        path sums the same _advance_term in chunks)."""
        rr = ti.f64(0.0)
        for n in range(self.n_unk[None]):
            rr += self._advance_term(self.unk[n], alpha)
        return rr

    @ti.func
    def _aplus(self, I, d: ti.template()):
        """The matrix's entry between unknown I and I + e_d, −a_f w_f β/Δx² (≤ 0; 0 where that is no unknown)."""
        return -self.aoff[I][ti.static(2 * d + 1)] / (self.model.dx * self.model.dx)

    @ti.kernel
    def mic0(self):
        """The MIC(0) factor of the sparse part (the body's rank-6 term is left to the CG), once per projection."""
        nx, ny, nz = ti.static(self.model.grid_shape)
        self.n_unk[None] = 0
        if ti.static(self.has_soft):
            self.n_soft[None] = 0
        ti.loop_config(serialize=True)
        for i, j, k in ti.ndrange(nx, ny, nz):
            I = ti.Vector([i, j, k])
            if ti.static(self.has_soft):  # (classify zeroed soft_dv)
                if self.soft_m[I] > 0.0 and self.kind[I] != WALL:
                    self.soft_nodes[self.n_soft[None]] = I
                    self.n_soft[None] += 1
            self.mic[I] = 0.0
            if self._unknown(I):
                self.unk[self.n_unk[None]] = I  # lexicographic: the sweeps' order
                self.n_unk[None] += 1
                ad = self.diag[I]
                e = ad
                for d in ti.static(range(3)):
                    Im = I - ti.Vector.unit(3, d, ti.i32)
                    if Im[d] >= 0:
                        if self._unknown(Im):
                            a = self._aplus(Im, d)
                            pm = self.mic[Im]
                            others = ti.f64(0.0)
                            for d2 in ti.static(range(3)):
                                if ti.static(d2 != d):
                                    others += self._aplus(Im, d2)
                            e -= (a * pm) ** 2 + MIC_TAU * a * others * pm * pm
                if e < MIC_SIGMA * ad:
                    e = ad
                self.mic[I] = 1.0 / ti.sqrt(e)

    @ti.func
    def _precondition(self, top: ti.template()):
        """z = M⁻¹ r over the unknowns: MIC(0)'s sweeps, or the diagonal's (Jacobi, with the body's rank-6 term's
        diagonal: pdiag). `top`: called at a kernel's top level."""
        if ti.static(self.preconditioner == "mic"):
            self._sweeps(top)
        else:
            for n in range(self.n_unk[None]):
                I = self.unk[n]
                self.z[I] = self.r[I] / self.pdiag[I]

    @ti.func
    def _sweeps(self, top: ti.template()):
        """z = M⁻¹ r by the two sweeps of the MIC(0) factor (serial, in the unknowns' lexicographic order). A
        neighbour that is no unknown counts for nothing: mic is 0 there (mic0), and z is 0 there (_start). `top`:
        called at a kernel's top level (its loops serialised there; nested, they are serial anyway)."""
        if ti.static(top):
            ti.loop_config(serialize=True)
        for n in range(self.n_unk[None]):
            I = self.unk[n]
            t = self.r[I]
            for d in ti.static(range(3)):
                Im = I - ti.Vector.unit(3, d, ti.i32)
                if Im[d] >= 0:
                    t -= self._aplus(Im, d) * self.mic[Im] * self.mic_q[Im]
            self.mic_q[I] = t * self.mic[I]
        if ti.static(top):
            ti.loop_config(serialize=True)
        for n_ in range(self.n_unk[None]):
            I = self.unk[self.n_unk[None] - 1 - n_]
            t = self.mic_q[I]
            for d in ti.static(range(3)):
                Ip = I + ti.Vector.unit(3, d, ti.i32)
                if Ip[d] < self.model.grid_shape[d]:
                    t -= self._aplus(I, d) * self.mic[I] * self.z[Ip]
            self.z[I] = t * self.mic[I]

    @ti.kernel
    def _solve_serial(self, tol: ti.f64):
        """The whole solve in one launch (the CPU's path, serial_cg): _start, z = M⁻¹ r, |b|², then the CG as one
        serial loop: d = z + β d, A d, α = r·z/(d·A d), p += α d, r −= α A d until |r| ≤ tol |b| or d·A d ≤ 0
        (breakdown) or MAX_IT iterations (into cg_its), then z = M⁻¹ r and β for the next; b = 0 gives p = 0. The
        same arithmetic as _iterate's, in one thread: the tasks' solves have a few hundred to a few thousand
        unknowns, and each launch and each parallel loop in one costs the CPU 40-100 µs to dispatch (GatheringEasy
        small: 808 unknowns; 0.37-0.48 ms an iteration by _iterate, 0.065 ms here)."""
        self._start_f()
        self._precond_f()
        self.cg_bn2[None] = self._sum(self._bb_term, 0.0)
        ti.loop_config(serialize=True)
        for _ in range(1):
            tol2 = tol * tol * self.cg_bn2[None]
            rz = self.cg_rz[None]
            beta = ti.f64(0.0)
            its = 0
            done = 0
            if self.cg_bn2[None] <= 0.0:
                done = 1
                for n in range(self.n_unk[None]):
                    self.p[self.unk[n]] = 0.0
            while its < ti.static(self.max_iterations()) and done == 0:
                its += 1
                for n in range(self.n_unk[None]):
                    I = self.unk[n]
                    self.d[I] = self.z[I] + beta * self.d[I]
                bxf, bxt = self._bx_of_serial(self.d)
                pAp = ti.f64(0.0)
                for n in range(self.n_unk[None]):
                    I = self.unk[n]
                    self.Ad[I] = self._A_with(self.d, I, bxf, bxt)
                    pAp += self.d[I] * self.Ad[I]
                if pAp <= 0.0:
                    done = 1
                else:
                    rr = self._advance(rz / pAp)
                    if rr <= tol2:
                        done = 1
                    else:
                        self._precondition(False)
                        rz_new = ti.f64(0.0)
                        for n in range(self.n_unk[None]):
                            I = self.unk[n]
                            rz_new += self.r[I] * self.z[I]
                        beta = rz_new / rz
                        rz = rz_new
            self.cg_its[None] = its

    @ti.kernel
    def _precond(self):
        self._precond_f()

    @ti.func
    def _precond_f(self):
        """z = M⁻¹ r (_precondition), r·z into cg_rz and β = 0: the CG's first direction is z."""
        self._precondition(True)
        self.cg_rz[None] = self._sum(self._rz_term, 0.0)
        self.cg_beta[None] = 0.0

    @ti.kernel
    def _zero(self):
        for I in ti.grouped(self.kind):
            self.p[I] = 0.0

    def max_iterations(self) -> int:
        """The CG's iteration cap for the preconditioner chosen."""
        return MAX_IT if self.preconditioner == "mic" else MAX_IT_JACOBI

    def factor(self):
        """Once per projection, before both solves: list the unknowns (and the solids' nodes) in lexicographic order,
        and with MIC(0) its factor (mic0, one serial loop), else by columns in parallel (_list_unknowns)."""
        if self.preconditioner == "mic":
            self.mic0()
        elif self.preconditioner == "jacobi":
            self._list_unknowns()
        else:
            raise ValueError(f"LiquidProjection.preconditioner must be 'mic' or 'jacobi', not {self.preconditioner!r}")

    @ti.kernel
    def _list_unknowns(self):
        """unk (and soft_nodes) in lexicographic order, as mic0 lists them, without its serial loop over the grid:
        each (i, j) column counts its nodes, a serial scan over the columns gives each its first index, and each
        column writes its own."""
        nx, ny, nz = ti.static(self.model.grid_shape)
        for i, j in ti.ndrange(nx, ny):
            cu, cs = 0, 0
            for k in range(nz):
                I = ti.Vector([i, j, k])
                if self._unknown(I):
                    cu += 1
                if ti.static(self.has_soft):
                    if self.soft_m[I] > 0.0 and self.kind[I] != WALL:
                        cs += 1
            self.col_start[i, j] = ti.Vector([cu, cs])
        ti.loop_config(serialize=True)
        for _ in range(1):
            tu, ts = 0, 0
            for i in range(nx):
                for j in range(ny):
                    c = self.col_start[i, j]
                    self.col_start[i, j] = ti.Vector([tu, ts])
                    tu += c[0]
                    ts += c[1]
            self.n_unk[None] = tu
            if ti.static(self.has_soft):
                self.n_soft[None] = ts
        for i, j in ti.ndrange(nx, ny):
            nu, ns = self.col_start[i, j][0], self.col_start[i, j][1]
            for k in range(nz):
                I = ti.Vector([i, j, k])
                if self._unknown(I):
                    self.unk[nu] = I
                    nu += 1
                if ti.static(self.has_soft):
                    if self.soft_m[I] > 0.0 and self.kind[I] != WALL:
                        self.soft_nodes[ns] = I
                        ns += 1

    def solve(self, iterations: list, tol: float = TOL):
        """Preconditioned CG on (A_a + Δx B M⁻¹ Bᵀ) p = b from the p held (warm start) to the relative residual
        `tol`; appends its iterations. b = 0 gives p = 0 (not the warm start)."""
        if self.serial_cg:
            self._solve_serial(tol)
            iterations.append(int(self.cg_its[None]))
            return
        self._start()
        self._precond()
        bn = np.sqrt(self._b_norm2())
        it = 0
        if bn > 0:
            for it in range(1, self.max_iterations() + 1):
                rr, pAp = self._iterate()
                if pAp <= 0 or np.sqrt(rr) <= tol * bn:
                    break
        else:
            self._zero()
        iterations.append(it)

    # --- the correction -----------------------------------------------------------------------------------
    @ti.func
    def _grad(self, I, weighted: ti.template()):
        """G_I (Pa/m, or m for ψ): per axis the mean of the open faces' gradients, each by its open share; with
        `weighted` each face's gradient times its 1/ρ (β), so that Δt G_I is the node's velocity change (m/s)."""
        dx = self.model.dx
        G = ti.Vector.zero(ti.f64, 3)
        for d in ti.static(range(3)):
            s, n = ti.f64(0.0), ti.f64(0.0)
            for sgn in ti.static((-1, 1)):
                J = I + sgn * ti.Vector.unit(3, d, ti.i32)
                if self._inside(J):
                    kj = self.kind[J]
                    a = self._open(I, d, sgn)
                    if kj == AIR:
                        beta = ti.f64(1.0)
                        if ti.static(weighted):
                            beta = 1.0 / self.rho_n[I]
                        s += a * sgn * beta * (0.0 - self.p[I]) / (self._theta(I, J) * dx)
                        n += a
                    elif kj != WALL and kj != BSOLID and kj != SOFT:
                        beta = ti.f64(1.0)
                        if ti.static(weighted):
                            beta = self._beta(I, J)
                        s += a * sgn * beta * (self.p[J] - self.p[I]) / dx
                        n += a
            if n > 1e-6:
                G[d] = s / n
        return G

    @ti.kernel
    def correct(self, state: ti.template()):
        """The liquid field's nodes corrected by the gradient (their mean face gradient; the air nodes with liquid
        mass by their faces to liquid nodes), then the walls: the fallback for faces outside the solve."""
        s = self.solver
        dt = self.model.dt
        for I in ti.grouped(self.kind):
            k = self.kind[I]
            self.was_enclosed[I] = self.enclosed[I]
            if k == LIQ:  # (a pocket node is one)
                du = dt * self._grad(I, True)
                s.grid_v_f[I] -= ti.cast(du, self.model.real)
                if self.enclosed[I] == 1:
                    self.pocket_v[I] = self.vs[I] - du
            elif k == AIR and s.grid_m_f[I] > self.model.mass_floor:
                G = ti.Vector.zero(ti.f64, 3)
                for d in ti.static(range(3)):
                    acc, n = ti.f64(0.0), 0
                    for sgn in ti.static((-1, 1)):
                        J = I + sgn * ti.Vector.unit(3, d, ti.i32)
                        if self._inside(J):
                            if self.kind[J] == LIQ:
                                acc += -sgn * (0.0 - self.p[J]) / (self.rho_n[J] * self._theta(J, I) * self.model.dx)
                                n += 1
                    if n > 0:
                        G[d] = acc / n
                s.grid_v_f[I] -= ti.cast(dt * G, self.model.real)
        for I in ti.grouped(self.kind):
            if s.grid_m_f[I] > self.model.mass_floor:
                s.grid_v_f[I] = grid.boundary(self.model, I, s.grid_v_f[I], state, 0)

    @ti.kernel
    def faces(self):
        """uf (after the solve, divergence-free where the solve reaches) and uf0 (before gravity) on every face
        I + ½e_d; a face the body shares takes its share of the body's velocity."""
        s = self.solver
        dx, dt = self.model.dx, self.model.dt
        g = ti.cast(ti.Vector(self.model.gravity), ti.f64)
        _, cb, _ = self._body()
        c = ti.cast(cb, ti.f64)
        ql_new = self.q_lin[None] + self.dq_lin[None]
        qa_new = self.q_ang[None] + self.dq_ang[None]
        ql_old = self.q_lin[None] - g * dt
        qa_old = self.q_ang[None]
        for I in ti.grouped(self.kind):
            for d in ti.static(range(3)):
                J = I + ti.Vector.unit(3, d, ti.i32)
                u = ti.f64(0.0)
                u0 = ti.f64(0.0)
                if self._inside(J):
                    ki, kj = self.kind[I], self.kind[J]
                    ui, uj = self._unknown(I), self._unknown(J)
                    v0i = ti.cast(s.grid_v0[I][d], ti.f64)
                    v0j = ti.cast(s.grid_v0[J][d], ti.f64)
                    # outside the solve: the nodes' means (corrected field; pre-gravity field)
                    u = 0.5 * ti.cast(s.grid_v_f[I][d] + s.grid_v_f[J][d], ti.f64)
                    u0 = 0.5 * (v0i + v0j)
                    if ui and uj:
                        u = 0.5 * (self.vs[I][d] + self.vs[J][d]) - dt * self._beta(I, J) * (self.p[J] - self.p[I]) / dx
                    elif ui and kj == AIR:
                        u = self.vs[I][d] - dt / self.rho_n[I] * (0.0 - self.p[I]) / (self._theta(I, J) * dx)
                        u0 = v0i
                    elif uj and ki == AIR:
                        u = self.vs[J][d] - dt / self.rho_n[J] * (self.p[J] - 0.0) / (self._theta(J, I) * dx)
                        u0 = v0j
                    elif (ui and kj == WALL) or (uj and ki == WALL):
                        u = 0.0
                        u0 = 0.0
                    elif ki == WALL or kj == WALL:
                        # a face inside a wall, a static or a tool, outside the solve, which the particles beside the
                        # wall gather from: it keeps its velocity before the substep (no change for AFLIP's delta).
                        # The nodes' mean carried gravity that no pressure balances (v* = v + Δt g at every node):
                        # AFLIP gave the liquid beside the walls a downward push each substep, and a still pool
                        # stirred itself to 0.03 m/s rms (0.05 beside the walls; 0.0001 with this, docs/engine.md)
                        u = u0
                    if ui or uj:
                        sig = self.sig_p[I][d]
                        sk, kf = ti.f64(0.0), ti.f64(0.0)
                        if ti.static(self.has_kin):
                            sk, kf = self.sig_k[I][d], self.k_flux[I][d]
                        if sig > 0.0 or sk > 0.0:
                            ub, ub0 = ti.f64(0.0), ti.f64(0.0)
                            if ti.static(self.has_soft):  # the solids' nodes after and before the solve
                                mi, mj = self.soft_m[I], self.soft_m[J]
                                if mi + mj > 0.0:
                                    vi = self.soft_v[I][d] + dt * dx * dx * self.soft_dv[I][d]
                                    vj = self.soft_v[J][d] + dt * dx * dx * self.soft_dv[J][d]
                                    ub = (mi * vi + mj * vj) / (mi + mj)
                                    if ti.static(s.soft_flip):  # (u⁰ is read by AFLIP only)
                                        # before the substep: the solids' transfer velocity without their stress.
                                        # v* − Δt g kept the stress's Δt f/m, which a body at rest holds against
                                        # the pressure: AFLIP gave the liquid beside a floating elastic body that
                                        # push each substep (docs/engine.md, "AFLIP beside deformable solids")
                                        ub0 = ti.cast(self._soft_face(I, J, d, s.grid_v0_s), ti.f64)
                            else:
                                xf = ti.cast(ti.Vector(self.model.origin) + I * self.model.dx, ti.f64) \
                                    + 0.5 * dx * ti.Vector.unit(3, d, ti.f64)
                                ub = ql_new[d] + qa_new.cross(xf - c)[d]
                                ub0 = ql_old[d] + qa_old.cross(xf - c)[d]
                            a = ti.max(1.0 - sig - sk, 0.0)
                            if sk < 1.0 - 1e-6:
                                # the liquid's and the body's shares; the statics' and tools' not blended in (their
                                # share weights the divergence only, as in Batty et al. 2007): a particle beside a
                                # wall gathers the liquid's velocity, not ½-¼ of it (a no-slip wall a cell thick)
                                u = (a * u + sig * ub) / (1.0 - sk)
                                u0 = (a * u0 + sig * ub0) / (1.0 - sk)
                            else:  # closed by them: their velocity
                                u = kf / sk
                                u0 = kf / sk
                self.uf[I][d] = ti.cast(u, self.model.real)
                self.uf0[I][d] = ti.cast(u0, self.model.real)

    @ti.func
    def gather_faces(self, uf: ti.template(), xp):
        """v_p and C_p = (4/Δx²) Σ w u_f (x_f − x_p)ᵀ from the face field uf, component d from the faces I + ½e_d
        with the quadratic B-spline (the node stencil at x − ½Δx e_d)."""
        v = ti.Vector.zero(self.model.real, 3)
        C = ti.Matrix.zero(self.model.real, 3, 3)
        for d in ti.static(range(3)):
            xs = xp - 0.5 * self.model.dx * ti.Vector.unit(3, d, self.model.real)
            base, fx, w = grid.stencil(self.model, xs)
            for offset in ti.static(ti.grouped(ti.ndrange(3, 3, 3))):
                dpos = offset - fx
                weight = w[offset[0]][0] * w[offset[1]][1] * w[offset[2]][2]
                u = uf[base + offset][d]
                v[d] += weight * u
                for e in ti.static(range(3)):
                    C[d, e] += 4.0 * self.model.inv_dx * weight * u * dpos[e]
        return v, C

    # --- the position correction ----------------------------------------------------------------------------
    @ti.kernel
    def _packing_rhs(self):
        """ψ into p (the solver's field) and the packing's right-hand side: −∇²ψ = φ − 1 beyond the band."""
        for I in ti.grouped(self.kind):
            self.p_keep[I] = self.p[I]
            self.p[I] = self.psi[I]
            val = ti.f64(0.0)
            if self.kind[I] == LIQ:
                f = self.phi_all[I]
                interior = True
                for d in ti.static(range(3)):
                    for sgn in ti.static((-1, 1)):
                        J = I + sgn * ti.Vector.unit(3, d, ti.i32)
                        if self._inside(J):
                            if self.kind[J] == AIR:
                                interior = False
                if f > 1.0 + PACKING_BAND:
                    val = f - 1.0 - PACKING_BAND
                elif f < 1.0 - PACKING_BAND and interior:
                    val = f - 1.0 + PACKING_BAND
            self.b[I] = self._cellw(I) * val / self.rho[None]  # A = −β ∇² with β = 1/ρ

    @ti.kernel
    def _packing_displacement(self):
        for I in ti.grouped(self.kind):
            d = ti.Vector.zero(ti.f64, 3)
            if self.kind[I] == LIQ:
                d = -self._grad(I, False)
            self.disp[I] = ti.cast(d, self.model.real)
        for I in ti.grouped(self.kind):
            self.psi[I] = self.p[I]
            self.p[I] = self.p_keep[I]

    @ti.kernel
    def displace(self, state: ti.template()):
        """Each liquid particle, where G2P put it (the rigid projection's input, or the state without a rigid body),
        by α × the displacement, then out of the statics, the tools and the walls. The mixture's solids keep their
        places: their F holds their shape."""
        a = ti.cast(POSITION_CORRECTION, self.model.real)
        for p in range(self.model.n_particles):
            # an emitter's pool particle still parked stays where it is (emitters.py)
            if takes_part(self.model, state, 0, p) and transfer.is_fluid(self.model, p):
                xg = state.x[0, p]
                if ti.static(self.has_body):
                    xg = self.solver.rigid.x_g[p]
                base, fx, w = grid.stencil(self.model, xg)
                d = ti.Vector.zero(self.model.real, 3)
                for i, j, k in ti.static(ti.ndrange(3, 3, 3)):
                    d += w[i][0] * w[j][1] * w[k][2] * self.disp[base + ti.Vector([i, j, k])]
                x_new, _ = grid.project(self.model, xg + a * d, ti.Vector.zero(self.model.real, 3), state, 0)
                if ti.static(self.has_body):
                    self.solver.rigid.x_g[p] = x_new
                else:
                    v_new = state.v[0, p]
                    for k in ti.static(range(self.model.n_tools)):
                        # out of every tool at its pose after the substep, with no velocity into it: the solve
                        # closes the tool's faces by their share only, and a paddle pushed through water at
                        # 0.15 m/s otherwise took 31 particles a millimetre inside it (tests/test_projection.py)
                        if ti.static(not self.model.tools[k].spec.keep_out):  # (grid.project did those)
                            x_new, v_new = self.model.tools[k].keep_out(
                                x_new, v_new, state.tool_p_real[k, 0], state.tool_R_real[k, 0],
                                state.tool_v_real[k, 0], state.tool_w_real[k, 0])
                    state.x[0, p] = x_new
                    state.v[0, p] = v_new

    # --- the body -------------------------------------------------------------------------------------------
    @ti.kernel
    def _push(self, state: ti.template()):
        rp = self.solver.rigid
        M = self.model.rigid.body_mass[0]
        c = rp.com_sum[0] / M
        dw = rp.inertia[0].inverse() @ self.torque[None] * self.model.dt
        dv = self.force[None] / M * self.model.dt
        for p in range(self.model.n_particles):
            if self.model.rigid.body[p] == 0:
                state.v[0, p] += dv + dw.cross(state.x[0, p] - c)

    def push(self, state):
        """The solve's impulse on the body's particles, after the rigid projection: v += Δt (F/M + (I⁻¹τ) × r),
        F = ΔP/Δt, τ = ΔL/Δt."""
        dt = float(self.model.dt)
        self.force.from_numpy((self.body_dP.to_numpy() / dt).astype(self.model.np_real))
        self.torque.from_numpy((self.body_dL.to_numpy() / dt).astype(self.model.np_real))
        self._push(state)

    def project(self, state):
        """The substep's projection, between the grid update and G2P."""
        if not self.primed:  # the body's pose before the first projection (nothing has projected it yet)
            self.rho[None] = self.rho_w
            self.pin[None] = -1  # no node pinned (_pin_node writes it only when that changes)
            self._pinned = False
            if self.has_body:
                self.solver.rigid.prime(state)
            self.primed = True
        if self.has_kin:
            if not self._statics_done:
                self._static_faces()
            self._statics_done = True
            self.kinematic(state)
        self.classify()
        self.enclose_air()
        if self.has_soft:
            self.soft_faces(state)
        self.rhs()
        self.factor()
        self.solve(self.iterations)
        self.body_impulse(state)
        self.correct(state)
        self.faces()
        self.position_correction()

    def position_correction(self):
        """ψ and the displacement −∇ψ: the same solver on the packing's right-hand side (ψ swapped into p); moved
        by `displace` after G2P. Not without air (a pinned solve, _pin_node): a liquid that fills the domain can only
        move its packing about, and the pinned solve drained the whole box's packing error to the pinned node (a
        full 10 cm box at 8 cells moved particles by 15.6 mm in its first steps; 0.66 mm in 0.1 s without it)."""
        if self._pinned:
            self.disp.fill(0.0)
            return
        self._packing_rhs()
        self.solve(self.correction_iterations, CORRECTION_TOL)
        self._packing_displacement()
