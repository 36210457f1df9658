"""The feedback page's logic without ROS or HTTP (``stars_ros.hri.feedback_page``): whom it
asks, what an answer sends (signed server-side when a key is set, through the bridge or not),
the refusals (stale, off the scale, malformed, flood, token), and the node's start checks."""
import json

import pytest

from stars_ros import feedback_auth
from stars_ros.errors import ConfigError
from stars_ros.hri.feedback_page import ANONYMOUS_ASKER, FeedbackPage, PageSettings, Refusal
from stars_ros.ros.feedback_page import read_token

SECRET = bytes(range(32))
SCENE = {'scene_id': 's1', 'graph': {'humans': [{'id': 1, 'xPos': 0, 'yPos': 150, 'orientation': 0}], 'objects': [],
                                     'links': [], 'room': [[-300, 300], [300, 300], [300, -300], [-300, -300]]}}


def question(user_id: str, scene_id: str = 's1') -> str:
    return json.dumps({'user_id': user_id, 'scene_id': scene_id, 'action': 'navigate',
                       'expected_variance_reduction': 0.01, 'score': 0.5, 'score_sd': 0.1, 'candidates': 1,
                       'targets': 1, 'fingerprint': '0' * 64})


class Clock:
    def __init__(self):
        self.ns = 10 ** 18

    def __call__(self):
        return self.ns


def test_an_answer_goes_to_the_ranker_as_the_served_users_feedback_and_the_next_ranking_is_shown():
    page = FeedbackPage(PageSettings(via_bridge=False), Clock())
    assert page.on_user_id('pat') == [('stars/question_request', '{"user_id":"pat"}')]
    page.on_scene(json.dumps(SCENE))
    page.on_question(question('someone-else'))
    assert page.view()['phase'] == 'waiting'
    page.on_question(question('pat'))
    view = page.view()
    assert view['question'] == {'number': 1, 'words': 'move through the room', 'has_picture': True}
    assert view['scale'] == [0.0, 0.25, 0.5, 0.75, 1.0] and not view['anonymous']
    out = page.answer({'question': 1, 'score': 0.75})
    assert out == [('stars/feedback', '{"user_id":"pat","scene_id":"s1","score":0.75,"action":"navigate"}'),
                   ('stars/question_request', '{"user_id":"pat"}')]
    page.on_question(question('pat'))  # the next question waits behind the thanks
    assert page.view()['phase'] == 'thanks' and page.view()['pending']
    page.on_ranking(json.dumps({'scene_id': 'x', 'user_id': 'pat', 'ranking': [
        {'candidate': 'left_50cm', 'score': 0.8, 'score_sd': 0.05, 'rank': 1}]}))
    assert page.view()['outcome'] == {'words': 'move 50 cm to its left', 'score': 0.8, 'score_sd': 0.05}
    assert page.next() == [] and page.view()['question']['number'] == 2


NO_QUESTION = json.dumps({'kind': 'no_question', 'message': 'no scene to ask about', 'level': 'warning',
                          'topic': '/stars/question_request', 'scene_id': None})
REQUEST = ('stars/question_request', '{"user_id":"pat"}')


def _ranking(user_id):
    return json.dumps({'scene_id': 'x', 'user_id': user_id,
                       'ranking': [{'action': 'navigate', 'score': 0.5}]})


def test_a_question_not_chosen_yet_is_asked_for_again_at_the_persons_next_ranking_and_said_so_meanwhile():
    page = FeedbackPage(PageSettings(via_bridge=False), Clock())
    assert page.on_user_id('pat') == [REQUEST]
    assert page.on_ranking(_ranking('pat')) == []  # a request is out: not asked twice
    page.on_error(json.dumps({'kind': 'overload', 'message': 'full', 'level': 'error'}))
    assert not page.view()['no_question']
    version = page.version
    page.on_error(NO_QUESTION)
    assert page.view()['no_question'] and page.view()['phase'] == 'waiting' and page.version > version
    assert page.on_ranking(_ranking('someone-else')) == []
    assert page.on_ranking(_ranking('pat')) == [REQUEST]
    assert page.on_ranking(_ranking('pat')) == []  # asked again once per no_question
    page.on_error(NO_QUESTION)
    assert page.on_ranking(_ranking('pat')) == [REQUEST]
    page.on_question(question('pat'))
    assert not page.view()['no_question'] and page.view()['phase'] == 'question'
    page.on_error(NO_QUESTION)  # none out: another page's
    assert not page.view()['no_question'] and page.on_ranking(_ranking('pat')) == []


def test_a_request_a_ranker_may_not_have_had_is_sent_again():
    """The page started while someone is served asked before the ranker's endpoints matched;
    two of the person's rankings overtook a request unanswered."""
    page = FeedbackPage(PageSettings(via_bridge=False), Clock())
    assert page.on_ranker_joined() == []  # nobody served
    assert page.on_user_id('pat') == [REQUEST]
    assert page.on_ranker_joined() == [REQUEST]
    page.on_question(question('pat'))
    assert page.on_ranker_joined() == []  # a question is shown
    assert page.on_user_id('kim') == [('stars/question_request', '{"user_id":"kim"}')]
    assert page.on_ranking(_ranking('kim')) == []  # the answer may be on its way
    assert page.on_ranking(_ranking('kim')) == [('stars/question_request', '{"user_id":"kim"}')]  # lost


def test_through_the_bridge_an_anonymous_person_is_asked_under_no_id_and_told_it_is_not_kept():
    page = FeedbackPage(PageSettings(signing_key=('tablet', SECRET)), Clock())
    out = page.on_served_person('{"person_id": "p7", "anonymous": true}')
    assert out == [('stars/question_request', json.dumps({'user_id': ANONYMOUS_ASKER}, separators=(',', ':')))]
    page.on_question(question(ANONYMOUS_ASKER))
    assert page.view()['anonymous']
    [(topic, payload), _] = page.answer({'question': 1, 'score': 0.25})
    assert topic == 'stars/person_feedback'
    assert json.loads(payload) == {'person_id': 'p7', 'scene_id': 's1', 'score': 0.25, 'action': 'navigate'}


def test_a_person_whose_answers_the_bridge_drops_is_told_why():
    """stars/served_person's ``kept``: false for someone not on the consent list (a recognised
    person, asked under their id); absent, as from an older bridge: kept unless anonymous."""
    page = FeedbackPage(PageSettings(), Clock())
    assert page.on_served_person('{"person_id": "bo", "anonymous": false, "kept": false}') == [
        ('stars/question_request', json.dumps({'user_id': 'bo'}, separators=(',', ':')))]
    assert page.view()['not_kept'] == 'consent' and not page.view()['anonymous']
    version = page.version
    assert page.on_served_person('{"person_id": "bo", "anonymous": false, "kept": true}') == []  # the same person
    assert page.view()['not_kept'] is None and page.version > version  # the page shows the change
    page.on_served_person('{"person_id": "p7", "anonymous": true, "kept": false}')
    assert page.view()['not_kept'] == 'anonymous'
    page.on_served_person('{"person_id": "ann", "anonymous": false}')
    assert page.view()['not_kept'] is None
    page.on_served_person('{"person_id": "p8", "anonymous": true}')
    assert page.view()['not_kept'] == 'anonymous'


def test_a_recognised_persons_answer_is_signed_here_and_verifies_once_the_bridge_relays_it():
    clock = Clock()
    page = FeedbackPage(PageSettings(signing_key=('tablet', SECRET)), clock)
    page.on_served_person('{"person_id": "ann", "anonymous": false}')
    page.on_question(question('ann'))
    assert SECRET.hex() not in json.dumps(page.view())  # the page never sees a key
    [(_, payload), _] = page.answer({'question': 1, 'score': 1})
    relayed = json.loads(payload)
    relayed['user_id'] = relayed.pop('person_id')  # what the bridge does (hri.bridge.on_person_feedback)
    checker = feedback_auth.FeedbackAuthenticator({'tablet': SECRET}, lambda: 60.0)
    assert checker.check(relayed, clock()) is None


@pytest.mark.parametrize('body, kind', [
    ({'question': 2, 'score': 0.5}, 'stale'), ({'question': 1, 'score': 1.5}, 'out_of_scale'),
    ({'question': 1, 'score': float('nan')}, 'out_of_scale'), ({'question': 1, 'score': 10 ** 400}, 'out_of_scale'),
    ({'question': 1, 'score': '0.5'}, 'schema'), ({'question': True, 'score': 0.5}, 'schema'),
    ({'question': 1, 'score': 0.5, 'user_id': 'mallory'}, 'schema'), ([1, 0.5], 'schema')])
def test_bad_answers_are_refused_naming_why_and_send_nothing(body, kind):
    page = FeedbackPage(PageSettings(via_bridge=False), Clock())
    page.on_user_id('pat')
    page.on_question(question('pat'))
    with pytest.raises(Refusal) as refused:
        page.answer(body)
    assert refused.value.kind == kind and page.view()['phase'] == 'question'


def test_a_flood_is_refused_until_the_bucket_refills_and_skip_sends_no_feedback():
    clock = Clock()
    page = FeedbackPage(PageSettings(via_bridge=False, posts_per_second=2.0, burst=3), clock)
    page.on_user_id('pat')
    for _ in range(3):
        with pytest.raises(Refusal, match='no longer asked'):
            page.skip({'question': 9})
    with pytest.raises(Refusal) as refused:
        page.skip({'question': 9})
    assert refused.value.kind == 'flood' and refused.value.status == 429
    clock.ns += 500_000_000  # one tap back
    page.on_question(question('pat'))
    assert page.skip({'question': 1}) == [('stars/question_request', '{"user_id":"pat"}')]


def test_the_token_is_checked_in_constant_time_and_required_off_loopback(tmp_path):
    page = FeedbackPage(PageSettings(token='t' * 20), Clock())
    page.check_token('t' * 20)
    for wrong in (None, '', 't' * 19):
        with pytest.raises(Refusal, match='wrong or missing page token'):
            page.check_token(wrong)
    assert read_token('', '127.0.0.1') == '' and read_token('', '::1') == ''
    with pytest.raises(ConfigError, match="host '0.0.0.0' is not loopback: serving there needs a token_file"):
        read_token('', '0.0.0.0')
    (tmp_path / 'short').write_text('abc\n')
    with pytest.raises(ConfigError, match='fewer than 16'):
        read_token(str(tmp_path / 'short'), '0.0.0.0')


def test_the_question_picture_is_the_packages_scene_drawing():
    from stars_ros.data.scene_source import placement_candidates
    from stars_ros.figures.scene import question_png
    stay, left = (c['graph'] for c in placement_candidates(SCENE['graph'], 2))
    for picture in (question_png(SCENE['graph']), question_png(stay, left)):
        assert picture.startswith(b'\x89PNG\r\n\x1a\n') and len(picture) > 5000
