"""The ranker's parameters (``PARAMETERS``: default, description, read-only, range) and its
topics with their QoS (``TOPICS``, ``topic_qos``): the one table ``ros.ranker`` declares,
``--help`` prints and ``config/ranker.yaml`` and the launch file are checked against.
"""
from __future__ import annotations

from typing import Mapping

from stars_ros import messages, recording
from stars_ros.resources import DEFAULT_CHECKPOINT

TOPICS = ('stars/scene', 'stars/user_id', 'stars/feedback', 'stars/ranking', 'stars/errors', 'stars/user_model',
          'stars/question_request', 'stars/question', 'stars/markers', 'stars/forget_person', 'stars/consent')
_INT_MAX = 2 ** 31 - 1
FORGETS_KEPT = 100  # stars/forget_person messages a peer that joins late still gets


def topic_qos(params: Mapping) -> dict:
    """topic -> (depth, latched) of every topic of TOPICS, all reliable: what the rclpy
    adapter subscribes and publishes with and the recorder offers again (``ros2 bag play``).
    A robot that joins late gets the last user models; with fleet sharing the history also
    holds a re-send of every user until the newcomer has it; a viewer that joins late gets
    the latest scene's markers; a peer that joins late gets the last forgets; the consent
    list is the latest one published."""
    depth = params['queue_depth']
    models = depth + (params['fold_in_max_users'] if params['fleet_sharing'] else 0)
    return {'stars/scene': (depth, False), 'stars/ranking': (depth, False), 'stars/feedback': (100, False),
            'stars/errors': (100, False), 'stars/user_id': (1, True), 'stars/user_model': (models, True),
            'stars/question_request': (10, False), 'stars/question': (10, False), 'stars/markers': (1, True),
            'stars/forget_person': (FORGETS_KEPT, True), 'stars/consent': (1, True)}


PARAMETERS = {  # name: (default, description, read_only, range)
    'checkpoint': ('', f'checkpoint file; empty: the packaged {DEFAULT_CHECKPOINT}. Read again by ~/reload',
                   False, None),
    'top_k': (0, 'publish only the best k entries of each ranking; 0: all', False, (0, _INT_MAX)),
    'explain': (False, "give every ranking entry its 'why' (the parts of its score and the entities that drive it, "
                'docs/explanations.md), as a request with "explain": true does', False, None),
    'explain_entities': (5, "entities a 'why' names, largest |effect| first; 0: all", False, (0, 4096)),
    'frame_id': ('base_link', "the robot's frame, REP 103 axes: that of stars/markers (the scene converted from "
                 'SocNav1 centimetres, docs/explanations.md) and the one typed scenes must be in (docs/interfaces.md)',
                 False, None),
    'record_markers': (True, 'record stars/markers (visualization_msgs/MarkerArray) in the bag; they are published '
                       'latched either way, so a viewer that joins later gets the latest', False, None),
    'record_folder': (str(recording.default_folder() / recording.NODE_PLACEHOLDER), 'folder for the MCAP bags and '
                      'the state store (state.db), one node each; {node} stands for the node\'s namespace and name '
                      '(robot1/ranker); default $ROS_HOME/stars_ros/records/{node} (ROS_HOME: ~/.ros unless set); '
                      'empty: do not record', True, None),
    'rotation_bytes': (64 << 20, 'start a new MCAP file once one reaches this size (bytes)', True,
                       (4096, _INT_MAX)),
    'flush_interval': (1.0, 'seconds between flushes of the recording (a hard kill loses at most this of its other '
                       'topics; stored feedback is never lost) and between two tries of a disk that refuses the state '
                       'store', True, (0.01, 3600.0)),
    'max_message_bytes': (messages.DEFAULT_MAX_BYTES, 'larger messages are refused (kind oversized)',
                          False, (1024, 64 << 20)),
    'queue_depth': (1000, 'QoS depth of stars/scene and the most requests waiting to be scored', True,
                    (1, 100000)),
    'max_batch': (16, 'most queued requests scored in one forward pass', False, (1, 1024)),
    'log_throttle': (5.0, 'seconds between two log lines about the same kind of error', False,
                     (0.0, 3600.0)),
    'diagnostics_period': (1.0, 'seconds between two /diagnostics messages', True, (0.05, 3600.0)),
    'fold_in': (True, "personalise from feedback: re-solve the user's embedding after each rating", False, None),
    'fold_in_min_ratings': (1, 'ratings a user needs before their folded-in embedding is served', False,
                            (1, 100000)),
    'fold_in_max_ratings': (200, "most recent ratings per user the fold-in is solved from (and the state store "
                            'keeps); older ones stay in the MCAP log for the offline refit', True, (1, 1000000)),
    'fold_in_max_users': (1000, 'folded-in users kept; beyond this the one who rated least recently goes back to '
                          'the checkpoint (their feedback stays in the MCAP log)', True, (1, 10000000)),
    'fold_in_regularisation': (0.0, '0: serve the Gaussian posterior of each person (no λ to set: the prior and '
                               'rating noise come from the checkpoint); > 0: the ridge solve with this λ towards the '
                               'prior mean instead', False, (0.0, 1e6)),
    'question_recent_scenes': (32, 'latest remembered scenes a stars/question_request without candidates chooses '
                               'among; the target set of every question request', False, (1, 4096)),
    'fleet_sharing': (False, 'share folded-in users with the other rankers on stars/user_model (remap it to one '
                      "fleet-wide topic): publish each model with the ratings it was solved from, take in peers' "
                      "ratings and solve each user from everyone's", True, None),
    'feedback_key_file': ('', 'file of feedback keys, one KEY_ID:HEX_SECRET a line (docs/security.md): feedback, and '
                          "with fleet sharing the ratings of peers' models, are taken only when one of them signed "
                          'it; empty: feedback is not authenticated', True, None),
    'feedback_max_age': (60.0, 'seconds signed feedback stays valid: a stamp further in the past or the future, or '
                         'a MAC already taken within it, is refused (kind auth)', False, (0.001, 86400.0)),
    'store_policy': ('all', "whom the node stores: 'all'; 'consented': only people on the consent list "
                     '(consent_file and stars/consent) are stored, learned and shared, everyone else is ranked as a '
                     'stranger and nothing of them is kept (docs/privacy.md)', True, None),
    'consent_file': ('', "with store_policy 'consented': a file of the ids of people who agreed to be stored, one a "
                     'line (# starts a comment), joined by those stars/consent lists; empty: none', True, None),
    'retention_days': (0.0, 'ratings older than this many days are erased from the state store and the bags, at '
                       'start and then hourly while the node serves; 0: kept until forgotten', False,
                       (0.0, 36500.0)),
}
