"""The feedback page in real Chromium (Debian's, driven by playwright; never `playwright
install`) against a real ranker on loopback: the question appears within 1 s of the ranker
choosing it, a tap sends feedback that moves the person's next ranking, "skip" sends nothing,
an anonymous person (through the real bridge) is told their answer will not be kept and it
is not stored, and a wrong token is refused on the page and on stars/errors.

Two pages run in this process on the ranker's domain: ``direct`` answers on stars/feedback for
stars/user_id, ``bridged`` on stars/person_feedback through an in-process hri_bridge whose
stars/user_id is remapped away, so the two do not serve the same user id. Set
STARS_PAGE_SCREENSHOT=docs/feedback_page.png to keep a screenshot of the question."""
import json
import os
from pathlib import Path

import pytest
from rclpy.parameter import Parameter
from rclpy.qos import QoSProfile, ReliabilityPolicy
from std_msgs.msg import String

from hri_fixtures import hri_msgs  # noqa: F401 - the fixture
from ros_helpers import RELIABLE, domain_id, running_ranker, stored_feedback
from waiting import wait_for
from stars_ros.data.scene_source import scene_request
from stars_ros.hri.people import ENGAGED

pytestmark = pytest.mark.filterwarnings('ignore::DeprecationWarning:lark.*')
CHROMIUM = '/usr/bin/chromium'
CHROMIUM_ARGS = ['--headless', '--no-sandbox', '--disable-gpu', '--disable-quic', '--no-first-run',
                 '--disable-background-networking', '--disable-component-update', '--disable-sync']
QUESTIONS = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE)
TOKEN = 'page-token-0123456789abcdef'
APPEARS_WITHIN_MS = 1000  # the requirement: the question shows within 1 s of being chosen


def _chromium():
    """playwright's sync API and Debian's chromium, or a skip saying which is missing."""
    if not os.access(CHROMIUM, os.X_OK):
        pytest.skip(f'{CHROMIUM} is missing (Debian package chromium; scripts/setup_venv.sh installs it as root)')
    try:
        from playwright.sync_api import expect, sync_playwright
    except ImportError as missing:
        pytest.skip(f'playwright is not installed (requirements-dev.txt): {missing}')
    return sync_playwright, expect


@pytest.fixture(scope='module')
def rig(tiny_checkpoint, synthetic_scenes, tmp_path_factory, hri_msgs):  # noqa: F811 - the fixture
    """A ranker (process), the two pages, the bridge and a scripted anonymous visitor (this
    process), and Chromium."""
    sync_playwright, expect = _chromium()
    from stars_ros.ros.feedback_page import FeedbackPageNode
    from stars_ros.ros.hri_bridge import HriBridge
    from stars_ros.ros.hri_world import World
    folder = tmp_path_factory.mktemp('page')
    (folder / 'token').write_text(TOKEN)
    records = folder / 'records'
    with running_ranker(domain_id(9), {'checkpoint': tiny_checkpoint, 'record_folder': records},
                        folder / 'ranker.log', scene_request('probe', synthetic_scenes[0])) as (process, client):
        node = client.node
        nodes = {
            'direct': FeedbackPageNode(context=client.context, parameter_overrides=[
                Parameter('port', value=0), Parameter('feedback_via', value='ranker'),
                Parameter('token_file', value=str(folder / 'token'))]),
            'bridged': FeedbackPageNode(context=client.context, parameter_overrides=[Parameter('port', value=0)],
                                        cli_args=['--ros-args', '-r', '__node:=feedback_page_bridged']),
            'bridge': HriBridge(context=client.context, parameter_overrides=[
                Parameter('pose_source', value='topic'), Parameter('rate', value=4.0)],
                cli_args=['--ros-args', '-r', 'stars/user_id:=bridge/user_id']),
        }
        for page_node in nodes.values():
            client.executor.add_node(page_node)
        world = World(node, 'base_link')
        world.track(['visitor'])
        world.anonymous('visitor', True)
        world.pose('visitor', 1.2, 0.3, 3.0, static=True)
        node.create_timer(0.2, lambda: world.engage('visitor', ENGAGED))
        taps = {'feedback': client.collect('/stars/feedback', RELIABLE),
                'person_feedback': client.collect('/stars/person_feedback', RELIABLE),
                'questions': client.collect('/stars/question', QUESTIONS),
                'requests': client.collect('/stars/question_request', QUESTIONS),
                'diagnostics': client.diagnostics}
        try:
            with sync_playwright() as playwright:
                browser = playwright.chromium.launch(executable_path=CHROMIUM, args=CHROMIUM_ARGS)
                yield {'client': client, 'process': process, 'nodes': nodes, 'taps': taps, 'browser': browser,
                       'expect': expect, 'records': records, 'scenes': synthetic_scenes}
                browser.close()
        finally:
            for page_node in nodes.values():
                client.executor.remove_node(page_node)
                page_node.destroy_node()
            nodes['direct'].close()
            nodes['bridged'].close()


def _open(rig, which: str, token: str | None = TOKEN):
    page = rig['browser'].new_page(viewport={'width': 800, 'height': 1000})
    address = rig['nodes'][which].address
    page.goto(address + (f'?token={token}' if token and which == 'direct' else ''))
    return page


def _question_for(rig, user_id: str, start: int):
    client, questions = rig['client'], rig['taps']['questions']
    assert client.wait(lambda: any(q['user_id'] == user_id for q in questions[start:]), 30), \
        f'no question for {user_id}'
    return next(q for q in questions[start:] if q['user_id'] == user_id)


def test_the_question_appears_within_1_s_and_a_tap_moves_the_next_ranking(rig):
    client, expect, taps = rig['client'], rig['expect'], rig['taps']
    scene = rig['scenes'][5]
    client.scene(scene_request('pat-before', scene, 'pat'))
    assert client.wait(lambda: client.ranking_for('pat-before') is not None, 30)
    before = client.ranking_for('pat-before')['ranking'][0]['score']
    page = _open(rig, 'direct')
    expect(page.locator('#connection')).to_have_text('Connected to the robot.', timeout=10_000)
    start = len(taps['questions'])
    client.user_pub.publish(String(data='pat'))
    question = _question_for(rig, 'pat', start)
    # chosen: the ranker has published it; the page must show it within 1 s
    expect(page.locator('#question-title')).to_be_visible(timeout=APPEARS_WITHIN_MS)
    expect(page.locator('#anonymous-note')).to_be_hidden()
    if os.environ.get('STARS_PAGE_SCREENSHOT'):
        if page.locator('#scene').is_visible():
            expect(page.locator('#scene')).to_have_js_property('complete', True)
        page.screenshot(path=os.environ['STARS_PAGE_SCREENSHOT'], full_page=True)
    page.get_by_role('button', name='very good, rating 1').click()
    assert client.wait(lambda: any(f['user_id'] == 'pat' for f in taps['feedback']), 10), 'the tap sent nothing'
    sent = next(f for f in taps['feedback'] if f['user_id'] == 'pat')
    assert (sent['scene_id'], sent['score']) == (question['scene_id'], 1.0)
    assert sent.get('action', sent.get('candidate')) == question.get('candidate', question['action'])
    expect(page.locator('#thanks-title')).to_be_focused()

    asked = []

    def personalised():  # the solve runs once no scene waits: ask again until it is served
        asked.append(scene_id := f'pat-after-{len(asked)}')
        client.scene(scene_request(scene_id, scene, 'pat'))
        assert client.wait(lambda: client.ranking_for(scene_id), 30), 'no ranking came back'
        return client.ranking_for(scene_id).get('personalised_from') == 1
    assert wait_for(personalised, 30), 'the answer was not folded in'
    assert client.ranking_for(asked[-1])['ranking'][0]['score'] != before
    expect(page.locator('#outcome')).to_contain_text('The robot will now')
    page.close()


def test_skip_by_keyboard_sends_nothing_and_asks_again(rig):
    client, expect, taps = rig['client'], rig['expect'], rig['taps']
    page = _open(rig, 'direct')
    start = len(taps['questions'])
    client.user_pub.publish(String(data='sam'))
    _question_for(rig, 'sam', start)
    expect(page.locator('#question-title')).to_be_visible(timeout=10_000)
    asked = len([r for r in taps['requests'] if r['user_id'] == 'sam'])
    expect(page.locator('#question-title')).to_be_focused()  # read out first; Tab goes on to the ratings
    page.keyboard.press('Tab')
    expect(page.get_by_role('button', name='very bad, rating 0')).to_be_focused()
    for _ in range(5):
        page.keyboard.press('Tab')
    expect(page.get_by_role('button', name='Skip this question')).to_be_focused()
    page.keyboard.press('Enter')  # skipped by keyboard
    assert client.wait(lambda: len([r for r in taps['requests'] if r['user_id'] == 'sam']) > asked, 10), \
        'skip did not ask for the next question'
    _question_for(rig, 'sam', start + 1)
    expect(page.locator('#question-title')).to_be_visible(timeout=10_000)
    assert not [f for f in client.snapshot(taps['feedback']) if f['user_id'] == 'sam']
    page.close()


def test_an_anonymous_persons_answer_is_not_kept(rig):
    """Through the bridge: the page says so, the answer goes to the bridge, which drops it
    (its anonymous_dropped count), and neither stars/feedback nor the ranker's store has it."""
    client, expect, taps = rig['client'], rig['expect'], rig['taps']
    page = _open(rig, 'bridged')
    expect(page.locator('#question-title')).to_be_visible(timeout=30_000)
    expect(page.locator('#anonymous-note')).to_have_text(
        'The robot does not know who you are: your answer will not be kept.')
    page.get_by_role('button', name='bad, rating 0.25').click()
    assert client.wait(lambda: any(f['person_id'] == 'visitor' for f in taps['person_feedback']), 10)
    expect(page.locator('#kept-note')).to_have_text(
        'Your answer will not be kept: the robot does not know who you are.')

    def dropped():
        return any(kv.key == 'problems.anonymous_dropped' and int(kv.value) >= 1
                   for array in taps['diagnostics'] for status in array.status if status.name.endswith('hri_bridge')
                   for kv in status.values)
    assert client.wait(dropped, 10), 'the bridge did not drop the answer'
    assert not [f for f in client.snapshot(taps['feedback']) if f['user_id'] == 'visitor']
    bags = list(Path(rig['records']).rglob('*.mcap'))
    assert bags and not [f for bag in bags for f in stored_feedback(bag) if f['user_id'] == 'visitor']
    page.close()


def test_a_wrong_token_is_refused_on_the_page_and_on_stars_errors(rig):
    client, expect = rig['client'], rig['expect']
    page = _open(rig, 'direct', token='not-the-token')
    expect(page.get_by_role('alert')).to_have_text('Refused: token')
    refused = page.request.post(rig['nodes']['direct'].address + 'answer?token=nope',
                                data=json.dumps({'question': 1, 'score': 0.5}),
                                headers={'Content-Type': 'application/json'})
    assert refused.status == 403 and refused.json()['error'] == 'token'
    assert client.wait(lambda: any(e['kind'] == 'token' and e['topic'].startswith('http ') for e in client.errors), 10)
    assert rig['process'].poll() is None
    page.close()
