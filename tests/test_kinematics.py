"""The seed conversion node's formulas (protocol doc §7) with its default parameters."""

from __future__ import annotations

import math

import pytest

from abh3_supervisor.core.kinematics import (
    Geometry,
    ab_to_twist,
    ab_to_yx,
    twist_to_ab,
    twist_to_yx,
    yx_to_ab,
    yx_to_twist,
)

G = Geometry()  # rateNum 1.0, rateDen 10.0, wheel 0.1, width 0.5


def test_defaults_are_the_seeds() -> None:
    assert (G.rate_num, G.rate_den, G.wheel, G.width) == (1.0, 10.0, 0.1, 0.5)


def test_ab_yx_both_ways() -> None:
    assert ab_to_yx(120.0, 80.0) == (100.0, 20.0)
    assert yx_to_ab(100.0, 20.0) == (120.0, 80.0)


def test_twist_to_yx_is_the_seed_formula() -> None:
    # Y = linear.x · 60 / (r · wheel · π); X = −angular.z · 60 / (r · wheel · π) · (width / 2)
    y, x = twist_to_yx(0.5, 0.2, G)
    k = 60 / (0.1 * 0.1 * math.pi)
    assert y == pytest.approx(0.5 * k)
    assert x == pytest.approx(-0.2 * k * 0.25)


def test_yx_to_twist_inverts_it() -> None:
    lin, ang = yx_to_twist(*twist_to_yx(0.5, -0.3, G), G)
    assert (lin, ang) == pytest.approx((0.5, -0.3))


def test_twist_ab_round_trip_with_other_geometry() -> None:
    g = Geometry(rate_num=1, rate_den=20, wheel=0.2, width=0.6)
    a, b = twist_to_ab(1.0, 0.5, g)
    assert ab_to_twist(a, b, g) == pytest.approx((1.0, 0.5))
    # turning left (positive angular.z) makes X negative, so the B motor runs faster
    assert b > a
