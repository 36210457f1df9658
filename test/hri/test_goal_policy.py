"""The goal policy without ROS: a goal only when the decision changes, hysteresis between
near-equal placements, cancels on abstain and when the person leaves, and the refusal of a
goal frame that moves with the robot."""
import math

import pytest

from stars_ros.hri.decisions import decide
from stars_ros.hri.goals import GoalPolicy, GoalSettings, robot_frame_goal_refusal
from stars_ros.hri.poses import Pose

ROBOT = Pose(10.0, 5.0, math.pi / 2, 0)


def ranking(scores: dict, p_best=None, scene_id='hri-1') -> dict:
    """A stars/ranking payload ranking placements by ``scores`` (label -> score)."""
    ordered = sorted(scores.items(), key=lambda item: -item[1])
    payload = {'scene_id': scene_id, 'user_id': 'alice',
               'ranking': [{'candidate': label, 'score': score, 'rank': k + 1} for k, (label, score) in
                           enumerate(ordered)]}
    if p_best is not None:
        payload['p_first_is_best'] = p_best
    return payload


def step(policy, scores, person='alice', robot=ROBOT, p_best=None):
    """As the bridge does: ``person`` served (its tick), then a ranking of a scene sent for them."""
    policy.on_served(person)
    return decide_for(policy, scores, person, robot, p_best)


def decide_for(policy, scores, person, robot=ROBOT, p_best=None):
    """A ranking of a scene sent while ``person`` was served, whoever is served now."""
    return policy.on_decision(decide(ranking(scores, p_best), 0.5, robot), person)


def test_an_unchanged_decision_for_60_s_at_2_hz_gives_one_goal():
    policy = GoalPolicy()
    steps = [step(policy, {'back_50cm': 0.8, 'stay': 0.3}) for _ in range(120)]
    sent = [s.send for s in steps if s.send is not None]
    assert len(sent) == 1
    assert (sent[0].x, sent[0].y) == (pytest.approx(10.0), pytest.approx(4.5))  # 0.5 m behind, facing +y
    assert not any(s.cancel for s in steps)


def test_a_changed_best_placement_gives_one_new_goal():
    policy = GoalPolicy()
    assert step(policy, {'back_50cm': 0.8, 'stay': 0.3}).send is not None
    changed = [step(policy, {'back_50cm': 0.3, 'stay': 0.8}) for _ in range(10)]
    assert sum(s.send is not None for s in changed) == 1
    assert changed[0].send.x == pytest.approx(ROBOT.x) and 'another placement' in changed[0].reason


def test_near_equal_placements_do_not_alternate():
    policy = GoalPolicy(GoalSettings(hysteresis=0.05))
    assert step(policy, {'back_50cm': 0.61, 'stay': 0.60}).send is not None
    flips = [step(policy, {'back_50cm': 0.60, 'stay': 0.61} if k % 2 else {'back_50cm': 0.61, 'stay': 0.60})
             for k in range(20)]
    assert not any(s.send for s in flips)
    assert 'hysteresis' in flips[1].reason


def test_a_new_best_at_the_same_place_keeps_the_goal():
    policy = GoalPolicy()
    assert step(policy, {'back_50cm': 0.9, 'stay': 0.1}).send is not None
    arrived = Pose(10.0, 4.5, math.pi / 2, 0)  # the robot reached the goal: 'stay' is where it is
    kept = step(policy, {'stay': 0.9, 'back_50cm': 0.1}, robot=arrived)
    assert kept.send is None and 'goal kept' in kept.reason


def test_abstain_cancels_and_its_end_sends_the_goal_again():
    policy = GoalPolicy()
    assert step(policy, {'back_50cm': 0.8, 'stay': 0.3}).send is not None
    abstained = step(policy, {'back_50cm': 0.8, 'stay': 0.3}, p_best=0.2)
    assert abstained.cancel and abstained.send is None and 'abstain' in abstained.reason
    assert not step(policy, {'back_50cm': 0.8, 'stay': 0.3}, p_best=0.2).cancel  # nothing left to cancel
    assert step(policy, {'back_50cm': 0.8, 'stay': 0.3}, p_best=0.9).send is not None


def test_another_person_sends_a_goal_and_a_person_leaving_cancels():
    policy = GoalPolicy()
    assert step(policy, {'back_50cm': 0.8, 'stay': 0.3}).send is not None
    assert step(policy, {'back_50cm': 0.8, 'stay': 0.3}, person='bob').send is not None
    assert not policy.on_served('bob').cancel
    assert policy.on_served(None).cancel
    assert step(policy, {'back_50cm': 0.8, 'stay': 0.3}, person='bob').send is not None


def test_after_the_served_person_leaves_their_cancelled_goal_is_not_sent_again_for_nobody():
    """The bridge cancels the goal as they leave; the rankings that follow, of scenes sent for
    nobody, send no goal at its place (identical or within the tolerances), nor do those of
    scenes sent for them before they left; a placement elsewhere for nobody is a goal."""
    policy = GoalPolicy()
    assert step(policy, {'back_50cm': 0.8, 'stay': 0.3}).send is not None
    assert policy.on_served(None).cancel
    for person in (None, 'alice', None):
        left = decide_for(policy, {'back_50cm': 0.8, 'stay': 0.3}, person)
        assert left.send is None and not left.cancel, left.reason
    assert 'not sent again' in left.reason
    elsewhere = decide_for(policy, {'back_50cm': 0.2, 'stay': 0.9}, None)
    assert elsewhere.send is not None and elsewhere.send.x == pytest.approx(ROBOT.x)
    assert step(policy, {'back_50cm': 0.8, 'stay': 0.3}).send is not None  # served again: a goal again


def test_nobody_served_gets_goals_and_a_ranking_from_before_a_change_sends_none():
    policy = GoalPolicy()
    assert step(policy, {'back_50cm': 0.8, 'stay': 0.3}, person=None).send is not None  # as at start-up
    policy.on_served('bob')
    stale = decide_for(policy, {'back_50cm': 0.2, 'stay': 0.9}, None)
    assert stale.send is None and 'sent while nobody was served' in stale.reason


def test_goal_frames_that_move_with_the_robot_need_the_opt_in():
    assert 'goal_in_robot_frame' in robot_frame_goal_refusal('base_link', 'base_link', False)
    assert robot_frame_goal_refusal('base_footprint', 'base_link', False)
    assert robot_frame_goal_refusal('base_link', 'base_link', True) is None
    assert robot_frame_goal_refusal('map', 'base_link', False) is None
    assert robot_frame_goal_refusal('odom', 'base_link', False) is None


def test_settings_are_checked():
    with pytest.raises(ValueError, match='hysteresis'):
        GoalSettings(hysteresis=-1.0)
