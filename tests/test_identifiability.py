"""Base parameters and classes (Khosla 5.4) against cases known in closed form."""

from __future__ import annotations

import warnings

import numpy as np
import pytest
from conftest import ROBOTS

from armid.identify.errors import PoorExcitationWarning
from armid.identify.identifiability import excitation
from armid.identify.identification import structural_base
from armid.identify.robot import Robot
from armid.io.robot_file import load_robot


def _classes(base):  # type: ignore[no-untyped-def]
    return dict(zip(base.names, base.classes()))


def test_planar_two_link_base_parameters_in_closed_form():  # type: ignore[no-untyped-def]
    robot = load_robot(ROBOTS / "planar2.yaml")
    base = structural_base(robot)
    # a planar nR arm with gravity in its plane has 3n base parameters
    assert base.n_base == 6
    exprs = set(base.expressions())
    a1, a2 = 0.5, 0.4
    # link frames sit at the distal joint: Izz about joint i = Izz_i - 2 a_i msx_i ... regroups
    assert f"Izz2 - {a2**2:.4g}*m2" in exprs
    assert f"msx2 + {a2:.4g}*m2" in exprs
    assert "msy2" in exprs and "msy1" in exprs
    assert f"msx1 + {a1:.4g}*m1 + {a1:.4g}*m2" in exprs
    cls = _classes(base)
    assert cls["msy1"] == "unique" and cls["msy2"] == "unique"
    assert cls["m2"] == "combination" and cls["Izz1"] == "combination"
    for name in ("Ixx1", "Iyy1", "Ixy1", "msz1", "Ixx2", "Iyz2", "msz2"):
        assert cls[name] == "unidentifiable"


def test_planar_without_gravity_loses_first_moments_of_link_one():  # type: ignore[no-untyped-def]
    robot = load_robot(ROBOTS / "planar2.yaml")
    free = Robot(robot.name, np.zeros(3), robot.joints)
    assert structural_base(free).n_base == 4  # 3n - 2 without gravity


def test_puma560_has_its_known_36_base_inertial_parameters():  # type: ignore[no-untyped-def]
    robot = load_robot(ROBOTS / "puma560.yaml")
    base = structural_base(robot, effects=[])
    assert base.n_base == 36
    # link 1 only turns about its (vertical) axis: only one of its 10 parameters counts
    cls = _classes(base)
    assert [cls[f"{p}1"] for p in ("m", "msx", "msy", "msz", "Ixx", "Ixy", "Ixz", "Iyz", "Izz")] == ["unidentifiable"] * 9


def test_table2_style_mass_combination_on_a_wrist():  # type: ignore[no-untyped-def]
    # the PUMA's m4, m5, m6 appear only together, as Khosla's m5 + m4 (Table 2)
    base = structural_base(load_robot(ROBOTS / "puma560.yaml"), effects=[])
    cls = _classes(base)
    assert cls["m5"] == "combination" and cls["m6"] == "combination"
    assert any("0.4318*m4 + 0.4318*m5 + 0.4318*m6" in e for e in base.expressions())


def test_values_map_through_the_regrouping():  # type: ignore[no-untyped-def]
    from armid.identify.dynamics import regressor
    from armid.identify.identification import random_motion

    robot = load_robot(ROBOTS / "scara_mdh.yaml")
    base = structural_base(robot)
    phi = robot.modeled_parameters()
    q, qd, qdd = random_motion(robot, 30, seed=5)
    w = regressor(robot, q, qd, qdd)
    assert np.allclose(w @ phi, w[..., base.independent] @ base.base_values(phi))


def test_poor_excitation_warns_and_names_the_weak_parameters():  # type: ignore[no-untyped-def]
    rng = np.random.default_rng(0)
    w = rng.normal(size=(200, 3))
    w[:, 2] = w[:, 0] + 1e-6 * rng.normal(size=200)
    with pytest.warns(PoorExcitationWarning, match="condition number"):
        exc = excitation(w, ["a", "b", "c"])
    assert set(exc.weak) == {"a", "c"}
    w[:, 2] = w[:, 0]
    with pytest.warns(PoorExcitationWarning, match="excites 2 of 3"):
        excitation(w, ["a", "b", "c"])
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        excitation(rng.normal(size=(200, 3)), ["a", "b", "c"])
