"""Tools: kinematics and workspace, the soft contact law at the grid, and tools moving liquid."""
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

import fluidlab_core as fl
from fluidlab_core import materials as M
from tests.conftest import report


def _plate_scene(softness, bottom):
    """Liquid at rest without gravity up to z = 5 cm, a wide flat plate with its bottom face at `bottom`,
    moving down at 0.2 m/s; one substep."""
    scene = fl.Scene(lower=(0, 0, 0), upper=(0.1, 0.1, 0.1), grid_res=20, dt=1e-4, substeps=1,
                     gravity=(0.0, 0.0, 0.0))
    scene.add_particles(fl.Box((0, 0, 0), (0.1, 0.1, 0.05)), M.WATER, name="water")
    scene.add_tool(fl.Box((-0.2, -0.2, 0.0), (0.2, 0.2, 0.02)), pose=(0.05, 0.05, bottom, 0, 0, 0, 1), name="plate",
                   softness=softness)
    return scene


@pytest.mark.parametrize("softness", [None, 200.0])
def test_contact_law_at_the_grid_nodes(softness):
    """After one substep the grid velocity below a plate approaching at u is s·u, with s = min(exp(−kφ), 1)
    for soft contact of sharpness k (φ: node distance to the plate, which starts 1.5 cm above the liquid) and
    s = 1 inside / 0 outside for hard contact (the plate dipping 5 mm into the liquid), exactly as the contact
    law in engine/tools.py states."""
    u = 0.2
    bottom = 0.045 if softness is None else 0.065
    scene = _plate_scene(softness, bottom)
    sim = scene.build()
    sim.step(np.array([0.0, 0.0, -u, 0.0, 0.0, 0.0]))
    solver, model = sim.solver, sim.model
    mass, vel = solver.grid_m.to_numpy(), solver.grid_v.to_numpy()
    idx = np.argwhere(mass > 0)
    z = model.origin[2] + idx[:, 2] * model.dx
    # the plate's bottom face was at `bottom` during the substep (its pose is written before it moves)
    phi = bottom - z
    measured = -vel[idx[:, 0], idx[:, 1], idx[:, 2], 2] / u
    inner = (np.abs(model.origin[0] + idx[:, 0] * model.dx - 0.05) < 0.03)  # away from the domain walls
    if softness is None:
        expected = (phi < 0).astype(float)
    else:
        expected = np.where(phi < 5.0 / softness, np.minimum(np.exp(-softness * phi), 1.0), 0.0)
        # the law's cut-off (exp(-5) = 0.0067 to 0) is a step: a node exactly at φ = 5/k (here z = 4 cm, since the
        # nodes lie on whole cells) is in or out by the float32 rounding of φ, so it is not judged
        inner &= np.abs(phi - 5.0 / softness) > 1e-6
    err = np.abs(measured - expected)[inner].max()
    report("contact law", softness=str(softness), nodes=int(inner.sum()), nodes_in_contact=int((expected > 0)[inner].sum()),
           max_error=err,
           influence_at_1cm=float(np.exp(-200.0 * 0.01)) if softness else 0.0)
    assert err < 1e-3
    assert (expected > 0.01)[inner].sum() > 100  # the law was exercised, not only its zero

def test_tool_kinematics_workspace_and_mask():
    scene = fl.Scene(lower=(0, 0, 0), upper=(0.2, 0.2, 0.2), grid_res=16, dt=2e-3, substeps=10)
    scene.add_particles(fl.Box((0.0, 0.0, 0.0), (0.2, 0.2, 0.02)), M.WATER, name="water")
    scene.add_tool(fl.Cylinder((0, 0, 0), 0.02, 0.05), pose=(0.1, 0.1, 0.12, 0, 0, 0, 1), name="stick",
                   action_mask=(1, 1, 0, 0, 0, 1), workspace=((0.05, 0.05, 0.1), (0.15, 0.15, 0.15)))
    sim = scene.build()
    # rotation about z at 2 rad/s for 0.1 s, and an ignored vz
    info = sim.step(np.array([0.0, 0.0, 5.0, 0.0, 0.0, 2.0]), n=50)
    pose = sim.tool_pose("stick")
    assert info["clipped"] == {"stick": False}
    np.testing.assert_allclose(pose[:3], (0.1, 0.1, 0.12), atol=1e-12)  # vz masked off
    yaw = Rotation.from_quat(pose[3:]).as_euler("xyz")[2]
    assert yaw == pytest.approx(0.2, abs=1e-9)
    # 0.5 m/s along x for 0.2 s would travel 0.1 m: the workspace stops it at x = 0.15
    info = sim.step(np.array([0.5, 0.0, 0.0, 0.0, 0.0, 0.0]), n=100)
    assert info["clipped"] == {"stick": True}
    assert sim.tool_pose("stick")[0] == pytest.approx(0.15, abs=1e-12)
    # the pose is part of the state
    state = sim.get_state()
    sim.step(np.array([-0.5, 0.0, 0.0, 0.0, 0.0, 0.0]), n=5)
    sim.set_state(state)
    assert sim.tool_pose("stick")[0] == pytest.approx(0.15, abs=1e-12)
    with pytest.raises(ValueError, match="shape"):
        sim.step(np.zeros(5))
    with pytest.raises(ValueError, match="NaN"):
        sim.step(np.full(6, np.nan))
    with pytest.raises(KeyError, match="no tool named"):
        sim.step({"spoon": np.zeros(6)})


def test_bad_tool_inputs_are_refused():
    scene = fl.Scene(lower=(0, 0, 0), upper=(0.2, 0.2, 0.2), grid_res=16)
    with pytest.raises(ValueError, match="quaternion"):
        scene.add_tool(fl.Sphere((0, 0, 0), 0.02), pose=(0.1, 0.1, 0.1, 0, 0, 0, 0))
    with pytest.raises(ValueError, match="softness"):
        scene.add_tool(fl.Sphere((0, 0, 0), 0.02), pose=(0.1, 0.1, 0.1, 0, 0, 0, 1), softness=-1.0)
    with pytest.raises(ValueError, match="contain the tool"):
        scene.add_tool(fl.Sphere((0, 0, 0), 0.02), pose=(0.1, 0.1, 0.1, 0, 0, 0, 1),
                       workspace=((0.0, 0.0, 0.0), (0.05, 0.05, 0.05)))


def test_paddle_makes_a_current_that_moves_a_floating_block():
    """A paddle pushed along +x through a water layer drives the water ahead of it, and a floating rigid block
    downstream moves with the current; no water gets inside the paddle."""
    scene = fl.Scene(lower=(0, 0, 0), upper=(0.3, 0.06, 0.1), grid_res=48, dt=2e-3, substeps=17)
    dx = scene.dx
    scene.add_particles(fl.Box((0.045, 0, 0), (0.3, 0.06, 0.03)), M.WATER, name="water")
    scene.add_particles(fl.Box((0.17, 0.015, 0.02), (0.21, 0.045, 0.04)), M.RIGID_LIGHT, name="block")
    scene.add_tool(fl.Box((-0.008, -0.04, -0.03), (0.008, 0.04, 0.03)), pose=(0.03, 0.03, 0.03, 0, 0, 0, 1),
                   name="paddle", softness=500.0, max_speed=0.3)
    sim = scene.build()
    x_block0 = sim.positions("block")[:, 0].mean()
    for _ in range(100):  # 0.2 s at 0.25 m/s: 5 cm
        sim.step(np.array([0.25, 0.0, 0.0, 0.0, 0.0, 0.0]))
    water_momentum = float((sim.masses("water") * sim.velocities("water")[:, 0]).sum())
    moved = sim.positions("block")[:, 0].mean() - x_block0
    paddle_x = sim.tool_pose("paddle")[0]
    xw = sim.positions("water")
    inside = (np.abs(xw[:, 0] - paddle_x) < 0.008 - 0.5 * dx) & (xw[:, 2] < 0.06)
    report("paddle", water_momentum_kg_m_s=water_momentum, block_moved_m=moved, water_inside_paddle=int(inside.sum()))
    assert water_momentum > 0.0
    assert moved > 0.002
    assert inside.sum() == 0


def test_mesh_tool_with_friction_drags_a_block(tmp_path):
    """A tool given as a mesh (a flat box exported by trimesh) presses on an elastic block lying on a
    frictionless floor and slides along +x: with tool friction μ = 1 the block is dragged along, without
    friction it stays where it is."""
    import trimesh

    plate = trimesh.creation.box(extents=(0.06, 0.06, 0.012))
    path = tmp_path / "plate.obj"
    plate.export(path)
    moved = {}
    for friction in (0.0, 1.0):
        scene = fl.Scene(lower=(0, 0, 0), upper=(0.2, 0.1, 0.1), grid_res=32, dt=1e-3, substeps=20)
        scene.add_particles(fl.Box((0.05, 0.03, 0.0), (0.09, 0.07, 0.03)), M.Elastic(
            "soft", density=1000.0, shear_modulus=5e4, lame_lambda=5e4), name="block")
        scene.add_tool(fl.Mesh(str(path)), pose=(0.07, 0.05, 0.0355, 0, 0, 0, 1), name="plate", friction=friction,
                       softness=None, max_speed=0.2)
        sim = scene.build()
        x0 = sim.positions("block")[:, 0].mean()
        sim.step(np.array([0.0, 0.0, -0.05, 0.0, 0.0, 0.0]), n=20)  # press 1 mm into the block
        sim.step(np.array([0.1, 0.0, 0.0, 0.0, 0.0, 0.0]), n=100)  # slide 1 cm
        moved[friction] = sim.positions("block")[:, 0].mean() - x0
    report("mesh tool friction", frictionless_m=moved[0.0], friction_1_m=moved[1.0])
    assert moved[1.0] > 0.005
    assert abs(moved[0.0]) < 0.2 * moved[1.0]
