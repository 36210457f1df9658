"""The ROS4HRI bridge's core without ROS: who is served, the scene, decisions, outcomes."""
import json
import math

import pytest

from stars_ros.data import frames
from stars_ros.errors import ConfigError
from stars_ros.hri.bridge import BridgeCore, BridgeSettings
from stars_ros.hri.decisions import decide
from stars_ros.hri.people import DISENGAGED, ENGAGED, ENGAGING, People, Served
from stars_ros.hri.poses import Pose, TransformTable, compose
from stars_ros.hri.scene import SceneSettings, placement_offset

SECOND = 10 ** 9


class Clock:
    def __init__(self):
        self.t = 100 * SECOND

    def __call__(self):
        return self.t

    def advance(self, seconds):
        self.t += int(seconds * SECOND)


@pytest.fixture
def world():
    clock, poses = Clock(), TransformTable()
    core = BridgeCore(BridgeSettings(scene=SceneSettings(max_age=0.5, min_confidence=0.5), outcome_window=3.0),
                      poses, clock)
    return core, poses, clock


def place(poses, clock, person_id, x, y, yaw=0.0, age=0.0):
    poses.put('base_link', f'person_{person_id}', Pose(x, y, yaw, clock() - int(age * SECOND)))


def person(core, person_id, level=ENGAGED, anonymous=False):
    core.on_person('anonymous', person_id, anonymous)
    core.on_person('engagement_status', person_id, level)


def test_served_tie_rule_recognised_then_nearest_then_longest_engaged():
    clock = Clock()
    people = People(clock)
    people.set_tracked(['far', 'near', 'anon', 'early'])
    distances = {'far': 3.0, 'near': 1.0, 'anon': 0.5, 'early': 1.0}
    people.set_engagement('anon', ENGAGED)  # anonymous by default, nearest of all
    assert people.served(distances.get).person_id == 'anon' and people.served(distances.get).user_id is None
    for pid in ('far', 'early'):
        people.set_anonymous(pid, False)
    people.set_engagement('far', ENGAGED)
    assert people.served(distances.get).person_id == 'far'  # recognised before anonymous
    clock.t += SECOND
    people.set_engagement('early', ENGAGED)
    people.set_anonymous('near', False)
    clock.t += SECOND
    people.set_engagement('near', ENGAGED)
    assert people.served(distances.get).person_id == 'early'  # as near as 'near', engaged longer
    people.set_engagement('early', DISENGAGED)
    assert people.served(distances.get).user_id == 'near'
    people.set_engagement('near', ENGAGING)
    people.set_engagement('far', DISENGAGED)
    served = people.served(distances.get)
    assert served.person_id == 'anon' and served.user_id is None
    people.set_engagement('anon', DISENGAGED)
    assert people.served(distances.get).person_id is None
    assert 'population prior' in people.served(distances.get).describe()


def test_aliases_are_followed_and_cycles_refused():
    people = People(Clock())
    people.set_tracked(['tmp', 'alice'])
    people.set_engagement('tmp', ENGAGED)
    people.set_anonymous('alice', False)
    assert people.served(lambda _: 1.0).user_id is None  # 'tmp' is anonymous
    people.set_alias('tmp', 'alice')
    served = people.served(lambda _: 1.0)
    assert served.person_id == 'alice' and served.user_id == 'alice'
    assert people.members() == {'alice': ['tmp', 'alice']}
    with pytest.raises(ValueError, match='cycle'):
        people.set_alias('alice', 'tmp')
    assert people.canonical('tmp') == 'alice'  # the refused alias changed nothing


def test_scene_positions_follow_the_poses_through_the_one_conversion(world):
    core, poses, clock = world
    core.on_tracked(['a', 'b'])
    person(core, 'a')
    person(core, 'b', level=DISENGAGED)
    place(poses, clock, 'a', 1.5, -0.25, yaw=0.3)
    place(poses, clock, 'b', 2.0, 1.0, yaw=-2.0)
    out = core.tick()
    assert out.user_id == 'a'
    request = out.scene
    stay = next(c['graph'] for c in request['candidates'] if c['candidate'] == 'stay')
    back = frames.from_socnav(stay)
    got = sorted(v for h in back.humans for v in (h.x, h.y))
    assert got == pytest.approx(sorted([1.5, -0.25, 2.0, 1.0]), abs=1e-3)
    assert {round(h.yaw, 3) for h in back.humans} == {0.3, -2.0}
    assert request['user_id'] == 'a' and len(request['candidates']) == 6
    assert all(isinstance(h['id'], int) for h in stay['humans'])  # no ROS4HRI id in a scene


def test_stale_low_confidence_and_missing_poses_are_left_out_and_counted(world):
    core, poses, clock = world
    core.on_tracked(['fresh', 'stale', 'unsure', 'ghost', 'nan'])
    for pid in ('fresh', 'stale', 'unsure', 'ghost', 'nan'):
        person(core, pid, level=DISENGAGED)
    place(poses, clock, 'fresh', 1.0, 0.0)
    place(poses, clock, 'stale', 1.0, 1.0, age=0.6)
    place(poses, clock, 'unsure', 1.0, -1.0)
    core.on_person('location_confidence', 'unsure', 0.2)
    core.on_person('location_confidence', 'fresh', 1.0)
    with pytest.raises(ValueError, match='not finite'):
        poses.put('base_link', 'person_nan', Pose(math.nan, 0.0, 0.0, clock()))
    core.tick()
    built = core.last_scene
    assert built.people == ('fresh',)
    assert built.left_out == {'stale': ['stale'], 'low_confidence': ['unsure'], 'no_pose': ['ghost', 'nan']}
    period, totals = core.problems.take_period()
    assert {'stale', 'low_confidence', 'no_pose'} <= set(totals)


def test_groups_and_mutual_gaze_become_interactions(world):
    core, poses, clock = world
    core.on_tracked(['a', 'b', 'c', 'd'])
    for k, pid in enumerate('abcd'):
        person(core, pid, level=DISENGAGED)
        place(poses, clock, pid, 1.0 + k, 0.0)
    core.on_group('g1', ['a', 'b', 'stranger'], clock())
    core.on_gaze('c', 'd', clock())
    core.tick()
    assert len(core.last_scene.scene.interactions) == 2  # the group only: c looks at d, not back
    core.on_gaze('d', 'c', clock())
    core.tick()
    assert len(core.last_scene.scene.interactions) == 4
    clock.advance(1.0)
    for k, pid in enumerate('abcd'):
        place(poses, clock, pid, 1.0 + k, 0.0)
    core.tick()
    assert core.last_scene.scene.interactions == ()  # facts older than max_age are forgotten
    assert 'unknown_id' in core.problems.take_period()[1]


def test_bad_input_is_counted_and_changes_nothing(world):
    core, poses, clock = world
    core.on_tracked(['a'])
    core.on_person('engagement_status', 'nobody', ENGAGED)
    core.on_person('engagement_status', 'a', 9)
    core.on_person('location_confidence', 'a', math.nan)
    core.on_executed('{not json')
    core.on_executed(json.dumps({'scene_id': 'never-sent', 'action': 'x'}))
    assert core.on_ranking('[]', None) is None
    totals = core.problems.take_period()[1]
    assert totals['untracked'] == 1 and totals['bad_value'] == 2 and totals['bad_executed'] == 2
    assert core.tick().scene is None  # nobody with a pose: nothing to rank


def test_scenes_are_sent_at_the_rate_and_on_change(world):
    core, poses, clock = world
    core.on_tracked(['a'])
    person(core, 'a', level=DISENGAGED)
    place(poses, clock, 'a', 1.0, 0.0)
    assert core.tick().scene is not None
    clock.advance(0.1)
    place(poses, clock, 'a', 1.0, 0.0)
    assert core.tick().scene is None  # 2 Hz: not due, nothing changed
    core.on_person('engagement_status', 'a', ENGAGED)
    out = core.tick()
    assert out.scene is not None and out.user_id == 'a'  # the served person changed
    clock.advance(0.5)
    place(poses, clock, 'a', 1.0, 0.0)
    out = core.tick()
    assert out.scene is not None and out.user_id is None  # due; user unchanged


def ranking(candidate_or_action, p_best=None, scene_id='hri-1'):
    key = 'candidate' if candidate_or_action in ('stay', 'left_50cm', 'ahead_50cm') else 'action'
    reply = {'scene_id': scene_id, 'user_id': 'a', 'ranking': [{key: candidate_or_action, 'score': 0.7, 'rank': 1,
                                                                 'score_sd': 0.1}]}
    if p_best is not None:
        reply['p_first_is_best'] = p_best
    return reply


def test_decisions_goal_and_abstain_rule():
    robot = Pose(10.0, 5.0, math.pi / 2, 0)
    decision = decide(ranking('ahead_50cm', 0.9), 0.5, robot)
    assert not decision.abstain and decision.goal.x == pytest.approx(10.0) and decision.goal.y == pytest.approx(5.5)
    assert placement_offset('left_50cm') == pytest.approx((0.0, 0.5))
    assert decide(ranking('stay', 0.3), 0.5, robot).abstain
    assert decide(ranking('stay', 0.3), 0.5, robot).goal is None
    assert decide(ranking('stay'), 0.5, None).abstain  # no robot pose in the navigation frame
    action = decide(ranking('navigate'), 0.5, None)
    assert not action.abstain and action.to_json()['action'] == 'navigate' and action.score_sd == 0.1
    assert compose(Pose(1, 0, 0, 0), Pose(1, 0, 0, 0)).x == 2


def test_implicit_outcomes_stay_disengage_and_never_for_anonymous(world):
    core, poses, clock = world
    core.on_tracked(['a', 'b', 'anon'])
    person(core, 'a')
    person(core, 'b')
    person(core, 'anon', anonymous=True)
    for pid in ('a', 'b', 'anon'):
        core.on_executed(json.dumps({'scene_id': 's', 'candidate': 'stay', 'person_id': pid}))
    clock.advance(1.0)
    core.on_person('engagement_status', 'b', DISENGAGED)
    out = core.tick()
    assert out.feedback == ({'user_id': 'b', 'scene_id': 's', 'candidate': 'stay', 'score': 0.0, 'implicit': True},)
    clock.advance(2.5)
    out = core.tick()
    assert out.feedback == ({'user_id': 'a', 'scene_id': 's', 'candidate': 'stay', 'score': 1.0, 'implicit': True},)
    assert core.outcomes.dropped_anonymous == 1 and 'anonymous_dropped' in core.problems.take_period()[1]


def test_an_outcome_follows_an_alias_and_leaving_is_disengaging(world):
    core, poses, clock = world
    core.on_tracked(['tmp', 'bob'])
    person(core, 'tmp', anonymous=True)
    core.on_person('anonymous', 'bob', False)
    core.on_executed(json.dumps({'scene_id': 's', 'action': 'navigate', 'person_id': 'tmp'}))
    core.on_person('alias', 'tmp', 'bob')
    core.tick()
    core.on_tracked(['bob'])  # 'tmp' merged away, then bob walks off
    core.on_tracked([])
    assert core.tick().feedback[0] == {'user_id': 'bob', 'scene_id': 's', 'action': 'navigate', 'score': 0.0,
                                       'implicit': True}


def test_person_feedback_relay_drops_anonymous(world):
    core, poses, clock = world
    core.on_tracked(['anon', 'carol'])
    person(core, 'anon', anonymous=True)
    person(core, 'carol')
    message = {'scene_id': 's', 'action': 'navigate', 'score': 0.8}
    assert core.on_person_feedback(json.dumps({**message, 'person_id': 'anon'})) is None
    assert core.on_person_feedback(json.dumps({**message, 'person_id': 'carol'})) == {**message, 'user_id': 'carol'}
    assert core.problems.take_period()[1]['anonymous_dropped'] == 1


def test_latched_facts_of_an_untracked_id_hold_once_it_is_tracked():
    people = People(Clock())
    people.set_anonymous('later', False)  # a person manager latches it for people it knows
    people.set_alias('merged', 'later')
    with pytest.raises(ValueError, match='not in /humans/persons/tracked'):
        people.set_engagement('later', ENGAGED)
    people.set_tracked(['later', 'merged'])
    people.set_engagement('merged', ENGAGED)
    assert people.served(lambda _: 1.0).user_id == 'later'
    people.set_tracked([])
    people.set_tracked(['later'])  # back again: still recognised, engagement starts afresh
    assert not people.is_anonymous('later') and people.level('later') == 0


def consented_world(tmp_path, listed=('a',)):
    """A bridge with store_policy consented, ``listed`` in its consent_file; a, b and c
    recognised and engaged."""
    clock, poses = Clock(), TransformTable()
    consent_file = tmp_path / 'consent.txt'
    consent_file.write_text('# agreed on the tablet\n' + ''.join(f'{pid}\n' for pid in listed))
    core = BridgeCore(BridgeSettings(outcome_window=3.0, store_policy='consented', consent_file=str(consent_file)),
                      poses, clock)
    core.on_tracked(['a', 'b', 'c'])
    for pid in 'abc':
        person(core, pid)
    return core, clock


def executed(core, person_id, scene_id='s'):
    core.on_executed(json.dumps({'scene_id': scene_id, 'candidate': 'stay', 'person_id': person_id}))


def test_consented_relays_only_people_on_the_list_and_never_names_the_others(tmp_path):
    core, clock = consented_world(tmp_path)  # the consent_file's 'a' only
    message = {'scene_id': 's', 'action': 'navigate', 'score': 0.8}
    assert core.on_person_feedback(json.dumps({**message, 'person_id': 'a'})) == {**message, 'user_id': 'a'}
    assert core.on_person_feedback(json.dumps({**message, 'person_id': 'b'})) is None
    executed(core, 'a')
    executed(core, 'b')  # not watched: nothing of b is kept for the ranker
    assert [item.person_id for item in core.outcomes.waiting] == ['a']
    clock.advance(3.0)
    assert [f['user_id'] for f in core.tick().feedback] == ['a']
    period, totals = core.problems.take_period()
    assert totals['consent'] == 2 and core.outcomes.dropped_unconsented == 1 and 'anonymous_dropped' not in totals
    assert "'b'" not in period['consent'][1] and 'b' not in period['consent'][1].split()
    core.on_tracked(['a'])  # b leaves: a report of his rating or action still does not name him
    assert core.on_person_feedback(json.dumps({**message, 'person_id': 'b'})) is None
    executed(core, 'b')
    period, _ = core.problems.take_period()
    assert {'anonymous_dropped', 'untracked'} <= set(period)
    assert not any("'b'" in detail for _, detail in period.values()), period


def test_the_served_persons_answers_are_kept_only_when_recognised_and_on_the_list(tmp_path):
    """What stars/served_person's ``kept`` says to the feedback page: the bridge would relay
    what the served person says."""
    core, _ = consented_world(tmp_path)  # the consent_file's 'a' only
    for served, kept in ((Served(), False), (Served('a'), True), (Served('b'), False), (Served('a', True), False)):
        core.served = served
        assert core.served_kept() is kept, served
    core.on_consent(json.dumps({'consented': ['b']}))
    core.served = Served('b')
    assert core.served_kept()
    everyone = BridgeCore(BridgeSettings(), TransformTable(), Clock())
    everyone.served = Served('b')
    assert everyone.served_kept()


def test_a_later_consent_message_replaces_the_topics_list_and_drops_what_waits(tmp_path):
    core, clock = consented_world(tmp_path)
    message = {'scene_id': 's', 'action': 'navigate', 'score': 0.8}
    assert core.on_consent(json.dumps({'consented': ['b', 'c']})) == 2
    assert core.on_person_feedback(json.dumps({**message, 'person_id': 'b'})) == {**message, 'user_id': 'b'}
    executed(core, 'b')
    executed(core, 'c')
    assert core.on_consent(json.dumps({'consented': ['c']})) == 1  # b taken off: b's waiting outcome goes now
    assert [item.person_id for item in core.outcomes.waiting] == ['c']
    assert core.on_person_feedback(json.dumps({**message, 'person_id': 'b'})) is None
    assert core.on_person_feedback(json.dumps({**message, 'person_id': 'a'})) is not None  # the file's list holds
    assert core.on_consent('{"consented": "c"}') is None  # refused: the list stays as it was
    assert core.consent.allows('c') and 'schema' in core.problems.take_period()[1]
    clock.advance(3.0)
    assert [f['user_id'] for f in core.tick().feedback] == ['c']
    assert core.outcomes.dropped_unconsented == 1


def test_an_outcome_is_checked_again_when_known_so_an_alias_to_someone_not_listed_drops_it(tmp_path):
    """An anonymous id is watched (an alias may make it a person on the list); once it turns
    out to be someone not on the list, the outcome is dropped."""
    core, clock = consented_world(tmp_path)
    core.on_tracked(['a', 'b', 'c', 'tmp'])
    person(core, 'tmp', anonymous=True)
    executed(core, 'tmp')  # anonymous now: watched, as an alias may make it a person on the list
    core.on_person('alias', 'tmp', 'b')
    clock.advance(3.0)
    assert core.tick().feedback == ()
    assert core.outcomes.dropped_unconsented == 1 and core.outcomes.dropped_anonymous == 0


def test_store_policy_all_relays_everyone_as_before(world, tmp_path):
    core, poses, clock = world
    assert not core.consent.restricted
    core.on_tracked(['a', 'b'])
    person(core, 'a')
    person(core, 'b')
    assert core.on_consent(json.dumps({'consented': ['a']})) == 1  # a list changes nothing under 'all'
    message = {'scene_id': 's', 'action': 'navigate', 'score': 0.8}
    assert core.on_person_feedback(json.dumps({**message, 'person_id': 'b'})) == {**message, 'user_id': 'b'}
    executed(core, 'b')
    clock.advance(3.0)
    assert core.tick().feedback == ({'user_id': 'b', 'scene_id': 's', 'candidate': 'stay', 'score': 1.0,
                                     'implicit': True},)
    assert 'consent' not in core.problems.take_period()[1]
    unread = BridgeCore(BridgeSettings(consent_file=str(tmp_path / 'absent')), poses, clock)  # not read under 'all'
    assert unread.consent.allows('anyone')


def test_scenes_of_a_person_not_on_the_list_still_go_out_under_their_id(tmp_path):
    """The ranker ranks them as a stranger and keeps nothing of them (docs/privacy.md)."""
    core, clock = consented_world(tmp_path, listed=())
    core.on_tracked(['b'])
    core.poses.put('base_link', 'person_b', Pose(1.0, 0.0, 0.0, clock()))
    out = core.tick()
    assert out.user_id == 'b' and out.scene['user_id'] == 'b'


def test_a_bad_store_policy_or_consent_file_stops_the_bridge(tmp_path):
    with pytest.raises(ConfigError, match="store_policy is 'some'"):
        BridgeCore(BridgeSettings(store_policy='some'), TransformTable(), Clock())
    with pytest.raises(ConfigError, match='consent_file .*absent'):
        BridgeCore(BridgeSettings(store_policy='consented', consent_file=str(tmp_path / 'absent')), TransformTable(),
                   Clock())
