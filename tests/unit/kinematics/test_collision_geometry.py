"""Capsule radii in robot descriptions: [collision] tables and URDF collision geometry."""

from __future__ import annotations

import tomllib

import pytest

from robocal.errors import ConfigError
from robocal.kinematics import (
    RobotDescription,
    default_link_radii,
    link_radii,
    load_robot,
    robot_to_toml,
    urdf_to_robot,
)


def test_builtin_ur10_carries_cited_radii_and_others_the_default() -> None:
    ur = load_robot("ur10")
    radii, source = link_radii(ur)
    assert [round(r * 1e3) for r in radii] == [78, 60, 43, 50, 46, 46]
    assert "Menagerie" in source
    lrd = load_robot("fanuc_lrmate200id")
    radii, source = link_radii(lrd)
    assert [round(r * 1e3) for r in radii] == [128, 124, 112, 71, 29, 29]
    assert "convex hulls" in source
    lr = load_robot("fanuc_lrmate200i")
    radii, source = link_radii(lr)
    assert lr.link_radii is None and radii == default_link_radii(lr)
    assert source.startswith("default")


def test_collision_table_round_trips_and_is_checked() -> None:
    d = load_robot("fanuc_lrmate200i").to_dict()
    d["collision"] = {"link_radii_mm": [70, 60, 50, 40, 35, 30], "source": "data sheet"}
    r = RobotDescription.from_dict(d)
    assert r.link_radii == pytest.approx((0.07, 0.06, 0.05, 0.04, 0.035, 0.03))
    again = RobotDescription.from_dict(tomllib.loads(robot_to_toml(r)))
    assert again.link_radii == r.link_radii and again.collision_source == "data sheet"
    for bad, key in (({"link_radii_mm": [1, 2]}, "collision.link_radii_mm"),
                     ({"link_radii_mm": [1, 2, 3, 4, 5, -6]}, "collision.link_radii_mm"),
                     ({"link_radii_mm": [1] * 6, "colour": "red"}, "collision.colour"),
                     ({"link_radii_mm": [1] * 6, "source": 3}, "collision.source")):
        with pytest.raises(ConfigError) as err:
            RobotDescription.from_dict({**d, "collision": bad})
        assert err.value.key == key


_URDF = """<robot name="two">
  <link name="base"/>
  <link name="l1"><collision><geometry><cylinder radius="0.07" length="0.3"/></geometry>
    </collision><collision><geometry><sphere radius="0.09"/></geometry></collision></link>
  <link name="l2"><collision><geometry><mesh filename="l2.stl"/></geometry></collision></link>
  <link name="l2_cover"><collision><geometry><box size="0.4 0.06 0.08"/></geometry>
    </collision></link>
  <link name="l3"><visual><geometry><cylinder radius="0.2" length="0.1"/></geometry></visual>
  </link>
  <link name="tool0"/>
  <joint name="j1" type="revolute"><parent link="base"/><child link="l1"/>
    <origin xyz="0 0 0.3"/><axis xyz="0 0 1"/><limit lower="-3" upper="3"/></joint>
  <joint name="j2" type="revolute"><parent link="l1"/><child link="l2"/>
    <origin xyz="0 0 0.1"/><axis xyz="0 1 0"/><limit lower="-2" upper="2"/></joint>
  <joint name="cover" type="fixed"><parent link="l2"/><child link="l2_cover"/></joint>
  <joint name="j3" type="revolute"><parent link="l2_cover"/><child link="l3"/>
    <origin xyz="0.4 0 0"/><axis xyz="0 1 0"/><limit lower="-2" upper="2"/></joint>
  <joint name="tool" type="fixed"><parent link="l3"/><child link="tool0"/>
    <origin xyz="0.2 0 0"/></joint>
</robot>"""


def test_urdf_import_takes_radii_from_collision_primitives() -> None:
    r = urdf_to_robot(_URDF, source="two.urdf", tool_mm=(0.0, 0.0, 50.0))
    assert r.link_radii is not None
    assert r.link_radii[0] == pytest.approx(0.09)                 # largest shape of l1
    assert r.link_radii[1] == pytest.approx(0.05)                 # box 0.06 x 0.08 on l2
    assert r.link_radii[2] == pytest.approx(default_link_radii(r)[2])   # visual only
    assert r.collision_source == ("URDF collision geometry (bodies 1, 2); default radii for "
                                  "bodies 3")
    meshes = _URDF.replace('<cylinder radius="0.07" length="0.3"/>', '<mesh filename="a"/>')
    meshes = meshes.replace('<sphere radius="0.09"/>', '<mesh filename="b"/>')
    meshes = meshes.replace('<box size="0.4 0.06 0.08"/>', '<mesh filename="c"/>')
    assert urdf_to_robot(meshes, source="m.urdf").link_radii is None
