"""The grid side of an MLS-MPM substep: the B-spline stencil, and the grid update with its boundary conditions.

Stencil (Hu et al. 2018, "A moving least squares material point method", eq. 3): a particle at x has grid
coordinates X = (x − origin)/Δx, base node ⌊X − ½⌋ and offset f = X − base ∈ [½, 3/2)³; its quadratic B-spline
weights along each axis are
    w₀ = ½ (3/2 − f)²,  w₁ = ¾ − (f − 1)²,  w₂ = ½ (f − ½)²
and w_ip = w₀(f_x) w₁(f_y) w₂(f_z) over the 3×3×3 nodes base + (a, b, c).

Grid update of node i with mass m_i and momentum (mv)_i after P2G (SI units):
    v_i = (mv)_i / m_i + Δt g                      (nodes under the model's mass floor stay at rest)
    statics (statics.py), then each tool's contact law at the pose it holds during the substep (tools.py),
    then the domain walls: a node on a wall or beyond it loses its velocity into it (slip, optional Coulomb
    friction μ_w: the tangential speed shrinks by μ_w × the normal speed removed). A row of nodes lies on each
    wall (model.py), so a flow along a wall keeps its speed into the wall everywhere inside the domain.
Two velocity fields (scenes with both fluids and solids; constitutive models registered with fluid=True are
fluids): P2G scatters the fluids' mass and momentum into one field and everything else's into another, and the
volume of all particles, V⁰_p det F_p, into a third. A node where both fields have mass and whose volume fill
φ_i = Σ_p w_ip V_p / Δx³, plus the share of its stencil beyond the walls or inside statics (`solid_share_of`), is at
least the scene's `contact_fill` (default 0.97) is a contact node: both fields
get the velocity of their summed mass and momentum, as on a single-velocity grid. Elsewhere each field has
its own velocity (the same boundary conditions), and G2P gathers each particle from its own field.
Why: on a single velocity field a liquid and a body interact wherever their stencils share a node, up to
about 1.5 cells apart, and the gap between them is then carried with them: nothing in an empty gap can close
it. A body dropped onto water stopped on a cushion of void about a cell thick and floated far too high (a
rigid cube of half water's density at 0.25 of its side below the surface after 1 s at 16 cells, an elastic one
on a mound above it; Archimedes 0.50; bench/buoyancy_3d.py, docs/engine.md). The fill test makes contact where the materials meet without a
void between them; a gap closes under the forces that act on each side.
After G2P, particles inside a static, inside a tool that keeps them out, or past a wall are put back on its
surface and lose their velocity into it (`project`).

Every function takes the Model (model.py) as a template argument; both solvers call them.
"""

import taichi as ti

from fluidlab_core.engine import statics


@ti.func
def stencil(model: ti.template(), xp):
    """Base node, offset f and quadratic B-spline weights [w₀, w₁, w₂] (per axis) of a particle at xp."""
    Xp = (xp - ti.Vector(model.origin)) * model.inv_dx
    base = ti.cast(Xp - 0.5, ti.i32)
    # never index off the grid, even for a NaN position (the NaN check then reports it)
    for d in ti.static(range(3)):
        base[d] = ti.min(ti.max(base[d], 0), model.grid_shape[d] - 3)
    fx = Xp - base
    w = [0.5 * (1.5 - fx) ** 2, 0.75 - (fx - 1.0) ** 2, 0.5 * (fx - 0.5) ** 2]
    return base, fx, w


@ti.func
def node_velocity(model: ti.template(), I, m, mv, state: ti.template(), s):
    """Velocity of node I from its mass and momentum: gravity, statics, tools at their slot-s pose, walls."""
    vn = ti.Vector.zero(float, 3)
    if m > model.mass_floor:
        vn = mv / m + model.dt * ti.Vector(model.gravity)
        vn = boundary(model, I, vn, state, s)
    return vn


@ti.func
def boundary(model: ti.template(), I, vn, state: ti.template(), s):
    """Velocity vn of node I after the statics' (their geometry there from fill_static_geometry), the tools' (at
    their slot-s pose) and the walls' conditions."""
    xn = ti.Vector(model.origin) + I * model.dx
    for k in ti.static(range(len(model.colliders))):
        vn = model.colliders[k].apply(model.static_mode[k, I[0], I[1], I[2]], model.static_normal[k, I[0], I[1], I[2]],
                                      model.static_normal2[k, I[0], I[1], I[2]], vn)
    for k in ti.static(range(model.n_tools)):
        vn = model.tools[k].contact_at(xn, vn, state.tool_p_real[k, s], state.tool_R_real[k, s],
                                       state.tool_v_real[k, s], state.tool_w_real[k, s])
    return walls(model, xn, vn)


@ti.kernel
def fill_static_geometry(model: ti.template()):
    """Each static's grid condition at each node (statics.Collider.geometry) into model.static_mode,
    static_normal and static_normal2: statics do not move, so it is computed once, when the model is uploaded."""
    for I in ti.grouped(ti.ndrange(*model.grid_shape)):
        xn = ti.Vector(model.origin) + I * model.dx
        for k in ti.static(range(len(model.colliders))):
            mode, n, n2 = model.colliders[k].geometry(xn)
            model.static_mode[k, I[0], I[1], I[2]] = ti.cast(mode, ti.i8)
            model.static_normal[k, I[0], I[1], I[2]] = n
            model.static_normal2[k, I[0], I[1], I[2]] = n2


@ti.func
def solid_share_of(model: ti.template(), I):
    """The share of node I's stencil that lies beyond the domain's walls or inside a static (the quadratic
    B-spline's weight there, statics.bspline_cdf; each static's surface taken as a plane at its distance φ).
    Walls and statics are not void: a liquid and a body that meet beside one fill such a node only up to this
    share, and the contact test counts it as filled (without it, a body against a wall, or in a slab between
    two, shared no velocity with the liquid at the nodes next to the wall and passed through it there)."""
    xn = ti.Vector(model.origin) + I * model.dx
    inside = 1.0
    for d in ti.static(range(3)):
        beyond = statics.bspline_cdf((model.lower[d] - xn[d]) * model.inv_dx) + \
            statics.bspline_cdf((xn[d] - model.upper[d]) * model.inv_dx)
        inside *= ti.max(1.0 - beyond, 0.0)
    share = 1.0 - inside
    for k in ti.static(range(len(model.colliders))):
        share = ti.max(share, model.colliders[k].stencil_fill(xn))
    return share


@ti.kernel
def fill_solid_share(model: ti.template()):
    """model.solid_share[I] = solid_share_of(model, I) for every node: walls and statics do not move, so the share
    is computed once, when the model is uploaded, and the grid update reads it."""
    for I in ti.grouped(model.solid_share):
        model.solid_share[I] = solid_share_of(model, I)


@ti.func
def in_contact(model: ti.template(), I, m_s, m_f, vol):
    """1.0 if node I, with solid mass m_s, fluid mass m_f and particle volume vol (m³), is a contact node, else
    0.0: both fields have mass there and the particles, with the walls' and statics' share of the stencil, fill
    it (the walls' and statics' share from model.solid_share, fill_solid_share). The fast solver computes it once
    per node and passes it to field_velocity for both fields."""
    fill = vol * model.inv_dx ** 3 + model.solid_share[I]
    return ti.cast(m_s > model.mass_floor and m_f > model.mass_floor and fill >= model.contact_fill, float)


@ti.func
def field_velocity(model: ti.template(), I, fluid, contact, m_s, mv_s, m_f, mv_f, state: ti.template(), s):
    """Velocity of node I in the solids' (fluid = 0) or the fluids' (fluid = 1) field: from that field's mass
    and momentum, or at a contact node (contact = 1.0, from in_contact) from both (node_velocity). Arithmetic
    selection, exact for 0/1 weights, rather than locals written in branches (Taichi's reverse mode)."""
    a = ti.cast(fluid, float)
    c = contact
    m = (1.0 - c) * ((1.0 - a) * m_s + a * m_f) + c * (m_s + m_f)
    mv = (1.0 - c) * ((1.0 - a) * mv_s + a * mv_f) + c * (mv_s + mv_f)
    return node_velocity(model, I, m, mv, state, s)


@ti.func
def walls(model: ti.template(), xn, vn):
    """Domain walls at lower/upper: nodes on a wall or beyond it lose their velocity into it (slip, optional
    Coulomb friction). Whole-vector updates only: Taichi's reverse mode mishandles a vector component written
    inside a runtime branch."""
    tol = 0.01 * model.dx  # the wall row, whatever the rounding of origin + k Δx
    for d in ti.static(range(3)):
        into = (xn[d] < model.lower[d] + tol and vn[d] < 0.0) or \
            (xn[d] > model.upper[d] - tol and vn[d] > 0.0)
        if into:
            normal_speed = ti.abs(vn[d])
            vn = vn * (1.0 - ti.Vector.unit(3, d, float))
            if ti.static(model.wall_friction > 0.0):
                vt_norm = statics.safe_norm(vn)
                if vt_norm > 1e-12:
                    vn *= ti.max(0.0, 1.0 - model.wall_friction * normal_speed / vt_norm)
    return vn


@ti.func
def clamp_to_walls(model: ti.template(), xp, vp):
    """Particles past a wall go back onto it and lose their velocity into it (whole-vector form, see walls)."""
    lo, hi = ti.Vector(model.lower), ti.Vector(model.upper)
    below = ti.cast(xp < lo, float)
    above = ti.cast(xp > hi, float)
    xp = ti.min(ti.max(xp, lo), hi)
    vp = vp - below * ti.min(vp, 0.0) - above * ti.max(vp, 0.0)
    return xp, vp


@ti.func
def project(model: ti.template(), xp, vp, state: ti.template(), s):
    """After G2P: out of the statics, out of the tools that keep particles out (at their slot-s pose), then back
    from past the walls."""
    for k in ti.static(range(len(model.colliders))):
        xp, vp = model.colliders[k].particle(xp, vp)
    for k in ti.static(range(model.n_tools)):
        if ti.static(model.tools[k].spec.keep_out):
            xp, vp = model.tools[k].keep_out(xp, vp, state.tool_p_real[k, s], state.tool_R_real[k, s],
                                             state.tool_v_real[k, s], state.tool_w_real[k, s])
    return clamp_to_walls(model, xp, vp)
