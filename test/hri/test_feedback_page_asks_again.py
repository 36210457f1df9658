"""The feedback page in real Chromium against a fresh ranker each (one that has seen no scene):
a person served before the ranker's first scene is told it has nothing to ask about yet, and
gets their rating buttons once their first scene is ranked; a page started while someone is
already served shows them their question. The conditions are waited for; how long the buttons
took is printed (``-s``), not asserted."""
import re
import signal
import time

import pytest
from std_msgs.msg import String

from ros_helpers import RosClient, domain_id, start_node, stop
from waiting import wait_for
from stars_ros.data.scene_source import scene_request
from test_feedback_page_browser import _chromium

pytestmark = [pytest.mark.slow, pytest.mark.filterwarnings('ignore::DeprecationWarning:lark.*')]
START_TIMEOUT = 90
ADDRESS = re.compile(r'serving the page at (http://\S+)')
TOPICS_OUT = ('ranking', 'question', 'errors')  # the ranker's, found once it is up
NO_SCENE_YET = 'The robot has not seen anything to ask you about yet: it will ask you once it has.'


class Graph:
    """A client on the test's domain and, once ``start_ranker`` is called, a ranker that has
    answered nothing and seen no scene (ready once its stars/scene subscription and
    stars/ranking, stars/question and stars/errors publishers are found)."""

    def __init__(self, checkpoint, folder):
        self.client, self.checkpoint, self.folder = RosClient(domain_id(9)), checkpoint, folder
        self.processes = []

    def start(self, module: str, params: dict, log_name: str):
        process = start_node(module, domain_id(9), params, self.folder / log_name)
        self.processes.append(process)
        return process

    def start_ranker(self):
        process = self.start('stars_ros.ros.ranker',
                             {'checkpoint': self.checkpoint, 'record_folder': self.folder}, 'ranker.log')

        def found():
            assert process.poll() is None, (self.folder / 'ranker.log').read_text()
            return self.client.scene_pub.get_subscription_count() and all(
                self.client.node.count_publishers(f'/stars/{topic}') for topic in TOPICS_OUT)
        assert self.client.wait(found, START_TIMEOUT), 'the ranker did not come up'

    def start_page(self):
        """The page as its own process, as ``ros2 run`` starts it: its address."""
        self.start('stars_ros.ros.feedback_page', {'port': 0, 'feedback_via': 'ranker'}, 'page.log')
        log = self.folder / 'page.log'
        assert wait_for(lambda: ADDRESS.search(log.read_text()) or self.processes[-1].poll() is not None,
                        START_TIMEOUT)
        assert self.processes[-1].poll() is None, log.read_text()
        return ADDRESS.search(log.read_text()).group(1)

    def close(self):
        """Each process must still run, and stop cleanly on SIGINT."""
        try:
            for process in self.processes:
                assert process.poll() is None, 'a node died during the test'
                assert stop(process, signal.SIGINT) == 0
        finally:
            for process in self.processes:
                if process.poll() is None:
                    process.kill()
            self.client.close()


@pytest.fixture
def graph(tiny_checkpoint, tmp_path):
    """The test's own ranker and page (on domain 9, after test_feedback_page_browser's, in turn)."""
    made = Graph(tiny_checkpoint, tmp_path)
    yield made
    made.close()


@pytest.fixture
def browser():
    sync_playwright, expect = _chromium()
    from test_feedback_page_browser import CHROMIUM, CHROMIUM_ARGS
    with sync_playwright() as playwright:
        launched = playwright.chromium.launch(executable_path=CHROMIUM, args=CHROMIUM_ARGS)
        yield launched, expect
        launched.close()


def _buttons_after_ranking(graph, expect, page, scene, user_id: str, what: str):
    """Rank ``scene`` for ``user_id``; the rating buttons then appear (how long after: printed)."""
    client = graph.client
    client.scene(scene_request(f'{user_id}-first', scene, user_id))
    assert client.wait(lambda: client.ranking_for(f'{user_id}-first') is not None, 30), 'no ranking came back'
    ranked = time.monotonic()
    expect(page.get_by_role('button', name='very good, rating 1')).to_be_visible(timeout=30_000)
    waited = time.monotonic() - ranked
    print(f'{what}: rating buttons {waited:.3f} s after the first ranking reached the test')


def test_a_person_served_before_the_first_scene_is_asked_once_their_scene_is_ranked(graph, browser,
                                                                                     synthetic_scenes):
    (chromium, expect), client = browser, graph.client
    graph.start_ranker()
    page = chromium.new_page()
    page.goto(graph.start_page())
    client.user_pub.publish(String(data='una'))
    assert client.wait(lambda: any(e['kind'] == 'no_question' for e in client.errors), 30), \
        'the ranker had a question before any scene'
    expect(page.locator('#waiting-title')).to_have_text(NO_SCENE_YET, timeout=30_000)
    _buttons_after_ranking(graph, expect, page, synthetic_scenes[0], 'una', 'served before the first scene')
    page.close()


def test_a_page_started_while_someone_is_served_shows_their_question(graph, browser, synthetic_scenes):
    (chromium, expect), client = browser, graph.client
    graph.start_ranker()
    client.scene(scene_request('seen', synthetic_scenes[1]))  # a scene to ask about
    assert client.wait(lambda: client.ranking_for('seen') is not None, 30), 'no ranking came back'
    client.user_pub.publish(String(data='vic'))  # latched: the page hears it as it starts
    started = time.monotonic()
    page = chromium.new_page()
    page.goto(graph.start_page())
    expect(page.get_by_role('button', name='very good, rating 1')).to_be_visible(timeout=30_000)
    waited = time.monotonic() - started
    print(f'page started while served: rating buttons {waited:.3f} s after its process started')
    page.close()


def test_a_page_started_while_someone_is_served_before_the_ranker_asks_once_the_ranker_is_up(
        graph, browser, synthetic_scenes):
    """Its first request goes out to no ranker: it is sent again when the ranker's endpoints join."""
    (chromium, expect), client = browser, graph.client
    client.user_pub.publish(String(data='wes'))
    page = chromium.new_page()
    page.goto(graph.start_page())
    expect(page.locator('#waiting-title')).to_have_text('Thinking of a question for you…', timeout=30_000)
    graph.start_ranker()
    expect(page.locator('#waiting-title')).to_have_text(NO_SCENE_YET, timeout=30_000)
    _buttons_after_ranking(graph, expect, page, synthetic_scenes[2], 'wes', 'page before the ranker')
    page.close()
