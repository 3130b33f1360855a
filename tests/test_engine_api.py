"""The engine's public API: initialisation, scene validation, state round trips, errors that say what to do."""
import subprocess
import sys

import numpy as np
import pytest

import fluidlab_core as fl
from fluidlab_core import materials as M
from fluidlab_core.simulator import NonFiniteStateError


def _small_scene(**kwargs):
    kwargs = {"dt": 1e-3, "substeps": 10, **kwargs}
    scene = fl.Scene(lower=(0, 0, 0), upper=(0.1, 0.1, 0.1), grid_res=16, **kwargs)
    water = scene.add_particles(fl.Box((0.02, 0.02, 0.0), (0.08, 0.08, 0.05)), M.WATER, name="water")
    return scene, water


def test_import_does_no_work():
    """Importing the package neither imports Taichi nor initialises anything."""
    code = ("import sys, fluidlab_core; from fluidlab_core import runtime; "
            "assert 'taichi' not in sys.modules, 'taichi imported'; assert runtime.current() is None; print('ok')")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "ok"


def test_auto_backend_probes_cuda_and_cuda_without_a_device_is_refused():
    """arch="auto" picks CUDA when Taichi finds a device and the CPU otherwise; arch="cuda" on a machine
    without one fails with a message (separate processes: init resets Taichi)."""
    code = ("import fluidlab_core, taichi as ti; from taichi.lang.misc import is_arch_supported; "
            "cfg = fluidlab_core.init(arch='auto'); "
            "expected = 'cuda' if is_arch_supported(ti.cuda) else 'cpu'; "
            "assert cfg.backend == expected, (cfg.backend, expected); print(cfg.backend)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    if out.stdout.strip() == "cpu":
        code = "import fluidlab_core; fluidlab_core.init(arch='cuda')"
        out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
        assert out.returncode != 0 and "no CUDA device" in out.stderr


def test_init_is_idempotent_and_validates():
    first = fl.init(arch="cpu", precision="f32", seed=0)
    assert fl.init(arch="cpu", precision="f32", seed=0) is first
    with pytest.raises(ValueError, match="arch must be one of"):
        fl.init(arch="tpu")
    with pytest.raises(ValueError, match="precision must be one of"):
        fl.init(precision="f16")


def test_fast_compilation_lowers_the_level_only_around_the_solvers_forward(monkeypatch):
    """FLUIDLAB_FAST_COMPILE (the suite sets 1, conftest.py): a `compiled_fast` method runs at Taichi's opt_level 0
    and the level goes back to 1 after it, also when it raises; a value other than 0 or 1 is refused by name."""
    import os

    from taichi.lang import impl

    cfg = fl.init(arch="cpu", precision="f32", seed=0)
    assert cfg.fast_compile == (os.environ.get("FLUIDLAB_FAST_COMPILE") == "1")
    seen = []

    @fl.runtime.compiled_fast
    def forward(fail=False):
        seen.append(impl.current_cfg().opt_level)
        if fail:
            raise RuntimeError("stop")

    forward()
    with pytest.raises(RuntimeError, match="stop"):
        forward(fail=True)
    inside = 0 if cfg.fast_compile else 1
    assert seen == [inside, inside] and impl.current_cfg().opt_level == 1
    monkeypatch.setenv("FLUIDLAB_FAST_COMPILE", "yes")
    with pytest.raises(ValueError, match="FLUIDLAB_FAST_COMPILE must be 0 or 1, got 'yes'"):
        fl.init(arch="cpu", precision="f32", seed=0)


def test_a_simulator_built_before_a_reset_says_so_when_used():
    """After a reset of Taichi (fluidlab_core.runtime.reset, or init with other arguments) a simulator built before
    it raises RuntimeError naming the reset when stepped, read or restored: its fields are gone (reading them gave
    Taichi's errors about fields of nonsense dimensions)."""
    scene, water = _small_scene()
    sim = scene.build()
    state = sim.get_state()
    assert sim.positions(water).shape == (state.x.shape[0], 3)
    fl.runtime.reset()
    uses = {"step": lambda: sim.step(), "positions": lambda: sim.positions(water), "velocities": sim.velocities,
            "get_state": sim.get_state, "set_state": lambda: sim.set_state(state), "check_finite": sim.check_finite}
    for name, use in uses.items():
        with pytest.raises(RuntimeError, match=r"runtime.reset\(\) reset Taichi.*build the scene again"):
            use()
            pytest.fail(f"{name} ran on a simulator from before the reset")


def test_particle_mass_and_volume_follow_the_sampling_density():
    """Mass = ρ × shape volume for shapes that fit the lattice; curved shapes within a few percent."""
    scene, water = _small_scene(substeps=25)
    sphere = scene.add_particles(fl.Sphere((0.05, 0.05, 0.08), 0.015), M.ELASTIC, name="ball")
    sim = scene.build()
    box_volume = 0.06 * 0.06 * 0.05
    assert sim.masses("water").sum() == pytest.approx(M.WATER.density * box_volume, rel=1e-4)
    assert sim.volumes("water").sum() == pytest.approx(box_volume, rel=1e-4)
    ball_volume = 4 / 3 * np.pi * 0.015 ** 3
    assert sim.masses(sphere).sum() == pytest.approx(M.ELASTIC.density * ball_volume, rel=0.06)
    assert sim.positions("water").shape == (water.count, 3)


def test_state_round_trip_is_exact():
    scene, _ = _small_scene()
    sim = scene.build()
    sim.step(n=5)
    state = sim.get_state()
    sim.step(n=5)
    after = sim.positions("water")
    sim.set_state(state)
    again = sim.get_state()
    for key in ("x", "v", "C", "F"):
        np.testing.assert_array_equal(getattr(again, key), getattr(state, key))
    assert sim.step_count == 5
    sim.step(n=5)
    # parallel float atomics may add in another order: equal to float32 round-off, not bit for bit
    np.testing.assert_allclose(sim.positions("water"), after, atol=1e-6)
    with pytest.raises(ValueError, match="rows"):
        sim.set_state(state.replace(x=state.x[:3]))


def test_unstable_time_step_is_refused_with_the_numbers_and_the_fix():
    scene, _ = _small_scene(dt=2e-3, substeps=2)
    with pytest.raises(fl.UnstableTimeStepError) as err:
        scene.build()
    message = str(err.value)
    assert "CFL" in message and "water" in message and "substeps >=" in message
    need = int(message.split("substeps >= ")[1].split()[0])
    fixed, _ = _small_scene(dt=2e-3, substeps=need)
    fixed.check()  # the suggested substep count is accepted


def test_viscous_limit_is_refused():
    honey = M.ViscousLiquid("very_viscous", density=1000.0, viscosity_pas=2000.0)
    scene = fl.Scene(lower=(0, 0, 0), upper=(0.1, 0.1, 0.1), grid_res=16, dt=2e-3, substeps=40)
    scene.add_particles(fl.Box((0.02, 0.02, 0.0), (0.08, 0.08, 0.05)), honey)
    with pytest.raises(fl.UnstableTimeStepError, match="viscous limit"):
        scene.build()


def test_bulk_viscosity_counts_in_the_viscous_limit_and_must_be_positive():
    """ρΔx²/(6(η + ζ)): ζ = 2000 Pa·s at Δx = 6.25 mm allows 3.3e-6 s, far below the 5e-5 s substep."""
    damped = M.DampedLiquid("very_damped", density=1000.0, bulk_viscosity_pas=2000.0)
    scene = fl.Scene(lower=(0, 0, 0), upper=(0.1, 0.1, 0.1), grid_res=16, dt=2e-3, substeps=40)
    scene.add_particles(fl.Box((0.02, 0.02, 0.0), (0.08, 0.08, 0.05)), damped)
    assert scene.stability_limits()["viscous_dt"] == pytest.approx(1000.0 * 0.00625 ** 2 / (6 * 2000.0))
    with pytest.raises(fl.UnstableTimeStepError, match="viscous limit.*very_damped"):
        scene.build()
    with pytest.raises(ValueError, match="bulk_viscosity_pas"):
        M.DampedLiquid("bad", density=1000.0, bulk_viscosity_pas=-1.0)


def test_bad_scene_inputs_name_the_problem():
    with pytest.raises(ValueError, match="lower < upper"):
        fl.Scene(lower=(0, 0, 0), upper=(0.1, -0.1, 0.1))
    with pytest.raises(ValueError, match="dt must be"):
        fl.Scene(dt=-1.0)
    scene = fl.Scene(lower=(0, 0, 0), upper=(0.1, 0.1, 0.1), grid_res=16)
    with pytest.raises(ValueError, match="outside the domain"):
        scene.add_particles(fl.Box((0.05, 0.05, 0.05), (0.2, 0.08, 0.08)), M.WATER)
    with pytest.raises(ValueError, match="no particle"):
        scene.add_particles(fl.Sphere((0.05, 0.05, 0.05), 1e-4), M.WATER)
    with pytest.raises(ValueError, match="container"):
        scene.add_particles(fl.Cup((0.05, 0.05, 0.0), 0.03, 0.05, 0.01), M.WATER)
    with pytest.raises(ValueError, match="no particles"):
        scene.build()
    with pytest.raises(ValueError, match="positive"):
        M.NewtonianLiquid("bad", density=-1.0)
    with pytest.raises(KeyError, match="known: "):
        M.get("lava")


def test_thin_container_walls_are_refused():
    scene, _ = _small_scene()
    dx = scene.dx
    scene.add_static(fl.Cup((0.05, 0.05, 0.0), 0.045, 0.08, wall_thickness=1.5 * dx))
    with pytest.raises(ValueError, match="2 grid cells"):
        scene.build()


def test_nan_raises_an_error_naming_field_and_step():
    scene, _ = _small_scene()
    sim = scene.build()
    sim.step(n=2)
    state = sim.get_state()
    state.v[7] = np.nan
    sim.set_state(state)
    with pytest.raises(NonFiniteStateError) as err:
        sim.step()
    message = str(err.value)
    assert "velocities (v)" in message and "step 3" in message and "'water'" in message


def test_catalogue_follows_the_paper_similarity():
    """λ = 277.78 paper units → 2.7778e5 Pa; μ 416.67 → 4.1667e5 Pa; densities scale by 1000 kg/m³."""
    assert M.WATER.lam == pytest.approx(277.78 * 1000.0)
    assert M.ELASTIC.mu == pytest.approx(416.67 * 1000.0)
    assert M.WATER.mu == 0.0
    assert M.MILK.density / M.COFFEE.density == pytest.approx(1.0)  # the paper's ρ = 1.0 for both
    assert (M.LIGHT_LIQUID.density, M.HEAVY_LIQUID.density) == (800.0, 1500.0)  # the paper's 0.8 and 1.5
    assert M.MILK_FOAM.density == 500.0  # the project's floating foam, under its own name
    mu, lam = M.lame_from_young(1000.0, 0.2)
    assert (mu, lam) == pytest.approx((416.667, 277.778), rel=1e-5)
    for name in ("water", "milk", "coffee", "frothed_milk", "ice_cream", "elastic", "plastic", "rigid",
                 "light_liquid", "heavy_liquid"):
        assert M.get(name).name == name


def test_double_precision_runs_the_same_physics():
    """The f64 path (which gradient tests will use) compiles every model and agrees with f32 on a short drop
    (separate process: init resets Taichi)."""
    code = """
import numpy as np, fluidlab_core as fl
from fluidlab_core import materials as M
out = {}
for precision in ("f64", "f32"):
    fl.init(arch="cpu", precision=precision)
    scene = fl.Scene(lower=(0, 0, 0), upper=(0.1, 0.1, 0.1), grid_res=16, dt=1e-3, substeps=30)
    for i, mat in enumerate((M.WATER, M.FROTHED_MILK, M.ELASTIC, M.PLASTIC, M.ICE_CREAM, M.RIGID)):
        x0 = 0.005 + 0.015 * i
        scene.add_particles(fl.Box((x0, 0.04, 0.02), (x0 + 0.012, 0.06, 0.04)), mat, name=mat.name)
    sim = scene.build()
    sim.step(n=20)
    out[precision] = sim.positions()
    assert sim.state.x.dtype == (fl.runtime.real_dtype())
err = np.abs(out["f64"] - out["f32"]).max()
assert err < 1e-4, err
print("max difference", err)
"""
    run = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=600)
    assert run.returncode == 0, run.stderr[-2000:]
    assert "max difference" in run.stdout


@pytest.mark.cuda
def test_cuda_runs_the_same_physics_as_the_cpu():
    """On a GPU machine (FLUIDLAB_TEST_ARCH=cuda): every material class, a static and a tool, 20 steps on CUDA
    and on the CPU (separate processes), positions equal to float32 round-off amplified by the dynamics."""
    code = """
import sys, numpy as np, fluidlab_core as fl
from fluidlab_core import materials as M
fl.init(arch=sys.argv[1], precision="f32", seed=0)
scene = fl.Scene(lower=(0, 0, 0), upper=(0.1, 0.1, 0.1), grid_res=16, dt=1e-3, substeps=30)
for i, mat in enumerate((M.WATER, M.FROTHED_MILK, M.ELASTIC, M.PLASTIC, M.ICE_CREAM, M.RIGID)):
    x0 = 0.005 + 0.015 * i
    scene.add_particles(fl.Box((x0, 0.04, 0.02), (x0 + 0.012, 0.06, 0.04)), mat, name=mat.name)
scene.add_static(fl.Box((0.0, 0.0, 0.0), (0.1, 0.1, 0.01)), friction=0.3)
scene.add_tool(fl.Sphere((0, 0, 0), 0.01), pose=(0.05, 0.02, 0.05, 0, 0, 0, 1), softness=400.0)
sim = scene.build()
assert fl.runtime.current().backend == sys.argv[1]
sim.step([0.0, 0.1, 0.0, 0.0, 0.0, 0.0], n=20)
np.save(sys.argv[2], sim.positions())
"""
    import tempfile

    with tempfile.TemporaryDirectory() as tmp:
        out = {}
        for arch in ("cuda", "cpu"):
            path = f"{tmp}/{arch}.npy"
            run = subprocess.run([sys.executable, "-c", code, arch, path], capture_output=True, text=True, timeout=900)
            assert run.returncode == 0, run.stderr[-2000:]
            out[arch] = np.load(path)
    err = np.abs(out["cuda"] - out["cpu"]).max()
    print(f"\n[cuda vs cpu] max position difference {err:.3g} m after 20 steps")
    assert err < 1e-4, err
