"""The feedback_page node: a touchscreen page that puts the robot's question to the person it
serves and sends back their answer.

Serves one page over HTTP (``host``:``port``; localhost unless a ``token_file`` is set). It
asks the ranker (stars/question_request) for the served person's question whenever the
served person changes and after each answer, shows the question of stars/question with a
picture of its scene (from stars/scene), a rating on the model's scale and "skip". With
``feedback_via`` bridge (default) the served person comes from the bridge's
stars/served_person and an answer goes out on stars/person_feedback, which the bridge drops
for an anonymous person; with ``ranker`` the served user is stars/user_id and an answer is
stars/feedback. After an answer the page shows what the robot does now, from the person's
next stars/ranking. A ``no_question`` on stars/errors (the ranker has seen no scene to ask
about yet) is shown to the person, and the question asked for again at their next ranking; a
request is sent again when a ranker's stars/question_request, stars/question or stars/errors
endpoint joins (the page started while someone was served). Refusals go back to the page
and out on stars/errors. The logic is ``stars_ros.hri.feedback_page``, the HTTP side
``stars_ros.hri.feedback_server``; docs/feedback_page.md.

    ros2 run stars_ros feedback_page --ros-args -p port:=8080
"""
from __future__ import annotations

import ipaddress
import json
import threading

from rcl_interfaces.msg import ParameterDescriptor
from rclpy.event_handler import PublisherEventCallbacks, SubscriptionEventCallbacks
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from std_msgs.msg import String

from stars_ros import feedback_auth, messages
from stars_ros.errors import ConfigError
from stars_ros.ros import usage
from stars_ros.ros.spinning import run_node
from stars_ros.ros.unknown_parameters import warn_unknown_overrides

RELIABLE = QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE)
QUESTIONS = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE)  # the ranker's stars/question(_request)
LATCHED = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL)
MIN_TOKEN_CHARS = 16

PARAMETERS = {  # name: (default, description)
    'host': ('127.0.0.1', 'address to serve on; one other than loopback needs token_file'),
    'port': (8080, 'TCP port (0: any free one, logged)'),
    'token_file': ('', 'file holding the token every request must carry (?token=...), at least 16 characters; '
                   'required when host is not loopback'),
    'feedback_via': ('bridge', 'bridge: the served person from stars/served_person, answers on '
                     'stars/person_feedback (an anonymous person\'s are dropped there); ranker: the served user from '
                     'stars/user_id, answers on stars/feedback'),
    'rating_min': (0.0, "the model's lowest rating"),
    'rating_max': (1.0, "the model's highest rating"),
    'rating_steps': (5, 'rating buttons from rating_min to rating_max'),
    'posts_per_second': (2.0, 'taps taken a second on average; more are refused as a flood'),
    'burst': (5, 'taps taken at once before posts_per_second applies'),
    'feedback_key_file': ('', "the ranker's signing keys (docs/security.md): answers are signed with the first "
                          'key here, never in the page; empty: unsigned'),
}


def read_token(path: str, host: str) -> str:
    """The page token of ``path`` ('' none); ConfigError when a non-loopback ``host`` has none
    or the token is short."""
    token = ''
    if path:
        try:
            with open(path, encoding='utf-8') as handle:
                token = handle.read().strip()
        except (OSError, UnicodeDecodeError) as error:
            raise ConfigError(f'token_file {path} cannot be read: {error}') from None
        if len(token) < MIN_TOKEN_CHARS:
            raise ConfigError(f'token_file {path} holds a token of {len(token)} characters, fewer than '
                              f'{MIN_TOKEN_CHARS}')
    try:
        loopback = host == 'localhost' or ipaddress.ip_address(host).is_loopback
    except ValueError:
        loopback = False
    if not loopback and not token:
        raise ConfigError(f"host '{host}' is not loopback: serving there needs a token_file")
    return token


class FeedbackPageNode(Node):
    """Topics in and out of ``FeedbackPage``, which ``PageServer`` serves (module docstring)."""

    def __init__(self, **kwargs):
        super().__init__('feedback_page', **kwargs)
        from stars_ros.hri.feedback_page import FeedbackPage, PageSettings  # aiohttp and matplotlib: not for --help
        from stars_ros.hri.feedback_server import ErrorThrottle, PageServer
        v = {name: self.declare_parameter(name, default, ParameterDescriptor(description=text, read_only=True)).value
             for name, (default, text) in PARAMETERS.items()}
        warn_unknown_overrides(self, 'feedback_page', PARAMETERS)
        if v['feedback_via'] not in ('bridge', 'ranker'):
            raise ConfigError(f"feedback_via must be 'bridge' or 'ranker', got '{v['feedback_via']}'")
        signing = None
        if v['feedback_key_file']:
            keys = feedback_auth.load_keys(v['feedback_key_file'])
            signing = next(iter(keys.items()))
        try:
            settings = PageSettings((v['rating_min'], v['rating_max']), v['rating_steps'],
                                    v['feedback_via'] == 'bridge', v['posts_per_second'], v['burst'],
                                    read_token(v['token_file'], v['host']), signing)
        except ValueError as error:
            raise ConfigError(str(error)) from None
        self._lock = threading.Lock()
        self.page = FeedbackPage(settings, lambda: self.get_clock().now().nanoseconds)
        answers = 'stars/person_feedback' if settings.via_bridge else 'stars/feedback'
        joined = PublisherEventCallbacks(matched=self._on_matched)
        self._out = {'stars/question_request': self.create_publisher(
                         String, 'stars/question_request', QUESTIONS, event_callbacks=joined),
                     answers: self.create_publisher(String, answers, RELIABLE),
                     'stars/errors': self.create_publisher(String, 'stars/errors', RELIABLE)}
        self._errors_topic = self.resolve_topic_name('stars/errors')
        report = ErrorThrottle(self.report)
        self.server = PageServer(self.page, self._lock, self._publish, report, v['host'], v['port'])
        if settings.via_bridge:
            self._listen('stars/served_person', LATCHED, self.page.on_served_person, report)
        else:
            self._listen('stars/user_id', LATCHED, self.page.on_user_id, report)
        self._listen('stars/scene', RELIABLE, self.page.on_scene, report)
        self._listen('stars/question', QUESTIONS, self.page.on_question, report,
                     SubscriptionEventCallbacks(matched=self._on_matched))
        self._listen('stars/ranking', RELIABLE, self.page.on_ranking, report)
        self._listen('stars/errors', RELIABLE, self.page.on_error, report,
                     SubscriptionEventCallbacks(matched=self._on_matched))
        self.address = self.server.start()
        self.get_logger().info(f'serving the page at {self.address}'
                               + ('' if not settings.token else ' (open it with ?token=...)'))

    def _listen(self, topic: str, qos, handle, report, events=None):
        """Subscribe ``topic``: ``handle(text)`` under the lock, what it returns published; a
        message it cannot read is reported, and the page serves on."""
        name = self.resolve_topic_name(topic)

        def callback(msg: String):
            try:
                with self._lock:
                    out = handle(msg.data)
            except (ValueError, TypeError, KeyError, AttributeError, messages.BadMessage) as error:
                report('bad_message', f'{type(error).__name__}: {error}'[:300], name)
                return
            self._publish(out or [])
            self.server.changed()
        self.create_subscription(String, topic, callback, qos, event_callbacks=events)

    def _on_matched(self, info):
        if info.current_count_change > 0:
            with self._lock:
                out = self.page.on_ranker_joined()
            self._publish(out)
            self.server.changed()

    def _publish(self, out: list):
        for topic, payload in out:
            self._out[topic].publish(String(data=payload))

    def report(self, kind: str, message: str, where: str):
        """A refusal on stars/errors, in the ranker's form (``kind``, ``message``, ``topic``,
        ``scene_id``, ``level``), and in the log."""
        self._out['stars/errors'].publish(String(data=json.dumps(
            {'kind': kind, 'message': message, 'topic': where, 'scene_id': None, 'level': 'error'})))
        self.get_logger().warning(f'[{kind}] {where}: {message}')

    def close(self):
        self.server.stop()


def main(args=None):
    if usage.print_help_if_asked('feedback_page', __doc__, PARAMETERS,
                                 'ros2 run stars_ros feedback_page --ros-args -p port:=8080', args):
        return
    run_node('feedback_page', FeedbackPageNode, fatal=(ConfigError, OSError), args=args,
             close=FeedbackPageNode.close)


if __name__ == '__main__':
    main()
