"""data.frames: the one conversion between SocNav1 (cm, +y ahead, +x right, degrees) and
REP 103 (m, x forward, y left, yaw in radians), worked by hand and round-tripped."""
import math

import pytest

from stars_ros.data.frames import (Entity, Rep103Scene, from_rep103, from_socnav, heading_yaw, to_rep103, to_socnav,
                                   yaw_heading)


def test_points_by_hand():
    assert to_rep103(0, 100) == (1.0, 0.0)          # 1 m ahead
    assert to_rep103(100, 0) == (0.0, -1.0)         # 1 m to the right
    assert from_rep103(1.0, 0.0) == (-0.0, 100.0)
    assert from_rep103(0.0, -1.0) == (100.0, 0.0)
    assert from_rep103(*to_rep103(-37.5, 212.0)) == pytest.approx((-37.5, 212.0))


@pytest.mark.parametrize('degrees', [0.0, 45.0, 90.0, -90.0, 179.0, -179.0])
def test_headings_round_trip(degrees):
    assert yaw_heading(heading_yaw(degrees)) == pytest.approx(degrees)


def test_a_person_facing_the_robot_has_yaw_pi():
    assert heading_yaw(0) == pytest.approx(math.pi)
    assert yaw_heading(math.pi) == pytest.approx(0.0, abs=1e-12)
    assert yaw_heading(0.0) == pytest.approx(180.0)  # facing away from the robot, along x


def test_scenes_round_trip():
    scene = Rep103Scene(humans=(Entity(1, 2.0, 0.5, 0.3), Entity(2, 1.0, -1.0, -2.0)),
                        objects=(Entity(3, 3.0, 0.0, 1.0),),
                        room=((5.0, 5.0), (5.0, -5.0), (-5.0, -5.0), (-5.0, 5.0)), interactions=((1, 2),))
    socnav = to_socnav(scene, identifier='s1')
    assert socnav['identifier'] == 's1'
    assert socnav['humans'][0]['xPos'] == pytest.approx(-50.0) and socnav['humans'][0]['yPos'] == pytest.approx(200.0)
    assert socnav['links'] == [[1, 2, 'interact']]
    back = from_socnav(socnav)
    for a, b in zip(back.humans + back.objects, scene.humans + scene.objects):
        assert (a.id, a.x, a.y) == (b.id, pytest.approx(b.x), pytest.approx(b.y))
        assert math.cos(a.yaw - b.yaw) == pytest.approx(1.0)
    assert [tuple(p) for p in back.room] == [pytest.approx(p) for p in scene.room]
    assert back.interactions == scene.interactions
