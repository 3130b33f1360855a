"""The reference models in bench/ that the floating-body experiment is read against (issue 19): the potential-flow
added mass (bench/added_mass.py) and the 1-DOF heave model (bench/heave_drop_model.py), checked on cases with
exact answers. Plain numpy/scipy, well under a second."""
import importlib.util
from pathlib import Path

import numpy as np
import pytest

BENCH = Path(__file__).resolve().parents[1] / "bench"


def _load(name):
    spec = importlib.util.spec_from_file_location(name, BENCH / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_added_mass_of_a_piston_is_the_liquid_column_it_carries():
    """A body filling the tank's cross-section on its floor, the liquid above it up to a free surface: heaving,
    it carries the whole column (φ = z − L is exact on the grid), so m_a = ρ W² H and C_a = H / h_piston."""
    am = _load("added_mass")
    h, width, level, piston = 0.005, 0.04, 0.05, 0.01
    solid = am.box_cells((-1, -1, -1), (1, 1, piston), h, (width, width, level))
    ca, _, _ = am.added_mass_coefficient(solid, h, free_top=True)
    assert ca == pytest.approx((level - piston) / piston, rel=1e-6)


def test_added_mass_of_a_cube_falls_towards_the_tabulated_value():
    """A 40 mm cube far from everything: C_a falls with refinement towards 0.67 (DNV-RP-H103; bench/added_mass.py
    extrapolates 0.63 with φ = 0 on a box 2.5 sides out): 0.790 and 0.697 on 10 and 5 mm cells."""
    am = _load("added_mass")
    values = []
    for h in (0.01, 0.005):
        solid = am.box_cells((0.1, 0.1, 0.1), (0.14, 0.14, 0.14), h, (0.24, 0.24, 0.24))
        values.append(am.added_mass_coefficient(solid, h, free_top=False, dirichlet_box=True)[0])
    assert values[0] > values[1] > 0.6
    assert values[1] == pytest.approx(0.67, abs=0.05)


def test_heave_model_rests_at_archimedes_and_settles_there_after_a_drop():
    hm = _load("heave_drop_model")
    a, width, rho = 0.04, 0.12, 800.0
    shrink = 1.0 - a * a / width ** 2
    draft = a * rho / 1000.0
    at_rest, _, _ = hm.first_seconds(rho, c_a=0.5, zeta=0.1, c_d=1.0, drop=-draft * shrink, seconds=1)
    assert at_rest[0] == pytest.approx(0.8, abs=1e-6)
    dropped, deepest, _ = hm.first_seconds(rho, c_a=0.5, zeta=0.2, c_d=1.0, drop=0.01, seconds=4)
    assert dropped[-1] == pytest.approx(0.8, abs=0.005)
    assert deepest > draft  # it plunges past its resting draft first
    assert np.all(np.isfinite(dropped))
